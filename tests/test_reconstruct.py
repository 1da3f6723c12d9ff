"""Volume scanning: the transform chain, the simulator against CAD, PLUS's volume, bad input."""

import hashlib
import json
import shutil

import numpy as np
import pytest

from probecal.core.acquisition.simulate import simulate_volume
from probecal.core.calibration.result import Calibration
from probecal.core.geometry.transforms import make_transform, transform_error
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import SessionWriter
from probecal.core.twin.twin import make_twin
from probecal.core.volume.pointcloud import base_points_from_pixels
from probecal.core.volume.reconstruct import reconstruct_plus
from probecal.core.volume.saved import load_reconstruction
from probecal.core.volume.surface import SurfaceParams, extract_surface
from probecal.core.volume.volumefile import read_volume
from tests.support.cli import run_cli
from tests.support.jsonkeys import golden_keys, key_paths
from tests.support.paths import PLUS
from tests.support.refusals import assert_one_line_error

SPINE = PLUS / "TestImages" / "SpinePhantomFreehand.igs.mha"
NN_MEAN = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml"


def test_transform_chain_on_a_synthetic_plane():
    """tool_to_base . image_to_tool_rigid . diag(sx, sy, 1) . (u, v, 0, 1), checked by hand."""
    rigid = make_transform(np.column_stack([[0, 1, 0], [0, 0, -1], [-1, 0, 0]]), [5.0, 0.0, 100.0])
    calibration = Calibration(rigid, (0.2, 0.1))
    tool_to_base = make_transform(np.eye(3), [100.0, -300.0, 50.0])
    u, v = np.array([0.0, 10.0, 0.0]), np.array([0.0, 0.0, 20.0])
    points = base_points_from_pixels(u, v, tool_to_base, calibration.image_to_tool)
    # u runs along tool +y at 0.2 mm/px, v along tool -z at 0.1 mm/px, origin at tool (5, 0, 100).
    assert np.allclose(points, [[105, -300, 150], [105, -298, 150], [105, -300, 148]])
    # Every pixel of the frame lies on one plane: the image plane, here tool x = 5.
    uu, vv = np.meshgrid(np.arange(0, 384, 50.0), np.arange(0, 500, 50.0))
    plane = base_points_from_pixels(uu.ravel(), vv.ravel(), tool_to_base, calibration.image_to_tool)
    assert np.allclose(plane[:, 0], 105.0)


@pytest.fixture(scope="module")
def volume_session(tmp_path_factory):
    return simulate_volume(tmp_path_factory.mktemp("vol") / "v", seed=2, noise="realistic", n_frames=40)


@pytest.mark.slow
def test_an_echo_s_steepest_rise_does_not_move_with_its_strength():
    """Four bands of scan lines, one interface at row 80.3 echoing ever weaker (as at ever more oblique
    incidence): the threshold's crossing comes later the weaker the echo, the steepest rise not."""
    rows = np.arange(200)[:, None]
    strength = np.repeat([255.0, 200.0, 160.0, 140.0], 10)  # bands wider than the median filter
    image = (strength / (1 + np.exp(-(rows - 80.3) / 1.5))).astype(np.uint8)
    _, crossing = extract_surface(image)
    _, rise = extract_surface(image, SurfaceParams(edge="steepest"))
    middles = [5, 15, 25, 35]
    assert np.ptp(crossing[middles]) > 1.5 and np.ptp(rise[middles]) < 0.2
    assert rise[middles] == pytest.approx(80.3, abs=0.2)


def test_simulated_scan_matches_cad_with_true_calibration(volume_session, tmp_path):
    out = tmp_path / "rec"
    result = run_cli("reconstruct", volume_session.path, "--calibration", volume_session.path / "truth.json",
                     "--out", out, "--cad", volume_session.path / "test_object.stl")
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    assert key_paths(report) == golden_keys("report")  # every field a report has held
    assert report["surface_mean_mm"] <= 0.3 and report["surface_p95_mm"] <= 1.0
    truth = volume_session.path / "truth.json"  # the calibration that made it, named and hashed
    assert report["calibration"] == {"file": str(truth.resolve()), "derived": False,
                                     "sha256": hashlib.sha256(truth.read_bytes()).hexdigest()}
    assert {p.name for p in out.iterdir()} == {"surface.ply", "surface_error.ply", "volume.nrrd", "report.json"}
    assert (out / "surface.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")
    volume = read_volume(out / "volume.nrrd")
    assert volume.spacing_mm == pytest.approx((0.5, 0.5, 0.5)) and volume.voxels.max() > 200
    assert result.stdout.startswith("Volume usable: surface ") and "200 of 200 planned poses" in result.stdout
    assert report["verdict"]["usable"] is True and report["coverage"] == {"recorded": 200, "planned": 200,
                                                                          "unit": "poses"}


