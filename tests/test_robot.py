"""The robot interface and the simulated UR3 (core/robot/simulated.py)."""

import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.geometry.transforms import interpolate_pose, make_transform, transform_error
from probecal.core.robot.contract import HOME_JOINTS, HOME_TOOL_TO_BASE, Robot, RobotError
from probecal.core.robot.simulated import SimulatedRobot, Unreachable
from probecal.core.robot.ur3 import (
    ArmModel,
    DhDeviation,
    MotionLimits,
    forward_kinematics,
    linear_move_duration,
    linear_path_joints,
)
from tests.support.waiting import assert_still, wait_until


def shifted(pose, dx=0.0, dy=0.0, dz=0.0, rot_deg=(0.0, 0.0, 0.0)):
    """``pose`` moved by (dx, dy, dz) mm in base and turned by xyz Euler angles about its origin."""
    rotation = Rotation.from_euler("xyz", rot_deg, degrees=True).as_matrix() @ pose[:3, :3]
    return make_transform(rotation, pose[:3, 3] + [dx, dy, dz])


def connected_robot(**kwargs) -> SimulatedRobot:
    robot = SimulatedRobot(**kwargs)
    robot.connect()
    return robot


def test_simulated_robot_implements_the_protocol():
    assert isinstance(SimulatedRobot(), Robot)


def test_home_pose_points_the_probe_down_inside_reach():
    np.testing.assert_allclose(forward_kinematics(HOME_JOINTS), HOME_TOOL_TO_BASE, atol=1e-9)
    np.testing.assert_allclose(HOME_TOOL_TO_BASE[:3, 2], [0.0, 0.0, -1.0])
    robot = connected_robot()
    np.testing.assert_allclose(robot.tool_to_base(), HOME_TOOL_TO_BASE, atol=1e-9)
    np.testing.assert_allclose(robot.joints(), HOME_JOINTS)


def test_interpolate_pose_is_linear_and_slerped():
    end = shifted(HOME_TOOL_TO_BASE, dx=40.0, rot_deg=(0.0, 0.0, 20.0))
    mid = interpolate_pose(HOME_TOOL_TO_BASE, end, 0.5)
    np.testing.assert_allclose(mid[:3, 3], HOME_TOOL_TO_BASE[:3, 3] + [20.0, 0.0, 0.0])
    assert transform_error(HOME_TOOL_TO_BASE, mid)[1] == pytest.approx(10.0)
    np.testing.assert_allclose(interpolate_pose(HOME_TOOL_TO_BASE, end, 1.0), end, atol=1e-12)


def test_linear_path_joints_is_continuous():
    target = shifted(HOME_TOOL_TO_BASE, dx=60.0, dz=-40.0, rot_deg=(10.0, -10.0, 30.0))
    path = linear_path_joints(HOME_JOINTS, target)
    assert path.shape == (21, 6)
    assert np.degrees(np.abs(np.diff(path, axis=0))).max() < 30.0
    np.testing.assert_allclose(forward_kinematics(path[-1]), target, atol=1e-6)


def test_not_connected_refuses_moves_and_reads_but_stop_is_safe():
    robot = SimulatedRobot(time_scale=0.0)
    assert not robot.connected
    with pytest.raises(RobotError, match="robot not connected"):
        robot.move_linear(HOME_TOOL_TO_BASE)
    with pytest.raises(RobotError):
        robot.tool_to_base()
    robot.stop()
    assert not robot.is_moving()
    assert robot.wait(0.0)


def test_blocking_move_reaches_target():
    robot = connected_robot(time_scale=0.05)
    start = robot.tool_to_base()
    target = shifted(HOME_TOOL_TO_BASE, dx=30.0, dy=-20.0, rot_deg=(0.0, 5.0, 10.0))
    robot.move_linear(target)
    assert not robot.is_moving()
    dt, dr = transform_error(robot.tool_to_base(), target)
    assert dt < 0.1 and dr < 0.02
    assert robot.elapsed_motion_s == pytest.approx(linear_move_duration(start, target, MotionLimits()))


SLOW = MotionLimits(linear_speed_mm_s=25.0)
"""Slow enough that a move is still under way when a busy test process looks (4 s for 100 mm)."""


def assert_asynchronous_move_then_wait(robot: Robot, wait_s: float) -> None:
    """The Robot contract for moveL without blocking, on any backend: moving until waited for,
    a second move refused meanwhile, and the target reached."""
    target = shifted(HOME_TOOL_TO_BASE, dx=100.0)
    robot.move_linear(target, SLOW, asynchronous=True)
    assert robot.is_moving()
    assert robot.wait(timeout=0.001) is False
    with pytest.raises(RobotError, match="already moving"):
        robot.move_linear(HOME_TOOL_TO_BASE)
    assert robot.wait(timeout=wait_s)
    assert not robot.is_moving()
    assert transform_error(robot.tool_to_base(), target)[0] < 0.1


