"""The twin's levels: ``bench`` records the bench's errors it adds, and they act as stated."""

from dataclasses import replace

import numpy as np
import pytest

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.kinematics import ARMS
from probecal.core.geometry.transforms import transform_error
from probecal.core.twin.levels import BENCH_SETUP, LEVELS, level, water_sound_speed
from probecal.core.twin.twin import make_twin


def test_water_sound_speed_follows_marczak():
    assert water_sound_speed(20.0) == pytest.approx(1482.3, abs=0.2)
    assert water_sound_speed(25.0) > water_sound_speed(18.0)


def test_an_unknown_level_is_refused_by_name():
    with pytest.raises(ValueError, match="none, realistic, harsh, bench"):
        level("loud")


def test_cli_offers_exactly_the_levels_and_arms_and_defaults_to_bench():
    from probecal.app import cli

    assert cli.NOISE_LEVELS == tuple(LEVELS) and cli.DEFAULT_LEVEL == "bench"
    assert cli.ARMS == ARMS


def test_the_perfect_levels_keep_a_perfect_set_up():
    twin = make_twin(3, setup=LEVELS["realistic"].setup)
    assert twin.built_phantom is None and twin.dh_deviation is None and twin.image_latency_s == 0.0
    assert twin.probe.medium_sound_speed == 1480.0


def test_mount_and_placement_of_a_seed_are_the_same_at_every_level():
    a, b = make_twin(5), make_twin(5, setup=BENCH_SETUP)
    assert np.array_equal(a.image_to_flange_rigid, b.image_to_flange_rigid)
    assert np.array_equal(a.phantom_to_base, b.phantom_to_base)


def test_layers_built_off_move_whole_and_leave_the_rest_of_the_seed_alone():
    plain = make_twin(5, setup=BENCH_SETUP)
    layered = make_twin(5, setup=replace(BENCH_SETUP, layer_tolerance=(0.5,) * 3 + (0.5,) * 3))
    assert np.array_equal(plain.image_to_flange_rigid, layered.image_to_flange_rigid)
    assert plain.image_latency_s == layered.image_latency_s
    assert np.array_equal(plain.dh_deviation.d, layered.dh_deviation.d)
    definition = plain.phantom.lines()
    # What the layers add to the wires' own tolerance, applied to the definition: each layer moved
    # rigidly, its end points keeping their distances.
    placed = definition + layered.built_phantom.lines() - plain.built_phantom.lines()
    assert np.abs(placed - definition).max() > 0.05
    for layer in range(len(plain.phantom.layers)):
        a, b = (ends[3 * layer:3 * layer + 3].reshape(-1, 3) for ends in (definition, placed))
        assert np.allclose(np.linalg.norm(a[:, None] - a[None], axis=2), np.linalg.norm(b[:, None] - b[None], axis=2))
    # Per axis: layers slid along their wires (phantom y) only move the end points along y.
    slid = make_twin(5, setup=replace(BENCH_SETUP, layer_tolerance=(0.0, 0.5, 0.0, 0.0, 0.0, 0.0)))
    moved = slid.built_phantom.lines() - plain.built_phantom.lines()
    assert np.abs(moved[..., 1]).max() > 0.05 and np.allclose(moved[..., [0, 2]], 0.0)
    # Diagonals built off across themselves: only the diagonal wires move, nothing else of the seed.
    diagonals = make_twin(5, setup=replace(BENCH_SETUP, diagonal_tolerance_mm=1.0))
    moved = diagonals.built_phantom.lines() - plain.built_phantom.lines()
    assert np.abs(moved[1::3]).max() > 0.2 and np.allclose(np.delete(moved, np.s_[1::3], axis=0), 0.0)
    assert diagonals.image_latency_s == plain.image_latency_s
    # Diagonals shifted across themselves as a whole: both ends of each by the same amount.
    shifted = make_twin(5, setup=replace(BENCH_SETUP, diagonal_shift_mm=1.0))
    moved = shifted.built_phantom.lines() - plain.built_phantom.lines()
    assert np.abs(moved[1::3]).max() > 0.2 and np.allclose(np.delete(moved, np.s_[1::3], axis=0), 0.0)
    assert np.allclose(moved[1::3, 0], moved[1::3, 1])
    # Diagonals turned about their middles: the ends the opposite ways.
    turned = make_twin(5, setup=replace(BENCH_SETUP, diagonal_turn_mm=1.0))
    moved = turned.built_phantom.lines() - plain.built_phantom.lines()
    assert np.abs(moved[1::3]).max() > 0.2 and np.allclose(np.delete(moved, np.s_[1::3], axis=0), 0.0)
    assert np.allclose(moved[1::3, 0], -moved[1::3, 1])
    assert np.all(np.abs(plain.phantom.diagonal_turns(moved)) <= 1.0)
    layers = len(plain.phantom.layers)
    np.testing.assert_allclose(plain.phantom.diagonal_turns(plain.phantom.diagonal_shifts([[-0.4, 0.4]] * layers)), 0.4)


