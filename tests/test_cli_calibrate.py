"""segment, calibrate and validate from the command line: on the simulator, on the real fCal
data, and on bad input."""

import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.result import load_calibration
from probecal.core.geometry.transforms import transform_error
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import SessionWriter
from probecal.core.twin.bmode import BModeRenderer
from probecal.core.twin.twin import make_twin
from tests.support.cli import run_cli
from tests.support.jsonkeys import golden_keys, key_paths
from tests.support.paths import FCAL_CALIBRATION, FCAL_CONFIG, FCAL_VALIDATION
from tests.support.refusals import assert_one_line_error


@pytest.fixture(scope="module")
def sim_session(tmp_path_factory):
    return simulate_calibration(tmp_path_factory.mktemp("cli") / "cal", n_poses=30, seed=21, noise="realistic")


def test_segment_writes_spec_json(sim_session, tmp_path):
    out = tmp_path / "seg.json"
    result = run_cli("segment", sim_session.path, "--out", out)
    assert result.returncode == 0, result.stderr
    data = json.loads(out.read_text())
    assert list(data) == ["frames"] and len(data["frames"]) == len(sim_session)
    frame = data["frames"][0]
    assert set(frame) == {"index", "found", "markers", "reason"}
    assert frame["found"] and len(frame["markers"]) == 12 and len(frame["markers"][0]) == 2


def test_calibrate_and_validate_on_the_simulator(sim_session, tmp_path):
    out = tmp_path / "cal.json"
    result = run_cli("calibrate", sim_session.path, "--out", out, "--verbose")
    assert result.returncode == 0, result.stderr
    for fragment in ("FRE", "PRE3D", "pixel spacing", "error vs poses", "OpenCV's closed-form hand-eye",
                     "all-wire", "middle-wire", "thesis", "image corners within ±", "(95 %", "agreement, not accuracy",
                     "the image-corner bound", "the 95 % bound over the image"):
        assert fragment in result.stdout
    data = json.loads(out.read_text())
    assert key_paths(data) == golden_keys("calibration")  # every field a calibration file has held
    for key in ("image_to_tool", "image_to_tool_rigid", "pixel_spacing_mm", "phantom_to_base", "metrics"):
        assert key in data
    metrics = data["metrics"]
    for key in ("method", "objective", "frames_used", "frames_total", "fre_mm", "pre3d_mm", "cv_pre3d_mm",
                "corner_error_95_mm", "objectives", "weakly_determined", "rejected_frames"):
        assert key in metrics, key
    assert metrics["method"] == "auto" and metrics["objective"] in metrics["objectives"]
    assert {name: row["cv_pre3d_mm"] > 0 for name, row in metrics["objectives"].items()} == {
        "all-wire": True, "middle-wire": True, "thesis": True}
    assert 0 < metrics["corner_error_95_mm"] < 1.0
    # The bound map: the same bound at every point of a grid over the image, at the corners within
    # the corner bound (which bounds the four at once), and read back as written.
    bounds, points = np.array(metrics["bound_map"]["bound_mm"]), np.array(metrics["bound_map"]["points_px"])
    assert points.shape == (*bounds.shape, 2) and bounds.shape[1] == 9 and bounds.shape[0] >= 9
    w, h = sim_session.image_size
    assert points[[0, 0, -1, -1], [0, -1, 0, -1]].tolist() == [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]]
    assert 0 < bounds.min() and bounds[[0, 0, -1, -1], [0, -1, 0, -1]].max() <= metrics["corner_error_95_mm"]
    assert load_calibration(out).metrics["bound_map"] == metrics["bound_map"]
    assert 'From="Image" To="Probe"' in out.with_suffix(".xml").read_text()
    truth = json.loads((sim_session.path / "truth.json").read_text())
    err = np.linalg.norm(np.array(data["image_to_tool_rigid"])[:3, 3] - np.array(truth["image_to_tool_rigid"])[:3, 3])
    assert err < 0.5
    # The same calibration scores well on a second sweep of the same set-up.
    other = simulate_calibration(tmp_path / "other", n_poses=12, seed=21, noise="realistic")
    metrics_file = tmp_path / "val.json"
    result = run_cli("validate", other.path, "--calibration", out, "--out", metrics_file)
    assert result.returncode == 0, result.stderr
    metrics = json.loads(metrics_file.read_text())["metrics"]
    assert metrics["pre3d_mm"] < 0.5 and metrics["phantom_pose_from"] == "calibration"
    # truth.json is accepted as a calibration too.
    assert run_cli("validate", other.path, "--calibration", sim_session.path / "truth.json").returncode == 0