def test_asynchronous_move_then_wait():
    assert_asynchronous_move_then_wait(connected_robot(time_scale=0.25), 10.0)  # 4 s on the robot, 1 s here


def assert_path_passes_without_stopping(robot: Robot, wait_s: float) -> None:
    """The Robot contract for move_path on any backend: through the poses without stopping
    (the pose stream never rests between the first and the last), near each of them, at rest on
    the last; a second move refused meanwhile."""
    start = robot.tool_to_base()
    poses = [shifted(start, dz=10.0), shifted(start, dx=20.0), shifted(start, dx=20.0, dz=10.0), start]
    began = time.time()
    robot.move_path(poses, MotionLimits(linear_speed_mm_s=50.0), asynchronous=True)
    with pytest.raises(RobotError, match="already moving"):
        robot.move_linear(start)
    assert robot.wait(timeout=wait_s) and not robot.is_moving()
    assert transform_error(robot.tool_to_base(), start)[0] < 0.1
    stream = robot.poses_since(began)
    positions = stream.tool_to_base[:, :3, 3]
    moving = np.flatnonzero(np.linalg.norm(positions - start[:3, 3], axis=1) > 0.5)
    steps = np.linalg.norm(np.diff(positions[moving[0] : moving[-1]], axis=0), axis=1)
    assert steps.min() > 0.0  # never at rest on the way
    for pose in poses[:-1]:
        assert distance_to_path(positions, pose[:3, 3]) < 5.0


def distance_to_path(positions: np.ndarray, point: np.ndarray) -> float:
    """How near (mm) the path through the sampled ``positions`` (N, 3), straight between samples,
    comes to ``point``: on a busy machine the pose stream can go a tenth of a second unsampled,
    several millimetres at path speed, so the nearest sample alone can miss where the path went."""
    a, ab = positions[:-1], np.diff(positions, axis=0)
    t = np.clip(np.einsum("ij,ij->i", point - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * ab - point, axis=1).min())


def travelled_mm(robot: Robot, start: np.ndarray) -> float:
    return float(np.linalg.norm(robot.tool_to_base()[:3, 3] - start[:3, 3]))


def stop_once_moving(robot: Robot) -> threading.Thread:
    """A thread that stops ``robot`` as soon as a move of it is under way."""
    def stop() -> None:
        wait_until(robot.is_moving, "the robot moving")
        robot.stop()

    thread = threading.Thread(target=stop, daemon=True)
    thread.start()
    return thread


def test_stop_halts_an_asynchronous_move_early():
    robot = connected_robot(time_scale=0.5)
    start = robot.tool_to_base()
    target = shifted(HOME_TOOL_TO_BASE, dx=150.0)  # 1.7 s on the robot, 0.85 s here
    robot.move_linear(target, asynchronous=True)
    wait_until(lambda: travelled_mm(robot, start) > 5.0, "5 mm of the move")
    robot.stop()
    assert not robot.is_moving()
    halted = robot.tool_to_base()
    assert 5.0 < travelled_mm(robot, start) < 140.0
    assert_still(robot, halted, time.time())
    # the arm followed the straight line and kept its orientation
    assert abs(halted[1, 3] - start[1, 3]) < 1e-4 and abs(halted[2, 3] - start[2, 3]) < 1e-4
    assert transform_error(halted, start)[1] < 1e-4  # degrees; arccos near 1 amplifies rounding
    assert robot.elapsed_motion_s < linear_move_duration(start, target, MotionLimits())
    robot.move_linear(start, asynchronous=False)
    assert transform_error(robot.tool_to_base(), start)[0] < 0.1


def test_stop_interrupts_a_blocking_move_with_an_error():
    robot = connected_robot(time_scale=0.5)
    stopper = stop_once_moving(robot)
    with pytest.raises(RobotError, match="stopped"):
        robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=150.0))
    stopper.join()
    assert not robot.is_moving()


def test_disconnect_stops_the_robot():
    robot = connected_robot(time_scale=0.5)
    robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=150.0), asynchronous=True)
    robot.disconnect()
    assert not robot.is_moving() and not robot.connected


@pytest.mark.parametrize(
    "target",
    [
        shifted(HOME_TOOL_TO_BASE, dy=-1000.0),  # 1 m away
        shifted(HOME_TOOL_TO_BASE, dy=600.0),  # reachable, but the line crosses the base axis
        np.full((4, 4), np.nan),
    ],
)
def test_unreachable_targets_are_refused_without_motion(target):
    robot = connected_robot(time_scale=0.0)
    with pytest.raises(Unreachable):
        robot.move_linear(target)
    np.testing.assert_array_equal(robot.joints(), HOME_JOINTS)
    assert robot.elapsed_motion_s == 0.0
    assert not robot.is_moving()


