"""Hostile OpenIGTLink peers for the fuzzing harness: a server that a sweep's ``--image
igtl:HOST:PORT`` connects to and that then streams what a broken or hostile scanner could send
(``PEERS``): spacings out of bounds, frames that change size, a flood, silence, bytes that are not
OpenIGTLink, a body past the memory limit, headers that lie, pixels of another type.

Hostile trackers (``TRACKERS``) are PLUS servers a tracked sweep's ``--tracker igtl:HOST:PORT``
connects to, its images and its poses, that send valid poses and then one thing wrong.

A peer serves one connection in a daemon thread of the process that runs the command, so it ends
with it."""

from __future__ import annotations

import contextlib
import functools
import random
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
from pyigtl.messages import CRC64, ImageMessage

from probecal.core.acquisition.igtl import IMAGE_DEVICE, TOOL_DEVICE, image_message, transform_message

RATE_HZ = 30.0
SIZE = (48, 64)
ACCEPT_S = 30.0
HEADER = struct.Struct("> H 12s 20s II Q Q")


def _image(rows: int = SIZE[0], cols: int = SIZE[1], spacing: tuple[float, float] = (0.1, 0.1)) -> bytes:
    image = np.random.default_rng(rows * cols).integers(0, 255, (rows, cols), dtype=np.uint8)
    with np.errstate(all="ignore"):  # a spacing past float32's range is what the peer sends
        return image_message(image, np.diag([*spacing, 1.0, 1.0]), time.time(), IMAGE_DEVICE).pack()


def _stamped(message: bytes, seconds: float) -> bytes:
    """``message`` with its header's timestamp set to ``seconds``."""
    fields = list(HEADER.unpack_from(message))
    fields[3], fields[4] = int(seconds), int((seconds % 1.0) * (1 << 32))
    return HEADER.pack(*fields) + message[HEADER.size:]


def _with_body(message: bytes, body: bytes, size: int | None = None) -> bytes:
    """``message``'s header over ``body``, its size field ``size`` (the body's own when None) and
    its CRC the body's."""
    fields = list(HEADER.unpack_from(message))
    fields[5], fields[6] = len(body) if size is None else size, CRC64(body)
    return HEADER.pack(*fields) + body


def _retyped(message: bytes, kind: bytes) -> bytes:
    fields = list(HEADER.unpack_from(message))
    fields[1] = kind
    return HEADER.pack(*fields) + message[HEADER.size:]


def _corrupted(message: bytes) -> bytes:
    """``message`` with one byte of its body changed (its CRC then wrong)."""
    return message[:-1] + bytes([message[-1] ^ 0xFF])


def _image_dims(rows: int, cols: int) -> bytes:
    """An IMAGE whose own header says ``cols`` x ``rows`` pixels over a 64 x 48 px body."""
    message = _image()
    body = bytearray(message[HEADER.size:])
    extended = struct.unpack_from(">H", body)[0] if HEADER.unpack_from(message)[0] > 1 else 0
    struct.pack_into(">HHH", body, extended + 6, cols, rows, 1)
    return _with_body(message, bytes(body))


def _volume() -> bytes:
    voxels = np.zeros((3, SIZE[0], SIZE[1]), np.uint8)
    return ImageMessage(voxels, timestamp=time.time(), device_name=IMAGE_DEVICE).pack()


def _typed(dtype: str, components: int = 1) -> bytes:
    shape = (1, *SIZE) + ((components,) if components > 1 else ())
    return ImageMessage(np.zeros(shape, dtype), timestamp=time.time(), device_name=IMAGE_DEVICE).pack()


def _pose(value: float) -> bytes:
    with np.errstate(all="ignore"):
        return transform_message(np.full((4, 4), value), time.time(), TOOL_DEVICE).pack()


Frames = Callable[[int], bytes]
"""The bytes a peer sends as its ``k``-th frame (each stamped with the time it is sent)."""


def _steady(make: Callable[[], bytes]) -> Frames:
    message = make()
    return lambda _k: _stamped(message, time.time())


def _alternating(*makes: Callable[[], bytes]) -> Frames:
    messages = [make() for make in makes]
    return lambda k: _stamped(messages[k % len(messages)], time.time())


