"""Acquisition (design §1 step 2, §7): drive a robot through a plan, record one frame at every
settled pose into a session, and stream live frames while it moves.

A sweep ends when the plan is done, when it is stopped, or when the robot or the image stream
fails, or sends what a session's reader would refuse (``RefusedRecord``); every frame recorded so
far is on disk either way, and reads back. The plan is stored in the session
(``plan.json``) and every record names its pose in the plan, so :func:`resume_sweep` picks up an
interrupted sweep where it ended, in the same session.

Poses are flange poses ``tool_to_base`` (4x4, mm); times are seconds since the epoch.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Collection, Generator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from probecal.core.acquisition.imagesource import ImageSource, ImageSourceError, SourceFrame
from probecal.core.acquisition.pairing import FETCH_S, LOOKBACK_S, FramePairer, Refusal
from probecal.core.acquisition.plan import Leg, SweepPlan, leg_durations_s, pose_durations_s
from probecal.core.errors import InputError
from probecal.core.io.files import no_space, write_atomic
from probecal.core.io.jsonio import to_json_text, write_json
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import MANIFEST, REFUSED, RefusedRecord, SessionWriter, load_session, read_manifest
from probecal.core.robot.contract import Robot, RobotError
from probecal.core.robot.ur3 import MotionLimits, Unreachable
from probecal.core.twin.scanner import TwinScanner, json_from_markers

PLAN_FILE = "plan.json"
LIVE_HZ = 20.0

ENDS_A_SWEEP = (RobotError, ImageSourceError, OSError, RefusedRecord)
"""What ends a sweep early, keeping what it recorded: the robot or the images failed, or sent what
the session's reader would refuse."""


@dataclass(frozen=True)
class Grab:
    """A frame taken at a settled pose, with the pose paired with it and both timestamps."""

    image: np.ndarray
    tool_to_base: np.ndarray
    timestamp: float
    pose_timestamp: float
    truth_markers: np.ndarray | None = None  # the twin's true marker pixels (calibration frames)


class Grabber(Protocol):
    """Where frames come from during a sweep."""

    refused: list[Refusal]  # frames that could not be recorded, each with its reason

    @property
    def name(self) -> str:
        """The frame source's name."""

    def live(self, robot: Robot) -> tuple[np.ndarray, np.ndarray] | None:
        """A frame to show while the robot moves and the flange pose it goes with (None:
        nothing new)."""

    def grab(self, robot: Robot) -> Grab:
        """A frame at the robot's settled pose. Raises ImageSourceError when none comes."""

    def stream(self, robot: Robot) -> Generator[tuple[SourceFrame, np.ndarray | None], None, None]:
        """Every frame of the stream while the robot moves, each with the twin's true marker
        pixels when it knows them; raises ImageSourceError when the stream stalls or fails."""


