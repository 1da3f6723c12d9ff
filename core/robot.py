"""The robot interface (SPEC §4, §7) and a simulated UR3 that implements it.

Poses are flange poses ``tool_to_base`` (4x4, mm), joints are in rad. A real backend converts
ur_rtde's metres and rotation vectors once, at its boundary.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from core.errors import DeviceError
from core.transforms import make_transform
from core.ur3 import (
    JOINT_LIMITS,
    MotionLimits,
    Unreachable,
    check_pose,
    closest_ik,
    forward_kinematics,
    linear_move_duration,
    linear_move_progress,
    trapezoid_duration,
    trapezoid_position,
)

HOME_TOOL_TO_BASE = make_transform(np.diag([-1.0, 1.0, -1.0]), [0.0, -300.0, 250.0])
"""Home flange pose: 300 mm in front of the base (-y), 250 mm up, tool z pointing down (-base z)."""

HOME_JOINTS = closest_ik(HOME_TOOL_TO_BASE, np.radians([90.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
"""Joints (rad) of ``HOME_TOOL_TO_BASE`` in the usual elbow-up, wrist-down configuration,
about (68.0, -92.5, 109.8, -107.3, -90.0, -22.0) degrees."""

PATH_SAMPLES = 20
MAX_JOINT_JUMP_DEG = 30.0
ROTATION_REPEATABILITY_DEG = 0.002
_TICK_S = 0.01


class RobotError(DeviceError):
    """The robot cannot do what was asked: not connected, already moving, move stopped or faulted."""


@runtime_checkable
class Robot(Protocol):
    """A UR-like arm driven by linear tool-space moves (mm, rad, s)."""

    @property
    def connected(self) -> bool: ...

    def connect(self) -> None: ...

    def disconnect(self) -> None:
        """Stop any motion and close the connection."""

    def tool_to_base(self) -> np.ndarray:
        """The measured flange pose (4x4, mm)."""

    def joints(self) -> np.ndarray:
        """The measured joint angles (6,), rad."""

    def move_linear(
        self,
        target_tool_to_base: np.ndarray,
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """moveL to a flange pose. Raises Unreachable (before any motion) or RobotError.

        A blocking move raises RobotError when it is stopped or faults before reaching the target.
        """

    def is_moving(self) -> bool: ...

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the current move; False on timeout. Raises RobotError if the move faulted."""

    def stop(self) -> None:
        """Halt at once where the robot is. Always safe, also when idle or not connected."""


def interpolate_pose(
    start_tool_to_base: np.ndarray, end_tool_to_base: np.ndarray, fraction
) -> np.ndarray:
    """The pose(s) a moveL passes at ``fraction`` (0..1, scalar or (n,)): position linear,
    orientation Slerp. Returns a 4x4, or (n, 4, 4) for n fractions."""
    rotations = Rotation.from_matrix(np.stack([start_tool_to_base[:3, :3], end_tool_to_base[:3, :3]]))
    fraction = np.asarray(fraction, dtype=float)
    weight = fraction[..., None]
    poses = np.zeros(fraction.shape + (4, 4))
    poses[..., :3, :3] = Slerp([0.0, 1.0], rotations)(fraction).as_matrix()
    poses[..., :3, 3] = (1.0 - weight) * start_tool_to_base[:3, 3] + weight * end_tool_to_base[:3, 3]
    poses[..., 3, 3] = 1.0
    return poses


def linear_path_joints(
    start_joints: np.ndarray,
    target_tool_to_base: np.ndarray,
    samples: int = PATH_SAMPLES,
    max_jump_deg: float = MAX_JOINT_JUMP_DEG,
) -> np.ndarray:
    """Joints (samples + 1, 6) in rad along the straight line from FK(start_joints) to the target.

    Each sample is the IK solution closest to the previous one. Raises Unreachable when a sample
    has no solution or a joint would jump more than ``max_jump_deg`` (a configuration change).
    """
    start_joints = np.asarray(start_joints, dtype=float)
    target = check_pose(target_tool_to_base)
    fractions = np.arange(1, samples + 1) / samples
    poses = interpolate_pose(forward_kinematics(start_joints), target, fractions)
    path = [start_joints]
    for fraction, pose in zip(fractions, poses):
        try:
            q = closest_ik(pose, path[-1])
        except Unreachable as exc:
            raise Unreachable(f"the straight path fails at {fraction:.0%}: {exc}") from exc
        jump = np.degrees(np.abs(q - path[-1]))
        if jump.max() > max_jump_deg:
            raise Unreachable(
                f"joint {jump.argmax() + 1} would jump {jump.max():.0f} deg at {fraction:.0%} "
                "of the straight path (configuration change)"
            )
        path.append(q)
    return np.array(path)


