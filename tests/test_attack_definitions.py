"""Hostile phantom and probe definitions, and jobs larger than the memory allows: a phantom of
thousands of layers or a wire at 1e300 mm, probe files past any scanner, frames or views past what
the memory limit holds. Each is refused through the command line in one line naming the file or
option, before the memory or the time it asks for is taken."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.geometry.phantom import MAX_LAYERS, REACH_MM
from probecal.core.io.limits import ENV as MEMORY_ENV
from probecal.core.io.phantomfile import DEFAULT_PHANTOM_FILE, dict_from_phantom, load_phantom
from probecal.core.io.session import MANIFEST, load_session
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error

FCAL = DEFAULT_PHANTOM_FILE.parent / "fCal_2.0.xml"
FAST_S = 30.0
"""What a refusal may take: every one here comes before the work it refuses."""


def _many_layers(count: int) -> dict:
    """The default phantom's definition with its layers repeated to ``count``."""
    data = dict_from_phantom(load_phantom(DEFAULT_PHANTOM_FILE))
    data["layers"] = [data["layers"][i % len(data["layers"])] for i in range(count)]
    return data


def _write_json(path: Path, data: object) -> Path:
    path.write_text(json.dumps(data))
    return path


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    return simulate_calibration(tmp_path_factory.mktemp("definitions") / "s", n_poses=3, seed=1, noise="none").path


@pytest.fixture
def session(recorded, tmp_path) -> Path:
    return Path(shutil.copytree(recorded, tmp_path / "s"))


@pytest.fixture
def low_memory(monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "300")


# -- phantoms --------------------------------------------------------------------------------------

@pytest.mark.parametrize("layers", [MAX_LAYERS + 1, 10_000])
def test_a_phantom_of_too_many_layers_is_refused_by_simulate(tmp_path, low_memory, layers):
    phantom = _write_json(tmp_path / "many.json", _many_layers(layers))
    result = run_cli("simulate", "calibration", tmp_path / "out", "--poses", "2", "--phantom", phantom,
                     timeout_s=FAST_S)
    assert_one_line_error(result, str(phantom), f"{layers} N layers", f"at most {MAX_LAYERS}")
    assert not (tmp_path / "out").exists()


def test_a_device_set_of_too_many_patterns_is_refused_before_they_are_read(tmp_path, low_memory):
    text = FCAL.read_text()
    start, end = text.index("<Pattern"), text.index("</Pattern>") + len("</Pattern>")
    pattern = text[start:end]
    bad = tmp_path / "many.xml"
    bad.write_text(text[:start] + pattern * 1000 + text[end:])
    result = run_cli("phantom", "export", bad, tmp_path / "pe", timeout_s=FAST_S)
    assert_one_line_error(result, str(bad), "N layers", f"at most {MAX_LAYERS}")


def test_an_nwire_pattern_of_thousands_of_wires_is_refused(tmp_path, low_memory):
    text = FCAL.read_text()
    wire = '<Wire Name="w" EndPointFront="1e300 0 0" EndPointBack="0 40 0" />'
    bad = tmp_path / "wires.xml"
    bad.write_text(text.replace("<Pattern Type=\"NWire\">", "<Pattern Type=\"NWire\">" + wire * 100_000, 1))
    result = run_cli("simulate", "calibration", tmp_path / "out", "--poses", "2", "--phantom", bad,
                     timeout_s=FAST_S)
    assert_one_line_error(result, str(bad), "100003 wires, an N needs 3")


@pytest.mark.parametrize("command", ["segment", "calibrate"])
def test_a_sessions_phantom_of_too_many_layers_is_refused(session, low_memory, command):
    _write_json(session / "phantom.json", _many_layers(1000))
    result = run_cli(command, session, "--out", session.parent / "out.json", timeout_s=FAST_S)
    assert_one_line_error(result, str(session / "phantom.json"), "1000 N layers")


@pytest.mark.parametrize("value", ["1e300", "-1e300", "1e150", "5000"])
def test_a_device_set_wire_far_off_is_refused_without_a_warning(tmp_path, value):
    bad = tmp_path / "far.xml"
    bad.write_text(FCAL.read_text().replace('EndPointFront="30.0 0.0 20.0"', f'EndPointFront="{value} 0.0 20.0"', 1))
    for argv in (("phantom", "export", bad, tmp_path / "pe"),
                 ("simulate", "calibration", tmp_path / "out", "--poses", "2", "--phantom", bad)):
        result = run_cli(*argv, timeout_s=FAST_S)
        assert_one_line_error(result, str(bad), "EndPointFront", f"beyond {REACH_MM:g} mm")
        assert "Warning" not in result.stderr


