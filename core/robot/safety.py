"""Motion safety (design §7): a workspace box and speed and acceleration limits, checked before any
command reaches a robot. Base frame, mm, deg, s.

:class:`GuardedRobot` wraps any :class:`core.robot.simulated.Robot`; a refused move raises
:class:`SafetyError` and nothing is sent. The flange path of a linear move is a straight segment
and the box is convex, so checking the start and the target keeps the whole path inside.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from probecal.core import STATIC_DIR
from probecal.core.errors import InputError
from probecal.core.io.jsonio import (
    expect_keys,
    expect_number,
    expect_numbers,
    expect_string,
    optional,
    read_json,
    required,
)
from probecal.core.robot.contract import Robot, RobotError
from probecal.core.robot.posestream import PoseSamples
from probecal.core.robot.ur3 import ArmModel, MotionLimits

DEFAULT_WORKSPACE_FILE = STATIC_DIR / "configs" / "workspace.json"


class SafetyError(RobotError):
    """A command was refused before it was sent: it would leave the workspace or exceed a limit."""


@dataclass(frozen=True)
class Workspace:
    """The box the flange must stay in (base frame, mm) and the fastest moves allowed."""

    box_min_mm: tuple[float, float, float]
    box_max_mm: tuple[float, float, float]
    max_limits: MotionLimits = MotionLimits(250.0, 1200.0, 90.0, 600.0)

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.box_min_mm, float), np.asarray(self.box_max_mm, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)) or np.any(lo >= hi):
            raise ValueError("the workspace box needs finite corners with min < max on every axis")

    def contains(self, tool_to_base: np.ndarray) -> bool:
        p = np.asarray(tool_to_base, float)[:3, 3]
        return bool(np.all(np.isfinite(p)) and np.all(p >= self.box_min_mm) and np.all(p <= self.box_max_mm))

    def check_pose(self, tool_to_base: np.ndarray, what: str = "target") -> None:
        """Raise SafetyError unless the flange position lies in the box."""
        if not self.contains(tool_to_base):
            p = np.asarray(tool_to_base, float)[:3, 3]
            raise SafetyError(
                f"refused: the {what} flange position ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm is outside the "
                f"workspace box {_fmt(self.box_min_mm)} to {_fmt(self.box_max_mm)} mm"
            )

    def check_limits(self, limits: MotionLimits) -> None:
        """Raise SafetyError if a move would be faster or accelerate harder than allowed."""
        top = self.max_limits
        for name, value, allowed, unit in (
            ("linear speed", limits.linear_speed_mm_s, top.linear_speed_mm_s, "mm/s"),
            ("linear acceleration", limits.linear_accel_mm_s2, top.linear_accel_mm_s2, "mm/s^2"),
            ("angular speed", limits.angular_speed_deg_s, top.angular_speed_deg_s, "deg/s"),
            ("angular acceleration", limits.angular_accel_deg_s2, top.angular_accel_deg_s2, "deg/s^2"),
        ):
            if value > allowed:
                raise SafetyError(f"refused: {name} {value:g} {unit} is above the limit of {allowed:g} {unit}")

    def to_dict(self) -> dict:
        top = self.max_limits
        return {
            "box_min_mm": list(self.box_min_mm),
            "box_max_mm": list(self.box_max_mm),
            "max_linear_speed_mm_s": top.linear_speed_mm_s,
            "max_linear_accel_mm_s2": top.linear_accel_mm_s2,
            "max_angular_speed_deg_s": top.angular_speed_deg_s,
            "max_angular_accel_deg_s2": top.angular_accel_deg_s2,
        }


def _fmt(point: Iterable[float]) -> str:
    return "(" + ", ".join(f"{v:.0f}" for v in point) + ")"


LIMIT_KEYS = ("max_linear_speed_mm_s", "max_linear_accel_mm_s2", "max_angular_speed_deg_s", "max_angular_accel_deg_s2")


def load_workspace(path: str | Path = DEFAULT_WORKSPACE_FILE) -> Workspace:
    """A workspace from JSON (the keys of :meth:`Workspace.to_dict`, and an optional
    ``description``); InputError naming the file and the field if it is bad: the box needs three
    finite numbers per corner, every limit a positive finite number."""
    path = Path(path)
    data = expect_keys(read_json(path), {"description", "box_min_mm", "box_max_mm", *LIMIT_KEYS}, path, "the workspace")
    optional(data, "description", expect_string, path)
    (x0, y0, z0), (x1, y1, z1) = (required(data, key, expect_numbers, path, count=3).tolist()
                                  for key in ("box_min_mm", "box_max_mm"))
    limits = [required(data, key, expect_number, path, positive=True) for key in LIMIT_KEYS]
    try:
        return Workspace((x0, y0, z0), (x1, y1, z1), MotionLimits(*limits))
    except ValueError as exc:
        raise InputError(path, str(exc))


class GuardedRobot:
    """A robot whose every move is checked against a workspace before it is sent (a Robot)."""

    def __init__(self, robot: Robot, workspace: Workspace):
        self.robot, self.workspace = robot, workspace

    @property
    def connected(self) -> bool:
        return self.robot.connected

    def connect(self) -> None:
        self.robot.connect()

    def disconnect(self) -> None:
        self.robot.disconnect()

    def tool_to_base(self) -> np.ndarray:
        return self.robot.tool_to_base()

    def joints(self) -> np.ndarray:
        return self.robot.joints()

    def kinematics(self) -> ArmModel | None:
        return self.robot.kinematics()

    def poses_since(self, after: float) -> PoseSamples:
        return self.robot.poses_since(after)

    def move_linear(self, target_tool_to_base: np.ndarray, limits: MotionLimits | None = None,
                    asynchronous: bool = False) -> None:
        limits = limits if limits is not None else MotionLimits()
        self.workspace.check_limits(limits)
        self.workspace.check_pose(target_tool_to_base)
        self.workspace.check_pose(self.robot.tool_to_base(), "current")
        self.robot.move_linear(target_tool_to_base, limits, asynchronous)

    def move_path(self, poses: list[np.ndarray], limits: MotionLimits | None = None,
                  asynchronous: bool = False) -> None:
        """Every pose is checked; the blended path stays inside the box, which is convex, because
        it never leaves the straight segments' convex hull."""
        limits = limits if limits is not None else MotionLimits()
        self.workspace.check_limits(limits)
        for pose in poses:
            self.workspace.check_pose(pose)
        self.workspace.check_pose(self.robot.tool_to_base(), "current")
        self.robot.move_path(poses, limits, asynchronous)

    def is_moving(self) -> bool:
        return self.robot.is_moving()

    def wait(self, timeout: float | None = None) -> bool:
        return self.robot.wait(timeout)

    def stop(self) -> None:
        self.robot.stop()