@dataclass(eq=False)
class _Motion:
    """One accepted move of the simulated robot and how it ended."""

    start: np.ndarray
    target: np.ndarray
    final_joints: np.ndarray
    limits: MotionLimits
    duration_s: float
    halt: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None
    running: bool = True
    reached: bool = False
    fault: str | None = None


class SimulatedRobot:
    """A UR3 on the kinematic model with trapezoidal timing and repeatability noise.

    ``time_scale`` is wall seconds per robot second: 1 moves in real time, 0 completes every move
    at once, values in between speed up. ``elapsed_motion_s`` is the robot time of all moves
    (trapezoid model plus settle), whatever the time scale. Each time a move settles, the reached
    pose differs from the commanded one by a random rigid error: translation with RMS norm
    ``repeatability_mm`` and rotation with per-axis sigma ``ROTATION_REPEATABILITY_DEG``.
    """

    def __init__(
        self,
        home_joints: np.ndarray | None = None,
        seed: int = 0,
        time_scale: float = 1.0,
        repeatability_mm: float = 0.03,
    ):
        joints = HOME_JOINTS if home_joints is None else np.asarray(home_joints, dtype=float)
        if joints.shape != (6,) or not np.all(
            (joints >= JOINT_LIMITS[:, 0]) & (joints <= JOINT_LIMITS[:, 1])
        ):
            raise ValueError("home joints must be 6 angles within the joint limits (rad)")
        if not (np.isfinite(time_scale) and time_scale >= 0.0):
            raise ValueError(f"time_scale must be finite and >= 0, got {time_scale}")
        if not (np.isfinite(repeatability_mm) and repeatability_mm >= 0.0):
            raise ValueError(f"repeatability_mm must be finite and >= 0, got {repeatability_mm}")
        self._joints = joints.copy()
        self._rng = np.random.default_rng(seed)
        self._time_scale = float(time_scale)
        self._repeatability_mm = float(repeatability_mm)
        self._lock = threading.Lock()
        self._connected = False
        self._motion: _Motion | None = None
        self._elapsed_motion_s = 0.0

    @property
    def connected(self) -> bool:
        with self._lock:
            return self._connected

    @property
    def elapsed_motion_s(self) -> float:
        """Cumulative robot time (s) of all moves, as a real UR3 would take them."""
        with self._lock:
            return self._elapsed_motion_s

    def connect(self) -> None:
        with self._lock:
            self._connected = True

    def disconnect(self) -> None:
        self.stop()
        with self._lock:
            self._connected = False

    def tool_to_base(self) -> np.ndarray:
        """The flange pose (mm) from the encoders: FK of the actual joints."""
        with self._lock:
            self._require_connected()
            return forward_kinematics(self._joints)

    def joints(self) -> np.ndarray:
        with self._lock:
            self._require_connected()
            return self._joints.copy()

    def is_moving(self) -> bool:
        with self._lock:
            return self._motion is not None and self._motion.running

    def move_linear(
        self,
        target_tool_to_base: np.ndarray,
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """moveL along a straight tool path; the whole path is checked before the robot moves."""
        limits = limits if limits is not None else MotionLimits()
        with self._lock:
            self._require_idle()
            target = check_pose(target_tool_to_base)
            path = linear_path_joints(self._joints, target)
            start = forward_kinematics(self._joints)
            motion = _Motion(
                start=start,
                target=target,
                final_joints=closest_ik(self._settled_pose(target), path[-1]),
                limits=limits,
                duration_s=linear_move_duration(start, target, limits),
            )
            self._launch(motion, self._follow)
        if not asynchronous:
            self.wait()
            if not motion.reached:
                raise RobotError("move stopped before reaching the target")

    def move_joints(self, q_target: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Start a moveJ to joints ``q_target`` (rad): every joint on one trapezoid, timed by the
        joint that turns furthest at ``speed_rad_s`` and ``accel_rad_s2``. Does not wait."""
        q_target = np.asarray(q_target, dtype=float)
        with self._lock:
            self._require_idle()
            q_start = self._joints.copy()
            distance = float(np.abs(q_target - q_start).max())
            motion = _Motion(
                start=forward_kinematics(q_start),
                target=forward_kinematics(q_target),
                final_joints=q_target,
                limits=MotionLimits(settle_s=0.0),
                duration_s=trapezoid_duration(distance, speed_rad_s, accel_rad_s2),
            )
            self._launch(motion, partial(self._follow_joints, q_start=q_start, distance=distance,
                                         speed=speed_rad_s, accel=accel_rad_s2))

    def _require_idle(self) -> None:
        self._require_connected()
        if self._motion is not None and self._motion.running:
            raise RobotError("robot is already moving")

    def _launch(self, motion: _Motion, follow: Callable[[_Motion, float], None]) -> None:
        """Make ``motion`` the current one (lock held): done at once at time scale 0 or when
        there is nothing to move, else ``follow(motion, t0)`` drives it in a worker thread."""
        self._motion = motion
        if self._time_scale == 0.0 or motion.duration_s == 0.0:
            self._joints = motion.final_joints
            self._elapsed_motion_s += motion.duration_s
            motion.running, motion.reached = False, True
            return
        motion.thread = threading.Thread(target=self._run, args=(motion, follow), daemon=True)
        motion.thread.start()

    def wait(self, timeout: float | None = None) -> bool:
        with self._lock:
            motion = self._motion
        if motion is None:
            return True
        if motion.thread is not None:
            motion.thread.join(timeout)
            if motion.thread.is_alive():
                return False
        if motion.fault is not None:
            raise RobotError(motion.fault)
        return True

    def stop(self) -> None:
        with self._lock:
            motion = self._motion
        if motion is None or motion.thread is None:
            return
        motion.halt.set()
        motion.thread.join()

    def _require_connected(self) -> None:
        if not self._connected:
            raise RobotError("robot not connected")

    def _settled_pose(self, target: np.ndarray) -> np.ndarray:
        """The commanded pose plus a random repeatability error (base-frame translation, mm)."""
        translation = self._rng.normal(0.0, self._repeatability_mm / np.sqrt(3.0), 3)
        rotation = Rotation.from_rotvec(
            np.radians(self._rng.normal(0.0, ROTATION_REPEATABILITY_DEG, 3))
        )
        return make_transform(
            (rotation * Rotation.from_matrix(target[:3, :3])).as_matrix(), target[:3, 3] + translation
        )

    def _run(self, motion: _Motion, follow: Callable[[_Motion, float], None]) -> None:
        """Worker thread: follow the profile tick by tick until reached, halted or faulted, then
        settle; the robot time it took is added to ``elapsed_motion_s``."""
        t0 = time.monotonic()
        try:
            follow(motion, t0)
            if motion.reached:
                motion.halt.wait(motion.limits.settle_s * self._time_scale)
        finally:
            completed = motion.reached and not motion.halt.is_set()
            robot_time = min((time.monotonic() - t0) / self._time_scale, motion.duration_s)
            with self._lock:
                self._elapsed_motion_s += motion.duration_s if completed else robot_time
                motion.running = False

    def _follow_joints(self, motion: _Motion, t0: float, q_start: np.ndarray, distance: float, speed: float,
                       accel: float) -> None:
        """Worker: joints along the trapezoid, all in step, until reached or halted."""
        while not motion.halt.wait(_TICK_S):
            t = (time.monotonic() - t0) / self._time_scale
            if t >= motion.duration_s:
                with self._lock:
                    self._joints = motion.final_joints
                motion.reached = True
                return
            fraction = trapezoid_position(t, distance, speed, accel) / distance
            with self._lock:
                self._joints = q_start + fraction * (motion.final_joints - q_start)

    def _follow(self, motion: _Motion, t0: float) -> None:
        with self._lock:
            q = self._joints
        while not motion.halt.wait(_TICK_S):
            t = (time.monotonic() - t0) / self._time_scale
            fraction = linear_move_progress(t, motion.start, motion.target, motion.limits)
            if fraction >= 1.0:
                with self._lock:
                    self._joints = motion.final_joints
                motion.reached = True
                return
            try:
                q_next = closest_ik(interpolate_pose(motion.start, motion.target, fraction), q)
            except Unreachable as exc:
                motion.fault = f"protective stop at {fraction:.0%} of the move: {exc}"
                return
            if np.degrees(np.abs(q_next - q)).max() > MAX_JOINT_JUMP_DEG:
                motion.fault = f"protective stop at {fraction:.0%} of the move: joint jump"
                return
            q = q_next
            with self._lock:
                self._joints = q