@pytest.mark.parametrize(("value", "fragment"), [(1e300, "finite numbers"), (5000.0, f"beyond {REACH_MM:g} mm")])
def test_a_phantom_json_wire_far_off_is_refused_without_a_warning(tmp_path, value, fragment):
    data = _many_layers(4)
    data["layers"][0]["wires"][0]["front"][0] = value
    bad = _write_json(tmp_path / "far.json", data)
    result = run_cli("phantom", "export", bad, tmp_path / "pe", timeout_s=FAST_S)
    assert_one_line_error(result, str(bad), fragment)
    assert "Warning" not in result.stderr


def test_a_device_set_landmark_at_the_edge_of_reach_gives_a_session_that_reads_back(tmp_path):
    far = tmp_path / "landmark.xml"
    far.write_text(FCAL.read_text().replace('Position="104.3 5.0 20.0"', 'Position="-999 5.0 20.0"', 1))
    result = run_cli("simulate", "calibration", tmp_path / "out", "--poses", "2", "--noise", "none", "--phantom", far,
                     timeout_s=FAST_S)
    assert result.returncode == 0, result.stderr
    assert load_session(tmp_path / "out").phantom is not None


def test_a_phantom_box_far_off_is_refused(tmp_path):
    data = _many_layers(4)
    data["box"]["max"] = [150, 100, 1e6]
    bad = _write_json(tmp_path / "box.json", data)
    result = run_cli("phantom", "export", bad, tmp_path / "pe", timeout_s=FAST_S)
    assert_one_line_error(result, str(bad), "box.max", f"beyond {REACH_MM:g} mm")


def test_a_name_longer_than_any_phantoms_is_refused_before_it_names_a_file(tmp_path):
    data = _many_layers(4)
    data["layers"][1]["name"] = "<b>" * 30_000
    bad = _write_json(tmp_path / "named.json", data)
    result = run_cli("phantom", "export", bad, tmp_path / "pe", timeout_s=FAST_S)
    assert_one_line_error(result, str(bad), "layer name", "longer than 64 characters")
    assert not (tmp_path / "pe").exists()


# -- probes ------------------------------------------------------------------------------------------

PROBES = [
    ({"width_px": 100_000, "height_px": 100_000}, "width_px must lie within 8 to 8192 px"),
    ({"depth_mm": 1e9}, "depth_mm must lie within 0.1 to 1000 mm"),
    ({"type": "convex", "width_px": 100_000}, "width_px must lie within 8 to 8192 px"),
    ({"type": "convex", "radius_mm": 1e6}, "radius_mm must lie within"),
    ({"pitch_mm": 1e-9}, "pitch_mm must lie within"),
    ({"n_elements": 128, "pitch_mm": 0.01, "width_px": 8000}, "its pixels would be"),
    ({"width_px": 1, "height_px": 1}, "width_px must lie within 8 to 8192 px"),
    ({"width_px": 8, "height_px": 8, "depth_mm": 1000}, "its pixels would be"),
    ({"medium_sound_speed": 1e12}, "medium_sound_speed must lie within"),
    ({"type": "convex", "fov_deg": 179.9, "radius_mm": 1000, "width_px": 8}, "fov_deg must lie within"),
]


@pytest.mark.parametrize(("fields", "fragment"), PROBES, ids=[f for _, f in PROBES])
def test_a_probe_file_past_any_scanner_is_refused_naming_it(tmp_path, low_memory, fields, fragment):
    probe = _write_json(tmp_path / "probe.json", {"type": "linear", **fields})
    result = run_cli("simulate", "calibration", tmp_path / "out", "--poses", "2", "--probe", probe,
                     timeout_s=FAST_S)
    assert_one_line_error(result, str(probe), fragment)
    assert not (tmp_path / "out").exists()


def test_a_probe_whose_frames_pass_the_memory_limit_is_refused_up_front(tmp_path, low_memory):
    probe = _write_json(tmp_path / "probe.json", {"type": "linear", "width_px": 8192, "height_px": 8192})
    result = run_cli("simulate", "calibration", tmp_path / "out", "--poses", "2", "--probe", probe,
                     timeout_s=FAST_S)
    assert_one_line_error(result, str(probe), "imaging frames of 8192 x 8192 px", "more than the limit of 300.0 MB")


def test_a_sweeps_probe_whose_frames_pass_the_memory_limit_is_refused_naming_it(tmp_path, low_memory):
    probe = _write_json(tmp_path / "probe.json", {"type": "linear", "width_px": 8192, "height_px": 8192})
    result = run_cli("sweep", "calibration", tmp_path / "out", "--poses", "2", "--time-scale", "0", "--probe", probe,
                     timeout_s=FAST_S)
    assert_one_line_error(result, str(probe), "imaging frames of 8192 x 8192 px")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("what", ["calibration", "volume"])
