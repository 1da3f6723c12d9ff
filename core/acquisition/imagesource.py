"""Image sources for live acquisition, behind one small protocol.

- ``IgtlSource``: OpenIGTLink IMAGE messages (and the tracker's TRANSFORM) from a PLUS server or
  3D Slicer;
- ``VideoSource``: an OpenCV frame grabber (device index) or a video file;
- ``ReplaySource``: a recorded probecal session, at its recorded timing or a given rate.

Each source fills a bounded buffer from a daemon thread. ``latest`` returns the newest frame
(skipping older ones); ``frames`` yields every frame after the last one returned, in order, and
raises rather than skip one when the reader falls behind the buffer. Images are uint8
(rows, columns): x = column, y = row. Timestamps are seconds on the source's clock; poses are
``tool_to_base`` 4x4 in mm; pixel spacing is (sx, sy) in mm.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from pyigtl.messages import CRC64, MessageBase

from probecal.core.errors import DeviceError, InputError
from probecal.core.io.session import FrameRecord, Session, load_session

BUFFER_FRAMES = 256  # about 130 MB of 820x616 frames, 8 s at 30 frames/s
POLL_S = 0.02  # socket time-out: how often a receive loop looks at its stop flag
JOIN_S = 2.0  # how long close() waits for a producer thread
MAX_BODY_BYTES = 1 << 28  # larger OpenIGTLink bodies are taken as a corrupt stream
READ_CHUNK_BYTES = 1 << 20  # most bytes read from the socket at once
POSES_KEPT = 64  # recent tracker poses an image can be paired with
DEFAULT_RATE_HZ = 30.0  # playback rate of a video file or session that does not give one


class ImageSourceError(DeviceError):
    """An image source failed: time-out, stall, dropped connection, end of stream or bad data.

    The message is one line and starts with the source's name.
    """


@dataclass(frozen=True)
class SourceFrame:
    """One frame: uint8 (rows, cols) image, its timestamp (s, source clock) and running index.

    ``tool_to_base`` (4x4 mm) and ``pose_timestamp`` (s) when the source carries a tracked pose;
    ``pixel_spacing_mm`` (sx, sy) when the source states it.
    """

    image: np.ndarray
    timestamp: float
    index: int
    tool_to_base: np.ndarray | None = None
    pose_timestamp: float | None = None
    pixel_spacing_mm: tuple[float, float] | None = None


class ImageSource(Protocol):
    """What the acquisition needs from an image source."""

    name: str

    def open(self) -> None: ...

    def close(self) -> None: ...

    def latest(self, timeout_s: float = 2.0) -> SourceFrame:
        """The newest frame, waiting up to ``timeout_s`` for one newer than the last returned."""
        ...

    def frames(self, timeout_s: float = 2.0) -> Iterator[SourceFrame]:
        """Every frame after the last one returned, in order; ends at a clean end of stream and
        raises ImageSourceError rather than skip a frame."""
        ...

    def __enter__(self) -> ImageSource:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


Emit = Callable[..., None]


class _FrameBuffer:
    """Frames handed from one producer thread to readers; when full, the oldest is dropped.

    ``next`` reports frames dropped since the last ``latest`` (which skips frames on purpose).
    """

    def __init__(self, name: str, capacity: int):
        self._name = name
        self._capacity = capacity
        self._frames: deque[SourceFrame] = deque()
        self._cond = threading.Condition()
        self._ended = False
        self._fault: str | None = None
        self.dropped = 0

    def put(self, frame: SourceFrame) -> None:
        with self._cond:
            if len(self._frames) >= self._capacity:
                self._frames.popleft()
                self.dropped += 1
            self._frames.append(frame)
            self._cond.notify_all()

    def end(self, fault: str | None = None) -> None:
        """No more frames: a clean end of stream, or ``fault``. Only the first call counts."""
        with self._cond:
            if not self._ended:
                self._ended, self._fault = True, fault
                self._cond.notify_all()

    def latest(self, timeout_s: float) -> SourceFrame:
        with self._cond:
            self._cond.wait_for(lambda: self._frames or self._ended, timeout_s)
            if self._frames:
                frame = self._frames[-1]
                self._frames.clear()
                self.dropped = 0
                return frame
            raise self._error(timeout_s)

    def next(self, timeout_s: float) -> SourceFrame | None:
        """The oldest unread frame; None at a clean end of stream."""
        with self._cond:
            self._cond.wait_for(lambda: self._frames or self._ended, timeout_s)
            if self.dropped:
                dropped, self.dropped = self.dropped, 0
                raise ImageSourceError(
                    f"{self._name}: {dropped} frames dropped: the reader fell behind the stream by "
                    f"more than {self._capacity} frames"
                )
            if self._frames:
                return self._frames.popleft()
            if self._ended and self._fault is None:
                return None
            raise self._error(timeout_s)

    def _error(self, timeout_s: float) -> ImageSourceError:
        if not self._ended:
            return ImageSourceError(f"{self._name}: no image for {timeout_s:.1f} s (stream stalled)")
        return ImageSourceError(self._fault or f"{self._name}: end of stream")


class _ThreadedSource(ImageSource):
    """A source whose frames come from a daemon producer thread.

    Subclasses implement ``_start`` (connect or open, in the caller's thread; returns a handle),
    ``_produce`` (the thread: emits frames until ``stop`` is set or the stream ends; raises
    ImageSourceError on a fault) and ``_release`` (frees the handle, in the thread).
    """

    def __init__(self, name: str, buffer_frames: int = BUFFER_FRAMES):
        self.name = name
        self._capacity = buffer_frames
        self._buffer: _FrameBuffer | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def _start(self) -> Any:
        raise NotImplementedError

    def _produce(self, handle: Any, stop: threading.Event, emit: Emit) -> None:
        raise NotImplementedError

    def _release(self, handle: Any) -> None:
        """Free what ``_start`` acquired; nothing by default."""

    def open(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        handle = self._start()
        self._stop = threading.Event()
        self._buffer = _FrameBuffer(self.name, self._capacity)
        self._thread = threading.Thread(
            target=self._run, args=(handle, self._stop, self._buffer), name=self.name, daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(JOIN_S)
        self._thread = None
        self._buffer = None

    def latest(self, timeout_s: float = 2.0) -> SourceFrame:
        return self._opened().latest(timeout_s)

    def frames(self, timeout_s: float = 2.0) -> Iterator[SourceFrame]:
        buffer = self._opened()
        while (frame := buffer.next(timeout_s)) is not None:
            yield frame

    def _opened(self) -> _FrameBuffer:
        if self._buffer is None:
            raise ImageSourceError(f"{self.name}: not open")
        return self._buffer

    def _run(self, handle: Any, stop: threading.Event, buffer: _FrameBuffer) -> None:
        count = 0

        def emit(image, timestamp, tool_to_base=None, pose_timestamp=None, pixel_spacing_mm=None):
            nonlocal count
            buffer.put(SourceFrame(image, timestamp, count, tool_to_base, pose_timestamp, pixel_spacing_mm))
            count += 1

        try:
            self._produce(handle, stop, emit)
            buffer.end()
        except ImageSourceError as exc:
            buffer.end(str(exc))
        finally:
            buffer.end(f"{self.name}: the image thread stopped unexpectedly")
            self._release(handle)


# --- OpenIGTLink --------------------------------------------------------------------------------


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
        body = self._read(fields["body_size"])
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
    ``tolerance_s``; an invalid (non-finite) pose pairs as None.
    """

    def __init__(self, emit: Emit, tolerance_s: float, wait_s: float):
        self._emit = emit
        self._tolerance_s = tolerance_s
        self._wait_s = wait_s
        self._pending: deque[_PendingImage] = deque()
        self._poses: deque[tuple[float, np.ndarray | None]] = deque(maxlen=POSES_KEPT)

    def add_pose(self, tool_to_base: np.ndarray, timestamp: float) -> None:
        self._poses.append((timestamp, tool_to_base if np.all(np.isfinite(tool_to_base)) else None))
        while self._pending and self._pending[0].timestamp <= timestamp:
            self._release()

    def add_image(self, image: np.ndarray, timestamp: float, spacing: tuple[float, float] | None) -> None:
        self.flush()
        self._pending.append(_PendingImage(image, timestamp, spacing, time.monotonic()))
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


class IgtlSource(_ThreadedSource):
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
            message.unpack(fields, body)
            if wanted_image:
                image, spacing = gray_frame(message.image, message.ijk_to_world_matrix)
        except Exception as exc:  # pyigtl raises anything from struct.error to TypeError on bad bodies
            raise ImageSourceError(f"{self.name}: bad {kind} message '{device}' ({exc})") from None
        if wanted_image:
            pairer.add_image(image, timestamp, spacing)
        else:
            pairer.add_pose(np.asarray(message.matrix, dtype=float), timestamp)


# --- OpenCV video -------------------------------------------------------------------------------


def to_gray(frame: np.ndarray) -> np.ndarray:
    """A uint8 gray image from an OpenCV frame (gray, BGR or BGRA)."""
    if frame.ndim == 2:
        return frame
    return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY if frame.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)


