"""Results that cannot be misread (issue 18): a calibration says what images it was made for and
is refused on others, and every command treats an existing output the same way: refused unless
--force."""

import json

import numpy as np
import pytest

from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.result import load_calibration
from probecal.core.errors import InputError
from tests.conftest import FCAL_CONFIG, FCAL_VALIDATION, assert_one_line_error, run_cli


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A twin's calibration session and its calibration, made by the command line."""
    root = tmp_path_factory.mktemp("outputs")
    session = simulate_calibration(root / "cal", n_poses=16, seed=4, noise="realistic")
    result = run_cli("calibrate", session.path, "--out", root / "cal.json")
    assert result.returncode == 0, result.stderr
    return session, root / "cal.json"


def test_a_calibration_records_the_images_it_was_made_for(calibrated):
    session, cal = calibrated
    made_for = json.loads(cal.read_text())["valid_for"]
    assert made_for["image_size"] == [384, 500] and made_for["nominal_spacing_mm"] == pytest.approx([0.1, 0.1])
    assert made_for["depth_mm"] == pytest.approx(50.0)
    assert made_for["source"].startswith("probecal twin: linear probe 128")
    assert load_calibration(cal).valid_for == made_for


def test_a_real_recording_refuses_a_simulated_calibration_unless_forced(calibrated, plus_data, tmp_path):
    _, cal = calibrated
    real = tmp_path / "fcal-validation"
    assert run_cli("import-plus", FCAL_VALIDATION, "--config", FCAL_CONFIG, real).returncode == 0
    result = run_cli("validate", real, "--calibration", cal, "--out", tmp_path / "v.json")
    assert_one_line_error(result, str(cal), "made for other images", "820 x 616", "384 x 500", "--force")
    assert not (tmp_path / "v.json").exists()
    forced = run_cli("validate", real, "--calibration", cal, "--force")
    assert forced.returncode == 0 and "applied anyway (--force)" in forced.stderr


def test_existing_outputs_are_refused_unless_forced(calibrated, tmp_path):
    session, cal = calibrated
    before = cal.read_text()
    assert_one_line_error(run_cli("calibrate", session.path, "--out", cal), str(cal), "--force overwrites it")
    assert cal.read_text() == before
    seg = tmp_path / "seg.json"
    seg.write_text("{}")
    assert_one_line_error(run_cli("segment", session.path, "--out", seg), str(seg), "--force")
    assert run_cli("segment", session.path, "--out", seg, "--force").returncode == 0
    assert len(json.loads(seg.read_text())["frames"]) == len(session)
    mha = tmp_path / "s.igs.mha"
    mha.write_bytes(b"x")
    assert_one_line_error(run_cli("export-plus", session.path, mha), str(mha), "--force")
    assert run_cli("export-plus", session.path, mha, "--force").returncode == 0 and mha.stat().st_size > 1000


def test_reconstruct_replaces_its_folder_only_when_forced_and_only_once_the_new_one_is_whole(tmp_path):
    sweep = simulate_volume(tmp_path / "vol", seed=1, noise="realistic", n_frames=12)
    out = tmp_path / "recon"
    args = ("reconstruct", sweep.path, "--calibration", sweep.path / "truth.json", "--out", out)
    assert run_cli(*args).returncode == 0
    first = (out / "report.json").read_text()
    assert_one_line_error(run_cli(*args), str(out), "--force replaces it")
    assert (out / "report.json").read_text() == first
    (out / "mine.txt").write_text("kept?")
    assert run_cli(*args, "--force").returncode == 0
    assert (out / "surface.ply").is_file() and not (out / "mine.txt").exists()
    assert not list(tmp_path.glob(".recon*"))


def test_a_hostile_valid_for_is_refused_naming_the_field(calibrated, tmp_path):
    _, cal = calibrated
    data = json.loads(cal.read_text())
    for bad, field in (([384], "valid_for.image_size"), ([0, 500], "valid_for.image_size"),
                       ("big", "valid_for.image_size")):
        data["valid_for"]["image_size"] = bad
        broken = tmp_path / "bad.json"
        broken.write_text(json.dumps(data))
        with pytest.raises(InputError, match=field.replace(".", r"\.")):
            load_calibration(broken)
    assert np.isfinite(load_calibration(cal).image_to_tool).all()
