"""UR3 and UR3e kinematics and the motion-time model (core/robot/ur3.py)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.errors import InputError
from probecal.core.geometry.transforms import make_transform, transform_error
from probecal.core.robot.armkinematics import model_of, record_of
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.ur3 import (
    JOINT_LIMITS,
    REFINE_MM,
    UR3,
    UR3E,
    ArmModel,
    DhDeviation,
    DhTable,
    MotionLimits,
    Unreachable,
    closest_ik,
    forward_kinematics,
    identify_arm,
    inverse_kinematics,
    linear_move_duration,
    linear_move_motion_time,
    linear_move_progress,
    link_frames,
    trapezoid_duration,
    trapezoid_position,
)


def wrapped(angles):
    return (np.asarray(angles) + np.pi) % (2 * np.pi) - np.pi


def test_fk_zero_joints_matches_hand_derivation():
    # all joints 0: x = a2 + a3, y = -(d4 + d6), z = d1 - d5; the tool z axis is -base y
    expected = np.array(
        [
            [1.0, 0.0, 0.0, -456.9],
            [0.0, 0.0, -1.0, -194.25],
            [0.0, 1.0, 0.0, 66.55],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    np.testing.assert_allclose(forward_kinematics(np.zeros(6)), expected, atol=1e-9)


def test_fk_upright_arm_matches_hand_derivation():
    # shoulder and wrist 1 at -90 deg: arm straight up, z = d1 - a2 - a3 + d5
    expected = np.array(
        [
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, -194.25],
            [0.0, -1.0, 0.0, 694.15],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    q = [0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]
    np.testing.assert_allclose(forward_kinematics(q), expected, atol=1e-9)


def test_link_frames_origins_at_zero_joints():
    frames = link_frames(np.zeros(6))
    assert len(frames) == 7
    origins = np.array([f[:3, 3] for f in frames])
    expected = [
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 151.9],
        [-243.65, 0.0, 151.9],
        [-456.9, 0.0, 151.9],
        [-456.9, -112.35, 151.9],
        [-456.9, -112.35, 66.55],
        [-456.9, -194.25, 66.55],
    ]
    np.testing.assert_allclose(origins, expected, atol=1e-9)
    np.testing.assert_array_equal(frames[-1], forward_kinematics(np.zeros(6)))


def test_base_joint_rotates_the_whole_arm_about_base_z():
    q = np.array([0.0, -1.1, 0.7, -0.4, 1.3, 0.2])
    angle = 0.8
    turned = forward_kinematics(q + [angle, 0, 0, 0, 0, 0])
    rz = make_transform(Rotation.from_euler("z", angle), np.zeros(3))
    np.testing.assert_allclose(turned, rz @ forward_kinematics(q), atol=1e-9)


def test_ik_inverts_fk_on_random_poses():
    rng = np.random.default_rng(7)
    for _ in range(500):
        q = rng.uniform(-np.pi, np.pi, 6)
        pose = forward_kinematics(q)
        solutions = inverse_kinematics(pose)
        assert 1 <= len(solutions) <= 8
        assert np.all((solutions >= JOINT_LIMITS[:, 0]) & (solutions <= JOINT_LIMITS[:, 1]))
        for solution in solutions:
            dt, dr_deg = transform_error(forward_kinematics(solution), pose)
            assert dt < 1e-6 and np.radians(dr_deg) < 1e-6
        gap = np.abs(wrapped(solutions - q)).max(axis=1).min()
        assert gap < 1e-6


def test_closest_ik_returns_generating_joints_with_2pi_shifts():
    q = np.array([3.9, -1.0, 1.4, -5.5, -1.2, 6.0])
    np.testing.assert_allclose(closest_ik(forward_kinematics(q), q), q, atol=1e-9)
    near = q + 0.05
    np.testing.assert_allclose(closest_ik(forward_kinematics(q), near), q, atol=1e-9)


def test_closest_ik_picks_the_nearest_configuration():
    q = np.array([0.5, -1.6, 1.9, -1.9, -1.57, 0.3])
    pose = forward_kinematics(q)
    others = [s for s in inverse_kinematics(pose) if np.abs(wrapped(s - q)).max() > 1e-6]
    assert others
    for other in others:
        solution = closest_ik(pose, other)
        assert np.abs(wrapped(solution - other)).max() < 1e-6


def test_wrist_singularity_keeps_q6_and_reproduces_pose():
    q = np.array([0.3, -1.0, 1.2, 0.4, 0.0, 0.7])
    pose = forward_kinematics(q)
    for solution in inverse_kinematics(pose):
        dt, dr_deg = transform_error(forward_kinematics(solution), pose)
        assert dt < 1e-6 and dr_deg < 1e-4
    np.testing.assert_allclose(closest_ik(pose, q), q, atol=1e-9)


@pytest.mark.parametrize(
    "pose",
    [
        make_transform(np.eye(3), [1000.0, 0.0, 300.0]),
        make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 300.0]),  # wrist on the base axis
        np.full((4, 4), np.nan),
        make_transform(np.eye(3), [np.nan, 0.0, 0.0]),
        np.diag([2.0, 1.0, 1.0, 1.0]),
    ],
)
def test_unreachable_or_invalid_poses_raise(pose):
    with pytest.raises(Unreachable):
        inverse_kinematics(pose)
    with pytest.raises(Unreachable):
        closest_ik(pose, np.zeros(6))


def test_unreachable_is_a_value_error():
    assert issubclass(Unreachable, ValueError)


def test_trapezoid_triangular_profile():
    # 10 mm at 100 mm/s, 500 mm/s^2: v_max is never reached (needs 20 mm)
    duration = trapezoid_duration(10.0, 100.0, 500.0)
    assert duration == pytest.approx(2.0 * np.sqrt(10.0 / 500.0))
    assert trapezoid_position(duration / 2, 10.0, 100.0, 500.0) == pytest.approx(5.0)
    assert trapezoid_position(duration, 10.0, 100.0, 500.0) == pytest.approx(10.0)


def test_trapezoid_profile_with_cruise():
    duration = trapezoid_duration(100.0, 100.0, 500.0)
    assert duration == pytest.approx(100.0 / 100.0 + 100.0 / 500.0)
    assert trapezoid_position(0.2, 100.0, 100.0, 500.0) == pytest.approx(10.0)  # end of ramp
    assert trapezoid_position(0.7, 100.0, 100.0, 500.0) == pytest.approx(60.0)  # cruising
    assert trapezoid_position(duration, 100.0, 100.0, 500.0) == pytest.approx(100.0)
    assert trapezoid_position(duration + 1.0, 100.0, 100.0, 500.0) == 100.0
    assert trapezoid_position(-1.0, 100.0, 100.0, 500.0) == 0.0
    t = np.linspace(0.0, duration, 200)
    positions = [trapezoid_position(ti, 100.0, 100.0, 500.0) for ti in t]
    assert np.all(np.diff(positions) >= 0.0)


def test_trapezoid_zero_distance_and_bad_limits():
    assert trapezoid_duration(0.0, 100.0, 500.0) == 0.0
    with pytest.raises(ValueError):
        trapezoid_duration(-1.0, 100.0, 500.0)
    with pytest.raises(ValueError):
        trapezoid_duration(1.0, 0.0, 500.0)
    with pytest.raises(ValueError):
        MotionLimits(linear_speed_mm_s=-1.0)


def test_linear_move_duration_takes_the_slower_axis_plus_settle():
    limits = MotionLimits()
    start = make_transform(np.eye(3), [0.0, -300.0, 250.0])
    shifted = make_transform(np.eye(3), [100.0, -300.0, 250.0])
    turned = make_transform(Rotation.from_euler("z", 90, degrees=True), [0.0, -300.0, 250.0])
    both = make_transform(Rotation.from_euler("z", 90, degrees=True), [100.0, -300.0, 250.0])
    assert linear_move_duration(start, shifted, limits) == pytest.approx(1.2 + limits.settle_s)
    assert linear_move_motion_time(start, turned, limits) == pytest.approx(90 / 60 + 60 / 300)
    assert linear_move_motion_time(start, both, limits) == pytest.approx(1.7)
    assert linear_move_duration(start, start, limits) == pytest.approx(limits.settle_s)


def test_linear_move_progress_runs_from_zero_to_one():
    limits = MotionLimits()
    start = make_transform(np.eye(3), [0.0, -300.0, 250.0])
    end = make_transform(Rotation.from_euler("x", 30, degrees=True), [50.0, -300.0, 250.0])
    motion = linear_move_motion_time(start, end, limits)
    assert linear_move_progress(0.0, start, end, limits) == 0.0
    assert linear_move_progress(motion / 2, start, end, limits) == pytest.approx(0.5)
    assert linear_move_progress(motion, start, end, limits) == pytest.approx(1.0)
    assert linear_move_progress(0.0, start, start, limits) == 1.0


def test_dh_deviation_moves_the_flange_systematically():
    """A real arm's DH parameters off UR's table by a few tenths of a mm and hundredths of a
    degree put the flange up to a few mm from where the table says, differently per pose."""
    zero = DhDeviation(*np.zeros((4, 6)))
    deviation = DhDeviation.draw(np.random.default_rng(4), 0.3, 0.03)
    q = np.array([[0.1, -1.2, 1.0, -1.4, -1.57, 0.3], [0.9, -1.7, 1.6, -0.8, -1.2, -0.5]])
    assert np.allclose(forward_kinematics(q, zero), forward_kinematics(q))
    offsets = forward_kinematics(q, deviation)[:, :3, 3] - forward_kinematics(q)[:, :3, 3]
    assert np.all((0.1 < np.linalg.norm(offsets, axis=1)) & (np.linalg.norm(offsets, axis=1) < 3.0))
    assert np.linalg.norm(offsets[0] - offsets[1]) > 0.05


def test_the_ur3e_table_inverts_and_each_arm_is_named_by_what_its_controller_reports():
    """A UR3e's joints and reported flange name its table (its links are centimetres from the
    UR3's); an arm of neither table, or a pose of another state, is named by none."""
    rng = np.random.default_rng(11)
    ur5 = DhTable("UR5", np.array([89.159, 0.0, 0.0, 109.15, 94.65, 82.3]),
                  np.array([0.0, -425.0, -392.25, 0.0, 0.0, 0.0]), UR3.alpha)
    for _ in range(100):
        q = rng.uniform(-np.pi, np.pi, 6)
        pose = forward_kinematics(q, table=UR3E)
        for solution in inverse_kinematics(pose, table=UR3E):
            dt, dr_deg = transform_error(forward_kinematics(solution, table=UR3E), pose)
            assert dt < 1e-6 and np.radians(dr_deg) < 1e-6
        np.testing.assert_allclose(closest_ik(pose, q, UR3E), q, atol=1e-9)
        assert identify_arm(q, pose) is UR3E
        assert identify_arm(q, forward_kinematics(q)) is UR3
        assert identify_arm(q, forward_kinematics(q, table=ur5)) is None
    moved = forward_kinematics(q + [0.05, 0, 0, 0, 0, 0])
    assert identify_arm(q, moved) is None