class VideoSource(_ThreadedSource):
    """An OpenCV VideoCapture: a frame grabber (device index, e.g. "0") or a video file, in gray.

    Device frames are stamped with the wall clock (time.time(), s) when read. File frames carry
    their position in the file (s) and are played at the file's frame rate, or ``rate_hz``; the end
    of the file is the end of the stream.
    """

    def __init__(self, device: str | int, rate_hz: float | None = None, buffer_frames: int = BUFFER_FRAMES):
        super().__init__(f"video:{device}", buffer_frames)
        self.device = str(device)
        self.is_device = self.device.isdigit()
        self.rate_hz = rate_hz

    def _start(self) -> cv2.VideoCapture:
        if not self.is_device and not Path(self.device).is_file():
            raise ImageSourceError(f"{self.name}: no such video file")
        capture = cv2.VideoCapture(int(self.device) if self.is_device else self.device)
        if not capture.isOpened():
            capture.release()
            what = "video device" if self.is_device else "file is not a readable video"
            raise ImageSourceError(f"{self.name}: cannot open the {what}")
        return capture

    def _release(self, capture: cv2.VideoCapture) -> None:
        capture.release()

    def _produce(self, capture: cv2.VideoCapture, stop: threading.Event, emit: Emit) -> None:
        fps = self.rate_hz or capture.get(cv2.CAP_PROP_FPS)
        if not fps > 0:
            fps = DEFAULT_RATE_HZ
        start = time.monotonic()
        n = 0
        while not stop.is_set():
            ok, frame = capture.read()
            if not ok:
                if self.is_device:
                    raise ImageSourceError(f"{self.name}: the device stopped giving frames (disconnected?)")
                return
            timestamp = time.time() if self.is_device else capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            emit(to_gray(frame), timestamp)
            n += 1
            if not self.is_device:
                stop.wait(max(0.0, start + n / fps - time.monotonic()))


