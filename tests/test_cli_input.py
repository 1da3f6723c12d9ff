"""Bad input on the command line: exit code 2, one line naming the file, nothing half-written."""

import shutil
from concurrent.futures import ProcessPoolExecutor

import pytest

from probecal.core.errors import InputError
from tests.support.cli import run_cli
from tests.support.paths import FCAL_CONFIG, FCAL_VALIDATION, PLUS
from tests.support.refusals import assert_one_line_error


def test_help_on_every_command():
    for args in (["--help"], ["simulate", "--help"], ["simulate", "calibration", "--help"],
                 ["simulate", "volume", "--help"], ["import-plus", "--help"], ["export-plus", "--help"],
                 ["serve", "--help"]):
        result = run_cli(*args)
        assert result.returncode == 0 and "usage:" in result.stdout


def test_usage_error_is_one_line():
    assert_one_line_error(run_cli("simulate", "calibration"), "OUT_DIR")
    assert_one_line_error(run_cli("simulate", "calibration", "x", "--poses", "0"), "--poses")


def test_import_missing_file(plus_data, tmp_path):
    out = tmp_path / "out"
    result = run_cli("import-plus", tmp_path / "nope.igs.mha", "--config", FCAL_CONFIG, out)
    assert_one_line_error(result, "nope.igs.mha", "file not found")
    assert not out.exists()


@pytest.mark.parametrize("spacing", [["0.0256"], ["0.1", "0.098"], ["0.1,0.098"]], ids=" ".join)
def test_spacing_never_takes_the_output_folder_after_it(tmp_path, spacing):
    """``--spacing SX [SY] OUT_DIR``: the folder is the folder, not a second number (the command
    goes on to find the recording missing, rather than "invalid number value: 'OUT_DIR'")."""
    result = run_cli("import-plus", tmp_path / "nope.igs.mha", "--spacing", *spacing, tmp_path / "out")
    assert_one_line_error(result, "nope.igs.mha", "file not found")


def test_import_truncated_mha(plus_data, tmp_path):
    truncated = tmp_path / "cut.igs.mha"
    data = FCAL_VALIDATION.read_bytes()
    truncated.write_bytes(data[: len(data) * 2 // 3])
    out = tmp_path / "out"
    result = run_cli("import-plus", truncated, "--config", FCAL_CONFIG, out)
    assert_one_line_error(result, "cut.igs.mha", "truncated")
    assert not out.exists() and list(tmp_path.iterdir()) == [truncated]


def test_import_truncated_header(plus_data, tmp_path):
    truncated = tmp_path / "head.igs.mha"
    truncated.write_bytes(FCAL_VALIDATION.read_bytes()[:5000])
    result = run_cli("import-plus", truncated, "--config", FCAL_CONFIG, tmp_path / "out")
    assert_one_line_error(result, "head.igs.mha")
    assert not (tmp_path / "out").exists()


def test_xml_without_phantom(plus_data, tmp_path):
    no_phantom = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml"
    out = tmp_path / "sim"
    result = run_cli("simulate", "calibration", out, "--phantom", no_phantom)
    assert_one_line_error(result, no_phantom.name, "no <PhantomDefinition>")
    assert not out.exists()


def test_not_a_plus_xml(tmp_path):
    bogus = tmp_path / "other.xml"
    bogus.write_text("<Something/>")
    out = tmp_path / "out"
    result = run_cli("import-plus", FCAL_VALIDATION, "--config", bogus, out)
    assert_one_line_error(result, "other.xml", "not a PLUS device-set")
    assert not out.exists()


def test_session_with_missing_frame(plus_data, tmp_path):
    session = tmp_path / "s"
    assert run_cli("import-plus", FCAL_VALIDATION, "--config", FCAL_CONFIG, session).returncode == 0
    (session / "frames" / "000010.png").unlink()
    out = tmp_path / "x.igs.mha"
    result = run_cli("export-plus", session, out)
    assert_one_line_error(result, "000010.png", "frame 10 is missing")
    assert not out.exists()


def test_output_folder_not_empty(plus_data, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    result = run_cli("import-plus", FCAL_VALIDATION, "--config", FCAL_CONFIG, out)
    assert_one_line_error(result, "busy", "not empty")
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_import_plus_prints_summary(plus_data, tmp_path):
    result = run_cli("import-plus", FCAL_VALIDATION, "--config", FCAL_CONFIG, tmp_path / "v")
    assert result.returncode == 0, result.stderr
    assert "94 frames (94 with a valid pose), phantom fCAL 1.2, phantom pose known" in result.stdout
    assert "; ProbeToReference = inv(ReferenceToTracker) @ ProbeToTracker" in result.stdout  # the frames composed
    shutil.rmtree(tmp_path / "v")


def test_import_plus_says_a_tool_pose_is_read_as_recorded(tmp_path):
    """A recording that holds the tool pose itself (probecal's own export) is not said to be
    composed of itself ("ProbeToReference = ProbeToReference")."""
    session, recording = tmp_path / "sim", tmp_path / "sim.igs.mha"
    assert run_cli("simulate", "calibration", session, "--poses", "4", "--noise", "none").returncode == 0
    assert run_cli("export-plus", session, recording).returncode == 0
    result = run_cli("import-plus", recording, tmp_path / "again")
    assert result.returncode == 0, result.stderr
    assert result.stdout.rstrip().endswith("; ProbeToReference as the recording holds it")


def test_an_input_error_crosses_to_another_process_whole():
    """The command line runs work in a process pool; a worker's InputError must reach the parent
    with its file and problem, not break the pool."""
    error = InputError("sessions/s/frames.mha", "truncated")
    with ProcessPoolExecutor(1) as pool:
        returned = pool.submit(_raise, error).exception()
    assert isinstance(returned, InputError)
    assert (returned.path, returned.problem, str(returned)) == (error.path, error.problem, str(error))


def _raise(error: Exception) -> None:
    raise error


NON_FINITE_OPTIONS = [
    ("sweep", "calibration", "OUT", "--latency", "nan"),
    ("sweep", "calibration", "OUT", "--latency", "inf"),
    ("sweep", "volume", "OUT", "--time-scale", "inf"),
    ("sweep", "volume", "OUT", "--speed", "nan"),
    ("simulate", "calibration", "OUT", "--frame-rate", "inf"),
    ("simulate", "volume", "OUT", "--speed", "inf"),
    ("simulate", "volume", "OUT", "--depth-mm", "nan"),
    ("import-rosbag", "BAG", "OUT", "--image-topic", "/i", "--pose-topic", "/p", "--latency", "inf"),
    ("reconstruct", "S", "--calibration", "C", "--out", "OUT", "--voxel", "inf"),
    ("phantom", "export", "OUT", "--wire-diameter", "inf"),
    ("temporal-calibrate", "S", "--out", "OUT", "--max-lag", "nan"),
    ("serve", "--start-depth-mm", "inf"),
    ("import-frames", "IMAGES", "--poses", "P", "OUT", "--spacing", "nan"),
    ("ursim", "--time-scale", "nan"),
    ("ursim", "--repeatability-mm", "inf"),
]


@pytest.mark.parametrize("args", NON_FINITE_OPTIONS, ids=" ".join)
def test_every_number_option_refuses_nan_and_infinity(tmp_path, args):
    out = tmp_path / "out"
    result = run_cli(*(str(out) if a == "OUT" else a for a in args))
    assert_one_line_error(result, f"argument {args[-2]}", "not a finite number")
    assert not out.exists()