def test_a_calibrated_model_meets_the_pose_its_own_kinematics_give():
    """The table's analytic IK, then Newton on the calibrated forward kinematics: the joints
    that put the flange there, to 1e-9 mm; UR's table alone answers as the table's IK does."""
    rng = np.random.default_rng(5)
    model = ArmModel(UR3, DhDeviation.draw(rng, 1.0, 0.1))
    for q in HOME_JOINTS + rng.uniform(-0.8, 0.8, (50, 6)):
        pose = model.forward(q)
        solution = model.closest_ik(pose, q)
        assert transform_error(model.forward(solution), pose)[0] < REFINE_MM
        np.testing.assert_allclose(solution, q, atol=1e-9)
        assert np.array_equal(ArmModel().closest_ik(pose, q), closest_ik(pose, q))


def test_a_controllers_dh_parameters_name_their_table_and_give_back_the_deviation():
    rng = np.random.default_rng(6)
    deviation = DhDeviation.draw(rng, 1.0, 0.1)
    q = HOME_JOINTS + rng.uniform(-0.5, 0.5, 6)
    for table in (UR3, UR3E):
        model = ArmModel.from_dh(*ArmModel(table, deviation).dh(), q)
        assert model is not None and model.table is table
        for name in ("theta", "d", "a", "alpha"):
            np.testing.assert_allclose(getattr(model.deviation, name), getattr(deviation, name), atol=1e-12)
    theta, a, d, alpha = ArmModel(UR3, deviation).dh()
    assert ArmModel.from_dh(theta, a * 1.5, d, alpha, q) is None  # an arm of no known table
    assert ArmModel.from_dh(theta, a, np.full(6, np.nan), alpha, q) is None


