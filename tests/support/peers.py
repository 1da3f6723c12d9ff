"""Hostile OpenIGTLink peers for the fuzzing harness: a server that a sweep's ``--image
igtl:HOST:PORT`` connects to and that then streams what a broken or hostile scanner could send
(``PEERS``): spacings out of bounds, frames that change size, a flood, silence, bytes that are not
OpenIGTLink, a body past the memory limit, headers that lie, pixels of another type.

A peer serves one connection in a daemon thread of the process that runs the command, so it ends
with it."""

from __future__ import annotations

import contextlib
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
