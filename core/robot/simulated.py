"""The twin's UR3: a ``Robot`` (``core.robot.contract``) on the kinematic model, with trapezoidal
timing, repeatability noise and a pose stream that is an exact function of its clock.

Poses are flange poses ``tool_to_base`` (4x4, mm), joints are in rad.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.geometry.transforms import interpolate_pose, make_transform
from probecal.core.robot.contract import HISTORY_S, HOME_JOINTS, RobotError
from probecal.core.robot.posestream import PoseSamples
from probecal.core.robot.trajectory import CHECK_STEP_S, BlendedPath, blended_path
from probecal.core.robot.ur3 import (
    JOINT_LIMITS,
    MAX_JOINT_JUMP_DEG,
    NOMINAL_UR3,
    UR3,
    ArmModel,
    DhDeviation,
    MotionLimits,
    Unreachable,
    check_pose,
    linear_move_duration,
    linear_move_progress,
    linear_path_joints,
    trapezoid_duration,
    trapezoid_position,
)

ROTATION_REPEATABILITY_DEG = 0.002
_TICK_S = 0.01
STREAM_HZ = 125.0
"""Rate (Hz) of the twin controller's pose stream."""


@dataclass(eq=False)
class _Motion:
    """One accepted move of the simulated robot, as a function of time, and how it ended.

    ``path`` maps robot times since the start (s, (n,)) to flange poses (n, 4, 4) on the way;
    at ``duration_s`` the robot stands at ``final_joints`` (the target with its repeatability
    error). Wall times are this machine's clock (``time.time()``, s); ``wall_per_robot_s`` is the
    robot's time scale. ``ended_at``/``end_pose``: when and where it came to rest (reached,
    halted or faulted), None while it runs.
    """

    start: np.ndarray
    target: np.ndarray
    final_joints: np.ndarray
    limits: MotionLimits
    duration_s: float
    path: Callable[[np.ndarray], np.ndarray]
    arm: ArmModel = NOMINAL_UR3
    started_at: float = 0.0
    wall_per_robot_s: float = 1.0
    ended_at: float | None = None
    end_pose: np.ndarray | None = None
    halted_at: float | None = None
    halt: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None
    running: bool = True
    reached: bool = False
    fault: str | None = None

    def poses_at(self, wall_times: np.ndarray) -> np.ndarray:
        """Flange poses (n, 4, 4) at ``wall_times`` (s), none before the start."""
        poses = np.empty((len(wall_times), 4, 4))
        rest = np.zeros(len(wall_times), bool) if self.ended_at is None else wall_times >= self.ended_at
        if self.wall_per_robot_s == 0.0:
            robot_times = np.full(len(wall_times), np.inf)
        else:
            robot_times = (wall_times - self.started_at) / self.wall_per_robot_s
        arrived = ~rest & (robot_times >= self.duration_s)
        moving = ~rest & ~arrived
        poses[rest] = self.end_pose
        poses[arrived] = self.arm.forward(self.final_joints)
        if moving.any():
            poses[moving] = self.path(robot_times[moving])
        return poses


def _linear_path(start: np.ndarray, target: np.ndarray, limits: MotionLimits) -> Callable[[np.ndarray], np.ndarray]:
    def path(robot_times: np.ndarray) -> np.ndarray:
        fractions = [linear_move_progress(t, start, target, limits) for t in robot_times]
        return interpolate_pose(start, target, np.array(fractions))

    return path


def _joint_path(q_start: np.ndarray, q_end: np.ndarray, speed: float, accel: float,
                arm: ArmModel) -> Callable[[np.ndarray], np.ndarray]:
    distance = float(np.abs(q_end - q_start).max())

    def path(robot_times: np.ndarray) -> np.ndarray:
        return np.array([arm.forward(q_start + trapezoid_position(t, distance, speed, accel) / distance
                                     * (q_end - q_start)) for t in robot_times])

    return path


