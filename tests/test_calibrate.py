"""Registration, hand-eye, the objectives, block cross-validation, the corner bound and validation,
against simulator truth and against PLUS's own numbers on the real fCal 1.2 data (mostly with
PLUS's segmented points as input, so that these tests isolate the calibration maths from
segmentation; the default method is also scored end to end on our segmentation)."""

import copy
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.app.report import calibration_details
from probecal.core.acquisition.plan import THESIS_RANGES, hand_path
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.crossval import block_folds, choose
from probecal.core.calibration.handeye import opencv_shah, qr24
from probecal.core.calibration.jointfit import WirePrior, refine
from probecal.core.calibration.kinematics import (
    DEVIATION_NAMES,
    DEVIATION_SD,
    ArmKinematics,
    arm_joints,
    arm_poses,
    deviation,
)
from probecal.core.calibration.metrics import pre3d
from probecal.core.calibration.objectives import Observations, Solution, fit
from probecal.core.calibration.register import register_frame
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.calibration.segment import FrameResult, segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import (
    along_wires_order,
    bound_grid_px,
    corner_bound,
    corner_distance_mm,
    image_corners_px,
    point_bounds_mm,
)
from probecal.core.calibration.validate import validate_session
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.transforms import make_transform, transform_error
from probecal.core.io.plusimport import import_plus
from probecal.core.io.plusresults import read_calibration_results
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.ur3 import UR3, UR3E, ArmModel
from probecal.core.robot.ursim import arm_calibration
from probecal.core.twin.levels import BENCH_SETUP, LEVELS, SetupErrors
from probecal.core.twin.twin import make_twin
from tests.support.paths import FCAL_CALIBRATION, FCAL_CONFIG, FCAL_RESULTS, FCAL_VALIDATION
from tests.support.refusals import assert_refused


def results_from(markers_list):
    """Segmentation-shaped results from known markers (None = not found)."""
    return [
        FrameResult(i, m is not None, None if m is None else np.asarray(m, float), "" if m is not None else "not found",
                    np.empty((0, 2)))
        for i, m in enumerate(markers_list)
    ]