def test_a_forced_method_keeps_its_objective(sim_session, tmp_path):
    result = run_cli("calibrate", sim_session.path, "--method", "seed", "--out", tmp_path / "seed.json")
    assert result.returncode == 0, result.stderr
    assert "objective thesis, as asked (--method thesis)" in result.stdout
    seed = json.loads((tmp_path / "seed.json").read_text())
    assert seed["pixel_spacing_mm"] == pytest.approx(list(sim_session.pixel_spacing_mm))
    assert seed["metrics"]["objective"] == "thesis" and seed["metrics"]["method"] == "thesis"  # seed: an alias
    assert seed["metrics"]["corner_error_95_mm"] > 3.0  # its nominal spacing cannot hide behind its PRE3D
    assert_one_line_error(run_cli("calibrate", sim_session.path, "--method", "best"), "invalid choice")


def test_a_recording_that_does_not_name_its_arm_is_told_it(sim_session, tmp_path):
    """A lab's own robot recording names no arm; --arm names it, and the arm's kinematic errors
    are fitted with the calibration. An arm other than the one the session names is refused."""
    lab = tmp_path / "lab"
    shutil.copytree(sim_session.path, lab)
    manifest = json.loads((lab / "manifest.json").read_text())
    assert manifest["arm"] == "UR3"
    (lab / "manifest.json").write_text(json.dumps({**manifest, "arm": None}))
    result = run_cli("calibrate", lab, "--method", "all-wire", "--arm", "UR3", "--out", tmp_path / "cal.json",
                     "--verbose")
    assert result.returncode == 0, result.stderr
    assert "arm: the UR3's kinematic errors fitted" in result.stdout
    assert json.loads((tmp_path / "cal.json").read_text())["arm"]["model"] == "UR3"
    assert_one_line_error(run_cli("calibrate", sim_session.path, "--arm", "UR3e", "--out", tmp_path / "e.json"),
                          str(sim_session.path), "recorded by the UR3, not the UR3e")
    assert not (tmp_path / "e.json").exists()


def test_poses_recorded_to_six_digits_fit_the_arm_as_the_exact_ones_do(sim_session, tmp_path):
    """A lab's own recording keeps its poses to 6 significant digits, so their rotations are
    rotations only to that precision (about 1e-6). --arm UR3 fits the arm's kinematic errors from
    them as from the exact poses, to the records' precision."""
    fitted = {}
    for name, number in (("exact", float), ("rounded", lambda v: float(f"{v:.6g}"))):
        lab = tmp_path / name
        shutil.copytree(sim_session.path, lab)
        manifest = json.loads((lab / "manifest.json").read_text())
        (lab / "manifest.json").write_text(json.dumps({**manifest, "arm": None}))
        records = [json.loads(line) for line in (lab / "records.jsonl").read_text().splitlines()]
        for record in records:
            record["tool_to_base"] = [[number(v) for v in row] for row in record["tool_to_base"]]
        (lab / "records.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
        result = run_cli("calibrate", lab, "--method", "all-wire", "--arm", "UR3", "--verbose",
                         "--out", tmp_path / f"{name}.json")
        assert result.returncode == 0, result.stderr
        assert "arm: the UR3's kinematic errors fitted" in result.stdout, result.stdout
        fitted[name] = load_calibration(tmp_path / f"{name}.json")
    assert fitted["rounded"].metrics["arm_correction_mm"] is not None
    shift_mm, turn_deg = transform_error(fitted["rounded"].image_to_tool_rigid, fitted["exact"].image_to_tool_rigid)
    assert shift_mm < 0.01 and turn_deg < 0.01, (shift_mm, turn_deg)


def test_calibrate_says_first_whether_the_calibration_is_usable_in_a_few_lines(sim_session, tmp_path):
    """The verdict comes first and the default output is short; the calibration's JSON keeps the
    verdict with everything else, and --tolerance is the user's."""
    out = tmp_path / "cal.json"
    result = run_cli("calibrate", sim_session.path, "--out", out)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("Calibration usable: image corners within ±"), lines[0]
    assert "under your 1.0 mm tolerance; 30 of 30 frames" in lines[0]
    assert len(lines) <= 10 and result.stderr == "", (lines, result.stderr)
    metrics = json.loads(out.read_text())["metrics"]
    assert metrics["verdict"] == {"usable": True, "text": lines[0], "tolerance_mm": 1.0}
    assert "objectives" in metrics and "error_vs_poses" in metrics  # the JSON keeps what --verbose prints
    strict = run_cli("calibrate", sim_session.path, "--out", tmp_path / "strict.json", "--tolerance", "0.05")
    assert strict.returncode == 0, strict.stderr
    first = strict.stdout.splitlines()[0]
    assert first.startswith("Not usable: image corners within ±") and "over your 0.05 mm tolerance" in first, first
    assert " Next: " in first  # more poses, or what more poses cannot close


def test_a_calibration_from_too_few_poses_is_not_usable_and_says_how_many_to_take(tmp_path):
    few = simulate_calibration(tmp_path / "few", n_poses=8, seed=1, noise="bench")
    result = run_cli("calibrate", few.path)
    assert result.returncode == 0, result.stderr
    first = result.stdout.splitlines()[0]
    assert first.startswith("Not usable: image corners within ±") and "over your 1.0 mm tolerance; 8 of 8" in first
    poses = int(first.split("sweep of about ")[1].split(" poses")[0])
    assert 8 < poses <= 100, first
    verdict = json.loads((few.path / "calibration.json").read_text())["metrics"]["verdict"]
    assert verdict["usable"] is False and verdict["text"] == first


@pytest.mark.slow
def test_fcal_calibrate_then_validate_beats_plus(plus_data, tmp_path):
    for name, seq in (("cal", FCAL_CALIBRATION), ("val", FCAL_VALIDATION)):
        assert run_cli("import-plus", seq, "--config", FCAL_CONFIG, tmp_path / name).returncode == 0
    result = run_cli("calibrate", tmp_path / "cal", "--out", tmp_path / "c.json")
    assert result.returncode == 0, result.stderr
    result = run_cli("validate", tmp_path / "val", "--calibration", tmp_path / "c.json", "--out", tmp_path / "m.json")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "m.json").read_text())["metrics"]
    assert metrics["phantom_pose_from"] == "session"
    assert metrics["pre3d_mm"] <= 1.20  # PLUS baseline: 1.247 mm


