"""Frames from OpenIGTLink: IMAGE messages (and the tracker's TRANSFORM ProbeToReference) from a
PLUS server or 3D Slicer, each image paired with the tracker pose at its timestamp."""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from probecal.core.acquisition.igtlreader import MessageReader, ReaderStopped, connect_to, message_time, unpacked
from probecal.core.acquisition.imagesource import BUFFER_FRAMES, POLL_S, Emit, ImageSourceError, ThreadedSource
from probecal.core.errors import quoted
from probecal.core.io.jsonio import MAX_MAGNITUDE

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
        return connect_to(self.host, self.port, self.connect_timeout_s, POLL_S, self.name, ImageSourceError)

    def _release(self, sock: socket.socket) -> None:
        sock.close()

    def _produce(self, sock: socket.socket, stop: threading.Event, emit: Emit) -> None:
        reader = MessageReader(sock, self.name, stop, ImageSourceError)
        pairer = _PosePairer(emit, self.pose_tolerance_s, self.pair_wait_s if self.transform_device else 0.0)
        try:
            while not stop.is_set():
                message = reader.read()
                if message is not None:
                    self._handle(*message, pairer)
                pairer.release_due()
        except ReaderStopped:
            return
        finally:
            pairer.flush()

    def _handle(self, fields: dict, body: bytearray, pairer: _PosePairer) -> None:
        kind, device = fields["message_type"], fields["device_name"]
        wanted_image = kind == "IMAGE" and self.image_device in (None, device)
        wanted_pose = kind == "TRANSFORM" and device == self.transform_device
        if not (wanted_image or wanted_pose):
            return
        timestamp = message_time(fields)
        message = unpacked(fields, body, self.name, ImageSourceError)
        if wanted_image:
            try:
                image, spacing = gray_frame(message.image, message.ijk_to_world_matrix)
            except ValueError as exc:
                raise ImageSourceError(f"{self.name}: bad {kind} message {quoted(device)} ({exc})") from None
        if wanted_image:
            pairer.add_image(image, timestamp, spacing)
        else:
            pairer.add_pose(np.asarray(message.matrix, dtype=float), timestamp)
