"""A path through flange poses without stopping (core.robot.trajectory)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.robot.contract import HOME_JOINTS, HOME_TOOL_TO_BASE
from probecal.core.robot.trajectory import blended_path
from probecal.core.robot.ur3 import MotionLimits, Unreachable


def _poses(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    poses = [HOME_TOOL_TO_BASE]
    for _ in range(n):
        pose = HOME_TOOL_TO_BASE.copy()
        pose[:3, 3] += rng.uniform(-20, 20, 3)
        pose[:3, :3] = Rotation.from_rotvec(rng.uniform(-0.2, 0.2, 3)).as_matrix() @ pose[:3, :3]
        poses.append(pose)
    return poses


def test_the_path_starts_and_ends_at_rest_on_its_poses_within_the_limits():
    poses, limits = _poses(8), MotionLimits()
    path = blended_path(poses, limits)
    t = np.linspace(0, path.duration_s, 20001)
    positions = path.poses_at(t)[:, :3, 3]
    velocity = np.gradient(positions, t, axis=0)
    accel = np.gradient(velocity, t, axis=0)
    assert np.linalg.norm(velocity, axis=1).max() <= limits.linear_speed_mm_s * 1.001
    assert np.linalg.norm(accel[5:-5], axis=1).max() <= limits.linear_accel_mm_s2 * 1.01
    assert np.allclose(path.poses_at(np.array([-1.0, 0.0]))[:, :3, 3], poses[0][:3, 3])
    assert np.allclose(path.poses_at(np.array([path.duration_s, path.duration_s + 5]))[:, :3, 3], poses[-1][:3, 3])
    assert np.allclose(path.end, poses[-1])
    # It passes near every pose (the blends cut the corners) and never jumps.
    for pose in poses[1:-1]:
        assert np.linalg.norm(positions - pose[:3, 3], axis=1).min() < 15.0
    assert np.linalg.norm(np.diff(positions, axis=0), axis=1).max() < 0.1
    # Faster than stopping at every pose.
    from probecal.core.robot.ur3 import linear_move_motion_time
    stops = sum(linear_move_motion_time(a, b, limits) for a, b in zip(poses, poses[1:]))
    assert path.duration_s < stops


def test_the_joints_along_the_path_are_checked_before_the_robot_moves():
    path = blended_path(_poses(4))
    joints = path.joints_along(HOME_JOINTS)
    assert joints.shape[1] == 6 and np.degrees(np.abs(np.diff(joints, axis=0))).max() < 5
    far = HOME_TOOL_TO_BASE.copy()
    far[:3, 3] = [0.0, -900.0, 250.0]  # beyond the UR3's reach
    with pytest.raises(Unreachable):
        blended_path([HOME_TOOL_TO_BASE, far]).joints_along(HOME_JOINTS)
    with pytest.raises(ValueError, match="a start and at least one more pose"):
        blended_path([HOME_TOOL_TO_BASE])