def test_fault_during_motion_is_a_protective_stop(monkeypatch):
    closest_ik = ArmModel.closest_ik
    main = threading.current_thread()

    def failing_off_main_thread(model, pose, q_ref):
        if threading.current_thread() is not main:
            raise Unreachable("simulated fault")
        return closest_ik(model, pose, q_ref)

    monkeypatch.setattr(ArmModel, "closest_ik", failing_off_main_thread)
    robot = connected_robot(time_scale=0.1)
    robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=50.0), asynchronous=True)
    with pytest.raises(RobotError, match="protective stop"):
        robot.wait(timeout=5.0)
    assert not robot.is_moving()
    np.testing.assert_array_equal(robot.joints(), HOME_JOINTS)
    with pytest.raises(RobotError, match="protective stop"):
        robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=50.0))


def test_a_calibrated_controller_reports_and_moves_by_its_own_kinematics():
    """Given a factory calibration, the pose it reports, the joints its moves solve for and its
    ``kinematics()`` follow the table plus those deviations; without one, the table and None."""
    deviation = DhDeviation.draw(np.random.default_rng(8), 1.0, 0.1)
    robot = connected_robot(time_scale=0.0, repeatability_mm=0.0, controller_calibration=deviation)
    assert robot.kinematics() is robot.model and robot.model.deviation is deviation
    assert connected_robot().kinematics() is None
    target = shifted(HOME_TOOL_TO_BASE, dx=40.0, dz=-30.0, rot_deg=(0.0, 10.0, 0.0))
    for move in (lambda: robot.move_linear(target), lambda: robot.move_path([shifted(target, dy=10.0), target])):
        robot.move_linear(HOME_TOOL_TO_BASE)
        move()
        assert transform_error(robot.tool_to_base(), target)[0] < 0.01
        np.testing.assert_allclose(robot.model.forward(robot.joints()), robot.tool_to_base(), atol=1e-6)
        assert transform_error(forward_kinematics(robot.joints()), target)[0] > 0.1  # not the table's joints


def test_repeatability_spread_is_about_0_03_mm_rms():
    robot = connected_robot(time_scale=0.0, seed=3)
    targets = [HOME_TOOL_TO_BASE, shifted(HOME_TOOL_TO_BASE, dx=10.0, rot_deg=(0.0, 0.0, 5.0))]
    errors, angles = [], []
    for k in range(150):
        target = targets[k % 2]
        robot.move_linear(target)
        pose = robot.tool_to_base()
        errors.append(np.linalg.norm(pose[:3, 3] - target[:3, 3]))
        angles.append(transform_error(pose, target)[1])
    rms = np.sqrt(np.mean(np.square(errors)))
    assert rms == pytest.approx(0.03, rel=0.15)
    assert np.max(angles) < 0.02


def test_zero_repeatability_is_exact_and_seeds_reproduce():
    target = shifted(HOME_TOOL_TO_BASE, dz=20.0)
    exact = connected_robot(time_scale=0.0, repeatability_mm=0.0)
    exact.move_linear(target)
    assert transform_error(exact.tool_to_base(), target)[0] < 1e-6
    first, second = connected_robot(time_scale=0.0, seed=5), connected_robot(time_scale=0.0, seed=5)
    first.move_linear(target)
    second.move_linear(target)
    np.testing.assert_array_equal(first.tool_to_base(), second.tool_to_base())


def test_elapsed_motion_accumulates_the_model_time():
    robot = connected_robot(time_scale=0.0)
    limits = MotionLimits(linear_speed_mm_s=50.0, settle_s=0.2)
    expected = 0.0
    for target in [
        shifted(HOME_TOOL_TO_BASE, dx=40.0),
        shifted(HOME_TOOL_TO_BASE, dx=40.0, rot_deg=(0.0, 0.0, 45.0)),
        HOME_TOOL_TO_BASE,
    ]:
        expected += linear_move_duration(robot.tool_to_base(), target, limits)
        robot.move_linear(target, limits)
    assert robot.elapsed_motion_s == pytest.approx(expected)
    assert expected > 3 * 0.2 + 40.0 / 50.0


def test_constructor_validates_arguments():
    with pytest.raises(ValueError):
        SimulatedRobot(home_joints=np.full(6, 7.0))
    with pytest.raises(ValueError):
        SimulatedRobot(time_scale=-1.0)
    with pytest.raises(ValueError):
        SimulatedRobot(repeatability_mm=np.nan)


def test_a_path_passes_its_poses_without_stopping():
    robot = connected_robot(time_scale=0.2)
    assert_path_passes_without_stopping(robot, 10.0)
    instant = connected_robot(time_scale=0.0)
    instant.move_path([shifted(HOME_TOOL_TO_BASE, dz=10.0), HOME_TOOL_TO_BASE])
    assert instant.elapsed_motion_s > 0.2 and transform_error(instant.tool_to_base(), HOME_TOOL_TO_BASE)[0] < 0.1
    with pytest.raises(Unreachable):
        instant.move_path([shifted(HOME_TOOL_TO_BASE, dy=-1000.0)])