STREAMS: dict[str, tuple[Frames, float | None]] = {
    "valid": (_steady(_image), RATE_HZ),
    **{f"spacing {v}": (_steady(lambda v=v: _image(spacing=(v, v))), RATE_HZ)
       for v in (1e-7, 1e6, float("nan"), float("inf"), 0.0, -0.1, 1e300)},
    "spacing changes": (_alternating(_image, lambda: _image(spacing=(0.2, 0.1))), RATE_HZ),
    "size changes": (lambda k: _stamped(_image(SIZE[0] + k % 7, SIZE[1]), time.time()), RATE_HZ),
    "flood": (_steady(_image), None),
    "dims lie": (_steady(lambda: _image_dims(65535, 65535)), RATE_HZ),
    "dims zero": (_steady(lambda: _image_dims(0, 0)), RATE_HZ),
    "3D volume": (_steady(_volume), RATE_HZ),
    "uint16 pixels": (_steady(lambda: _typed("uint16")), RATE_HZ),
    "float pixels": (_steady(lambda: _typed("float32")), RATE_HZ),
    "RGB pixels": (_steady(lambda: _typed("uint8", 3)), RATE_HZ),
    "epoch timestamps": (lambda _k: _stamped(_image(), 1.0), RATE_HZ),
    "future timestamps": (lambda _k: _stamped(_image(), 4e9), RATE_HZ),
    "nan poses": (_alternating(_image, lambda: _pose(float("nan"))), RATE_HZ),
    "huge poses": (_alternating(_image, lambda: _pose(1e30)), RATE_HZ),
    "unknown type": (_steady(lambda: _retyped(_image(), b"FOOBAR")), RATE_HZ),
    "type not text": (_steady(lambda: _retyped(_image(), b"\xff\xfe")), RATE_HZ),
    "bad crc": (_steady(lambda: _corrupted(_image())), RATE_HZ),
}
"""Peers that stream frames: what each sends, and how often (None: as fast as it can)."""

ONCE: dict[str, Callable[[], Iterator[bytes]]] = {
    "silent": lambda: iter(()),
    "closes": lambda: iter(()),
    "garbage": lambda: iter([random.Random(7).randbytes(4096)]),
    "truncated": lambda: iter([_image()[:200]]),
    "huge body": lambda: _huge_body(200 << 20),
    "body 2^64-1": lambda: iter([_with_body(_image(), b"", (1 << 64) - 1)]),
    "header only": lambda: iter([_image()[:HEADER.size]]),
}
"""Peers that send a fixed thing and then stop: silence (the connection kept open), a closed
connection, noise, half a message, a body past the memory limit sent in full, a body of 2^64 - 1
bytes announced, a header with no body."""

PEERS = (*STREAMS, *ONCE)


def _huge_body(size: int) -> Iterator[bytes]:
    yield HEADER.pack(2, b"IMAGE", IMAGE_DEVICE.encode(), int(time.time()), 0, size, 0)
    chunk = bytes(1 << 20)
    for _ in range(size >> 20):
        yield chunk


def start_peer(kind: str) -> int:
    """Listen on a free loopback port, serve one connection as the peer ``kind`` in a daemon
    thread; the port."""
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(ACCEPT_S)
    threading.Thread(target=_serve, args=(listener, kind), name=f"peer {kind}", daemon=True).start()
    return listener.getsockname()[1]


def _serve(listener: socket.socket, kind: str) -> None:
    with contextlib.suppress(OSError), listener:
        connection, _ = listener.accept()
        with connection:
            if kind == "closes":
                return
            if kind in ONCE:
                for data in ONCE[kind]():
                    connection.sendall(data)
                connection.recv(1)  # keeps the connection open until the client closes it
                return
            frames, rate = STREAMS[kind]
            started = time.monotonic()
            for k in range(1 << 62):
                if rate is not None:
                    time.sleep(max(0.0, started + k / rate - time.monotonic()))
                connection.sendall(frames(k))


# -- hostile trackers ----------------------------------------------------------------------------

TRACKER_RATE_HZ = 30.0
TRACKER_SAMPLES = 120
"""A hostile tracker's samples before it closes the connection (4 s): a recording it does not end
ends with the stream."""
BAD_AT = 30
"""The first hostile sample (1 s in): the poses before it are valid."""
TRACKER_SIZE = (48, 64)
"""Its frames' rows and columns: blank, at ``TRACKER_SPACING_MM`` large enough to guide over the
default phantom; at ``SMALL_SPACING_MM``, too small."""
TRACKER_SPACING_MM = 1.0
SMALL_SPACING_MM = 0.1
NAMES_PER_SAMPLE = 300
HUGE_STATUS = "X" * (5 << 20)
POSES_PER_SAMPLE = 50  # a pose flood: 1500 a second


def _moving(k: int) -> np.ndarray:
    """The probe's pose in the tracker's frame at sample ``k`` (mm): drifting slowly along x."""
    pose = np.eye(4)
    pose[:3, 3] = [0.1 * k, 0.0, 100.0]
    return pose


