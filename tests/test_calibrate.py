"""Registration, hand-eye and validation, stage by stage, against simulator truth and against
PLUS's own numbers on the real fCal 1.2 data (with PLUS's segmented points as input, so that these
tests isolate the calibration maths from segmentation)."""

from types import SimpleNamespace

import numpy as np
import pytest

from core.calibrate import calibrate_session
from core.errors import InputError
from core.handeye import opencv_shah, qr24
from core.metrics import pre3d
from core.plusimport import import_plus
from core.plusresults import read_calibration_results
from core.register import register_frame
from core.simulation import make_twin, simulate_calibration
from core.transforms import transform_error
from tests.conftest import FCAL_CALIBRATION, FCAL_CONFIG, FCAL_RESULTS, FCAL_VALIDATION


def results_from(markers_list):
    """Segmentation-shaped results from known markers (None = not found)."""
    return [
        SimpleNamespace(index=i, found=m is not None, markers=None if m is None else np.asarray(m, float),
                        reason="" if m is not None else "not found")
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
    return simulate_calibration(tmp_path_factory.mktemp("cal") / "s", n_poses=40, seed=11, noise="none")


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
        best = register_frame(sim.phantom, markers, spacing, "best")
        seed = register_frame(sim.phantom, markers, spacing, "seed")
        assert best.fre_mm < 1e-6 and max(transform_error(best.image_to_phantom, truth)) < 1e-5
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


def test_best_beats_seed_and_recovers_truth(sim):
    truth = sim.truth()
    results = results_from(truth_markers(sim, noise_px=0.5))
    seed = calibrate_session(sim, results, "seed", with_validation=False).calibration
    best = calibrate_session(sim, results, "best", with_validation=False).calibration
    x_true = np.array(truth["image_to_tool_rigid"])
    dt_best, dr_best = transform_error(best.image_to_tool_rigid, x_true)
    dt_seed, dr_seed = transform_error(seed.image_to_tool_rigid, x_true)
    assert dt_best < 0.3 and dr_best < 0.15
    assert dt_best < dt_seed and dr_best < dr_seed
    sx, sy = truth["pixel_spacing_mm"]
    assert best.pixel_spacing_mm[0] == pytest.approx(sx, rel=2e-3)
    assert best.pixel_spacing_mm[1] == pytest.approx(sy, rel=2e-3)
    assert seed.pixel_spacing_mm == sim.pixel_spacing_mm  # the seed never estimates spacing


def test_report_carries_validation_and_curve(sim):
    report = calibrate_session(sim, results_from(truth_markers(sim, 0.3)), "best")
    metrics = report.calibration.metrics
    assert metrics["cross_validation"]["folds"] == 5
    assert [row["poses"] for row in report.curve] == sorted(row["poses"] for row in report.curve)
    assert report.shah is not None
    assert metrics["pre3d_mm"] < 0.3
    assert len(metrics["fre_per_frame_mm"]) == metrics["frames_used"]
    assert max(metrics["fre_per_frame_mm"].values()) < 0.1


def test_mislabelled_frames_are_rejected(sim):
    markers = truth_markers(sim, 0.3)
    for i in (3, 17, 29):  # swap two layers: a plausible labelling mistake
        markers[i] = markers[i][[3, 4, 5, 0, 1, 2, 6, 7, 8, 9, 10, 11]]
    report = calibrate_session(sim, results_from(markers), "best", with_validation=False)
    assert {3, 17, 29} <= set(report.frames_rejected)
    assert transform_error(report.calibration.image_to_tool_rigid, np.array(sim.truth()["image_to_tool_rigid"]))[0] < 0.3


def test_pre3d_reproduces_plus_baseline(fcal):
    calibration, validation = fcal
    matrix = read_calibration_results(FCAL_RESULTS).image_to_probe
    mean, std = pre3d(validation.phantom, np.array(plus_points("validation")), validation.poses(), matrix,
                      validation.phantom_to_base)
    assert mean == pytest.approx(1.24684, abs=5e-5) and std == pytest.approx(0.493905, abs=5e-5)
    mean, std = pre3d(calibration.phantom, np.array(plus_points("calibration")), calibration.poses(), matrix,
                      calibration.phantom_to_base)
    assert mean == pytest.approx(1.15532, abs=5e-5) and std == pytest.approx(0.519517, abs=5e-5)


def test_best_calibration_beats_plus_on_its_own_points(fcal):
    calibration, validation = fcal
    report = calibrate_session(calibration, results_from(plus_points("calibration")), "best", with_validation=False)
    mean, _ = pre3d(validation.phantom, np.array(plus_points("validation")), validation.poses(),
                    report.calibration.image_to_tool, validation.phantom_to_base)
    assert mean <= 1.20  # PLUS: 1.247 mm


def test_degenerate_pose_sets_are_refused(sim):
    markers = truth_markers(sim)
    with pytest.raises(InputError, match="too few usable poses"):
        calibrate_session(sim, results_from(markers[:4] + [None] * (len(markers) - 4)), with_validation=False)
    with pytest.raises(InputError, match="no usable frame"):
        calibrate_session(sim, results_from([None] * len(markers)), with_validation=False)


def test_single_axis_rotation_is_refused(tmp_path):
    from core.session import SessionWriter, load_session
    from scipy.spatial.transform import Rotation

    twin = make_twin(0)
    with SessionWriter(tmp_path / "s", {"kind": "calibration", "pixel_spacing_mm": list(twin.probe.nominal_spacing_mm)},
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
