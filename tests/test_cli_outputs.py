"""Results that cannot be misread (issue 18): a calibration says what images it was made for and
is refused on others, and every command treats an existing output the same way: refused unless
--force."""

import json
from dataclasses import replace

import numpy as np
import pytest

from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.presets import derived_for
from probecal.core.calibration.result import load_calibration
from probecal.core.calibration.validity import valid_for
from probecal.core.errors import InputError
from probecal.core.geometry.probe import LinearProbe
from tests.support.cli import run_cli
from tests.support.paths import FCAL_CONFIG, FCAL_VALIDATION
from tests.support.refusals import assert_one_line_error


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
    assert forced.returncode == 0 and "applied anyway" in forced.stderr  # --force needs no naming: it was given


def test_a_refusal_says_the_start_depth_would_derive_the_calibration(calibrated, plus_data, tmp_path):
    """The twin's calibration knows its images' first row's depth; a PLUS recording imported
    without one gets only the refusal, which names the option that records it, and with it the
    calibration is derived for the recording's images."""
    _, cal = calibrated
    unknown, known = tmp_path / "unknown", tmp_path / "known"
    assert run_cli("import-plus", FCAL_VALIDATION, "--config", FCAL_CONFIG, unknown).returncode == 0
    result = run_cli("validate", unknown, "--calibration", cal)
    assert_one_line_error(result, str(cal), f"were {unknown}'s first row's depth below the probe's face known",
                          "--start-depth-mm records it", "--force applies it anyway")
    imported = run_cli("import-plus", FCAL_VALIDATION, "--config", FCAL_CONFIG, known, "--start-depth-mm", "0")
    assert imported.returncode == 0, imported.stderr
    derived = run_cli("validate", known, "--calibration", cal)
    assert derived.returncode == 0, derived.stderr
    assert "derived for" in derived.stderr


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


def test_a_calibration_at_one_depth_preset_is_derived_for_another(calibrated, tmp_path):
    """Another preset of the same probe (other image size and spacing, its first row 2 mm below the
    face): the probe's face and axis stay, the pixel map changes. The twin's truth at one preset,
    derived for another, is the truth there; a point maps where it did; validate says so."""
    session, cal = calibrated
    other = simulate_calibration(tmp_path / "other", n_poses=16, seed=4, noise="realistic",
                                 probe=replace(LinearProbe(), width_px=512, height_px=480, start_depth_mm=2.0,
                                               depth_mm=48.0))
    truth = replace(load_calibration(session.path / "truth.json"), valid_for=valid_for(session))
    derived = derived_for(truth, other)
    assert derived is not None
    assert np.abs(derived.image_to_tool - load_calibration(other.path / "truth.json").image_to_tool).max() < 1e-9
    deeper = replace(other, manifest=replace(other.manifest, start_depth_mm=5.0))
    shifted = derived_for(truth, deeper)
    (sx, sy), (osx, osy) = session.nominal_spacing_mm, other.nominal_spacing_mm
    for u, v in ((0.0, 0.0), (100.0, 250.0), (511.0, 479.0)):
        x_face, depth = u * osx - 512 * osx / 2, 5.0 + v * osy  # where the point is under the probe's face
        at_made = [(x_face + 384 * sx / 2) / sx, depth / sy, 0.0, 1.0]
        assert np.allclose(shifted.image_to_tool @ [u, v, 0.0, 1.0], truth.image_to_tool @ at_made, atol=1e-9)
    result = run_cli("validate", other.path, "--calibration", cal)
    assert result.returncode == 0, result.stderr
    assert "derived for" in result.stderr and "512 x 480" in result.stderr
    unknown = replace(other, manifest=replace(other.manifest, start_depth_mm=None))
    assert derived_for(truth, unknown) is None


@pytest.mark.parametrize("name", ["out.json", "out.txt", "out", "out.png", "out.mhd"])
def test_export_plus_writes_only_the_formats_it_names(calibrated, tmp_path, name):
    """SimpleITK picks the format from the name: .json failed in 22 lines, .png wrote an image
    without the transforms, .mhd a header whose pixel file stayed behind under a temporary name."""
    session, _ = calibrated
    result = run_cli("export-plus", session.path, tmp_path / name)
    assert_one_line_error(result, str(tmp_path / name), ".igs.mha or .seq.nrrd")
    assert list(tmp_path.iterdir()) == []


def test_an_output_folder_that_is_a_link_is_refused_by_every_command(tmp_path):
    """A link's target would be written into, or replaced (rmtree refused it half way, leaving the
    new folder behind); every command refuses it alike, before any work, and leaves nothing."""
    sweep = simulate_volume(tmp_path / "vol", seed=1, noise="none", n_frames=6)
    (tmp_path / "empty").mkdir()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "mine.txt").write_text("kept")
    reconstruct = ("reconstruct", sweep.path, "--calibration", sweep.path / "truth.json", "--out")
    for target in ("empty", "full"):
        link = tmp_path / f"to-{target}"
        link.symlink_to(tmp_path / target)
        for command in ((*reconstruct, link), (*reconstruct, link, "--force"), ("phantom", "export", link),
                        ("simulate", "volume", link, "--frames-per-pass", "2"), ("simulate", "calibration", link)):
            assert_one_line_error(run_cli(*command), str(link), "symbolic link")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "full", "to-empty", "to-full", "vol"]
    assert list((tmp_path / "empty").iterdir()) == []
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["mine.txt"]