def write_session(path, frames, poses, twin):
    with SessionWriter(path, Manifest(kind="calibration", pixel_spacing_mm=twin.probe.nominal_spacing_mm),
                       twin.phantom, twin.probe) as w:
        for image, pose in zip(frames, poses):
            w.append(image, pose)


def test_empty_session(tmp_path):
    twin = make_twin(0)
    write_session(tmp_path / "empty", [], [], twin)
    assert_one_line_error(run_cli("calibrate", tmp_path / "empty"), "empty", "no frames")
    assert not (tmp_path / "empty" / "calibration.json").exists()


def test_every_frame_failing(tmp_path):
    twin = make_twin(0)
    centre = twin.nominal.tool_to_base(twin.nominal.image_to_phantom)
    write_session(tmp_path / "black", [np.zeros((500, 384), np.uint8)] * 8, [centre] * 8, twin)
    assert_one_line_error(run_cli("calibrate", tmp_path / "black"), "black", "no usable frame")
    assert not (tmp_path / "black" / "calibration.json").exists()


def test_no_valid_poses(sim_session, tmp_path):
    """Frames recorded while the pose was invalid (a tracker's marker out of view): none to calibrate."""
    twin = make_twin(21)
    frames = [sim_session.image(i) for i in range(10)]
    write_session(tmp_path / "none", frames, [None] * 10, twin)
    assert_one_line_error(run_cli("calibrate", tmp_path / "none"), "none", "no valid pose")


def test_degenerate_pose_set(tmp_path):
    twin = make_twin(0)
    renderer = BModeRenderer(twin.probe, "none", 0)
    centre = twin.nominal.tool_to_base(twin.nominal.image_to_phantom)
    poses, frames = [], []
    for angle in np.linspace(-8, 8, 10):
        pose = centre.copy()
        pose[:3, :3] = centre[:3, :3] @ Rotation.from_euler("x", angle, degrees=True).as_matrix()
        poses.append(pose)
        frames.append(renderer.render(twin.markers_px(pose)))
    write_session(tmp_path / "axis", frames, poses, twin)
    assert_one_line_error(run_cli("calibrate", tmp_path / "axis"), "axis", "single axis")


def test_validate_bad_calibration_file(sim_session, tmp_path):
    bogus = tmp_path / "bogus.json"
    bogus.write_text('{"image_to_tool_rigid": [[1, 0], [0, 1]]}')
    assert_one_line_error(run_cli("validate", sim_session.path, "--calibration", bogus), "bogus.json", "4x4")
    assert_one_line_error(run_cli("validate", sim_session.path, "--calibration", tmp_path / "missing.json"),
                          "missing.json", "file not found")
