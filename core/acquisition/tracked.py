"""Recording a tracked probe that probecal does not move: frames from any image source, each paired
with the pose the tracker (:mod:`core.acquisition.tracker`) reported at its time, into a session
that keeps the tracker's pose stream, as a robot's continuous sweep does. ``probecal calibrate``
then measures the image latency on the frames and pairs them again.

Frames from the tracker's own server (a PLUS server sends both) are stamped by the tracker's clock,
and the tracker then keeps that clock for its poses (``IgtlTracker.device_clock``); other sources
stamp their frames on this machine's clock, as the tracker maps its poses, and the latency
measured absorbs what is left. While the tracker is paused (a
marker out of view, no poses) frames are refused with the reason, and recording goes on when it
comes back. The first pose a session's reader would refuse ends the recording
(:class:`~probecal.core.acquisition.tracker.BadTrackerData`); every frame recorded stays on disk
whatever ends it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from probecal.core.acquisition.imagesource import ImageSource, ImageSourceError, SourceFrame
from probecal.core.acquisition.pairing import FramePairer, Refusal
from probecal.core.acquisition.tracker import BadTrackerData, IgtlTracker, TrackerError
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.manifest import CONTINUOUS, Manifest, matrix_of
from probecal.core.io.session import SessionWriter

TRACKED = "tracked"
"""The kind of source a tracked session names in its manifest (``source.kind``)."""
POSE_KEEP_S = 0.25
"""How often (s) the pose stream is written into the session."""
PAIR_WAIT_S = 0.5
"""How long a frame waits for the tracker's stream to reach its time (s)."""
REFUSALS_HELD = 100
"""The refusals an outcome holds (the first ones; it counts them all): a recording refused at
every frame for hours holds no more."""


@dataclass(frozen=True)
class TrackedSetup:
    """What a tracked recording knows besides its streams: the phantom and, when it is registered
    to the tracked reference, its pose ``phantom_to_base`` (None: solved by the calibration);
    PLUS's segmentation settings; the scanner's nominal spacing (mm/px) and its first row's depth
    (mm); ``plus_frames`` when the frames come as PLUS holds them (MF), labelled by PLUS's
    convention."""

    phantom: Phantom | None = None
    phantom_to_base: np.ndarray | None = None
    segmentation_hints: dict[str, str] | None = None
    spacing_mm: tuple[float, float] | None = None
    start_depth_mm: float | None = None
    plus_frames: bool = False


def setup_from_device_set(path: str | Path) -> TrackedSetup:
    """A PLUS device set's phantom, its registered pose PhantomToReference and its segmentation
    settings; InputError naming the file when it defines no phantom."""
    config = read_device_set(path)
    if config.phantom is None:
        raise InputError(path, "defines no N-wire phantom (PhantomDefinition)")
    return TrackedSetup(config.phantom, config.rigid_transform("Phantom", "Reference"),
                        dict(config.segmentation.attributes) if config.segmentation else None, plus_frames=True)


@dataclass
class TrackedOutcome:
    """How a tracked recording went: frames recorded, refused (how many, and the first
    ``REFUSALS_HELD`` with their reasons) and why it ended (None: it took every frame asked for,
    or was stopped)."""

    recorded: int = 0
    refused: int = 0
    refusals: list[Refusal] = field(default_factory=list)
    error: str | None = None
    stopped: bool = False
    bad_input: bool = False  # the error is the tracker's data, not a stream that ended or broke

    def refuse(self, refusal: Refusal) -> None:
        """Count a frame refused, and hold it while fewer than ``REFUSALS_HELD`` are."""
        self.refused += 1
        if len(self.refusals) < REFUSALS_HELD:
            self.refusals.append(refusal)


