"""A path through flange poses without stopping: straight segments at constant speed joined by
blends of constant acceleration, the way a UR's moveL with a blend radius runs a list of poses.

The pose is (position mm, orientation) with the orientation as a rotation vector relative to
the first pose's, so segments and blends are straight lines and parabolas in six numbers.
Segment speeds follow the linear and angular speed limits; each blend lasts long enough to keep
within the acceleration limits, and a segment is slowed until its two blends fit inside it. The
path starts at rest on the first pose, passes near the others (the blends cut their corners)
and ends at rest on the last. Poses are ``tool_to_base`` 4x4 (mm), times in s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.robot.ur3 import (
    MAX_JOINT_JUMP_DEG,
    NOMINAL_UR3,
    ArmModel,
    MotionLimits,
    Unreachable,
    check_pose,
)

MIN_SEGMENT_S = 0.01
"""Shortest segment (s): repeated poses still take a moment."""
SLOWDOWN = 1.1
"""Factor a segment is slowed by, per round, until its blends fit inside it."""
CHECK_STEP_S = 0.02
"""Spacing (s) of the samples whose joints are checked before the robot moves."""


@dataclass(frozen=True)
class BlendedPath:
    """The path through ``waypoints`` (n, 6: position mm, rotation vector rad relative to
    ``reference`` 3x3) passing waypoint k's line at ``times[k]`` (s) with blends of half-width
    ``blends[k]`` (s) and ``velocities`` (n + 1, 6) per segment, zero before and after."""

    reference: np.ndarray
    waypoints: np.ndarray
    times: np.ndarray
    blends: np.ndarray
    velocities: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.times[-1] + self.blends[-1])

    @property
    def end(self) -> np.ndarray:
        return self._poses(self.waypoints[-1:])[0]

    def _poses(self, q: np.ndarray) -> np.ndarray:
        poses = np.zeros((len(q), 4, 4))
        poses[:, :3, :3] = self.reference @ Rotation.from_rotvec(q[:, 3:]).as_matrix()
        poses[:, :3, 3] = q[:, :3]
        poses[:, 3, 3] = 1.0
        return poses

    def poses_at(self, t: np.ndarray) -> np.ndarray:
        """Flange poses (n, 4, 4) at times ``t`` (n,) s since the start; at rest before and after."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration_s)
        k = np.clip(np.searchsorted(self.times - self.blends, t, side="right") - 1, 0, len(self.times) - 1)
        dt = t - self.times[k]
        tau = self.blends[k]
        before, after = self.velocities[k], self.velocities[k + 1]
        in_blend = (dt <= tau)[:, None]
        ramp = np.where(tau > 0, (dt + tau) ** 2 / (4 * np.where(tau > 0, tau, 1.0)), 0.0)[:, None]
        q = self.waypoints[k] + np.where(in_blend, before * dt[:, None] + (after - before) * ramp, after * dt[:, None])
        return self._poses(q)

    def joints_along(self, start_joints: np.ndarray, step_s: float = CHECK_STEP_S,
                     arm: ArmModel = NOMINAL_UR3) -> np.ndarray:
        """Joints (rad) at every ``step_s`` along the path and at its end, each the IK solution of
        ``arm`` closest to the one before, from ``start_joints``. Raises Unreachable where a pose
        has no solution or a joint would jump (a configuration change)."""
        times = np.append(np.arange(0.0, self.duration_s, step_s), self.duration_s)
        joints = [np.asarray(start_joints, dtype=float)]
        for t, pose in zip(times, self.poses_at(times)):
            try:
                q = arm.closest_ik(pose, joints[-1])
            except Unreachable as exc:
                raise Unreachable(f"the blended path fails {t:.2f} s in: {exc}") from exc
            if np.degrees(np.abs(q - joints[-1])).max() > MAX_JOINT_JUMP_DEG:
                raise Unreachable(f"a joint would jump {t:.2f} s into the blended path (configuration change)")
            joints.append(q)
        return np.array(joints[1:])


def blended_path(poses: list[np.ndarray], limits: MotionLimits | None = None) -> BlendedPath:
    """The path through ``poses`` (the first is where the robot stands) within ``limits``'s
    speeds and accelerations (mm/s, mm/s^2, deg/s, deg/s^2)."""
    limits = limits or MotionLimits()
    if len(poses) < 2:
        raise ValueError("a path needs a start and at least one more pose")
    checked = [check_pose(p) for p in poses]
    reference = checked[0][:3, :3]
    waypoints = np.array([[*p[:3, 3], *Rotation.from_matrix(reference.T @ p[:3, :3]).as_rotvec()] for p in checked])
    steps = np.diff(waypoints, axis=0)
    speed = np.array([limits.linear_speed_mm_s, np.radians(limits.angular_speed_deg_s)])
    accel = np.array([limits.linear_accel_mm_s2, np.radians(limits.angular_accel_deg_s2)])
    norms = np.column_stack([np.linalg.norm(steps[:, :3], axis=1), np.linalg.norm(steps[:, 3:], axis=1)])
    durations = np.maximum((norms / speed).max(axis=1), MIN_SEGMENT_S)
    while True:
        velocities = np.vstack([np.zeros(6), steps / durations[:, None], np.zeros(6)])
        change = np.diff(velocities, axis=0)
        jumps = np.column_stack([np.linalg.norm(change[:, :3], axis=1), np.linalg.norm(change[:, 3:], axis=1)])
        blends = (jumps / (2 * accel)).max(axis=1)
        crowded = blends[:-1] + blends[1:] > durations
        if not crowded.any():
            break
        durations = np.where(crowded, durations * SLOWDOWN, durations)
    times = blends[0] + np.concatenate([[0.0], np.cumsum(durations)])
    return BlendedPath(reference, waypoints, times, blends, velocities)
