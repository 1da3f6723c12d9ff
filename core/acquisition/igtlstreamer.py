"""A stand-in for a PLUS server or 3D Slicer: streams tracked frames over OpenIGTLink, and can stall or
die mid-stream. It is the scanner side's simulator as ``probecal ursim`` is the robot's: the tests
and benchmarks of the OpenIGTLink image source and of the tracker play frames through it, and it
plays PLUS's own recordings as a PLUS server would send them (:func:`recording_batches`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Iterator

import numpy as np
from pyigtl.messages import MessageBase

from probecal.core.acquisition.igtl import (
    IMAGE_DEVICE,
    POLL_S,
    TOOL_DEVICE,
    IgtlServer,
    image_message,
    transform_message,
)
from probecal.core.acquisition.imagesource import SourceFrame
from probecal.core.io.sequence import TrackedSequence, oriented_mf


class IgtlStreamer:
    """Plays frames over OpenIGTLink like a PLUS server, for tests and benchmarks.

    Each frame goes out as ``frame_messages`` (IMAGE, then TRANSFORM ProbeToReference when it has
    a pose), to every client, without loss: a slow client slows the stream down. ``stall`` stops
    sending while connections stay open; ``kill`` closes every socket at once.
    """

    def __init__(self, port: int = 0, host: str = "127.0.0.1"):
        self._server = IgtlServer(port, host, STREAM_OUTBOX)
        self._running = threading.Event()
        self._running.set()
        self._stop = threading.Event()
        self._done = threading.Event()
        self.sent = 0

    @property
    def port(self) -> int:
        return self._server.port

    def play(
        self, frames: Iterable[SourceFrame], rate_hz: float | None = None, wait_for_client_s: float = 5.0
    ) -> None:
        """Start sending ``frames`` in a daemon thread once a client is connected (giving up after
        ``wait_for_client_s``), at ``rate_hz`` or, when None, as fast as the clients take them."""
        period = 1.0 / rate_hz if rate_hz else 0.0
        self.play_batches(((k * period, frame_messages(f)) for k, f in enumerate(frames)), wait_for_client_s)

    def play_batches(self, batches: Iterable[tuple[float, list[MessageBase]]], wait_for_client_s: float = 5.0,
                     clients: int = 1) -> None:
        """Start sending ``batches`` (each: when to send it, s after ``clients`` clients are
        connected, and its messages) in a daemon thread, every message to every client."""
        self._done.clear()
        args = (batches, wait_for_client_s, clients)
        threading.Thread(target=self._play, args=args, name="igtl-stream", daemon=True).start()

    def wait_done(self, timeout_s: float) -> bool:
        """True once the frames are all sent (or the stream was killed)."""
        return self._done.wait(timeout_s)

    def stall(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def kill(self) -> None:
        self._stop.set()
        self._server.close()

    close = kill

    def __enter__(self) -> IgtlStreamer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill()

    def _play(self, batches: Iterable[tuple[float, list[MessageBase]]], wait_for_client_s: float,
              clients: int) -> None:
        try:
            if not self._server.wait_for_client(wait_for_client_s, clients):
                return
            start = time.monotonic()
            for due, messages in batches:
                if self._stop.wait(max(0.0, start + due - time.monotonic())):
                    return
                while not self._running.wait(POLL_S):
                    if self._stop.is_set():
                        return
                self._server.send(*messages, block=True)
                self.sent += 1
        finally:
            self._done.set()


STREAM_OUTBOX = 32  # frames queued per client by the lossless streamer


def frame_messages(frame: SourceFrame) -> list[MessageBase]:
    """What a PLUS server sends for a tracked frame: the IMAGE (spacing in its ijk-to-world matrix,
    identity when unknown) then TRANSFORM ProbeToReference when the frame has a pose."""
    ijk_to_world = np.eye(4)
    if frame.pixel_spacing_mm is not None:
        ijk_to_world = np.diag([*frame.pixel_spacing_mm, 1.0, 1.0])
    messages: list[MessageBase] = [image_message(frame.image, ijk_to_world, frame.timestamp, IMAGE_DEVICE)]
    if frame.tool_to_base is not None:
        pose_time = frame.pose_timestamp if frame.pose_timestamp is not None else frame.timestamp
        messages.append(transform_message(frame.tool_to_base, pose_time, TOOL_DEVICE))
    return messages


PLUS_OK, PLUS_INVALID, PLUS_MISSING = "OK", "INVALID", "MISSING"
"""PLUS's TransformStatus of a tool seen, of one that is not, and of a marker out of the tracker's view."""


def recording_batches(sequence: TrackedSequence, start: float) -> Iterator[tuple[float, list[MessageBase]]]:
    """A PLUS recording as a PLUS server streams it: per frame the IMAGE (as PLUS holds it, MF, in
    pixels) and every transform the recording holds (``XToTracker``: device ``XToTracker`` with its
    TransformStatus), all stamped with the frame's time moved to start at ``start`` (s, this
    machine's clock), each batch due as long after the first as its frame came."""
    times = sequence.timestamps if sequence.timestamps is not None else np.arange(len(sequence)) / 10.0
    frames = oriented_mf(sequence.frames, sequence.fields.get("UltrasoundImageOrientation", "MF"))
    for k in range(len(sequence)):
        stamp = start + float(times[k] - times[0])
        messages: list[MessageBase] = [image_message(frames[k], np.eye(4), stamp, IMAGE_DEVICE)]
        for name, matrices in sequence.transforms.items():
            valid = bool(sequence.statuses.get(name, np.ones(len(sequence), bool))[k])
            matrix = matrices[k] if valid and np.all(np.isfinite(matrices[k])) else np.eye(4)
            messages.append(transform_message(matrix, stamp, name, PLUS_OK if valid else PLUS_INVALID))
        yield float(times[k] - times[0]), messages