@dataclass
class TwinGrabber:
    """The twin's scanner imaging where the flange is when the robot reports a pose (calibration
    or volume); frames are stamped as late as the twin's scanner runs."""

    scanner: TwinScanner
    kind: str
    seed: int = 0
    name: str = "sim"
    frame_rate_hz: float = 25.0  # its frame rate in a continuous sweep
    refused: list[Refusal] = field(default_factory=list)  # the twin images every pose it is asked for
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed + 1)

    def _image(self, robot: Robot, reported: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        tool_to_base = self.scanner.twin.actual_tool_to_base(reported, robot.joints())
        if self.kind == "calibration":
            return self.scanner.calibration_frame(tool_to_base, self.rng)
        return self.scanner.volume_frame(tool_to_base, self.rng), None

    def live(self, robot: Robot) -> tuple[np.ndarray, np.ndarray]:
        pose = robot.tool_to_base()
        return self._image(robot, pose)[0], pose

    def grab(self, robot: Robot) -> Grab:
        pose = robot.tool_to_base()
        now = time.time()
        image, markers = self._image(robot, pose)
        return Grab(image, pose, now + self.scanner.image_delay_s(self.rng), now, markers)

    def stream(self, robot: Robot) -> Generator[tuple[SourceFrame, np.ndarray | None], None, None]:
        """Frames at ``frame_rate_hz`` (wall clock), each imaged where the flange is at that
        instant and stamped as late as the twin's scanner runs: the pose it goes with is the pose
        stream's, as for any scanner."""
        period, index = 1.0 / self.frame_rate_hz, 0
        due = time.monotonic()
        while True:
            time.sleep(max(0.0, due - time.monotonic()))
            due = max(due + period, time.monotonic())
            now = time.time()
            image, markers = self._image(robot, robot.tool_to_base())
            yield SourceFrame(image, now + self.scanner.image_delay_s(self.rng), index), markers
            index += 1


@dataclass
class SourceGrabber:
    """A live image source (OpenIGTLink, frame grabber, replay) paired with the robot's pose.

    Each frame is paired with the pose in the robot's own pose stream at the frame's timestamp
    minus ``latency_s`` (the image path's delay, plus any offset of the source's clock). After the
    robot settles the sweep takes the first frame that shows the settled pose; a frame that cannot
    be paired is refused, counted in ``refused`` with its reason, and the next one is tried. A
    source that tracks the probe itself (a PLUS server's ProbeToReference) gives the pose with
    the frame.
    """

    source: ImageSource
    latency_s: float = 0.0
    timeout_s: float = 2.0
    refused: list[Refusal] = field(default_factory=list)
    pairer: FramePairer | None = field(init=False, default=None)

    @property
    def name(self) -> str:
        return self.source.name

    def live(self, robot: Robot) -> tuple[np.ndarray, np.ndarray] | None:
        try:
            frame = self.source.latest(1.0 / LIVE_HZ)
        except ImageSourceError:
            return None  # nothing new within a live period; a real stall shows in grab()
        return frame.image, frame.tool_to_base if frame.tool_to_base is not None else robot.tool_to_base()

    def grab(self, robot: Robot) -> Grab:
        if self.pairer is None:
            self.pairer = FramePairer(robot, self.latency_s)
        settled = time.time()
        deadline = time.monotonic() + self.timeout_s
        early: tuple[SourceFrame, float] | None = None  # the last frame imaged before the robot settled
        while True:
            if early is not None and time.monotonic() >= deadline:
                raise self._clock_error(early[0], early[1], "before the robot settled")
            # raises on a stall: none within the time left, or in a whole time-out once frames came early
            frame = self.source.latest(max(deadline - time.monotonic(), 1e-3) if early is None else self.timeout_s)
            if frame.tool_to_base is not None:
                return Grab(frame.image, frame.tool_to_base, frame.timestamp, frame.pose_timestamp or frame.timestamp)
            imaged = frame.timestamp - self.latency_s
            if imaged < settled:
                early = frame, settled - imaged
                continue
            paired = self.pairer.pair(frame.timestamp, wait_s=max(deadline - time.monotonic(), 0.0))
            if paired.tool_to_base is not None:
                return Grab(frame.image, paired.tool_to_base, frame.timestamp, paired.pose_timestamp)
            self.refused.append(Refusal(frame.index, frame.timestamp, paired.reason))
            if time.monotonic() >= deadline:
                ahead_s = imaged - time.time()
                if ahead_s > self.timeout_s:
                    raise self._clock_error(frame, ahead_s, "ahead of this computer's clock")
                raise ImageSourceError(f"{self.name}: no frame after the robot settled could be paired with a "
                                       f"robot pose within {self.timeout_s:g} s (frame {frame.index}: {paired.reason})")

    def _clock_error(self, frame: SourceFrame, offset_s: float, where: str) -> ImageSourceError:
        """Frames that kept coming for ``timeout_s`` stamped out of reach of the robot's poses (by
        ``offset_s``, s): the scanner's clock is not this computer's, or the latency is wrong."""
        return ImageSourceError(
            f"{self.name}: no frame in {self.timeout_s:g} s could be paired with a robot pose: the last, frame "
            f"{frame.index}, was imaged {abs(offset_s):.3g} s {where} (latency {self.latency_s:g} s): {CLOCK_HINT}")

    def stream(self, robot: Robot) -> Generator[tuple[SourceFrame, np.ndarray | None], None, None]:
        for frame in self.source.frames(self.timeout_s):
            yield frame, None
        raise ImageSourceError(f"{self.name}: end of stream")


@dataclass(frozen=True)
class LiveFrame:
    """What a sweep shows: an image at a pose, and whether (as what) it was recorded."""

    image: np.ndarray
    tool_to_base: np.ndarray
    joints: np.ndarray
    index: int | None  # session index when recorded, None for a live frame
    done: int
    total: int
    refused: int = 0  # frames refused so far in this sweep
    progress_label: str = "Frames recorded"  # what done / total count
    left_s: float | None = None  # wall time (s) the sweep has left, from its plan (None: not known yet)
    fraction: float | None = None  # of the sweep done, when done / total does not measure it (None: it does)


@dataclass
class TimeLeft:
    """The wall time a motion has left, planned as steps of estimated robot time (s): the steps
    still to go at the pace of those done, each step's wall time fitted as a pace (wall over
    planned robot time: a robot run faster or slower than real time) plus a time of its own (the
    frame grabbed and shown) once three steps tell them apart."""

    steps_s: np.ndarray
    told_after: int = 1  # steps done before an estimate is told
    clock: Callable[[], float] = time.monotonic
    started: float = field(init=False)
    done_at: list[float] = field(default_factory=list, init=False)  # the clock as each step ended
    to_go_s: float | None = field(default=None, init=False)  # wall s left as the last step ended (None: not told)

    def __post_init__(self) -> None:
        self.started = self.clock()

    def step_done(self) -> None:
        """A step has ended: the pace is fitted again on the steps done (once, not per frame shown)."""
        self.done_at.append(self.clock())
        model = self._pace()
        if model is not None:
            pace, own = model
            k = len(self.done_at)
            self.to_go_s = float(np.sum(self.steps_s[k:])) * pace + own * (len(self.steps_s) - k)

    def _pace(self) -> tuple[float, float] | None:
        """Wall s per planned robot s, and wall s per step, from the steps done (None: too few yet)."""
        k = len(self.done_at)
        if k < min(self.told_after, len(self.steps_s)):
            return None
        walls, planned = np.diff([self.started, *self.done_at]), self.steps_s[:k]
        if k >= 3 and np.ptp(planned) > 0:
            (pace, own), *_ = np.linalg.lstsq(np.column_stack([planned, np.ones(k)]), walls, rcond=None)
            if pace >= 0 and own >= 0:
                return float(pace), float(own)
        if planned.sum() > 0:
            return float(walls.sum() / planned.sum()), 0.0
        return 0.0, float(walls.mean())

    def left_s(self) -> float | None:
        """Wall seconds left (None before enough steps have ended)."""
        if self.to_go_s is None:
            return None
        return max(0.0, self.to_go_s - (self.clock() - self.done_at[-1]))

    def fraction(self) -> float:
        """Of the wall time the motion takes, how much has passed (0 before a step has ended)."""
        left = self.left_s()
        if left is None:
            return 0.0
        elapsed = self.clock() - self.started
        return 1.0 if elapsed + left <= 0 else elapsed / (elapsed + left)


@dataclass
class SweepOutcome:
    recorded: int = 0
    skipped: int = 0  # unreachable poses
    stopped: bool = False
    held: bool = False  # stopped by its hold (nobody watching), not by Stop
    error: str | None = None  # why the sweep ended early (robot or image stream)
    remaining: int = 0
    refusals: list[Refusal] = field(default_factory=list)  # frames refused (not recorded), with the reason

    @property
    def complete(self) -> bool:
        return not self.stopped and self.error is None

    @property
    def refused(self) -> int:
        return len(self.refusals)

    def notes(self) -> str:
        """What else happened, for a one-line report: ", N unreachable poses skipped, M frames
        refused (the first reason)", or "" when nothing did."""
        text = f", {self.skipped} unreachable poses skipped" if self.skipped else ""
        if self.refusals:
            text += f", {self.refused} frames refused ({self.refusals[0]}; every one in {REFUSED})"
        return text


Show = Callable[[LiveFrame], None]


@dataclass
class Sweep:
    """One acquisition of ``plan`` on a connected robot, recorded into a session."""

    robot: Robot
    grabber: Grabber
    plan: SweepPlan
    limits: MotionLimits = MotionLimits()
    show: Show | None = None
    live_hz: float = LIVE_HZ
    halt: threading.Event = field(default_factory=threading.Event)
    hold: threading.Event = field(default_factory=threading.Event)
    """Set, the sweep ends before its next move, as if stopped there, and can be resumed (the
    console sets it when its last page closes); cleared in time, it goes on."""
    truth_frames: list[dict] = field(default_factory=list)
    _refusals_logged: int = field(default=0, init=False)
    time_left: TimeLeft = field(default_factory=lambda: TimeLeft(np.zeros(0)), init=False)

    @property
    def total(self) -> int:
        return len(self.plan.poses)

    def stop(self) -> None:
        """Halt the motion at once and end the sweep; what is recorded stays recorded."""
        self.halt.set()
        self.robot.stop()

    def run(self, writer: SessionWriter, done: Collection[int] = frozenset()) -> SweepOutcome:
        """Visit every pose of the plan not in ``done`` (plan indices already recorded)."""
        outcome = SweepOutcome()
        todo = [k for k in range(self.total) if k not in done]
        try:
            # Told once a tenth of the poses (3 at least) tell a pose's own time from the robot's pace.
            self.time_left = TimeLeft(pose_durations_s([self.plan.poses[k] for k in todo], self.robot.tool_to_base(),
                                                       self.limits), told_after=max(3, len(todo) // 10))
            for position, k in enumerate(todo):
                finished = len(done) + position + 1  # poses visited, for the progress shown
                if self.halt.is_set() or self.hold.is_set():
                    break
                try:
                    self.robot.move_linear(self.plan.poses[k], self.limits, asynchronous=True)
                except Unreachable:
                    outcome.skipped += 1
                    self.time_left.step_done()
                    continue
                self._stream_until_settled(finished)
                self.robot.wait()
                if self.halt.is_set():
                    break
                self.time_left.step_done()
                self._record(writer, k, finished)
                outcome.recorded += 1
        except ENDS_A_SWEEP as exc:
            outcome.error = _why_ended(exc)
            self.robot.stop()
        finally:
            self._log_refusals(writer)
            outcome.refusals = list(self.grabber.refused)
        outcome.remaining = len(todo) - outcome.recorded - outcome.skipped
        return _ended(outcome, self.halt, self.hold)

    def _stream_until_settled(self, finished: int) -> None:
        period = 1.0 / self.live_hz
        while self.robot.is_moving() and not self.halt.is_set():
            started = time.monotonic()
            live = self.grabber.live(self.robot)
            if live is not None and self.show is not None:
                image, pose = live
                self.show(LiveFrame(image, pose, self.robot.joints(), None, finished - 1, self.total,
                                    left_s=self.time_left.left_s()))
            time.sleep(max(0.0, period - (time.monotonic() - started)))

    def _log_refusals(self, writer: SessionWriter) -> None:
        """Write the frames refused since the last call into the session."""
        for refusal in self.grabber.refused[self._refusals_logged:]:
            writer.refuse(refusal.to_json())
        self._refusals_logged = len(self.grabber.refused)

    def _record(self, writer: SessionWriter, k: int, finished: int) -> None:
        try:
            grab = self.grabber.grab(self.robot)
        finally:
            self._log_refusals(writer)
        extra = {"plan_index": k}
        if self.plan.n_passes > 1:
            extra["sweep"] = self.plan.passes[k]
        if self.plan.views is not None:
            extra["view"] = self.plan.views[k]
        index = writer.append(grab.image, grab.tool_to_base, timestamp=grab.timestamp,
                              pose_timestamp=grab.pose_timestamp, **extra)
        if grab.truth_markers is not None:
            self.truth_frames.append({"index": index, "markers_px": json_from_markers(grab.truth_markers)})
        if self.show is not None:
            self.show(LiveFrame(grab.image, grab.tool_to_base, self.robot.joints(), index, finished, self.total,
                                len(self.grabber.refused), left_s=self.time_left.left_s()))


POSE_KEEP_S = 0.25
"""How often (s) a continuous sweep writes the pose stream it fetched into the session."""
POSE_TAIL_S = 0.6
"""How long (s) the pose stream is kept after the last leg: longer than the lags searched
(``core.temporal.lag.MAX_LAG_S``), so the last frames can be paired again with any of them."""


def _ended(outcome: SweepOutcome, halt: threading.Event, hold: threading.Event) -> SweepOutcome:
    """``outcome`` said stopped when a sweep ended early with no error, by Stop or by its hold."""
    outcome.stopped = outcome.error is None and outcome.remaining > 0 and (halt.is_set() or hold.is_set())
    outcome.held = outcome.stopped and not halt.is_set()
    return outcome


CLOCK_HINT = "the scanner's clock is not this computer's, or the image latency is wrong"
"""What frames stamped out of reach of the robot's poses say about the rig."""


def _why_ended(exc: Exception) -> str:
    """Why a sweep ended early, in one line: a full disk as every command says it (naming the
    device and the file)."""
    full = no_space(exc) if isinstance(exc, OSError) else None
    return str(full or exc)


def _none_paired(source: str, refusals: list[Refusal]) -> str:
    """Why a continuous sweep that refused every frame failed: they were all stamped out of reach
    of the robot's poses."""
    return (f"{source}: none of the {len(refusals)} frames of the stream could be paired with a robot pose "
            f"(the last, {refusals[-1]}): {CLOCK_HINT}")


@dataclass
class ContinuousSweep:
    """One acquisition driven without stopping: each leg of ``legs`` is a ``Robot.move_path``,
    and while the robot moves every frame of the stream is shown and, on a recorded leg, recorded
    with the leg's fields, paired with the robot's pose stream at its timestamp minus
    ``latency_s`` (or with the pose the source sends with it). The pose stream is kept in the
    session (``posestream.jsonl``), so that ``probecal calibrate`` can measure the latency and
    pair the frames again. ``total`` counts legs."""

    robot: Robot
    grabber: Grabber
    legs: list[Leg]
    latency_s: float = 0.0
    show: Show | None = None
    halt: threading.Event = field(default_factory=threading.Event)
    hold: threading.Event = field(default_factory=threading.Event)
    """As :attr:`Sweep.hold`, before the next leg: a leg stopped halfway would be lost, and a
    continuous sweep is not resumed."""
    truth_frames: list[dict] = field(default_factory=list)
    time_left: TimeLeft = field(default_factory=lambda: TimeLeft(np.zeros(0)), init=False)

    @property
    def total(self) -> int:
        return len(self.legs)

    def stop(self) -> None:
        """Halt the motion at once and end the sweep; what is recorded stays recorded."""
        self.halt.set()
        self.robot.stop()

    def run(self, writer: SessionWriter, done: Collection[int] = frozenset()) -> SweepOutcome:
        """Drive every leg; ``done`` must be empty (a continuous sweep is not resumed)."""
        if done:
            raise InputError(writer.path, "a continuous sweep cannot be resumed: record a new one")
        outcome = SweepOutcome()
        pairer = FramePairer(self.robot, self.latency_s)
        kept = time.time() - LOOKBACK_S
        frames = self.grabber.stream(self.robot)  # a generator: it starts at its first frame
        finished = 0
        try:
            pairer.fetch(kept)
            self.time_left = TimeLeft(leg_durations_s(self.robot.tool_to_base(), self.legs))
            for k, leg in enumerate(self.legs):
                if self.halt.is_set() or self.hold.is_set():
                    break
                self.robot.move_path(leg.poses, leg.limits, asynchronous=True)
                last_kept = time.monotonic()
                while self.robot.is_moving() and not self.halt.is_set():
                    frame, markers = next(frames)
                    self._take(writer, pairer, frame, markers, leg, k, outcome)
                    if time.monotonic() - last_kept > POSE_KEEP_S:
                        kept, last_kept = self._keep_poses(writer, pairer, kept), time.monotonic()
                self.robot.wait()
                if not self.halt.is_set():
                    finished += 1
                    self.time_left.step_done()
        except ENDS_A_SWEEP as exc:
            outcome.error = _why_ended(exc)
            self.robot.stop()
        finally:
            frames.close()
            try:
                self._wait_for_poses(pairer, time.time() + POSE_TAIL_S)
                self._keep_poses(writer, pairer, kept)
            except (RobotError, OSError):
                pass  # the robot is gone: the poses fetched so far are kept already
            except RefusedRecord as exc:
                outcome.error = outcome.error or _why_ended(exc)
            outcome.refusals = list(self.grabber.refused)
        if outcome.error is None and not outcome.recorded and outcome.refusals:
            outcome.error = _none_paired(self.grabber.name, outcome.refusals)
        outcome.remaining = self.total - finished
        return _ended(outcome, self.halt, self.hold)

    def _take(self, writer: SessionWriter, pairer: FramePairer, frame: SourceFrame, markers: np.ndarray | None,
              leg: Leg, k: int, outcome: SweepOutcome) -> None:
        """Show a frame and, on a recorded leg, record it with its pose (or refuse it, with why)."""
        index, reason = None, ""
        pose: np.ndarray | None
        if frame.tool_to_base is not None:
            pose, pose_timestamp = frame.tool_to_base, frame.pose_timestamp or frame.timestamp
        else:
            paired = pairer.pair(frame.timestamp)
            pose, pose_timestamp, reason = paired.tool_to_base, paired.pose_timestamp, paired.reason
        if leg.record is not None:
            if pose is None:
                self.grabber.refused.append(Refusal(frame.index, frame.timestamp, reason))
                writer.refuse(self.grabber.refused[-1].to_json())
            else:
                index = writer.append(frame.image, pose, timestamp=frame.timestamp, pose_timestamp=pose_timestamp,
                                      source_index=frame.index, **leg.record)
                outcome.recorded += 1
                if markers is not None:
                    self.truth_frames.append({"index": index, "markers_px": json_from_markers(markers)})
        if self.show is not None:
            shown = pose if pose is not None else self.robot.tool_to_base()
            self.show(LiveFrame(frame.image, shown, self.robot.joints(), index, outcome.recorded, 0,
                                len(self.grabber.refused), left_s=self.time_left.left_s(),
                                fraction=self.time_left.fraction()))

    def _wait_for_poses(self, pairer: FramePairer, until: float) -> None:
        """Fetch the pose stream until it reaches ``until`` (s) or ``POSE_TAIL_S`` more have passed,
        so that the last frames have poses on both sides of any lag searched."""
        deadline = time.monotonic() + 2 * POSE_TAIL_S
        while (pairer.poses.newest or -np.inf) < until and time.monotonic() < deadline and not self.halt.is_set():
            time.sleep(FETCH_S)
            pairer.fetch(until - LOOKBACK_S)

    @staticmethod
    def _keep_poses(writer: SessionWriter, pairer: FramePairer, kept: float) -> float:
        """Write the poses fetched since ``kept`` (s) into the session; returns the newest kept."""
        pairer.fetch(kept)
        samples = pairer.poses.since(kept)
        writer.append_poses(samples.timestamps, samples.tool_to_base)
        return float(samples.timestamps[-1]) if len(samples) else kept


@dataclass
class StreamOutcome:
    """How a continuous recording went: frames recorded, refused (with the reason) and why it
    ended early (None when it took every frame it was asked for)."""

    recorded: int = 0
    refusals: list[Refusal] = field(default_factory=list)
    error: str | None = None

    @property
    def refused(self) -> int:
        return len(self.refusals)


def record_stream(source: ImageSource, pairer: FramePairer, writer: SessionWriter, frames: int,
                  timeout_s: float = 2.0, halt: threading.Event | None = None) -> StreamOutcome:
    """Record the next ``frames`` frames of ``source``, every one in order, each with the robot's
    pose at its timestamp from ``pairer``; a frame that cannot be paired is refused with its
    reason (in the session's ``refused.jsonl`` too). Ends early on ``halt``, a stalled or broken
    stream or a reader that fell behind the source's buffer (the source then says how many frames
    it dropped)."""
    outcome = StreamOutcome()
    try:
        for frame in source.frames(timeout_s):
            if halt is not None and halt.is_set():
                break
            pose: np.ndarray | None
            if frame.tool_to_base is not None:
                pose, pose_timestamp = frame.tool_to_base, frame.pose_timestamp or frame.timestamp
            else:
                paired = pairer.pair(frame.timestamp, wait_s=timeout_s)
                pose, pose_timestamp = paired.tool_to_base, paired.pose_timestamp
                if pose is None:
                    outcome.refusals.append(Refusal(frame.index, frame.timestamp, paired.reason))
                    writer.refuse(outcome.refusals[-1].to_json())
            if pose is not None:
                writer.append(frame.image, pose, timestamp=frame.timestamp, pose_timestamp=pose_timestamp,
                              source_index=frame.index)
                outcome.recorded += 1
            if outcome.recorded + outcome.refused >= frames:
                break
        else:
            outcome.error = f"{source.name}: end of stream"
    except ENDS_A_SWEEP as exc:
        outcome.error = _why_ended(exc)
    return outcome


def start_session(path: Path, manifest: Manifest, plan: SweepPlan, files: dict[str, bytes] | None = None,
                  **writer_args: Any) -> SessionWriter:
    """A new session folder for a sweep, with its plan (and any other ``files``) stored beside the
    manifest before the folder appears."""
    files = {PLAN_FILE: to_json_text(plan.to_dict()).encode(), **(files or {})}
    return SessionWriter(path, manifest, files=files, **writer_args)


def extend_plan(path: Path, more: SweepPlan) -> None:
    """Add ``more`` poses to the plan of the sweep recorded in ``path`` (its plan file and its
    manifest's count), so that resuming it records them after those it holds."""
    plan, _ = resume_state(path)
    views = None if plan.views is None or more.views is None else [*plan.views, *more.views]
    extended = SweepPlan([*plan.poses, *more.poses], [*plan.passes, *more.passes], plan.duration_s + more.duration_s,
                         views)
    write_atomic(Path(path) / PLAN_FILE, to_json_text(extended.to_dict()))
    manifest = read_manifest(path)
    write_json(Path(path) / MANIFEST, replace(manifest, plan={**(manifest.plan or {}), **extended.summary()}).to_json())


def resume_state(path: Path) -> tuple[SweepPlan, set[int]]:
    """The plan of an interrupted sweep and the plan indices already recorded in its session."""
    session = load_session(path)
    if not (Path(path) / PLAN_FILE).is_file():
        raise InputError(path, f"no {PLAN_FILE}: this session was not recorded by a sweep and cannot be resumed")
    plan = SweepPlan.load(Path(path) / PLAN_FILE)
    done = {int(r.extra["plan_index"]) for r in session.records if "plan_index" in r.extra}
    return plan, done