def test_a_partial_scan_s_verdict_warns_first(volume_session, tmp_path):
    """A scan stopped at a quarter of its poses: the verdict says the volume is partial, before
    any figure, and the report keeps it; the reconstruction reads back as it was written."""
    partial = tmp_path / "partial"
    shutil.copytree(volume_session.path, partial)
    records = (partial / "records.jsonl").read_text().splitlines()
    (partial / "records.jsonl").write_text("\n".join(records[:len(records) // 4]) + "\n")
    out = tmp_path / "rec"
    result = run_cli("reconstruct", partial, "--calibration", partial / "truth.json", "--out", out,
                     "--cad", partial / "test_object.stl")
    assert result.returncode == 0, result.stderr
    first = result.stdout.splitlines()[0]
    assert first.startswith(f"Partial volume: {len(records) // 4} of {len(records)} planned poses scanned"), first
    assert "Next: resume the scan" in first
    report = json.loads((out / "report.json").read_text())
    assert report["verdict"] == {"usable": False, "text": first, "tolerance_mm": 1.0}
    saved = load_reconstruction(out)
    assert saved.report == report and len(saved.points_base) == report["surface_points"]
    assert saved.error_colors is not None and saved.volume.voxels.shape == tuple(report["volume"]["shape_zyx"])


def test_a_cad_placed_away_from_the_scan_is_judged_not_usable_in_a_report_that_reads_back(volume_session, tmp_path):
    """The object recorded 280 mm from where it was scanned (a truth field made hostile): no CAD
    face lies under the surface, so CAD-to-points has nothing to measure: null, not NaN."""
    moved = tmp_path / "moved"
    shutil.copytree(volume_session.path, moved)
    truth = json.loads((moved / "truth.json").read_text())
    truth["object_to_base"][1][3] = -0.0
    (moved / "truth.json").write_text(json.dumps(truth))
    out = tmp_path / "rec"
    result = run_cli("reconstruct", moved, "--calibration", moved / "truth.json", "--out", out,
                     "--cad", moved / "test_object.stl")
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("Not usable: no face of the CAD model lies under the scanned surface")
    assert "CAD to points none under the scan" in result.stdout
    report = json.loads((out / "report.json").read_text())
    assert report["cad_to_points_mean_mm"] is None and report["verdict"]["usable"] is False
    assert load_reconstruction(out).report == report


def test_icp_registration_finds_a_displaced_cad(volume_session, tmp_path):
    """--register refines the CAD pose from a start that is 2 mm and 2 degrees off. Across the
    extrusion (object x) and in height the surface pins the pose down; along the extrusion (y)
    only the object's ends do, and the 40 mm passes barely reach them."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from probecal.core.volume.cad import cad_placement_from_session
    from probecal.core.volume.pointcloud import refine_cad_placement

    out = tmp_path / "rec"
    assert run_cli("reconstruct", volume_session.path, "--calibration", volume_session.path / "truth.json",
                   "--out", out).returncode == 0
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(str(out / "surface.ply")).points)
    mesh = trimesh.load_mesh(volume_session.path / "test_object.stl")
    truth = cad_placement_from_session(volume_session)
    start = truth @ make_transform(Rotation.from_euler("z", 2, degrees=True), [2.0, -1.5, 0.5])
    found = refine_cad_placement(points, mesh, start)
    dx, dy, dz = (np.linalg.inv(truth) @ found)[:3, 3]
    assert abs(dx) < 0.1 and abs(dz) < 0.1 and abs(dy) < 0.75
    assert transform_error(found, truth)[1] < 0.2


def test_plus_spine_volume_matches_plus(plus_data, tmp_path):
    assert run_cli("import-plus", SPINE, "--config", NN_MEAN, tmp_path / "spine").returncode == 0
    result = run_cli("reconstruct", tmp_path / "spine", "--calibration", NN_MEAN, "--out", tmp_path / "rec")
    assert result.returncode == 0, result.stderr
    ours = read_volume(tmp_path / "rec" / "volume.nrrd")
    ref = read_volume(PLUS / "TestImages" / "vtkVolumeReconstructorTestNNMEANvolumeRef.mha")
    assert ours.voxels.shape == ref.voxels.shape
    assert np.allclose(ours.origin_mm, ref.origin_mm, atol=1e-3)
    both = (ours.voxels > 0) & (ref.voxels > 0)
    assert np.corrcoef(ours.voxels[both].astype(float), ref.voxels[both].astype(float))[0, 1] >= 0.99


@pytest.mark.slow
def test_a_volume_config_gives_the_volume_its_plus_config_gives(plus_data, tmp_path):
    """One config, one volume: ``--volume-config`` keeps every setting PLUS's own path keeps, hole
    filling included (sticks of 5 voxels, 3 averaged, unlike the defaults)."""
    sticks = tmp_path / "sticks.xml"
    sticks.write_text(NN_MEAN.read_text().replace('StickLengthLimit="9"', 'StickLengthLimit="5"')
                      .replace('NumberOfSticksToUse="1"', 'NumberOfSticksToUse="3"'))
    assert run_cli("import-plus", SPINE, "--config", NN_MEAN, tmp_path / "spine").returncode == 0
    for config, out in ((NN_MEAN, "default"), (sticks, "sticks")):
        result = run_cli("reconstruct", tmp_path / "spine", "--calibration", NN_MEAN, "--volume-config", config,
                         "--out", tmp_path / out)
        assert result.returncode == 0, result.stderr
    ours = read_volume(tmp_path / "sticks" / "volume.nrrd")
    plus_path = reconstruct_plus(SPINE, sticks)
    assert np.array_equal(ours.voxels, plus_path.voxels) and np.allclose(ours.origin_mm, plus_path.origin_mm)
    assert not np.array_equal(ours.voxels, read_volume(tmp_path / "default" / "volume.nrrd").voxels)


def write(path, frames, poses):
    twin = make_twin(0)
    with SessionWriter(path, Manifest(kind="volume"), probe=twin.probe) as w:
        for image, pose in zip(frames, poses):
            w.append(image, pose)


def test_missing_calibration(volume_session, tmp_path):
    result = run_cli("reconstruct", volume_session.path, "--calibration", tmp_path / "none.json",
                     "--out", tmp_path / "o")
    assert_one_line_error(result, "none.json", "file not found")
    assert not (tmp_path / "o").exists()


def test_frames_without_poses(volume_session, tmp_path):
    write(tmp_path / "s", [volume_session.image(i) for i in range(5)], [None] * 5)
    result = run_cli("reconstruct", tmp_path / "s", "--calibration", volume_session.path / "truth.json",
                     "--out", tmp_path / "o")
    assert_one_line_error(result, "no frame has a valid pose")
    assert not (tmp_path / "o").exists()


def test_empty_surface(volume_session, tmp_path):
    write(tmp_path / "s", [np.zeros((500, 384), np.uint8)] * 5,
          [volume_session.records[i].tool_to_base for i in range(5)])
    result = run_cli("reconstruct", tmp_path / "s", "--calibration", volume_session.path / "truth.json",
                     "--out", tmp_path / "o")
    assert_one_line_error(result, "no surface found")
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".o*"))


def test_a_calibration_that_knows_the_arm_puts_the_volume_where_the_object_is(tmp_path):
    """At ``bench`` the arm's kinematic errors put the object off its CAD model even with the true
    calibration; with the arm's true deviations in the calibration, reconstruct maps every frame
    through that arm and the surface lies on the CAD model."""
    from dataclasses import replace

    from probecal.core.calibration.kinematics import DEVIATION_SD, deviation_json
    from probecal.core.calibration.result import load_calibration
    from probecal.core.volume.cad import session_cad_target
    from probecal.core.volume.reconstruct import reconstruct_session

    sweep = simulate_volume(tmp_path / "vol", seed=0, noise="bench", n_frames=16)
    true = load_calibration(sweep.path / "truth.json")
    dh = sweep.truth()["setup"]["dh_deviation"]
    units = np.concatenate([np.radians(dh["theta_deg"]), dh["d_mm"], dh["a_mm"], np.radians(dh["alpha_deg"])])
    knows_arm = replace(true, arm=deviation_json("UR3", units / DEVIATION_SD))
    cad = session_cad_target(sweep)
    reported = reconstruct_session(sweep, true, tmp_path / "reported", cad=cad).report["surface_mean_mm"]
    through_arm = reconstruct_session(sweep, knows_arm, tmp_path / "arm", cad=cad).report["surface_mean_mm"]
    assert through_arm < 0.1 < reported
