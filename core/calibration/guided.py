"""Guided acquisition: a calibration recorded from a probe that probecal does not move (held by
hand, or by a robot that only reports its pose), frame by frame as the stream brings them.

It runs in two phases, each frame segmented as it comes:

1. *latency*: the person moves the probe up and down over the wires. Every frame is recorded
   (``phase`` "temporal"), and the image latency is measured on them against the pose stream, as
   for a robot's continuous sweep (:func:`~probecal.core.calibration.latency.session_latency`).
2. *guided*: frames are kept only where the probe holds still enough for that latency, at most
   one per ``keep_every_s``. Each kept frame is recorded and counts toward the targets it
   reaches (:mod:`core.acquisition.guidance`). The corner bound is measured again as frames
   accumulate (:meth:`GuidedAcquisition.measure_bound`, a full calibration, slow: the caller runs
   it beside the stream). The acquisition has *enough* once the bound lies within the tolerance.

The session keeps its pose stream, so ``probecal calibrate`` measures the latency and pairs the
frames again as it does for any continuous sweep. Poses are ``tool_to_base`` (mm): the probe in
the tracked reference's frame; times in s on this machine's clock.

A live run (:class:`GuidedRun`) waits while the tracker is paused (a marker out of view), and ends
at the first thing a session's reader would refuse from it, keeping every frame recorded before:
a tracker does not come back from sending what is not a pose. An image that cannot show every
wire at the guided poses is refused before any session is made (:func:`first_targets`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.guidance import GUIDE_RANGES, TARGETS, Coverage, facing, guide_targets, offsets_of
from probecal.core.acquisition.imagesource import ImageSource, SourceFrame
from probecal.core.acquisition.pairing import FramePairer
from probecal.core.acquisition.plan import PoseRanges
from probecal.core.acquisition.tracker import BadTrackerData
from probecal.core.calibration.latency import TEMPORAL_PHASE, session_latency
from probecal.core.calibration.register import refine_with_depth_scale, register_frame
from probecal.core.calibration.segment import FrameResult, Segmenter
from probecal.core.calibration.solve import CalibrationReport, calibrate_session
from probecal.core.errors import DeviceError, InputError
from probecal.core.geometry.probe import image_mm_from_pixels
from probecal.core.geometry.setup import Setup
from probecal.core.io.session import SessionWriter, load_session
from probecal.core.temporal.lag import LatencyEstimate

GUIDED_PHASE = "guided"
LATENCY_EVERY_S = 1.0
"""How often (s of frames) the latency is measured again while the probe moves up and down."""
LATENCY_FIRST_S = 5.0
"""The latency is first measured after this much motion (s of frames)."""
LATENCY_SE_S = 0.005
"""The latency phase ends once the latency's standard error is within this (s)."""
SPEED_FIT_S = 0.15
"""The probe's speed at a frame is fitted over the pose stream this long (s) either side of it."""
IMAGE_TIMEOUT_S = 10.0
"""A guided run ends when no image comes for this long (s): a person may pause, and the bound's
calibration shares the machine with the stream."""
TARGET_PATIENCE_S = 20.0
"""A target shown this long (s) without being reached is given up: another is shown instead."""
POSE_KEEP_S = 0.25
"""How often (s) the pose stream is written into the session."""


@dataclass(frozen=True)
class GuideSettings:
    """How a guided acquisition keeps frames and when it has enough.

    ``tolerance_mm``: "enough" when the image corners' 95 % bound is within it (the calibration
    verdict's tolerance); ``steady_mm``: the most the probe may move within the latency's
    uncertainty (translation plus turn times ``lever_mm``, the reach from the tracked marker to
    the image); ``keep_every_s``: at most one kept frame per this while the probe is held.
    """

    tolerance_mm: float = 1.0
    steady_mm: float = 0.1
    lever_mm: float = 150.0
    keep_every_s: float = 0.2
    targets: int = TARGETS
    ranges: PoseRanges = GUIDE_RANGES
    first_bound: int = 60  # kept frames before the bound is first measured
    bound_every: int = 40  # kept frames between measurements
    solve_phantom_pose: bool = True
    pose_wait_s: float = 0.1  # how long a frame waits for the pose stream to reach its time
    seed: int = 0


