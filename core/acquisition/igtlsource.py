"""Frames from OpenIGTLink: IMAGE messages (and the tracker's TRANSFORM ProbeToReference) from a
PLUS server or 3D Slicer, each image paired with the tracker pose at its timestamp."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from pyigtl.messages import CRC64, MessageBase

from probecal.core.acquisition.imagesource import BUFFER_FRAMES, POLL_S, Emit, ImageSourceError, ThreadedSource
from probecal.core.errors import InputError
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.io.limits import checked_bytes

MAX_BODY_BYTES = 1 << 28  # larger OpenIGTLink bodies are taken as a corrupt stream
DECODED_COPIES = 3  # a body is held while its pixels are unpacked and made grey
READ_CHUNK_BYTES = 1 << 20  # most bytes read from the socket at once
POSES_KEPT = 64  # recent tracker poses an image can be paired with


def gray_frame(voxels: np.ndarray, ijk_to_world: np.ndarray) -> tuple[np.ndarray, tuple[float, float] | None]:
    """A uint8 (rows, cols) frame and its pixel spacing (mm) from an IMAGE message's voxels.

    ``voxels`` are pyigtl's (k, j, i) or (k, j, i, components) array. A frame is one slice: k = 1
    (as PLUS and Slicer send it: columns along i, rows along j), or i = 1 (a 2D array sent by
    pyigtl: columns along j, rows along k). RGB(A) is converted to gray; other scalar types than
    uint8 are refused (ValueError). The spacing is the length of the ijk-to-world matrix's column
    and row axes; it is None when both are 1, since PLUS sends frames in pixels and keeps the
    spacing in ImageToProbe.
    """
    data = voxels if voxels.ndim == 4 else voxels[..., np.newaxis]
    if data.ndim != 4:
        raise ValueError(f"image of shape {voxels.shape}")
    k, j, i, components = data.shape
    if k == 1:
        plane, x_axis, y_axis = data[0], 0, 1
    elif i == 1:
        plane, x_axis, y_axis = data[:, :, 0], 1, 2
    else:
        raise ValueError(f"a {i}x{j}x{k} volume, not a 2D frame")
    if plane.dtype != np.uint8:
        raise ValueError(f"{plane.dtype} pixels (only 8-bit frames are supported)")
    if components == 1:
        image = plane[..., 0]
    elif components in (3, 4):
        code = cv2.COLOR_RGB2GRAY if components == 3 else cv2.COLOR_RGBA2GRAY
        image = cv2.cvtColor(np.ascontiguousarray(plane), code)
    else:
        raise ValueError(f"{components} components per pixel (expected 1, 3 or 4)")
    spacing = (float(np.linalg.norm(ijk_to_world[:3, x_axis])), float(np.linalg.norm(ijk_to_world[:3, y_axis])))
    return np.ascontiguousarray(image), None if np.allclose(spacing, 1.0) else spacing


class _Stopped(Exception):
    """The reader was asked to stop in the middle of a message."""


class _MessageReader:
    """Reads whole OpenIGTLink messages from a socket with a short time-out, keeping partial ones.

    Checks each body's CRC-64. Raises ImageSourceError when the connection closes or breaks or the
    data is not OpenIGTLink, and _Stopped when ``stop`` is set mid-message.
    """

    def __init__(self, sock: socket.socket, name: str, stop: threading.Event):
        self._sock = sock
        self._name = name
        self._stop = stop

    def read(self) -> tuple[dict, bytearray] | None:
        """(header fields, body) of the next message, or None when none started within POLL_S."""
        header = self._read(MessageBase.IGTL_HEADER_SIZE, idle_ok=True)
        if header is None:
            return None
        try:
            fields = MessageBase.parse_header(bytes(header))
        except (struct.error, UnicodeDecodeError) as exc:
            raise ImageSourceError(f"{self._name}: bad data, not an OpenIGTLink header ({exc})") from None
        if fields["body_size"] > MAX_BODY_BYTES:
            raise ImageSourceError(
                f"{self._name}: bad data, a {fields['message_type']!r} message of {fields['body_size']} bytes"
            )
        try:
            checked_bytes(None, f"a {fields['message_type']!r} message of {fields['body_size']} bytes",
                          (DECODED_COPIES, fields["body_size"]))
        except InputError as exc:
            raise ImageSourceError(f"{self._name}: {exc}") from None
        body = self._read(fields["body_size"])
        assert body is not None  # _read returns None only when idle_ok
        crc = struct.unpack_from(">Q", header, MessageBase.IGTL_HEADER_SIZE - 8)[0]
        if CRC64(body) != crc:
            raise ImageSourceError(
                f"{self._name}: bad data, CRC mismatch in {fields['message_type']} '{fields['device_name']}'"
            )
        return fields, body

    def _read(self, size: int, idle_ok: bool = False) -> bytearray | None:
        """``size`` bytes, held as they arrive (a header that claims a large body takes memory only
        as the body comes)."""
        buffer = bytearray()
        while len(buffer) < size:
            try:
                chunk = self._sock.recv(min(size - len(buffer), READ_CHUNK_BYTES))
            except TimeoutError:
                if self._stop.is_set():
                    raise _Stopped from None
                if idle_ok and not buffer:
                    return None
                continue
            except OSError as exc:
                raise ImageSourceError(f"{self._name}: connection lost ({exc.strerror or exc})") from None
            if not chunk:
                raise ImageSourceError(f"{self._name}: connection closed by the server")
            buffer += chunk
        return buffer


@dataclass
class _PendingImage:
    image: np.ndarray
    timestamp: float
    spacing: tuple[float, float] | None
    received: float


class _PosePairer:
    """Emits each image with the tracker pose nearest to it in time, once that pose can be known.

    An image waits until a pose at or after its timestamp arrives, a newer image arrives, or
    ``wait_s`` passes (a stream without poses). The nearest pose counts only within
    ``tolerance_s``; an invalid pose (not finite, or a value past MAX_MAGNITUDE mm) pairs as None.
    """

    def __init__(self, emit: Emit, tolerance_s: float, wait_s: float):
        self._emit = emit
        self._tolerance_s = tolerance_s
        self._wait_s = wait_s
        self._pending: deque[_PendingImage] = deque()
        self._poses: deque[tuple[float, np.ndarray | None]] = deque(maxlen=POSES_KEPT)

    def add_pose(self, tool_to_base: np.ndarray, timestamp: float) -> None:
        valid = bool(np.all(np.abs(tool_to_base) <= MAX_MAGNITUDE))  # as a session's reader takes them
        self._poses.append((timestamp, tool_to_base if valid else None))
        while self._pending and self._pending[0].timestamp <= timestamp:
            self._release()

    def add_image(self, image: np.ndarray, timestamp: float, spacing_mm: tuple[float, float] | None) -> None:
        self.flush()
        self._pending.append(_PendingImage(image, timestamp, spacing_mm, time.monotonic()))
        if self._poses and self._poses[-1][0] >= timestamp:
            self._release()

    def release_due(self) -> None:
        """Emit the images that have waited ``wait_s`` for a pose."""
        now = time.monotonic()
        while self._pending and now - self._pending[0].received >= self._wait_s:
            self._release()

    def flush(self) -> None:
        while self._pending:
            self._release()

    def _release(self) -> None:
        item = self._pending.popleft()
        pose = pose_timestamp = None
        if self._poses:
            pose_timestamp, pose = min(self._poses, key=lambda p: abs(p[0] - item.timestamp))
            if pose is None or abs(pose_timestamp - item.timestamp) > self._tolerance_s:
                pose = pose_timestamp = None
        self._emit(item.image, item.timestamp, pose, pose_timestamp, item.spacing)


class IgtlSource(ThreadedSource):
    """IMAGE messages from an OpenIGTLink server (PLUS, 3D Slicer), paired with the tool pose.

    ``image_device`` selects the IMAGE device (None: any). Poses come from TRANSFORM messages named
    ``transform_device`` (the tool in the reference frame, e.g. PLUS's ProbeToReference; None: no
    pairing). Frame timestamps are the messages' (the receive time when a sender leaves them 0).
    Connection refused, lost or stalled, and bad data raise ImageSourceError; nothing waits
    longer than the given time-outs.
    """

    def __init__(
        self,
        host: str,
        port: int,
        image_device: str | None = None,
        transform_device: str | None = "ProbeToReference",
        connect_timeout_s: float = 2.0,
        pose_tolerance_s: float = 0.05,
        pair_wait_s: float = 0.1,
        buffer_frames: int = BUFFER_FRAMES,
    ):
        super().__init__(f"igtl:{host}:{port}", buffer_frames)
        self.host, self.port = host, port
        self.image_device = image_device
        self.transform_device = transform_device
        self.connect_timeout_s = connect_timeout_s
        self.pose_tolerance_s = pose_tolerance_s
        self.pair_wait_s = pair_wait_s

    def _start(self) -> socket.socket:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except ConnectionRefusedError:
            raise ImageSourceError(
                f"{self.name}: connection refused (is the OpenIGTLink server running?)"
            ) from None
        except TimeoutError:
            raise ImageSourceError(f"{self.name}: no answer within {self.connect_timeout_s:.1f} s") from None
        except OSError as exc:
            raise ImageSourceError(f"{self.name}: cannot connect ({exc.strerror or exc})") from None
        sock.settimeout(POLL_S)
        return sock

    def _release(self, sock: socket.socket) -> None:
        sock.close()

    def _produce(self, sock: socket.socket, stop: threading.Event, emit: Emit) -> None:
        reader = _MessageReader(sock, self.name, stop)
        pairer = _PosePairer(emit, self.pose_tolerance_s, self.pair_wait_s if self.transform_device else 0.0)
        try:
            while not stop.is_set():
                message = reader.read()
                if message is not None:
                    self._handle(*message, pairer)
                pairer.release_due()
        except _Stopped:
            return
        finally:
            pairer.flush()

    def _handle(self, fields: dict, body: bytearray, pairer: _PosePairer) -> None:
        kind, device = fields["message_type"], fields["device_name"]
        wanted_image = kind == "IMAGE" and self.image_device in (None, device)
        wanted_pose = kind == "TRANSFORM" and device == self.transform_device
        if not (wanted_image or wanted_pose):
            return
        timestamp = fields["timestamp"] or time.time()
        message = MessageBase.create_message(kind)
        try:
            with np.errstate(all="ignore"):  # a hostile matrix is refused below, not warned of
                message.unpack(fields, body)
            if wanted_image:
                image, spacing = gray_frame(message.image, message.ijk_to_world_matrix)
        except Exception as exc:  # pyigtl raises anything from struct.error to TypeError on bad bodies
            raise ImageSourceError(f"{self.name}: bad {kind} message '{device}' ({exc})") from None
        if wanted_image:
            pairer.add_image(image, timestamp, spacing)
        else:
            pairer.add_pose(np.asarray(message.matrix, dtype=float), timestamp)