def truth_markers(session, noise_px=0.0, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for frame in session.truth()["frames"]:
        m = np.array([p if p is not None else [np.nan, np.nan] for p in frame["markers_px"]], float)
        out.append(m + rng.normal(0, noise_px, m.shape) if np.isfinite(m).all() else None)
    return out


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate_calibration(tmp_path_factory.mktemp("cal") / "s", n_poses=40, seed=11, noise="none",
                                ranges=THESIS_RANGES)


def plus_points(section):
    return [f.points for f in getattr(read_calibration_results(FCAL_RESULTS), section)]


@pytest.fixture(scope="module")
def fcal(plus_data, tmp_path_factory):
    root = tmp_path_factory.mktemp("fcal")
    return (import_plus(FCAL_CALIBRATION, FCAL_CONFIG, root / "cal"),
            import_plus(FCAL_VALIDATION, FCAL_CONFIG, root / "val"))


def test_registration_is_exact_on_exact_markers(sim):
    twin = make_twin(11)
    spacing = tuple(sim.truth()["pixel_spacing_mm"])
    for i, markers in enumerate(truth_markers(sim)[:10]):
        truth = twin.image_to_phantom(sim.records[i].tool_to_base)
        exact = register_frame(sim.phantom, markers, spacing, "point-to-wire")
        seed = register_frame(sim.phantom, markers, spacing, "thesis")
        assert exact.fre_mm < 1e-6 and max(transform_error(exact.image_to_phantom, truth)) < 1e-5
        assert seed.fre_mm < 0.05 and transform_error(seed.image_to_phantom, truth)[0] < 0.3


def test_registration_needs_two_complete_patterns(sim):
    markers = truth_markers(sim)[0].copy()
    markers[3:] = np.nan
    assert register_frame(sim.phantom, markers, (0.1, 0.1)) is None


def test_qr24_and_shah_are_exact_on_exact_data(sim):
    twin = make_twin(11)
    m = sim.poses()
    n = np.array([twin.image_to_phantom(p) for p in m])
    for x, y in (qr24(m, n), opencv_shah(m, n)):
        assert max(transform_error(x, twin.image_to_tool_rigid)) < 1e-6
        assert max(transform_error(y, twin.phantom_to_base)) < 1e-6


def _fit_on_built_wires(sim, shifts, prior, freehand=False):
    """The all-wire fit, from the truth, of exact markers of a phantom built ``shifts`` off its
    definition, under the wire ``prior``, over the robot's poses or (``freehand``) a hand's path
    with the phantom pose known: the fit and its image corners' distance to the truth (mm)."""
    twin = make_twin(11)
    built = replace(twin, built_phantom=twin.phantom.moved(shifts))
    poses = np.array(hand_path(twin.nominal, 60, seed=11)) if freehand else sim.poses()
    markers = np.array([built.markers_px(p) for p in poses])
    x, y, spacing = twin.image_to_tool_rigid, twin.phantom_to_base, twin.pixel_spacing_mm
    fit = refine(twin.phantom, markers, poses, x, y, spacing, solve_y=not freehand, prior=prior)
    calibration = Calibration(fit.image_to_tool_rigid, fit.pixel_spacing_mm)
    return fit, corner_distance_mm(calibration, Calibration(x, spacing), image_corners_px(sim.image_size))


def test_fitting_the_wires_keeps_a_phantom_built_off_its_definition_from_pulling_the_calibration(sim):
    """Every wire end point up to 0.3 mm off (the bench's tolerance)."""
    shifts = np.random.default_rng(3).uniform(-0.3, 0.3, (12, 2, 3))
    _, held = _fit_on_built_wires(sim, shifts, WirePrior(0.0))
    _, fitted = _fit_on_built_wires(sim, shifts, WirePrior(0.05))
    assert fitted < 0.7 * held  # 0.067 against 0.111 mm: the poses' spread sets how well wires and mount part


def test_fitting_the_layers_keeps_a_layer_built_off_its_place_from_pulling_the_calibration(sim):
    """The first layer's three wires strung 0.5 mm along x and turned 0.5 deg about z, together, under a
    layer prior of 0.3 mm and 0.3 deg (not the default: see ``objectives.WIRE_PRIOR``)."""
    ends = make_twin(11).phantom.lines()[:3]
    centre = ends.reshape(-1, 3).mean(axis=0)
    shifts = np.zeros((12, 2, 3))
    turn = Rotation.from_euler("z", 0.5, degrees=True).as_matrix()
    shifts[:3] = (ends - centre) @ turn.T + centre + [0.5, 0, 0] - ends
    _, held = _fit_on_built_wires(sim, shifts, WirePrior(0.05))
    _, layered = _fit_on_built_wires(sim, shifts, WirePrior(0.05, layer_sigma=(0.3, np.radians(0.3))))
    assert layered < 0.2 * held  # 0.015 against 0.146 mm


def test_a_looser_prior_on_the_diagonals_keeps_diagonals_built_off_from_pulling_the_calibration(sim):
    """Every diagonal's ends 1 mm across it (the ratio of every N moves; no frame shows it), under
    the wires' prior and under one ten times looser on the diagonals alone (``WirePrior.diagonal_factor``)."""
    phantom = make_twin(11).phantom
    shifts = phantom.diagonal_shifts(np.random.default_rng(4).choice([-1.0, 1.0], (len(phantom.layers), 2)))
    _, held = _fit_on_built_wires(sim, shifts, WirePrior(0.05))
    _, loose = _fit_on_built_wires(sim, shifts, WirePrior(0.05, diagonal_factor=10.0))
    assert loose < 0.5 * held  # 0.059 against 0.141 mm

def test_a_turn_prior_on_the_diagonals_locates_diagonals_turned_within_their_layers(sim):
    """Every diagonal turned about its middle, its ends 0.6 mm across it the opposite ways (what the
    fCal phantoms' recordings show, ``benchmarks/bench_diagonal_turn.py``), seen along a hand's
    sweep with the phantom pose known (the robot's turns locate them under the wires' prior
    alone), under that prior and with each diagonal also free to turn
    (``WirePrior.diagonal_turn_mm``): the fit finds the turns and the calibration is no longer
    pulled."""
    phantom = make_twin(11).phantom
    signs = np.random.default_rng(5).choice([-1.0, 1.0], len(phantom.layers))
    shifts = phantom.diagonal_shifts(0.6 * signs[:, None] * [-1.0, 1.0])
    _, held = _fit_on_built_wires(sim, shifts, WirePrior(0.05), freehand=True)
    fit, turned = _fit_on_built_wires(sim, shifts, WirePrior(0.05, diagonal_turn_mm=0.5), freehand=True)
    assert turned < 0.5 * held  # 0.003 against 0.023 mm
    np.testing.assert_allclose(phantom.diagonal_turns(fit.wire_shifts_mm), 0.6 * signs, atol=0.1)


def test_fitting_the_wires_finds_a_wire_built_off_its_definition(sim):
    """Found relative to the rest: a shift of them all is the phantom's pose."""
    shifts = np.zeros((12, 2, 3))
    shifts[3, :, 0] = 0.5  # an outer wire (along y) moved along x, across itself
    fit, _ = _fit_on_built_wires(sim, shifts, WirePrior(0.05))
    across = fit.wire_shifts_mm[..., 0] - np.median(fit.wire_shifts_mm[..., 0])
    assert np.abs(across[3] - 0.5).max() < 0.05
    assert np.abs(np.delete(across, 3, axis=0)).max() < 0.05
    assert np.abs(fit.wire_shifts_mm[3, :, 1]).max() < 1e-9  # the wire runs along y: no shift along it


def test_all_wire_beats_seed_and_recovers_truth(sim):
    truth = sim.truth()
    results = results_from(truth_markers(sim, noise_px=0.5))
    seed = calibrate_session(sim, results, "thesis", with_validation=False).calibration
    all_wire = calibrate_session(sim, results, "all-wire", with_validation=False).calibration
    x_true = np.array(truth["image_to_tool_rigid"])
    dt_all, dr_all = transform_error(all_wire.image_to_tool_rigid, x_true)
    dt_seed, dr_seed = transform_error(seed.image_to_tool_rigid, x_true)
    assert dt_all < 0.3 and dr_all < 0.15
    assert dt_all < dt_seed and dr_all < dr_seed
    sx, sy = truth["pixel_spacing_mm"]
    assert all_wire.pixel_spacing_mm[0] == pytest.approx(sx, rel=2e-3)
    assert all_wire.pixel_spacing_mm[1] == pytest.approx(sy, rel=2e-3)
    assert seed.pixel_spacing_mm == sim.pixel_spacing_mm  # the seed never estimates spacing


@pytest.fixture(scope="module")
def realistic(tmp_path_factory):
    session = simulate_calibration(tmp_path_factory.mktemp("real") / "s", n_poses=40, seed=5, noise="realistic",
                                   ranges=THESIS_RANGES)
    return session, segment_session(session)


def test_middle_wire_recovers_the_truth_from_segmented_frames(realistic):
    session, results = realistic
    truth = session.truth()
    calibration = calibrate_session(session, results, "middle-wire", with_validation=False).calibration
    dt, dr = transform_error(calibration.image_to_tool_rigid, np.array(truth["image_to_tool_rigid"]))
    # One point per N pins the rotation less than every marker does (all-wire: 0.03 deg here).
    assert dt < 0.2 and dr < 0.2 and corner_error(calibration, session) < 0.2
    # probecal's centroids weigh the whole blob, as PLUS's do, so they take in the twin's dot tails,
    # which grow with depth: the axial spacing comes out 0.2-0.25 % short (the seed finder's
    # half-maximum centroids gave 0.05 %); open in issue #14.
    assert calibration.pixel_spacing_mm == pytest.approx(truth["pixel_spacing_mm"], rel=3e-3)
    assert calibration.metrics["objective"] == "middle-wire" and calibration.metrics["method"] == "middle-wire"


def test_block_folds_are_contiguous_and_cover_every_frame():
    for n, k in ((188, 6), (40, 6), (7, 6), (4, 6), (60, 8)):
        folds = block_folds(n, k)
        assert len(folds) == min(n, k)
        assert np.array_equal(np.concatenate(folds), np.arange(n))  # in recording order, each frame once
        assert all(np.array_equal(f, np.arange(f[0], f[-1] + 1)) for f in folds)  # consecutive frames
        assert max(map(len, folds)) - min(map(len, folds)) <= 1


def cv_row(per_block):
    values = [v for v in per_block if v is not None]
    return {"pre3d_mm": float(np.mean(values)) if values else None, "pre3d_per_block_mm": per_block}


def test_auto_keeps_the_lowest_cross_validated_objective_that_the_blocks_agree_on():
    # The phantom pose known: middle-wire is kept unless another objective is clearly better.
    cv = {"middle-wire": cv_row([1.0, 1.1, 0.9, 1.2, 1.0, 1.1]),
          "all-wire": cv_row([0.8, 0.9, 0.7, 1.0, 0.8, 0.9]),  # lower on every block
          "thesis": cv_row([0.9, 1.0, 0.8, 1.1, 0.9, 1.0])}
    assert choose(cv) == ("all-wire",
                          "lowest held-out PRE3D, below that of middle-wire on the blocks beyond their scatter")
    cv["all-wire"] = cv_row([1.3, 0.6, 1.2, 0.7, 0.9, 0.8])  # lower on the whole, but not block by block
    objective, why = choose(cv)
    assert objective == "thesis"  # the lowest of those that beat middle-wire on every block
    cv["thesis"] = cv_row([1.2, 1.0, 0.8, 1.1, 0.9, None])
    objective, why = choose(cv)
    assert objective == "middle-wire" and "within the block-to-block scatter" in why and "all-wire" in why
    cv["middle-wire"] = cv_row([None] * 6)
    objective, why = choose(cv)
    assert objective == "middle-wire" and "no block could be held out" in why  # nothing to compare with


def test_auto_keeps_all_wire_when_the_phantom_pose_is_solved():
    # Held-out PRE3D then measures how well mount and phantom pose agree, not accuracy.
    cv = {"all-wire": cv_row([1.0, 1.1, 0.9, 1.2, 1.0, 1.1]),
          "middle-wire": cv_row([0.5, 0.6, 0.4, 0.6, 0.5, 0.5])}
    assert choose(cv)[0] == "middle-wire"
    objective, why = choose(cv, phantom_pose_solved=True)
    assert objective == "all-wire" and "phantom pose solved" in why and "not accuracy" in why


def test_report_lists_every_objective_and_keeps_the_chosen_one(realistic):
    session, results = realistic
    said: list[str] = []
    metrics = calibrate_session(session, results, progress=said.append).calibration.metrics
    for name in ("all-wire", "middle-wire", "thesis"):  # a long step is announced before it runs
        assert any(line.startswith(f"cross-validating the {name} objective") for line in said)
    assert set(metrics["objectives"]) == {"all-wire", "middle-wire", "thesis"}
    rows = {name: {"pre3d_mm": row["cv_pre3d_mm"], "pre3d_per_block_mm": row["cv_pre3d_per_block_mm"]}
            for name, row in metrics["objectives"].items()}
    solved = metrics["phantom_pose"] == "solved"
    assert metrics["method"] == "auto" and (metrics["objective"], metrics["objective_choice"]) == choose(rows, solved)
    assert metrics["objective"] != "thesis"  # nominal spacing: clearly worse held out
    assert metrics["cv_pre3d_mm"] == metrics["objectives"][metrics["objective"]]["cv_pre3d_mm"]
    assert metrics["objectives"]["thesis"]["cv_pre3d_mm"] > 3 * metrics["cv_pre3d_mm"]
    assert metrics["cross_validation"]["blocks"] == 6 and metrics["cross_validation"]["folds"] == 6
    assert metrics["weakly_determined"] == []
    shifts = metrics["wire_shifts_mm"]  # a perfect phantom: the wires are found where defined
    if metrics["objective"] == "all-wire":
        assert set(shifts) == {w.name for w in session.phantom.wires} and max(shifts.values()) < 0.05
    else:
        assert shifts is None


def test_report_carries_validation_and_curve(sim):
    report = calibrate_session(sim, results_from(truth_markers(sim, 0.3)), "all-wire")
    metrics = report.calibration.metrics
    assert metrics["cross_validation"]["folds"] == 6
    assert [row["poses"] for row in report.curve] == sorted(row["poses"] for row in report.curve)
    assert report.shah is not None
    assert metrics["pre3d_mm"] < 0.3
    assert len(metrics["fre_per_frame_mm"]) == metrics["frames_used"]
    assert max(metrics["fre_per_frame_mm"].values()) < 0.1


def corner_error(calibration, session):
    truth = session.truth()
    true = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
    return corner_distance_mm(calibration, true, image_corners_px(session.image_size))


def test_corner_bound_grows_with_noise_and_with_fewer_poses(sim):
    bounds = {}
    for noise_px, poses in ((0.2, 40), (1.0, 40), (1.0, 12)):
        markers = truth_markers(sim, noise_px, seed=1)[:poses]
        report = calibrate_session(sim, results_from(markers + [None] * (len(sim) - poses)), "all-wire")
        bounds[noise_px, poses] = report.calibration.metrics["corner_error_95_mm"]
        assert 0 < corner_error(report.calibration, sim) <= bounds[noise_px, poses]
    assert 0 < bounds[0.2, 40] < bounds[1.0, 40] < bounds[1.0, 12]


def test_the_bootstrap_blocks_frames_by_where_they_see_the_wires_not_by_when():
    """A sweep that comes back over the same stretch of wire: its frames are ordered by where
    their patterns sit along the wires, so the frames of one stretch share a block."""
    phantom = make_twin(0).phantom
    along = np.array([0.0, 12.0, 24.0, 1.0, 13.0, 25.0])  # mm along the wires, two passes
    direction = phantom.layers[0].wires[0].direction
    poses = np.array([make_transform(np.eye(3), a * direction) for a in along])
    markers = np.full((len(along), phantom.n_wires, 2), np.nan)
    markers[:, 0] = [10.0, 20.0]
    obs = Observations(markers, poses, np.arange(len(along)))
    solution = Solution("all-wire", np.eye(4), np.eye(4), (0.1, 0.1), np.arange(len(along)))
    assert along_wires_order(phantom, obs, solution).tolist() == [0, 3, 1, 4, 2, 5]


def test_corner_bound_takes_the_larger_random_part_and_counts_the_other_objective_as_chosen():
    """The random part is the bootstrap's 95th percentile or twice the chosen fit's block jackknife,
    whichever is larger; another objective counts beyond its own scatter only where the phantom
    pose was solved (elsewhere the choice itself is uncertain, and all of it counts)."""
    frames = np.arange(10)

    def shifted(objective, mm):  # a fit whose image corners all move by ``mm``
        return Solution(objective, make_transform(np.eye(3), [mm, 0.0, 0.0]), np.eye(4), (0.1, 0.1), frames)

    chosen, corners = shifted("all-wire", 0.0), image_corners_px((100, 100))
    refits, others = [shifted("all-wire", 0.1)] * 20, {"middle-wire": shifted("middle-wire", 1.0)}
    spreads = {"all-wire": 0.3, "middle-wire": 0.2}
    solved = corner_bound(chosen, refits, others, corners, spreads=spreads)
    assert solved.bootstrap_mm == pytest.approx(0.1) and solved.jackknife_mm == pytest.approx(0.6)
    assert solved.bound_mm == pytest.approx(0.6 + (1.0 - 2 * 0.2))
    known = corner_bound(chosen, refits, others, corners, spreads=spreads, excess_only=False)
    assert known.bound_mm == pytest.approx(0.6 + 1.0)
    steady = corner_bound(chosen, refits, others, corners, spreads={"all-wire": 0.01}, excess_only=False)
    assert steady.bound_mm == pytest.approx(0.1 + 1.0)  # the bootstrap is the larger


def test_the_bound_map_is_the_corner_bound_point_by_point():
    """The map takes every part of the corner bound at each point on its own: at a point it is
    the corner bound of that point alone, so at the corners it is at most the corner bound (the
    farthest of the four at once), and where every fit differs by a shift alone it is the same
    everywhere. Refits turned about the image's middle leave the middle pinned down."""
    frames, size = np.arange(10), (100, 80)

    def moved(objective, mm, deg=0.0):  # a fit shifted by ``mm`` and turned by ``deg`` about the image's middle
        middle = np.array([50.0, 40.0, 0.0]) * 0.1
        turn = make_transform(Rotation.from_rotvec([0.0, 0.0, np.radians(deg)]).as_matrix(), [mm, 0.0, 0.0])
        x = make_transform(np.eye(3), middle) @ turn @ make_transform(np.eye(3), -middle)
        return Solution(objective, x, np.eye(4), (0.1, 0.1), frames)

    chosen = moved("all-wire", 0.0)
    refits = [moved("all-wire", 0.01 * k, 0.2 * (k - 10)) for k in range(20)]
    others, echo, loose = {"middle-wire": moved("middle-wire", 0.3, 1.0)}, moved("all-wire", 0.05, -0.5), None
    corners = image_corners_px(size)
    spreads = {"all-wire": 0.02, "middle-wire": 0.05}
    grid = bound_grid_px(size, None, np.array([40.0]))
    assert grid.shape == (10, 9, 2) and 40.0 in grid[:, 0, 1]  # every 1/8 and the wires' row
    assert np.array_equal(grid[[0, 0, -1, -1], [0, -1, 0, -1]], corners)
    point_spreads = {name: np.full(grid.shape[:2], s) for name, s in spreads.items()}
    bounds = point_bounds_mm(chosen, refits, others, grid, echo, point_spreads, loose)
    for (row, column) in ((0, 0), (4, 4), (9, 8)):
        alone = corner_bound(chosen, refits, others, grid[row, column][None], echo, spreads, loose)
        assert bounds[row, column] == pytest.approx(alone.bound_mm)
    corner = corner_bound(chosen, refits, others, corners, echo, spreads, loose).bound_mm
    assert bounds[[0, 0, -1, -1], [0, -1, 0, -1]].max() <= corner + 1e-12
    assert bounds.min() < 0.5 * bounds.max()  # the turns pin the middle down, the corners swing
    assert np.unravel_index(bounds.argmin(), bounds.shape)[1] == 4
    shifted = point_bounds_mm(chosen, [moved("all-wire", 0.01 * k) for k in range(20)],
                              {"middle-wire": moved("middle-wire", 0.3)}, grid)
    assert np.allclose(shifted, shifted[0, 0])


def test_the_bound_map_of_a_fan_image_lies_in_its_fan():
    fan = Fan((-30.0, 30.0), (200.0, -20.0), 40.0, 400.0)
    grid = bound_grid_px((400, 400), fan, np.array([150.0]))
    assert grid.shape == (10, 9, 2)
    assert np.all(fan.contains(grid.reshape(-1, 2), margin_px=-1e-6))
    assert np.allclose(grid[[0, 0, -1, -1], [0, -1, 0, -1]], fan.corners_px())


def test_corner_bound_covers_the_echo_ring_bias(realistic):
    """Centroids sit below the wires by more at depth, a spacing bias that every bootstrap
    resample and every objective shares; the refit to the echo peaks sees it, and the bound
    covers the true corner error."""
    session, results = realistic
    report = calibrate_session(session, results)
    metrics = report.calibration.metrics
    echo = metrics["corner_error"]["echo_peak_disagreement_mm"]
    assert echo > metrics["corner_error"]["bootstrap_95_mm"]
    assert corner_error(report.calibration, session) <= metrics["corner_error_95_mm"]


def test_wires_built_off_widen_the_bound_by_their_pull_and_it_still_covers_the_truth(tmp_path):
    """Wire end points up to 0.8 mm off their definition, the phantom pose solved (the robot's
    way): the all-wire fit, its wires held tightly, is pulled; the refit under the loose wire prior
    sees that pull, middle-wire is compared on the wires as all-wire located them (on the
    definition it keeps its own, larger pull), and the bound covers the truth."""
    phantom = make_twin(11).phantom
    shifts = np.random.default_rng(4).uniform(-0.8, 0.8, (phantom.n_wires, 2, 3))
    session = simulate_calibration(tmp_path / "s", n_poses=40, seed=11, noise="none",
                                   built_phantom=phantom.moved(shifts))
    results = results_from(truth_markers(session, 0.2, seed=2))
    report = calibrate_session(session, results)
    metrics = report.calibration.metrics
    parts = metrics["corner_error"]
    assert metrics["phantom_pose"] == "solved" and metrics["objective"] == "all-wire"
    assert parts["wire_prior_disagreement_mm"] > parts["bootstrap_95_mm"]  # 0.56 against 0.19 mm
    on_definition = calibrate_session(session, results, "middle-wire", with_validation=False).calibration
    corners = image_corners_px(session.image_size)
    assert parts["objective_disagreement_mm"]["middle-wire"] < corner_distance_mm(report.calibration, on_definition,
                                                                                  corners)
    # 0.63 mm off, bound 0.82; without the loose prior's refit it would be 0.48.
    assert corner_error(report.calibration, session) <= metrics["corner_error_95_mm"]


def test_the_seed_objective_cannot_hide_its_spacing_bias(realistic):
    """With the phantom pose solved, seed's PRE3D looks fine (consistency) while its mount is far
    off; the corner bound says so."""
    session, results = realistic
    report = calibrate_session(session, results, "thesis")
    metrics = report.calibration.metrics
    error = corner_error(report.calibration, session)
    assert error > 3.0 and metrics["pre3d_mm"] < error / 3
    assert metrics["corner_error_95_mm"] >= error
    assert metrics["corner_error"]["objective_disagreement_mm"].keys() == {"all-wire", "middle-wire"}


@pytest.mark.parametrize("objective", ["all-wire", "middle-wire", "thesis"])
def test_a_mislabelled_frame_is_rejected_with_its_reason(realistic, objective):
    session, results = realistic
    planted = copy.deepcopy(results)
    frame = next(r for r in planted if r.found and np.linalg.norm(r.markers[3] - r.markers[4]) > 80)
    frame.markers[[3, 4]] = frame.markers[[4, 3]]  # the diagonal's dot taken for the outer wire's and back
    report = calibrate_session(session, planted, objective, with_validation=False)
    assert f"disagrees with the {objective} fit" in report.frames_rejected[frame.index]
    assert "mm" in report.frames_rejected[frame.index]
    assert frame.index not in report.frames_used and report.calibration.metrics["frames_rejected"] >= 1
    # The fit is the one without that frame (seed's fixed spacing leaves it weakly determined, so
    # any one frame more or less moves it by millimetres: compare like with like).
    without = [replace(r, found=False, markers=None) if r.index == frame.index else r for r in results]
    clean = calibrate_session(session, without, objective, with_validation=False).calibration
    assert corner_distance_mm(report.calibration, clean, image_corners_px(session.image_size)) < 0.05


def test_mislabelled_frames_are_rejected(sim):
    markers = truth_markers(sim, 0.3)
    for i in (3, 17, 29):  # swap two layers: a plausible labelling mistake
        markers[i] = markers[i][[3, 4, 5, 0, 1, 2, 6, 7, 8, 9, 10, 11]]
    for objective in ("all-wire", "middle-wire", "thesis"):
        report = calibrate_session(sim, results_from(markers), objective, with_validation=False)
        assert {3, 17, 29} <= set(report.frames_rejected), objective
        if objective != "thesis":  # the thesis's nominal spacing puts it millimetres off in any case
            assert transform_error(report.calibration.image_to_tool_rigid,
                                   np.array(sim.truth()["image_to_tool_rigid"]))[0] < 0.3


def test_pre3d_reproduces_plus_baseline(fcal):
    calibration, validation = fcal
    matrix = read_calibration_results(FCAL_RESULTS).image_to_probe
    mean, std = pre3d(validation.phantom, np.array(plus_points("validation")), validation.poses(), matrix,
                      validation.phantom_to_base)
    assert mean == pytest.approx(1.24684, abs=5e-5) and std == pytest.approx(0.493905, abs=5e-5)
    mean, std = pre3d(calibration.phantom, np.array(plus_points("calibration")), calibration.poses(), matrix,
                      calibration.phantom_to_base)
    assert mean == pytest.approx(1.15532, abs=5e-5) and std == pytest.approx(0.519517, abs=5e-5)


def test_all_wire_calibration_beats_plus_on_its_own_points(fcal):
    calibration, validation = fcal
    report = calibrate_session(calibration, results_from(plus_points("calibration")), "all-wire", with_validation=False)
    mean, _ = pre3d(validation.phantom, np.array(plus_points("validation")), validation.poses(),
                    report.calibration.image_to_tool, validation.phantom_to_base)
    assert mean <= 1.20  # PLUS: 1.247 mm


def test_fcal_default_method_on_our_segmentation_beats_plus(fcal):
    """Tracked case (PLUS's PhantomToReference), our segmenter with PLUS's hints, ``auto``."""
    calibration, validation = fcal
    report = calibrate_session(calibration, segment_session(calibration), with_validation=False)
    metrics = validate_session(validation, report.calibration, segment_session(validation))
    assert metrics["phantom_pose_from"] == "session"
    assert metrics["pre3d_mm"] <= 1.20  # PLUS: 1.247 mm
    assert all(row["cv_pre3d_mm"] is not None for row in report.calibration.metrics["objectives"].values())


def test_fcal_with_the_phantom_pose_solved_says_it_is_weakly_determined(fcal):
    """The freehand fCal sweep hardly rotates the probe: fine with the phantom pose known, too
    little to tell the phantom pose from the mount."""
    calibration, _ = fcal
    report = calibrate_session(calibration, results_from(plus_points("calibration")), "all-wire",
                               solve_phantom_pose=True, with_validation=False)
    assert any("rotate little about a second axis" in reason for reason in report.weakly_determined)
    assert report.calibration.metrics["weakly_determined"] == report.weakly_determined
    known = calibrate_session(calibration, results_from(plus_points("calibration")), "all-wire", with_validation=False)
    assert known.weakly_determined == []


def test_degenerate_pose_sets_are_refused(sim):
    markers = truth_markers(sim)
    with pytest.raises(InputError, match="too few usable poses"):
        calibrate_session(sim, results_from(markers[:4] + [None] * (len(markers) - 4)), with_validation=False)
    with pytest.raises(InputError, match="no usable frame"):
        calibrate_session(sim, results_from([None] * len(markers)), with_validation=False)
    empty = Observations(np.empty((0, 12, 2)), np.empty((0, 4, 4)), np.empty(0, int), np.empty((0, 4, 4)))
    with pytest.raises(InputError, match="too few usable poses: 0"):
        fit(sim.phantom, empty, (0.1, 0.1), "all-wire")


def test_single_axis_rotation_is_refused(tmp_path):
    from scipy.spatial.transform import Rotation

    from probecal.core.io.manifest import Manifest
    from probecal.core.io.session import SessionWriter, load_session

    twin = make_twin(0)
    with SessionWriter(tmp_path / "s", Manifest(kind="calibration", pixel_spacing_mm=twin.probe.nominal_spacing_mm),
                       twin.phantom, twin.probe) as w:
        centre = twin.nominal.tool_to_base(twin.nominal.image_to_phantom)
        markers = []
        for angle in np.linspace(-10, 10, 12):
            pose = centre.copy()
            pose[:3, :3] = centre[:3, :3] @ Rotation.from_euler("z", angle, degrees=True).as_matrix()
            w.append(np.zeros((500, 384), np.uint8), pose)
            markers.append(twin.markers_px(pose))
    session = load_session(tmp_path / "s")
    with pytest.raises(InputError, match="single axis"):
        calibrate_session(session, results_from(markers), with_validation=False)


@pytest.fixture(scope="module")
def bent_arm(tmp_path_factory):
    """A sweep by a UR3 whose links are off UR's table (the bench tolerance), nothing else off."""
    level = replace(LEVELS["realistic"], setup=SetupErrors(dh_length_mm=BENCH_SETUP.dh_length_mm,
                                                            dh_angle_deg=BENCH_SETUP.dh_angle_deg))
    session = simulate_calibration(tmp_path_factory.mktemp("arm") / "s", n_poses=40, seed=6, noise=level)
    return session, segment_session(session)


def test_the_arms_kinematic_errors_are_fitted_with_the_calibration(bent_arm, tmp_path):
    session, results = bent_arm
    assert session.manifest.arm == "UR3"
    fitted = calibrate_session(session, results, "all-wire", with_validation=False).calibration
    unknown = replace(session, manifest=replace(session.manifest, arm=None))
    held = calibrate_session(unknown, results, "all-wire", with_validation=False).calibration
    assert held.arm is None and held.metrics["arm_correction_mm"] is None
    assert corner_error(fitted, session) < 0.12 < corner_error(held, session)  # 0.06 against 0.24 mm
    assert fitted.arm["model"] == "UR3" and 0.02 < fitted.metrics["arm_correction_mm"] < 1.0
    truth = session.truth()["setup"]["dh_deviation"]
    # What the sweep determines of the deviations moves toward the truth; the rest stays at the table.
    assert np.corrcoef(fitted.arm["d_mm"] + fitted.arm["a_mm"], truth["d_mm"] + truth["a_mm"])[0, 1] > 0.5  # 0.79
    fitted.write(tmp_path / "cal.json")
    assert load_calibration(tmp_path / "cal.json").arm == fitted.arm
    # It names the deviations the poses leave undetermined, and those it does not name lie near
    # the truth (0.16 of a prior sd, RMS, against the truth's 0.6).
    undetermined = fitted.metrics["arm_undetermined"]
    assert {"d1", "θ1"} <= set(undetermined) and len(undetermined) < len(DEVIATION_NAMES)  # 12 of 24 here

    def units(arm) -> np.ndarray:
        theta, alpha = (np.radians(arm[key]) for key in ("theta_deg", "alpha_deg"))
        return np.concatenate([theta, arm["d_mm"], arm["a_mm"], alpha]) / DEVIATION_SD

    error, size = units(fitted.arm) - units(truth), units(truth)
    determined = np.array([name not in undetermined for name in DEVIATION_NAMES])
    assert np.sqrt(np.mean(error[determined] ** 2)) < 0.5 * np.sqrt(np.mean(size[determined] ** 2))
    assert "determine" in " ".join(str(block) for block in calibration_details(fitted))



@pytest.mark.parametrize("arm", [ArmModel(UR3E), ArmModel(UR3, arm_calibration(4))], ids=["ur3e", "calibrated-ur3"])
def test_an_arm_is_modelled_by_the_kinematics_its_controller_computes_with(arm):
    """The poses, joints and their derivatives by the deviations come from the controller's own
    kinematics (a UR3e's table; a UR3's factory calibration): the joints put the flange where it
    was reported, no deviation leaves it there, and a few units of deviation move the poses as
    the linear model says, within micrometres."""
    rng = np.random.default_rng(3)
    q = HOME_JOINTS + rng.uniform(-0.4, 0.4, (12, 6))
    reported = arm.forward(q)
    joints = arm_joints(reported, arm)
    np.testing.assert_allclose(arm.forward(joints), reported, atol=1e-6)
    kinematics = ArmKinematics.at(joints, arm)
    np.testing.assert_allclose(kinematics.poses(np.zeros(kinematics.n_params)), reported, atol=1e-6)
    units = rng.normal(0.0, 2.0, kinematics.n_params)
    exact = arm_poses(joints, deviation(units), arm)
    assert np.abs(kinematics.poses(units) - exact)[:, :3, 3].max() < 0.005
    assert np.abs(exact - reported)[:, :3, 3].max() > 0.1  # the deviations do move the flange


def test_an_arm_in_a_calibration_file_is_checked(tmp_path):
    good = {"image_to_tool_rigid": np.eye(4).tolist(), "pixel_spacing_mm": [0.1, 0.1],
            "arm": {"model": "UR3", "theta_deg": [0.0] * 6, "d_mm": [0.1] * 6, "a_mm": [0.0] * 6,
                    "alpha_deg": [0.0] * 6}}
    file = tmp_path / "cal.json"
    file.write_text(json.dumps(good))
    assert load_calibration(file).arm["d_mm"] == [0.1] * 6
    for arm, fragment in (({**good["arm"], "model": "UR5"}, "not an arm probecal knows"),
                          ({**good["arm"], "d_mm": [0.1] * 5}, "arm.d_mm"),
                          ({**good["arm"], "a_mm": [50.0] * 6}, "not an arm that matches its table"),
                          ({**good["arm"], "alpha_deg": ["0"] * 6}, "arm.alpha_deg")):
        file.write_text(json.dumps({**good, "arm": arm}, allow_nan=True))
        assert_refused(lambda: load_calibration(file), file, fragment)
