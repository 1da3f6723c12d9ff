"""Image sources for live acquisition, behind one small protocol.

- ``IgtlSource`` (``igtlsource``): OpenIGTLink IMAGE messages (and the tracker's TRANSFORM) from
  a PLUS server or 3D Slicer;
- ``VideoSource`` (``videosource``): an OpenCV frame grabber (device index) or a video file;
- ``ReplaySource`` (``videosource``): a recorded probecal session, at its recorded timing or a
  given rate.

This module holds the protocol and the buffered, threaded base they share; ``app.rigspec`` makes
one from the name the user gives it.

Each source fills a bounded buffer from a daemon thread. ``latest`` returns the newest frame
(skipping older ones); ``frames`` yields every frame after the last one returned, in order, and
raises rather than skip one when the reader falls behind the buffer. Images are uint8
(rows, columns): x = column, y = row. Timestamps are seconds on the source's clock; poses are
``tool_to_base`` 4x4 in mm; pixel spacing is (sx, sy) in mm.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from probecal.core.errors import DeviceError
from probecal.core.io.jsonio import PIXEL_SPACING_MM

BUFFER_FRAMES = 256  # about 130 MB of 820x616 frames, 8 s at 30 frames/s
POLL_S = 0.02  # socket time-out: how often a receive loop looks at its stop flag
JOIN_S = 2.0  # how long close() waits for a producer thread
DEFAULT_RATE_HZ = 30.0  # playback rate of a video file or session that does not give one
MAX_RATE_HZ = 1000.0
"""The most frames a second a source may send (the simulated scanner's frame rate is bound so too):
beyond, it floods, and is named so."""


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

    def __exit__(self, *exc: object) -> None:
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
        self._arrivals: deque[float] = deque(maxlen=capacity)  # monotonic times of the latest puts

    def put(self, frame: SourceFrame) -> None:
        with self._cond:
            self._arrivals.append(time.monotonic())
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
                rate = (len(self._arrivals) - 1) / max(self._arrivals[-1] - self._arrivals[0], 1e-9)
                flood = ": flooded, more than any scanner sends" if rate > MAX_RATE_HZ else ""
                raise ImageSourceError(
                    f"{self._name}: {dropped} frames dropped: the reader fell behind the stream "
                    f"({rate:.0f} frames/s) by more than {self._capacity} frames{flood}"
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


class StreamFormat:
    """What every frame of a live stream must keep, checked as it arrives with the rules the
    readers apply: a grey 8- or 16-bit image, the first frame's size, a stated pixel spacing within
    the bounds a session holds (``core.io.jsonio.PIXEL_SPACING_MM``) and the first one stated,
    and at most MAX_RATE_HZ frames a second. A frame that breaks one ends the stream with that
    reason: a sweep then stops there, its frames kept, to be resumed once the source is fixed."""

    def __init__(self, name: str):
        self.name = name
        self.size: tuple[int, int] | None = None
        self.spacing: tuple[float, float] | None = None
        self._arrivals: deque[float] = deque()

    def check(self, frame: SourceFrame) -> None:
        image, what = frame.image, f"{self.name}: frame {frame.index}"
        if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
            raise ImageSourceError(f"{what} is not a grey 8- or 16-bit image ({image.dtype}, {image.shape})")
        size = (image.shape[1], image.shape[0])
        if self.size is not None and size != self.size:
            raise ImageSourceError(f"{what} is {size[0]}x{size[1]} px, the stream's frames {self.size[0]}x"
                                   f"{self.size[1]}: the scanner's settings changed")
        self.size = size
        if frame.pixel_spacing_mm is not None:
            self._check_spacing(frame.pixel_spacing_mm, what)
        self._check_rate()

    def _check_spacing(self, spacing: tuple[float, float], what: str) -> None:
        low, high = PIXEL_SPACING_MM
        sx, sy = spacing
        if not (low <= sx <= high and low <= sy <= high):
            raise ImageSourceError(f"{what} states a pixel spacing of {sx:g} x {sy:g} mm, not two pixel sizes "
                                   f"within [{low:g}, {high:g}] mm")
        if self.spacing is not None and not np.allclose(spacing, self.spacing, rtol=1e-6):
            raise ImageSourceError(f"{what} states a pixel spacing of {sx:g} x {sy:g} mm, the stream's frames "
                                   f"{self.spacing[0]:g} x {self.spacing[1]:g} mm: the scanner's settings changed")
        self.spacing = spacing

    def _check_rate(self) -> None:
        now = time.monotonic()
        self._arrivals.append(now)
        while self._arrivals[0] < now - 1.0:
            self._arrivals.popleft()
        if len(self._arrivals) > MAX_RATE_HZ:
            raise ImageSourceError(f"{self.name}: flooded: more than {MAX_RATE_HZ:g} frames in a second, more than "
                                   "any scanner sends")


class ThreadedSource(ImageSource):
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
        stream = StreamFormat(self.name)

        def emit(image: np.ndarray, timestamp: float, tool_to_base: np.ndarray | None = None,
                 pose_timestamp: float | None = None, pixel_spacing_mm: tuple[float, float] | None = None) -> None:
            nonlocal count
            frame = SourceFrame(image, timestamp, count, tool_to_base, pose_timestamp, pixel_spacing_mm)
            stream.check(frame)
            buffer.put(frame)
            count += 1

        try:
            self._produce(handle, stop, emit)
            buffer.end()
        except ImageSourceError as exc:
            buffer.end(str(exc))
        finally:
            buffer.end(f"{self.name}: the image thread stopped unexpectedly")
            self._release(handle)