def test_recorded_kinematics_give_back_the_model_or_are_refused():
    deviation = DhDeviation.draw(np.random.default_rng(7), 1.0, 0.1)
    model = model_of(record_of(ArmModel(UR3E, deviation)), Path("manifest.json"))
    assert model.table is UR3E
    for name in ("theta", "d", "a", "alpha"):
        np.testing.assert_allclose(getattr(model.deviation, name), getattr(deviation, name), atol=1e-15)
    record = record_of(ArmModel(UR3, deviation))
    with pytest.raises(InputError, match="manifest.json: arm_kinematics.model: 'UR5' is not an arm"):
        model_of(replace(record, model="UR5"), Path("manifest.json"))
    with pytest.raises(InputError, match="manifest.json: arm_kinematics: these deviations do not describe a UR3"):
        model_of(replace(record, d_mm=(500.0, *record.d_mm[1:])), Path("manifest.json"))


def test_a_calibration_that_moves_parallel_joints_far_along_their_axes_is_the_same_arm():
    """A UR's calibration can put the common normal of joints 2 and 3 hundreds of metres away
    (d2 and d3 large and opposite): recorded, read back and inverted, it is still the table's arm."""
    far = DhDeviation(theta=np.zeros(6), d=np.array([0.0, 4e8, -4e8, 0.0, 0.0, 0.0]), a=np.zeros(6),
                      alpha=np.zeros(6))
    model = model_of(record_of(ArmModel(UR3, far)), Path("manifest.json"))
    q = HOME_JOINTS + 0.3
    assert transform_error(model.forward(q), forward_kinematics(q))[0] < 1e-6
    np.testing.assert_allclose(model.closest_ik(forward_kinematics(q), q), q, atol=1e-9)