def _far(value: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = value
    return pose


def _renamed(message: bytes, name: str) -> bytes:
    """``message`` with its header's device name set to ``name`` (its body, and so its CRC, kept)."""
    fields = list(HEADER.unpack_from(message))
    fields[2] = name.encode()
    return HEADER.pack(*fields) + message[HEADER.size:]


@functools.cache
def _blank_image(spacing: float) -> bytes:
    image = np.zeros(TRACKER_SIZE, np.uint8)
    return image_message(image, np.diag([spacing, spacing, 1.0, 1.0]), 0.0, IMAGE_DEVICE).pack()


@functools.cache
def _other_device() -> bytes:
    return transform_message(np.eye(4), 0.0, "Other").pack()


@functools.cache
def _huge_status() -> bytes:
    return transform_message(np.eye(4), 0.0, "ProbeToTracker", HUGE_STATUS).pack()


def _sample(k: int, t: float, probe: np.ndarray | None = None, reference: np.ndarray | None = None,
            probe_t: float | None = None, spacing: float = TRACKER_SPACING_MM) -> bytes:
    """What a PLUS server sends at sample ``k`` (stamped ``t``): the frame, ProbeToTracker (``probe``,
    stamped ``probe_t``; by default moving, stamped ``t``) and ReferenceToTracker (``reference``;
    by default the identity)."""
    with np.errstate(all="ignore"):  # a NaN or huge matrix is what the tracker sends
        return (_stamped(_blank_image(spacing), t)
                + transform_message(_moving(k) if probe is None else probe, t if probe_t is None else probe_t,
                                    "ProbeToTracker").pack()
                + transform_message(np.eye(4) if reference is None else reference, t, "ReferenceToTracker").pack())


TrackerSample = Callable[[int, int, float], bytes]
"""What a hostile tracker sends at sample ``k``, ``since`` samples after its first hostile one
(negative before it), stamped ``t`` (s)."""


def _once(matrix: np.ndarray) -> TrackerSample:
    return lambda k, since, t: _sample(k, t, probe=matrix if since == 0 else None)


def _names_flood(k: int, since: int, t: float) -> bytes:
    names = range(NAMES_PER_SAMPLE) if since >= 0 else range(0)
    return _sample(k, t) + b"".join(_renamed(_other_device(), f"N{since:05d}x{j:05d}") for j in names)


def _status_flood(k: int, since: int, t: float) -> bytes:
    huge = since >= 0 and since % 5 == 0
    return _sample(k, t) + (_stamped(_huge_status(), t + 0.001) if huge else b"")


def _pose_flood(k: int, since: int, t: float) -> bytes:
    extra = range(POSES_PER_SAMPLE) if since >= 0 else range(0)
    return _sample(k, t) + b"".join(transform_message(_moving(k), t + (j + 1) * 1e-5, "ProbeToTracker").pack()
                                    for j in extra)


TRACKERS: dict[str, TrackerSample] = {
    "valid": lambda k, since, t: _sample(k, t),
    "nan pose": _once(np.full((4, 4), np.nan)),
    "mirrored pose": _once(np.diag([-1.0, 1.0, 1.0, 1.0])),
    "huge pose": _once(_far(1e30)),
    "timestamps backwards": lambda k, since, t: _sample(k, t, probe_t=t - 1.0 if since == 0 else None),
    "composed huge": lambda k, since, t: _sample(k, t, *((_far(9e11), _far(-9e11)) if since >= 0 else ())),
    "device names flood": _names_flood,
    "huge status": _status_flood,
    "pose flood": _pose_flood,
    "small frames": lambda k, since, t: _sample(k, t, spacing=SMALL_SPACING_MM),
}
"""Hostile trackers, each a PLUS server's stream (frames, ProbeToTracker, ReferenceToTracker at
30 Hz) with one thing wrong from sample ``BAD_AT`` on: one pose NaN, mirrored or of 1e30 mm, one
pose stamped a second back, the probe at +9e11 mm and the reference at -9e11 mm (each a pose, their
composition 1.8e12 mm), a new device name in 300 messages a sample, a TransformStatus of 5 MB in
every fifth, 1500 probe poses a second; and frames too small to guide over the phantom."""
TRACKER_BAD_INPUT = ("nan pose", "mirrored pose", "huge pose", "timestamps backwards", "composed huge", "pose flood")
"""The hostile trackers whose data ends a recording as bad input."""


def start_tracker(kind: str, bad_at: int = BAD_AT) -> int:
    """Listen on a free loopback port and serve the hostile tracker ``kind`` to the two connections a
    tracked sweep opens (its images and its tracker), each its own stream, in daemon threads; the
    port. ``bad_at`` is the first hostile sample."""
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(ACCEPT_S)
    threading.Thread(target=_accept_two, args=(listener, kind, bad_at), name=f"tracker {kind}", daemon=True).start()
    return listener.getsockname()[1]


def _accept_two(listener: socket.socket, kind: str, bad_at: int) -> None:
    with contextlib.suppress(OSError), listener:
        for _ in range(2):
            connection, _ = listener.accept()
            threading.Thread(target=_serve_tracker, args=(connection, kind, bad_at), daemon=True).start()


def _serve_tracker(connection: socket.socket, kind: str, bad_at: int) -> None:
    sample = TRACKERS[kind]
    started = time.monotonic()
    with contextlib.suppress(OSError), connection:
        for k in range(max(TRACKER_SAMPLES, bad_at + TRACKER_SAMPLES - BAD_AT)):
            time.sleep(max(0.0, started + k / TRACKER_RATE_HZ - time.monotonic()))
            connection.sendall(sample(k, k - bad_at, time.time()))