def test_an_image_size_past_the_memory_limit_is_refused_up_front(tmp_path, low_memory, what):
    result = run_cli("simulate", what, tmp_path / "out", "--image-size", "8192", "8192", timeout_s=FAST_S)
    assert_one_line_error(result, "--image-size 8192 8192", "imaging frames of 8192 x 8192 px")
    assert not (tmp_path / "out").exists()


def test_a_convex_fan_higher_than_any_frame_is_refused(tmp_path):
    probe = _write_json(tmp_path / "probe.json", {"type": "convex", "fov_deg": 20.0, "depth_mm": 1000.0})
    result = run_cli("simulate", "calibration", tmp_path / "out", "--probe", probe, "--image-size", "8192", "8192",
                     timeout_s=FAST_S)
    assert_one_line_error(result, f"{probe} at --image-size 8192 8192", "its fan 8192 px wide is", "px high")


def test_a_session_whose_probe_is_past_any_scanner_is_refused_naming_its_manifest(session):
    manifest = json.loads((session / MANIFEST).read_text())
    manifest["probe"] = {"type": "linear", "width_px": 1, "height_px": 1}
    (session / MANIFEST).write_text(json.dumps(manifest))
    result = run_cli("segment", session, "--out", session.parent / "seg.json", timeout_s=FAST_S)
    assert_one_line_error(result, str(session / MANIFEST), "width_px must lie within")


def test_a_fan_too_shallow_to_show_an_echo_is_imaged_without_a_warning(tmp_path):
    result = run_cli("simulate", "volume", tmp_path / "out", "--frames-per-pass", "2", "--probe", "convex-50",
                     "--depth-mm", "0.1", timeout_s=FAST_S)
    assert result.returncode == 0, result.stderr
    assert "Warning" not in result.stderr


# -- job cost ----------------------------------------------------------------------------------------

def test_too_many_views_are_refused_before_any_is_planned(tmp_path):
    views = ",".join(str(a) for a in range(0, 360, 2))
    result = run_cli("simulate", "volume", tmp_path / "out", "--frames-per-pass", "1000", "--views", views,
                     timeout_s=FAST_S)
    assert_one_line_error(result, "--views", "180 views: at most 8")
    assert not (tmp_path / "out").exists()


def test_a_simulated_sweep_of_more_frames_than_the_memory_holds_is_refused_before_it_is_planned(tmp_path,
                                                                                                monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "100")
    result = run_cli("simulate", "volume", tmp_path / "out", "--frames-per-pass", "1000", "--views",
                     "0,45,90,135,180,225,270,315", timeout_s=FAST_S)
    assert_one_line_error(result, "simulating 24000 frames of 384 x 500 px", "more than the limit of 100.0 MB")
    assert not (tmp_path / "out").exists()


def test_segmenting_frames_past_the_memory_limit_is_refused_before_they_are_read(session, monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "100")
    manifest = json.loads((session / MANIFEST).read_text())
    manifest["image_size"] = [8192, 8192]
    (session / MANIFEST).write_text(json.dumps(manifest))
    result = run_cli("segment", session, "--out", session.parent / "seg.json", timeout_s=FAST_S)
    assert_one_line_error(result, str(session), "segmenting frames of 8192 x 8192 px", "more than the limit")


def test_a_frame_larger_than_the_sessions_frames_is_refused(session):
    manifest = json.loads((session / MANIFEST).read_text())
    manifest["image_size"] = [64, 64]
    (session / MANIFEST).write_text(json.dumps(manifest))
    result = run_cli("segment", session, "--out", session.parent / "seg.json", timeout_s=FAST_S)
    assert_one_line_error(result, "000000.png", "larger than the session's frames (64 x 64 px)")


def test_a_plan_no_pose_of_which_sees_every_wire_gives_up_at_once(tmp_path):
    data = _many_layers(4)
    for k, layer in enumerate(data["layers"]):  # layers 200 mm apart: no frame shows them all
        for wire in layer["wires"]:
            wire["front"][2] = wire["back"][2] = 100 + 200 * k
    data["box"] = {"min": [0, 0, 0], "max": [150, 100, 800]}
    phantom = _write_json(tmp_path / "tall.json", data)
    result = run_cli("simulate", "calibration", tmp_path / "out", "--poses", "1000", "--phantom", phantom,
                     timeout_s=FAST_S)
    assert_one_line_error(result, str(phantom), "only 0 of 1000 poses keep every wire in view")