def tracked_manifest(tracker: IgtlTracker, source: ImageSource, kind: str, setup: TrackedSetup,
                     first: SourceFrame) -> Manifest:
    """The manifest of a tracked session of ``kind``: its kind of source and the set-up; the
    ``first`` frame gives the image's size (and its spacing, when the set-up has none)."""
    return Manifest(
        kind=kind, motion=CONTINUOUS,
        source={"kind": TRACKED, "tracker": tracker.name, "devices": list(tracker.devices.names), "image": source.name},
        image_size=(first.image.shape[1], first.image.shape[0]),
        image_orientation_in_file="MF" if setup.plus_frames else None,
        pixel_spacing_mm=setup.spacing_mm or first.pixel_spacing_mm, start_depth_mm=setup.start_depth_mm,
        phantom_to_base=None if setup.phantom_to_base is None else matrix_of(setup.phantom_to_base),
        segmentation_hints=setup.segmentation_hints)


@dataclass
class TrackedRecording:
    """Every frame of ``source`` paired with ``tracker``'s pose, recorded into a new session at
    ``path`` of ``kind`` (calibration, volume). ``stop`` ends it from another thread."""

    tracker: IgtlTracker
    source: ImageSource
    path: Path
    kind: str = "calibration"
    setup: TrackedSetup = TrackedSetup()
    show: Callable[[SourceFrame, np.ndarray | None, str], None] | None = None
    halt: threading.Event = field(default_factory=threading.Event)
    writer: SessionWriter | None = field(init=False, default=None)
    _kept: float = field(init=False, default=-np.inf)

    def stop(self) -> None:
        self.halt.set()

    def run(self, frames: int | None = None, timeout_s: float = 2.0) -> TrackedOutcome:
        """Record until ``frames`` frames were taken (recorded or refused; None: no limit), the
        stream ends or fails, or :meth:`stop`."""
        outcome = TrackedOutcome()
        pairer = FramePairer(self.tracker)
        try:
            for frame in self.source.frames(timeout_s):
                if self.halt.is_set():
                    outcome.stopped = True
                    break
                self._take(frame, pairer, outcome)
                if frames is not None and outcome.recorded + outcome.refused >= frames:
                    break
            else:
                outcome.error = f"{self.source.name}: end of stream"
        except BadTrackerData as exc:
            outcome.error, outcome.bad_input = str(exc), True
        except (TrackerError, ImageSourceError, OSError) as exc:
            outcome.error = str(exc)
        finally:
            if self.writer is not None:
                self._keep_poses(pairer)
                self.writer.close()
        return outcome

    def _take(self, frame: SourceFrame, pairer: FramePairer, outcome: TrackedOutcome) -> None:
        paused = self.tracker.paused  # raises once the tracker's stream has ended
        pose: np.ndarray | None = None
        if paused is not None:
            reason = f"paused: {paused}"
        else:
            paired = pairer.pair(frame.timestamp, wait_s=PAIR_WAIT_S)
            pose, reason = paired.tool_to_base, paired.reason
        writer = self._writer(frame)
        if pose is None:
            refusal = Refusal(frame.index, frame.timestamp, reason)
            outcome.refuse(refusal)
            writer.refuse(refusal.to_json())
        else:
            writer.append(frame.image, pose, timestamp=frame.timestamp, pose_timestamp=frame.timestamp,
                          source_index=frame.index)
            outcome.recorded += 1
        if (pairer.poses.newest or -np.inf) - self._kept >= POSE_KEEP_S:
            self._keep_poses(pairer)
        if self.show is not None:
            self.show(frame, pose, reason)

    def _writer(self, frame: SourceFrame) -> SessionWriter:
        """The session's writer, made at the first frame, which gives the frames' size."""
        if self.writer is None:
            manifest = tracked_manifest(self.tracker, self.source, self.kind, self.setup, frame)
            self.writer = SessionWriter(self.path, manifest, self.setup.phantom)
        return self.writer

    def _keep_poses(self, pairer: FramePairer) -> None:
        """Write the tracker's poses fetched since the last written into the session."""
        assert self.writer is not None
        pairer.fetch(time.time() - 1.0)
        samples = pairer.poses.since(self._kept)
        self.writer.append_poses(samples.timestamps, samples.tool_to_base)
        if len(samples):
            self._kept = float(samples.timestamps[-1])
