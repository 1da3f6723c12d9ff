"""Frames from an OpenCV frame grabber or video file (``VideoSource``) and from a recorded probecal
session played back with its poses and timing (``ReplaySource``)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np

from probecal.core.acquisition.imagesource import (
    BUFFER_FRAMES,
    DEFAULT_RATE_HZ,
    Emit,
    ImageSourceError,
    ThreadedSource,
)
from probecal.core.errors import InputError
from probecal.core.io.session import FrameRecord, Session, load_session


def to_gray(frame: np.ndarray) -> np.ndarray:
    """A uint8 gray image from an OpenCV frame (gray, BGR or BGRA)."""
    if frame.ndim == 2:
        return frame
    return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY if frame.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)


class VideoSource(ThreadedSource):
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


def replay_times(records: list[FrameRecord], rate_hz: float | None) -> np.ndarray:
    """When (s after the first) to play each record: as recorded when ``rate_hz`` is None and every
    record has a timestamp in order, else at ``rate_hz`` (DEFAULT_RATE_HZ when None)."""
    stamps = [r.timestamp for r in records if r.timestamp is not None]
    if rate_hz is None and stamps and len(stamps) == len(records) and np.all(np.diff(stamps) >= 0):
        return np.asarray(stamps, dtype=float) - stamps[0]
    return np.arange(len(records)) / (rate_hz or DEFAULT_RATE_HZ)


class ReplaySource(ThreadedSource):
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