class SimulatedRobot:
    """A UR3 on the kinematic model with trapezoidal timing and repeatability noise.

    ``time_scale`` is wall seconds per robot second: 1 moves in real time, 0 completes every move
    at once, values in between speed up. ``elapsed_motion_s`` is the robot time of all moves
    (trapezoid model plus settle), whatever the time scale. Each time a move settles, the reached
    pose differs from the commanded one by a random rigid error: translation with RMS norm
    ``repeatability_mm`` and rotation with per-axis sigma ``ROTATION_REPEATABILITY_DEG``.

    The flange pose is an exact function of the twin's clock (this machine's ``time.time()``):
    the pose stream (``poses_since``, ``STREAM_HZ``) and ``tool_to_base`` show where the profile
    puts the flange at that instant, however late a busy program asks. A worker thread per move
    follows it in joint space (every ``_TICK_S``) to find faults and the end of the move.

    Its controller computes poses with UR's table, or, given a ``controller_calibration``, with
    the table plus those deviations, as a factory-calibrated UR does: the flange poses it
    reports, the joints its moves solve for and its ``kinematics()`` then follow that model.
    """

    def __init__(
        self,
        home_joints: np.ndarray | None = None,
        seed: int = 0,
        time_scale: float = 1.0,
        repeatability_mm: float = 0.03,
        controller_calibration: DhDeviation | None = None,
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
        self._arm = ArmModel(UR3, controller_calibration)
        self._rng = np.random.default_rng(seed)
        self._time_scale = float(time_scale)
        self._repeatability_mm = float(repeatability_mm)
        self._lock = threading.Lock()
        self._connected = False
        self._motion: _Motion | None = None
        self._motions: list[_Motion] = []  # the pose stream's recent moves, oldest first
        self._rest_pose = self._arm.forward(joints)  # where the robot stood before them
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

    @property
    def model(self) -> ArmModel:
        """The kinematics its controller computes flange poses with."""
        return self._arm

    def kinematics(self) -> ArmModel | None:
        """The controller's calibrated kinematics; None for the twin's uncalibrated controller,
        which states none."""
        return None if self._arm.deviation is None else self._arm

    def connect(self) -> None:
        with self._lock:
            self._connected = True

    def disconnect(self) -> None:
        self.stop()
        with self._lock:
            self._connected = False

    def tool_to_base(self) -> np.ndarray:
        """The flange pose (mm) at this instant."""
        with self._lock:
            self._require_connected()
            return self._poses_at(np.array([time.time()]))[0]

    def joints(self) -> np.ndarray:
        with self._lock:
            self._require_connected()
            return self._joints.copy()

    def poses_since(self, after: float) -> PoseSamples:
        """The pose stream on the ``STREAM_HZ`` grid of the twin's clock, after ``after`` (s)."""
        now = time.time()
        first = int(np.floor(max(after, now - HISTORY_S) * STREAM_HZ)) + 1
        times = np.arange(first, int(np.floor(now * STREAM_HZ)) + 1) / STREAM_HZ
        with self._lock:
            self._require_connected()
            return PoseSamples(times, self._poses_at(times))

    def _poses_at(self, wall_times: np.ndarray) -> np.ndarray:
        """Flange poses (n, 4, 4) at ``wall_times`` (s) within the kept history (lock held)."""
        poses = np.broadcast_to(self._rest_pose, (len(wall_times), 4, 4)).copy()
        starts = np.array([m.started_at for m in self._motions])
        governing = np.searchsorted(starts, wall_times, side="right") - 1
        for k in np.unique(governing[governing >= 0]):
            mask = governing == k
            poses[mask] = self._motions[k].poses_at(wall_times[mask])
        return poses

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
            planned = linear_path_joints(self._joints, target, arm=self._arm)
            start = self._arm.forward(self._joints)
            motion = _Motion(
                start=start,
                target=target,
                final_joints=self._arm.closest_ik(self._settled_pose(target), planned[-1]),
                limits=limits,
                duration_s=linear_move_duration(start, target, limits),
                path=_linear_path(start, target, limits),
                arm=self._arm,
            )
            self._launch(motion, partial(self._follow, planned=planned))
        if not asynchronous:
            self.wait()
            if not motion.reached:
                raise RobotError("move stopped before reaching the target")

    def move_path(
        self,
        poses: list[np.ndarray],
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """Through ``poses`` without stopping (``core.robot.trajectory``); the joints along the
        whole path are checked before the robot moves."""
        limits = limits if limits is not None else MotionLimits()
        with self._lock:
            self._require_idle()
            start = self._arm.forward(self._joints)
            path = blended_path([start, *poses], limits)
            planned = path.joints_along(self._joints, arm=self._arm)
            motion = _Motion(
                start=start,
                target=path.end,
                final_joints=self._arm.closest_ik(self._settled_pose(path.end), planned[-1]),
                limits=limits,
                duration_s=path.duration_s + limits.settle_s,
                path=path.poses_at,
                arm=self._arm,
            )
            self._launch(motion, partial(self._follow_path, path=path, planned=planned))
        if not asynchronous:
            self.wait()
            if not motion.reached:
                raise RobotError("move stopped before the end of the path")

    def move_joints(self, q_target: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Start a moveJ to joints ``q_target`` (rad): every joint on one trapezoid, timed by the
        joint that turns furthest at ``speed_rad_s`` and ``accel_rad_s2``. Does not wait."""
        q_target = np.asarray(q_target, dtype=float)
        with self._lock:
            self._require_idle()
            q_start = self._joints.copy()
            distance = float(np.abs(q_target - q_start).max())
            motion = _Motion(
                start=self._arm.forward(q_start),
                target=self._arm.forward(q_target),
                final_joints=q_target,
                limits=MotionLimits(settle_s=0.0),
                duration_s=trapezoid_duration(distance, speed_rad_s, accel_rad_s2),
                path=_joint_path(q_start, q_target, speed_rad_s, accel_rad_s2, self._arm),
                arm=self._arm,
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
        motion.started_at = time.time()
        motion.wall_per_robot_s = self._time_scale
        self._remember(motion)
        self._motion = motion
        if self._time_scale == 0.0 or motion.duration_s == 0.0:
            self._joints = motion.final_joints
            self._elapsed_motion_s += motion.duration_s
            motion.running, motion.reached = False, True
            self._end_motion(motion, motion.started_at, self._arm.forward(motion.final_joints))
            return
        motion.thread = threading.Thread(target=self._run, args=(motion, follow), daemon=True)
        motion.thread.start()

    def _remember(self, motion: _Motion) -> None:
        """Add ``motion`` to the pose stream's history, forgetting moves older than it keeps."""
        self._motions.append(motion)
        horizon = motion.started_at - HISTORY_S
        while len(self._motions) > 1 and self._motions[1].started_at < horizon:
            end_pose = self._motions.pop(0).end_pose
            assert end_pose is not None  # a move starts only once the one before it has come to rest
            self._rest_pose = end_pose

    @staticmethod
    def _end_motion(motion: _Motion, at: float, pose: np.ndarray) -> None:
        motion.ended_at, motion.end_pose = at, pose

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
            if motion.running and motion.halted_at is None:
                motion.halted_at = time.time()
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
        settle; the robot time it took is added to ``elapsed_motion_s``. The profile's time runs
        from the move's start on the twin's clock, as the pose stream's does."""
        t0 = time.monotonic() - (time.time() - motion.started_at)
        try:
            follow(motion, t0)
            if not motion.reached and motion.fault is None:
                self._halt_where_stopped(motion)
            if motion.reached:
                motion.halt.wait(motion.limits.settle_s * self._time_scale)
        finally:
            completed = motion.reached and not motion.halt.is_set()
            robot_time = min((time.monotonic() - t0) / self._time_scale, motion.duration_s)
            with self._lock:
                self._elapsed_motion_s += motion.duration_s if completed else robot_time
                motion.running = False

    def _halt_where_stopped(self, motion: _Motion) -> None:
        """A halted move rests where the profile had the flange when Stop came."""
        at = motion.halted_at if motion.halted_at is not None else time.time()
        pose = motion.poses_at(np.array([at]))[0]
        with self._lock:
            q = self._joints
        try:
            q = self._arm.closest_ik(pose, q)
        except Unreachable:
            pose = self._arm.forward(q)
        with self._lock:
            self._joints = q
            self._end_motion(motion, at, pose)

    def _arrive(self, motion: _Motion) -> None:
        with self._lock:
            self._joints = motion.final_joints
            arrived_at = motion.started_at + motion.duration_s * motion.wall_per_robot_s
            self._end_motion(motion, arrived_at, self._arm.forward(motion.final_joints))
        motion.reached = True

    def _fault(self, motion: _Motion, text: str) -> None:
        with self._lock:
            motion.fault = text
            self._end_motion(motion, time.time(), self._arm.forward(self._joints))

    def _follow_joints(self, motion: _Motion, t0: float, q_start: np.ndarray, distance: float, speed: float,
                       accel: float) -> None:
        """Worker: joints along the trapezoid, all in step, until reached or halted."""
        while not motion.halt.wait(_TICK_S):
            t = (time.monotonic() - t0) / self._time_scale
            if t >= motion.duration_s:
                self._arrive(motion)
                return
            fraction = trapezoid_position(t, distance, speed, accel) / distance
            with self._lock:
                self._joints = q_start + fraction * (motion.final_joints - q_start)

    def _track(self, motion: _Motion, t0: float,
               at: Callable[[float], tuple[np.ndarray, np.ndarray, str] | None]) -> None:
        """Worker: each tick, ``at(t)`` gives the flange pose the profile has at robot time ``t``,
        the joints planned there and how to name the place (None once the move has arrived); the
        IK solution nearest the planned joints becomes the arm's, so that a configuration change
        is found however far apart a busy machine's ticks fall."""
        while not motion.halt.wait(_TICK_S):
            step = at((time.monotonic() - t0) / self._time_scale)
            if step is None:
                self._arrive(motion)
                return
            pose, expected, where = step
            try:
                q = self._arm.closest_ik(pose, expected)
            except Unreachable as exc:
                self._fault(motion, f"protective stop {where}: {exc}")
                return
            if np.degrees(np.abs(q - expected)).max() > MAX_JOINT_JUMP_DEG:
                self._fault(motion, f"protective stop {where}: joint jump")
                return
            with self._lock:
                self._joints = q

    def _follow_path(self, motion: _Motion, t0: float, path: BlendedPath, planned: np.ndarray) -> None:
        """Worker: the joints along a blended path, planned at its ``CHECK_STEP_S`` samples."""

        def at(t: float) -> tuple[np.ndarray, np.ndarray, str] | None:
            if t >= path.duration_s:
                return None
            expected = planned[min(int(t / CHECK_STEP_S), len(planned) - 1)]
            return path.poses_at(np.array([t]))[0], expected, f"{t:.2f} s into the path"

        self._track(motion, t0, at)

    def _follow(self, motion: _Motion, t0: float, planned: np.ndarray) -> None:
        """Worker: the joints along the straight path, planned before the move at evenly spaced
        fractions (``planned``)."""
        samples = np.linspace(0.0, 1.0, len(planned))

        def at(t: float) -> tuple[np.ndarray, np.ndarray, str] | None:
            fraction = linear_move_progress(t, motion.start, motion.target, motion.limits)
            if fraction >= 1.0:
                return None
            expected = np.array([np.interp(fraction, samples, planned[:, j]) for j in range(6)])
            return (interpolate_pose(motion.start, motion.target, fraction), expected,
                    f"at {fraction:.0%} of the move")

        self._track(motion, t0, at)
