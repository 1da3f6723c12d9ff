"""The digital twin records sessions with exact ground truth."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.plan import (
    FREEHAND_RANGES,
    HAND_PIVOT_DEG_PER_MM,
    HAND_SWEEP_MM,
    calibration_plan,
    crossings_in_view,
    hand_path,
)
from probecal.core.acquisition.simulate import simulate_calibration, simulate_freehand, simulate_volume
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.geometry.transforms import invert_transform, is_rigid, transform_error, transform_points
from probecal.core.twin.levels import level
from probecal.core.twin.twin import make_twin
from probecal.core.volume.surface import extract_surface


@pytest.fixture(scope="module")
def calibration_none(tmp_path_factory):
    return simulate_calibration(tmp_path_factory.mktemp("sim") / "cal", n_poses=12, seed=3, noise="none")


def markers_to_phantom(truth, tool_to_base, markers_px):
    """Map pixels to the phantom frame with nothing but truth.json and the recorded pose."""
    image_to_tool = np.array(truth["image_to_tool"])
    phantom_to_base = np.array(truth["phantom_to_base"])
    pixels = np.column_stack([markers_px, np.zeros(len(markers_px))])
    return transform_points(invert_transform(phantom_to_base) @ tool_to_base @ image_to_tool, pixels)


def test_truth_has_spec_keys_and_is_consistent(calibration_none):
    truth = calibration_none.truth()
    for key in ("image_to_tool", "image_to_tool_rigid", "pixel_spacing_mm", "phantom_to_base", "frames"):
        assert key in truth
    rigid, full = np.array(truth["image_to_tool_rigid"]), np.array(truth["image_to_tool"])
    sx, sy = truth["pixel_spacing_mm"]
    assert is_rigid(rigid) and is_rigid(np.array(truth["phantom_to_base"]))
    assert np.allclose(full, rigid @ np.diag([sx, sy, 1, 1]))
    assert sy == pytest.approx(0.1 * 1480 / 1540) and sx == pytest.approx(0.1)
    # The image origin sits about 100 mm beyond the flange.
    assert 95 < np.linalg.norm(rigid[:3, 3]) < 110


def test_true_markers_lie_exactly_on_the_wires(calibration_none):
    truth = calibration_none.truth()
    phantom = calibration_none.phantom
    assert len(truth["frames"]) == len(calibration_none) == 12
    for frame in truth["frames"]:
        markers = np.array(frame["markers_px"], dtype=float)
        assert markers.shape == (12, 2) and np.isfinite(markers).all()
        points = markers_to_phantom(truth, calibration_none.records[frame["index"]].tool_to_base, markers)
        assert phantom.wire_distances(points, np.arange(12)).max() < 1e-6


def test_true_markers_land_on_the_bright_dots(calibration_none):
    truth = calibration_none.truth()
    for frame in truth["frames"]:
        image = calibration_none.image(frame["index"])
        n, labels, stats, centroids = cv2.connectedComponentsWithStats((image > 127).astype(np.uint8))
        for u, v in frame["markers_px"]:
            assert image[int(round(v)), int(round(u))] >= 200
            label = labels[int(round(v)), int(round(u))]
            assert label > 0
            assert np.hypot(*(centroids[label] - (u, v))) < 1.5


def test_realistic_frames_keep_dots_bright_and_background_dark(tmp_path):
    session = simulate_calibration(tmp_path / "r", n_poses=6, seed=1, noise="realistic")
    truth = session.truth()
    for frame in truth["frames"]:
        image = session.image(frame["index"])
        assert np.median(image) < 30
        for u, v in frame["markers_px"]:
            window = image[int(v) - 2 : int(v) + 3, int(u) - 2 : int(u) + 3]
            assert window.max() >= 200


def test_harsh_noise_drops_frames_or_wires(tmp_path):
    session = simulate_calibration(tmp_path / "h", n_poses=60, seed=2, noise="harsh")
    truth = session.truth()
    missing_wires = sum(any(m is None for m in f["markers_px"]) for f in truth["frames"])
    dropped = session.manifest.dropped_frames
    assert dropped + missing_wires > 0
    assert len(session) == 60 - dropped


def test_plan_keeps_every_wire_in_view_and_reachable():
    twin = make_twin(5)
    plan = calibration_plan(twin.nominal, 40, seed=5)
    assert len(plan.poses) == 40 and plan.duration_s > 0
    for pose in plan.poses:
        assert np.isfinite(twin.markers_px(pose)).all()
    # The poses are diverse: rotations span most of the +-15 degree ranges.
    from scipy.spatial.transform import Rotation

    centre = twin.nominal.tool_to_base(twin.nominal.image_to_phantom)
    angles = np.array([Rotation.from_matrix(centre[:3, :3].T @ p[:3, :3]).as_rotvec(degrees=True) for p in plan.poses])
    assert np.all(angles.max(axis=0) - angles.min(axis=0) > 15)


def test_plan_rejects_an_image_that_misses_wires():
    twin = make_twin(0)
    setup = twin.nominal
    far = setup.image_to_phantom.copy()
    far[0, 3] += 15.0
    assert crossings_in_view(setup, setup.image_to_phantom)
    assert not crossings_in_view(setup, far)


def _image_poses(setup, tool_to_base):
    """(N, 6): image centre (mm, phantom frame) and rotation vector (deg) from the centre pose,
    image axes."""
    image_to_phantom = [invert_transform(setup.phantom_to_base) @ p @ setup.image_to_tool_rigid for p in tool_to_base]
    centre = np.array([setup.probe.width_mm / 2, setup.probe.depth_mm / 2, 0.0])
    return np.array([[*transform_points(m, centre[None])[0],
                      *Rotation.from_matrix(setup.image_to_phantom[:3, :3].T @ m[:3, :3]).as_rotvec(degrees=True)]
                     for m in image_to_phantom])


def test_a_hand_path_is_smooth_keeps_the_wires_in_view_sweeps_along_them_and_its_halves_cover_different_poses():
    setup = make_twin(4).nominal
    poses = hand_path(setup, 60, seed=4)
    assert len(poses) == 60
    assert all(crossings_in_view(setup, invert_transform(setup.phantom_to_base) @ p @ setup.image_to_tool_rigid)
               for p in poses)
    hand = _image_poses(setup, poses)
    # The hand pivots as it slides the probe along the wires (phantom y): about each axis the
    # turn follows the sweep at a slope within PLUS's recordings' and wanders about it like a
    # uniform draw over the ranges.
    for axis, column in enumerate((3, 5, 4)):  # phantom x, y, z: image x, z, -y
        slope, intercept = np.polyfit(hand[:, 1], hand[:, column], 1)
        low, high = HAND_PIVOT_DEG_PER_MM[axis]
        assert 0.8 * low < abs(slope) < 1.2 * high
        wander = np.std(hand[:, column] - slope * hand[:, 1] - intercept)
        assert wander < 1.25 * FREEHAND_RANGES.rotation_deg[axis] / np.sqrt(3)
    # Smooth: a typical step is a small fraction of the spread (the robot's plan jumps about).
    steps = np.median(np.abs(np.diff(hand, axis=0)), axis=0)
    assert np.all(steps < 0.2 * hand.std(axis=0))
    planned = _image_poses(setup, calibration_plan(setup, 60, seed=4).poses)  # the robot's

    def halves_apart(x):  # the halves' means apart, in units of the whole's spread, mean over the axes
        return np.mean(np.abs(x[:30].mean(axis=0) - x[30:].mean(axis=0)) / x.std(axis=0))

    assert halves_apart(hand) > max(1.0, 1.5 * halves_apart(planned))
    # It sweeps along the wires (phantom y) from one end to the other: half a cosine puts the
    # halves' means 2 / pi of the sweep apart, the wander a little more or less.
    assert abs(hand[:30, 1].mean() - hand[30:, 1].mean()) == pytest.approx(2 / np.pi * HAND_SWEEP_MM, rel=0.3)
    again, other = hand_path(setup, 60, seed=4), hand_path(setup, 60, seed=4, path=1)
    assert np.array_equal(np.array(again), np.array(poses))
    assert not np.allclose(np.array(other), np.array(poses))


def test_a_tracked_freehand_recording_knows_its_phantom_and_calibrates_as_plus_records_one(tmp_path):
    session = simulate_freehand(tmp_path / "hand", n_poses=40, seed=2)
    truth = session.truth()
    assert session.manifest.arm is None
    # The phantom pose as registered: off the truth about the vertical only (1.2 deg sd at bench).
    registered_to_true = invert_transform(np.array(truth["phantom_to_base"])) @ session.phantom_to_base
    assert np.allclose(registered_to_true[:3, 3], 0.0, atol=1e-9) and np.allclose(registered_to_true[2, :3], [0, 0, 1])
    assert 0.01 < transform_error(registered_to_true, np.eye(4))[1] < 5.0
    # The tracker reports every pose off by its noise (0.15 mm sd per axis at bench), which jitters
    # from frame to frame, and by its drift (0.22 mm RMS per axis), which wanders slowly: nine
    # frames in a row average the noise out, not the drift.
    actual = np.array([f["tool_to_base"] for f in truth["frames"]])
    tracked = session.poses()[[f["index"] for f in truth["frames"]]]
    error_mm = np.array([invert_transform(a) @ t for a, t in zip(actual, tracked)])[:, :3, 3]
    jitter = np.median(np.abs(np.diff(error_mm, 2, axis=0)), axis=0) / 0.6745 / np.sqrt(6)
    means = np.array([np.convolve(axis, np.ones(9) / 9, mode="valid") for axis in error_mm.T])
    np.testing.assert_allclose(jitter, 0.15, rtol=0.3)
    np.testing.assert_allclose(error_mm.std(axis=0), np.hypot(0.22, 0.15), rtol=0.3)
    assert np.all(means.std(axis=1) > 2 * jitter / 3)  # twice what the noise alone would leave
    results = segment_session(session)
    assert sum(r.found for r in results) >= 36
    calibration = calibrate_session(session, results, with_validation=False).calibration
    true = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
    assert calibration.metrics["phantom_pose"] == "known"
    assert corner_distance_mm(calibration, true, image_corners_px(session.image_size)) < 5.0


def test_a_freehand_bench_registers_its_phantom_off_alike_on_every_recording(tmp_path):
    lvl = level("bench")
    lvl = replace(lvl, setup=replace(lvl.setup, phantom_registration=(1.0,) * 6))
    paths = [simulate_freehand(tmp_path / f"hand{path}", n_poses=3, seed=5, noise=lvl, path=path) for path in (0, 1)]
    truth = np.array(paths[0].truth()["phantom_to_base"])
    np.testing.assert_array_equal(paths[0].phantom_to_base, paths[1].phantom_to_base)
    np.testing.assert_array_equal(truth, paths[1].truth()["phantom_to_base"])
    mm, deg = transform_error(paths[0].phantom_to_base, truth)
    assert 0.1 < mm < 5.0 and 0.1 < deg < 5.0
    other = simulate_freehand(tmp_path / "other", n_poses=3, seed=6, noise=lvl)
    assert not np.allclose(other.phantom_to_base @ invert_transform(np.array(other.truth()["phantom_to_base"])),
                           paths[0].phantom_to_base @ invert_transform(truth))


def test_volume_session_surface_matches_cad(tmp_path):
    session = simulate_volume(tmp_path / "v", seed=0, noise="none", n_frames=30)
    truth = session.truth()
    assert (session.path / truth["cad_mesh"]).is_file()
    mesh = trimesh.load_mesh(session.path / truth["cad_mesh"])
    object_to_base = np.array(truth["object_to_base"])
    image_to_tool = np.array(truth["image_to_tool"])
    assert session.manifest.plan["passes"] >= 2 and len(session) == session.manifest.plan["poses"]
    checked = 0
    for i in range(0, len(session), 20):
        image = session.image(i)
        columns, rows = extract_surface(image)
        if len(columns) == 0:
            continue
        pixels = np.column_stack([columns, rows, np.zeros(len(columns))])
        points = transform_points(
            invert_transform(object_to_base) @ session.records[i].tool_to_base @ image_to_tool, pixels
        )
        _, distance, _ = trimesh.proximity.closest_point(mesh, points)
        assert np.median(distance) < 0.1
        checked += 1
    assert checked >= 5