# --- Recorded sessions --------------------------------------------------------------------------


def replay_times(records: list[FrameRecord], rate_hz: float | None) -> np.ndarray:
    """When (s after the first) to play each record: as recorded when ``rate_hz`` is None and every
    record has a timestamp in order, else at ``rate_hz`` (DEFAULT_RATE_HZ when None)."""
    stamps = [r.timestamp for r in records]
    if rate_hz is None and stamps and None not in stamps and np.all(np.diff(stamps) >= 0):
        return np.asarray(stamps, dtype=float) - stamps[0]
    return np.arange(len(records)) / (rate_hz or DEFAULT_RATE_HZ)


class ReplaySource(_ThreadedSource):
    """A recorded probecal session played back with its recorded poses, timestamps and spacing.

    Frames come at the recorded timing, or at ``rate_hz``; a frame without a recorded timestamp is
    stamped with its playback time (s after the first frame). The last frame ends the stream.
    """

    def __init__(
        self, session_path: str | Path, rate_hz: float | None = None, buffer_frames: int = BUFFER_FRAMES
    ):
        super().__init__(f"replay:{session_path}", buffer_frames)
        self.session_path = Path(session_path)
        self.rate_hz = rate_hz

    def _problem(self, exc: InputError) -> ImageSourceError:
        where = exc.problem if exc.path == self.session_path else str(exc)
        return ImageSourceError(f"{self.name}: {where}")

    def _start(self) -> Session:
        try:
            return load_session(self.session_path)
        except InputError as exc:
            raise self._problem(exc) from None

    def _produce(self, session: Session, stop: threading.Event, emit: Emit) -> None:
        times = replay_times(session.records, self.rate_hz)
        start = time.monotonic()
        for i, record in enumerate(session.records):
            if stop.wait(max(0.0, start + times[i] - time.monotonic())):
                return
            try:
                image = session.image(i)
            except InputError as exc:
                raise self._problem(exc) from None
            timestamp = record.timestamp if record.timestamp is not None else float(times[i])
            emit(image, timestamp, record.tool_to_base, record.pose_timestamp, session.pixel_spacing_mm)


# --- Command line -------------------------------------------------------------------------------


def parse_image_spec(text: str) -> ImageSource | None:
    """The source named on the command line: igtl:HOST:PORT, video:DEVICE_OR_FILE or
    replay:SESSION_DIR; None for "sim" (the simulator, handled by the caller)."""
    if text == "sim":
        return None
    kind, _, rest = text.partition(":")
    if kind == "igtl":
        host, _, port = rest.rpartition(":")
        if host and port.isdigit() and 0 < int(port) < 65536:
            return IgtlSource(host, int(port))
    elif kind == "video" and rest:
        return VideoSource(rest)
    elif kind == "replay" and rest:
        return ReplaySource(rest)
    raise InputError(
        None, f"bad image source {text!r}: expected sim, igtl:HOST:PORT, video:DEVICE_OR_FILE or replay:SESSION_DIR"
    )