@pytest.fixture(scope="module")
def bench_session(tmp_path_factory):
    return simulate_calibration(tmp_path_factory.mktemp("bench") / "cal", n_poses=12, seed=2, noise="bench")


def test_bench_truth_records_every_error(bench_session):
    setup = bench_session.truth()["setup"]
    lo, hi = BENCH_SETUP.water_temperature_c
    assert lo <= setup["water_temperature_c"] <= hi
    assert setup["sound_speed_m_s"] == pytest.approx(water_sound_speed(setup["water_temperature_c"]), abs=0.01)
    sx, sy = bench_session.truth()["pixel_spacing_mm"]
    assert sy == pytest.approx(0.1 * setup["sound_speed_m_s"] / 1540.0)
    assert BENCH_SETUP.image_latency_s[0] <= setup["image_latency_s"] <= BENCH_SETUP.image_latency_s[1]
    built = np.array(setup["wires_as_built"])
    offsets = np.abs(built - bench_session.phantom.lines())
    assert offsets.max() <= BENCH_SETUP.phantom_tolerance_mm and offsets.max() > 0.0
    assert len(setup["dh_deviation"]["d_mm"]) == 6
    assert bench_session.manifest.source["noise"] == "bench"


def test_bench_records_the_reported_pose_and_images_the_actual_one(bench_session):
    """The session holds what the controller reports; truth holds where the tool frame was, a
    systematic sub-mm to mm away (absolute error of the arm), and the images show that."""
    frames = bench_session.truth()["frames"]
    poses = bench_session.poses()
    gaps = [transform_error(poses[f["index"]], np.array(f["tool_to_base"]))[0] for f in frames]
    assert all(0.05 < g < 3.0 for g in gaps)


def test_bench_frames_are_stamped_late_by_the_latency(bench_session):
    setup = bench_session.truth()["setup"]
    delays = np.array([r.timestamp - r.pose_timestamp for r in bench_session.records])
    assert np.all(np.abs(delays - setup["image_latency_s"]) < 5 * setup["timestamp_jitter_s"])
    assert delays.std() > 0.0


def test_the_true_calibration_carries_the_arms_constant_flange_error():
    """Link 6's own deviations move the flange by the same transform at every pose: to the
    controller that is part of the mount. With only those, the true calibration and the reported
    poses put every image point exactly where the real flange and mount put it."""
    from dataclasses import replace

    from probecal.core.robot.ur3 import DhDeviation, forward_kinematics

    twin = make_twin(4, setup=BENCH_SETUP)
    link6 = DhDeviation(*(np.eye(6)[5] * v for v in (4e-4, 0.25, -0.2, 3e-4)))
    twin = replace(twin, dh_deviation=link6)
    for q in np.random.default_rng(0).uniform(-2.0, 2.0, (5, 6)):
        reported = forward_kinematics(q)
        flange = forward_kinematics(q, link6)
        assert transform_error(flange @ twin.image_to_flange_rigid, reported @ twin.image_to_tool_rigid)[0] < 1e-9
        assert transform_error(twin.actual_tool_to_base(reported, q), reported)[0] < 1e-9
    assert transform_error(twin.image_to_flange_rigid, twin.image_to_tool_rigid)[0] > 0.1


def test_a_calibrated_controller_reports_what_its_kinematics_say_and_the_arm_deviates_from_them():
    """On a factory-calibrated UR the controller reports poses by its calibration; the twin's arm
    is off that calibration by the bench's deviations. The image then lies where the real flange
    and the mount put it, and the calibration's arm model, started from the controller's
    kinematics, puts the flange there with those deviations (within micrometres: linearised)."""
    from probecal.core.calibration.kinematics import DEVIATION_SD, ArmKinematics
    from probecal.core.robot.ur3 import UR3, ArmModel, forward_kinematics
    from probecal.core.robot.ursim import arm_calibration

    twin = make_twin(4, setup=BENCH_SETUP)
    twin = replace(twin, controller=arm_calibration(7))
    controller = ArmModel(UR3, twin.controller)
    dh = twin.dh_deviation
    q = np.random.default_rng(0).uniform(-2.0, 2.0, (5, 6))
    reported = controller.forward(q)
    actual = np.array([twin.actual_tool_to_base(pose, joints) for pose, joints in zip(reported, q)])
    real_flange = forward_kinematics(q, dh.plus(twin.controller))
    for a, flange in zip(actual, real_flange):
        assert transform_error(flange @ twin.image_to_flange_rigid, a @ twin.image_to_tool_rigid)[0] < 1e-9
    units = np.concatenate([dh.theta, dh.d, dh.a, dh.alpha]) / DEVIATION_SD
    modelled = ArmKinematics.at(q, controller).poses(units)
    assert np.abs(modelled - actual)[:, :3, 3].max() < 0.005
    assert np.abs(reported - actual)[:, :3, 3].max() > 0.1  # the arm is off its controller's kinematics