def first_targets(setup: Setup, settings: GuideSettings) -> np.ndarray:
    """The first round of targets (n, 6 plan offsets) for ``setup``'s image; InputError naming
    the image's size when too few poses keep every wire of the phantom in view (frames too small,
    or a spacing too fine, for the phantom)."""
    try:
        return guide_targets(setup, settings.targets, settings.ranges, settings.seed)
    except ValueError as exc:
        probe = setup.probe
        width, depth = probe.width_px * probe.nominal_spacing_mm[0], probe.height_px * probe.nominal_spacing_mm[1]
        raise InputError(None, f"frames of {probe.width_px} x {probe.height_px} px ({width:.3g} x {depth:.3g} mm) "
                               f"are too small to guide over the phantom: {exc}") from None


@dataclass(frozen=True)
class GuideStep:
    """What one frame did: its live segmentation, its pose as its dots place it (plan offsets,
    None without a pattern), and whether it was recorded (``index``) or why not."""

    frame: SourceFrame
    result: FrameResult
    offsets: np.ndarray | None
    tool_to_base: np.ndarray | None
    index: int | None
    why: str = ""


@dataclass
class GuidedAcquisition:
    """One guided acquisition into ``writer``'s session (see the module's docstring).

    ``setup`` gives the phantom, the probe's image and the centre pose the targets are placed
    about; ``pairer`` the pose source's stream. Not thread-safe but for :meth:`measure_bound`,
    which may run beside :meth:`take`.
    """

    writer: SessionWriter
    setup: Setup
    segmenter: Segmenter
    pairer: FramePairer
    settings: GuideSettings = GuideSettings()
    phase: str = field(init=False, default=TEMPORAL_PHASE)
    latency: LatencyEstimate | None = field(init=False, default=None)
    latency_problem: str = field(init=False, default="")
    coverage: Coverage = field(init=False)
    bound: CalibrationReport | None = field(init=False, default=None)
    bound_problem: str = field(init=False, default="")
    results: list[FrameResult] = field(init=False, default_factory=list)  # by session index
    kept: int = field(init=False, default=0)
    showing: np.ndarray | None = field(init=False, default=None)  # the target shown after the newest frame
    _last_kept: float = field(init=False, default=-np.inf)
    _last_latency: float = field(init=False, default=-np.inf)
    _first_frame: float | None = field(init=False, default=None)
    _measured_at: int = field(init=False, default=0)
    _kept_poses: float = field(init=False, default=-np.inf)
    _facing: Setup | None = field(init=False, default=None)
    _shown: tuple[int, float] | None = field(init=False, default=None)  # the target shown, and since when (s)
    _now: float = field(init=False, default=0.0)  # the newest frame's time (s)
    _lock: threading.Lock = field(init=False, default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self.coverage = Coverage(first_targets(self.setup, self.settings), self.settings.ranges)

    @property
    def centre(self) -> Setup:
        """The set-up whose centre pose the offsets (targets and readings) are taken from: turned
        the way round the person holds the probe, once a frame has shown it."""
        return self._facing or self.setup

    @property
    def enough(self) -> bool:
        """Whether the bound lies within the tolerance."""
        return self.bound_mm is not None and self.bound_mm <= self.settings.tolerance_mm

    @property
    def bound_mm(self) -> float | None:
        """The image corners' 95 % bound (mm) last measured; None before."""
        if self.bound is None:
            return None
        bound = self.bound.calibration.metrics["corner_error_95_mm"]
        return None if bound is None else float(bound)

    def target(self, offsets: np.ndarray | None) -> int:
        """The target to show next to a probe at ``offsets``: the nearest neither reached nor
        shown for ``TARGET_PATIENCE_S`` in vain, from a new round of targets once none is left."""
        shown = self._shown
        if shown is not None and not self.coverage.reached[shown[0]] and self._now - shown[1] > TARGET_PATIENCE_S:
            self.coverage.give_up(shown[0])
        k = self.coverage.next_target(offsets)
        if k is None:
            self.coverage.extend(self._next_round())
            k = self.coverage.next_target(offsets)
            assert k is not None
        if shown is None or shown[0] != k:
            self._shown = (k, self._now)
        return k

    def _next_round(self) -> np.ndarray:
        """A new round of targets; the first round's again when too few new ones keep every wire
        in view (an image that barely shows them all)."""
        s = self.settings
        rng = np.random.default_rng([s.seed, self.coverage.round + 1])
        try:
            return guide_targets(self.setup, s.targets, s.ranges, rng)
        except ValueError:
            return self.coverage.targets[self.coverage.rounds == 0]

    def take(self, frame: SourceFrame) -> GuideStep:
        """Segment a frame, pair it with its pose and record it when its phase keeps it."""
        self._now = frame.timestamp
        result = self.segmenter(frame.image, frame.index)
        offsets = self._offsets(result)
        paired = self.pairer.pair(frame.timestamp, wait_s=self.settings.pose_wait_s)
        if (self.pairer.poses.newest or -np.inf) - self._kept_poses >= POSE_KEEP_S:
            with self._lock:
                self._write_poses()
        if self.phase == GUIDED_PHASE:
            k = self.target(offsets)  # before the targets are read: it may set a new round
            self.showing = self.coverage.targets[k]
        pose = paired.tool_to_base
        if pose is None:
            return GuideStep(frame, result, offsets, None, None, f"no pose: {paired.reason}")
        if self.phase == TEMPORAL_PHASE:
            return self._moving(frame, result, offsets, pose, paired.pose_timestamp)
        why = self._unkept(frame, result, paired.pose_timestamp)
        if why:
            return GuideStep(frame, result, offsets, pose, None, why)
        index = self._record(frame, result, pose, paired.pose_timestamp, GUIDED_PHASE)
        self._last_kept = frame.timestamp
        self.kept += 1
        if offsets is not None:
            self.coverage.add(offsets)
        return GuideStep(frame, result, offsets, pose, index)

    def _offsets(self, result: FrameResult) -> np.ndarray | None:
        """The frame's pose as plan offsets, from its own dots (None without a pattern)."""
        if not result.found or result.markers is None:
            return None
        spacing = self.segmenter.spacing_mm
        registration = register_frame(self.setup.phantom, result.markers, spacing)
        if registration is None:
            return None
        wires = registration.wire_indices
        # the depth scale fitted too: the nominal spacing's error would read as a tilt
        image_to_phantom, _ = refine_with_depth_scale(self.setup.phantom, registration.image_to_phantom,
                                                      image_mm_from_pixels(result.markers, spacing)[wires], wires)
        if self._facing is None:  # the way round the person holds the probe, from the first frame seen
            self._facing = facing(self.setup, image_to_phantom)
        return offsets_of(self._facing, image_to_phantom)

    def _moving(self, frame: SourceFrame, result: FrameResult, offsets: np.ndarray | None, pose: np.ndarray,
                pose_timestamp: float) -> GuideStep:
        """The latency phase: record every frame; measure the latency once a second of frames."""
        index = self._record(frame, result, pose, pose_timestamp, TEMPORAL_PHASE)
        if self._first_frame is None:
            self._first_frame = frame.timestamp
        elapsed = frame.timestamp - self._first_frame
        if elapsed >= LATENCY_FIRST_S and frame.timestamp - self._last_latency >= LATENCY_EVERY_S:
            self._last_latency = frame.timestamp
            self._measure_latency()
        return GuideStep(frame, result, offsets, pose, index)

    def _measure_latency(self) -> None:
        with self._lock:
            self._write_poses()
            session = load_session(self.writer.path, check_frames=False)
        try:
            latency = session_latency(session, self.results)
        except InputError as exc:
            self.latency_problem = exc.problem
            return
        self.latency, self.latency_problem = latency, ""
        if latency.std_error_s <= LATENCY_SE_S:
            self.pairer.latency_s = latency.image_latency_s
            self.phase = GUIDED_PHASE

    def _unkept(self, frame: SourceFrame, result: FrameResult, pose_timestamp: float) -> str:
        """Why a guided frame is not kept ("" when it is)."""
        if not result.found:
            return f"no pattern ({result.reason})"
        if frame.timestamp - self._last_kept < self.settings.keep_every_s:
            return f"held: one frame per {self.settings.keep_every_s:g} s"
        moved = self._moved_mm(pose_timestamp)
        if moved is None or moved > self.settings.steady_mm:
            return "moving" if moved is None else f"moving ({moved:.2f} mm within the latency's uncertainty)"
        return ""

    def _moved_mm(self, t: float) -> float | None:
        """How far the probe moved (mm: translation plus turn times the lever) within the latency's
        uncertainty either side of ``t``, at its speed fitted over the pose stream around ``t``
        (a line through ``SPEED_FIT_S`` of poses each side, so that the tracker's noise on each
        pose averages out); None where the stream does not tell."""
        assert self.latency is not None
        window = max(3 * self.latency.std_error_s, 0.01)
        samples = self.pairer.poses.since(t - SPEED_FIT_S)
        near = samples.timestamps <= t + SPEED_FIT_S
        times, poses = samples.timestamps[near], samples.tool_to_base[near]
        if len(times) < 3 or np.ptp(times) < SPEED_FIT_S:
            return None
        middle = poses[len(poses) // 2]
        turns = Rotation.from_matrix(poses[:, :3, :3] @ middle[:3, :3].T).as_rotvec()
        (velocity, _), *_ = np.linalg.lstsq(np.column_stack([times - t, np.ones(len(times))]),
                                            np.column_stack([poses[:, :3, 3], turns]), rcond=None)
        speed = np.linalg.norm(velocity[:3]) + np.linalg.norm(velocity[3:]) * self.settings.lever_mm
        return float(speed * 2 * window)

    def _record(self, frame: SourceFrame, result: FrameResult, pose: np.ndarray, pose_timestamp: float,
                phase: str) -> int:
        with self._lock:
            index = self.writer.append(frame.image, pose, timestamp=frame.timestamp, pose_timestamp=pose_timestamp,
                                       source_index=frame.index, phase=phase)
            self.results.append(replace(result, index=index))
        return index

    def keep_poses(self) -> None:
        """Write the pose stream fetched so far into the session: at the end, so that it reaches
        the last frame recorded."""
        with self._lock:
            self._write_poses()

    def _write_poses(self) -> None:
        """Write the pose stream fetched since it was last written into the session (under the lock)."""
        samples = self.pairer.poses.since(self._kept_poses)
        if len(samples):
            self.writer.append_poses(samples.timestamps, samples.tool_to_base)
            self._kept_poses = float(samples.timestamps[-1])

    def bound_due(self) -> bool:
        """Whether enough frames were kept since the bound was last measured."""
        if self.phase != GUIDED_PHASE:
            return False
        first = self._measured_at == 0
        return self.kept >= (self.settings.first_bound if first else self._measured_at + self.settings.bound_every)

    def measure_bound(self) -> float | None:
        """Calibrate on the frames recorded so far and keep the corner bound (mm); None, with
        ``bound_problem`` saying why, when they calibrate nothing yet."""
        with self._lock:
            self._write_poses()
            session = load_session(self.writer.path, check_frames=False)
            results = list(self.results)
        self._measured_at = self.kept
        try:
            self.bound = calibrate_session(session, results, solve_phantom_pose=self.settings.solve_phantom_pose)
        except InputError as exc:
            self.bound_problem = exc.problem
            return None
        self.bound_problem = ""
        return self.bound_mm


@dataclass
class GuidedOutcome:
    """How a guided run ended: with enough, stopped, or with ``error`` (the stream or the tracker;
    ``bad_input`` when the tracker sent what no session may record)."""

    enough: bool = False
    stopped: bool = False
    error: str | None = None
    bad_input: bool = False


@dataclass
class GuidedRun:
    """A guided acquisition fed by a live stream: each frame taken as it comes unless the pose
    source is ``paused``, the bound measured again in a worker thread whenever due, until enough,
    :meth:`stop`, or the stream or the pose source ends (``paused`` raises DeviceError then)."""

    acquisition: GuidedAcquisition
    source: ImageSource
    paused: Callable[[], str | None]
    show: Callable[[GuideStep | str], None] | None = None
    halt: threading.Event = field(default_factory=threading.Event)
    _worker: threading.Thread | None = field(init=False, default=None)

    def stop(self) -> None:
        self.halt.set()

    def run(self, timeout_s: float = IMAGE_TIMEOUT_S) -> GuidedOutcome:
        outcome = GuidedOutcome()
        try:
            for frame in self.source.frames(timeout_s):
                if self.halt.is_set():
                    outcome.stopped = True
                    break
                self._take(frame)
                if self.acquisition.enough:
                    outcome.enough = True
                    break
            else:
                outcome.error = f"{self.source.name}: end of stream"
        except BadTrackerData as exc:
            outcome.error, outcome.bad_input = str(exc), True
        except (DeviceError, OSError) as exc:
            outcome.error = str(exc)
        finally:
            if self._worker is not None:
                self._worker.join()
        try:
            self.acquisition.keep_poses()
        except OSError as exc:  # a full disk: the frames recorded stay, with the stream written before
            outcome.error = outcome.error or str(exc)
        return outcome

    def _take(self, frame: SourceFrame) -> None:
        paused = self.paused()
        if paused is not None:
            if self.show is not None:
                self.show(paused)
            return
        step = self.acquisition.take(frame)
        if self.show is not None:
            self.show(step)
        if self.acquisition.bound_due() and (self._worker is None or not self._worker.is_alive()):
            self._worker = threading.Thread(target=self.acquisition.measure_bound, name="guided-bound", daemon=True)
            self._worker.start()
