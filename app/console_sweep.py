"""Driving a sweep: move through the plan, stream live frames while moving, record one frame at
every settled pose into a session. Stopping halts the robot at once and keeps what is recorded."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from core.plan import Plan
from core.robot import Robot
from core.session import SessionWriter
from core.ur3 import MotionLimits, Unreachable

FrameSource = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, np.ndarray | None]]


@dataclass(frozen=True)
class Frame:
    """What the console shows: an image at a flange pose, and whether (as what) it was recorded."""

    image: np.ndarray
    tool_to_base: np.ndarray
    joints: np.ndarray
    index: int | None  # session index when recorded, None for a live frame
    done: int
    total: int


@dataclass
class SweepOutcome:
    recorded: int = 0
    skipped: int = 0  # unreachable poses
    stopped: bool = False
    truth_frames: list[dict] = field(default_factory=list)


@dataclass
class Sweep:
    """One acquisition over ``plans`` (one plan per pass) on a connected robot."""

    robot: Robot
    plans: list[Plan]
    limits: MotionLimits
    source: FrameSource
    show: Callable[[Frame], None]
    live_hz: float = 20.0
    seed: int = 0
    halt: threading.Event = field(default_factory=threading.Event)
    outcome: SweepOutcome = field(default_factory=SweepOutcome)

    @property
    def total(self) -> int:
        return sum(len(p.poses) for p in self.plans)

    def stop(self) -> None:
        """Halt the motion at once and end the sweep after the current step."""
        self.halt.set()
        self.robot.stop()

    def run(self, writer: SessionWriter) -> SweepOutcome:
        """Record into ``writer``; raises RobotError if the robot faults (frames so far are kept)."""
        rng = np.random.default_rng(self.seed + 1)
        outcome = self.outcome
        done = 0
        for pass_index, plan in enumerate(self.plans):
            for target in plan.poses:
                if self.halt.is_set():
                    outcome.stopped = True
                    return outcome
                done += 1
                try:
                    self.robot.move_linear(target, self.limits, asynchronous=True)
                except Unreachable:
                    outcome.skipped += 1
                    continue
                self._stream_until_settled(rng, done)
                self.robot.wait()
                if self.halt.is_set():
                    outcome.stopped = True
                    return outcome
                self._record(writer, rng, pass_index, done, outcome)
        return outcome

    def _stream_until_settled(self, rng: np.random.Generator, done: int) -> None:
        period = 1.0 / self.live_hz
        while self.robot.is_moving() and not self.halt.is_set():
            started = time.monotonic()
            pose, joints = self.robot.tool_to_base(), self.robot.joints()
            image, _ = self.source(pose, rng)
            self.show(Frame(image, pose, joints, None, done - 1, self.total))
            time.sleep(max(0.0, period - (time.monotonic() - started)))

    def _record(self, writer: SessionWriter, rng: np.random.Generator, pass_index: int, done: int,
                outcome: SweepOutcome) -> None:
        pose, joints = self.robot.tool_to_base(), self.robot.joints()
        image, markers = self.source(pose, rng)
        extra = {"sweep": pass_index} if len(self.plans) > 1 else {}
        index = writer.append(image, pose, timestamp=time.time(), pose_timestamp=time.time(), **extra)
        outcome.recorded += 1
        if markers is not None:
            outcome.truth_frames.append(
                {"index": index, "markers_px": [None if np.isnan(m[0]) else m.tolist() for m in markers]}
            )
        self.show(Frame(image, pose, joints, index, done, self.total))
