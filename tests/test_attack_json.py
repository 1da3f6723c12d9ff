"""Hostile JSON: every JSON file probecal reads (calibrations, phantoms, workspaces, plans) goes
through one parser that refuses NaN, Infinity, overflowing numbers, endless integers and deep
nesting, and each field of a valid file replaced by the wrong type or shape is refused with
InputError naming the file and the field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.plan import SweepPlan
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.errors import InputError
from probecal.core.geometry.transforms import make_transform
from probecal.core.io.jsonio import parse_json, read_json, to_json_text
from probecal.core.io.phantomfile import default_phantom, dict_from_phantom, load_phantom
from probecal.core.robot.safety import DEFAULT_WORKSPACE_FILE, load_workspace
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error, assert_refused

RAW = "@@raw@@"
WRONG = {"string": "x", "list": ["x", "y"], "object": {"a": 1}, "bool": True, "number": 7.5, "null": None}
HOSTILE_TEXT = {
    "nan": "NaN",
    "infinity": "Infinity",
    "overflow": "-1e999",
    "5000-digit integer": "9" * 5000,
    "400-digit integer": "-" + "9" * 400,
    "deep array": "[" * 100_000 + "]" * 100_000,
    "deep object": '{"a":' * 100_000 + "1" + "}" * 100_000,
}
POSE = make_transform(Rotation.from_euler("xyz", [10, 20, 30], degrees=True), [1.0, 2.0, 3.0])


def write(path: Path, value, raw: str | None = None) -> Path:
    """``value`` as JSON in ``path``; the string ``RAW`` inside it becomes the text ``raw``."""
    text = json.dumps(value)
    path.write_text(text if raw is None else text.replace(json.dumps(RAW), raw))
    return path


def refused(load, path: Path, *fragments: str) -> str:
    """``load(path)`` raises InputError naming ``path`` and every fragment, on one line."""
    return assert_refused(lambda: load(path), path, *fragments)


@pytest.mark.parametrize("hostile", sorted(HOSTILE_TEXT))
def test_parser_refuses_hostile_numbers_and_nesting(hostile):
    with pytest.raises(InputError) as info:
        parse_json(f'{{"value": {HOSTILE_TEXT[hostile]}}}', "x.json")
    assert str(info.value).startswith("x.json: not valid JSON (")
    assert len(str(info.value)) < 200


@pytest.mark.parametrize("text", ['{"a": 1', "", "\ufeff{}", '{"a": 1} {"b": 2}', "{'a': 1}", '{"a": .5}'])
def test_parser_refuses_malformed_text(text):
    with pytest.raises(InputError, match="not valid JSON"):
        parse_json(text, "x.json")


def test_parser_keeps_large_but_finite_numbers():
    value = parse_json('{"a": 1e308, "b": -' + "9" * 300 + ', "c": [[[1]]]}', "x.json")
    assert value["a"] == 1e308 and value["b"] == -int("9" * 300) and value["c"] == [[[1]]]


def test_read_json_refuses_what_is_not_a_json_object_file(tmp_path):
    refused(read_json, tmp_path / "missing.json", "file not found")
    (tmp_path / "folder.json").mkdir()
    refused(read_json, tmp_path / "folder.json", "file not found")
    refused(read_json, write(tmp_path / "list.json", [1, 2]), "the file must be a JSON object, got a list of 2")
    (tmp_path / "latin1.json").write_bytes(b'{"name": "\xe9"}')
    refused(read_json, tmp_path / "latin1.json", "not valid JSON")


def test_read_json_refuses_a_file_past_the_memory_limit(tmp_path, monkeypatch):
    monkeypatch.setenv("PROBECAL_MAX_MEMORY_MB", "1")
    big = tmp_path / "big.json"
    big.write_text('{"a": "' + "x" * (2 << 20) + '"}')
    refused(read_json, big, "more than the limit")


# Calibration JSON (ours, or a simulated session's truth.json).


def calibration_dict() -> dict:
    return json.loads(to_json_text(Calibration(POSE, (0.1, 0.12), POSE, {"pre3d_mm": 0.5}).to_dict()))


def test_valid_calibration_loads(tmp_path):
    calibration = load_calibration(write(tmp_path / "c.json", calibration_dict()))
    assert np.allclose(calibration.image_to_tool_rigid, POSE) and calibration.pixel_spacing_mm == (0.1, 0.12)
    assert np.allclose(calibration.phantom_to_base, POSE) and calibration.metrics == {"pre3d_mm": 0.5}


CALIBRATION_OPTIONAL = {"image_to_tool", "phantom_to_base", "metrics"}
CALIBRATION_CASES = [
    (key, kind)
    for key in ("image_to_tool", "image_to_tool_rigid", "pixel_spacing_mm", "phantom_to_base", "metrics")
    for kind in WRONG
    if not (kind == "null" and key in CALIBRATION_OPTIONAL) and not (kind == "object" and key == "metrics")
]


@pytest.mark.parametrize("key, kind", CALIBRATION_CASES)
def test_calibration_field_of_the_wrong_type(tmp_path, key, kind):
    data = calibration_dict() | {key: WRONG[kind]}
    refused(load_calibration, write(tmp_path / "c.json", data), key)


@pytest.mark.parametrize("key", ["image_to_tool_rigid", "pixel_spacing_mm", "phantom_to_base"])
@pytest.mark.parametrize("hostile", sorted(HOSTILE_TEXT))
def test_calibration_field_with_hostile_json(tmp_path, key, hostile):
    data = calibration_dict() | {key: RAW}
    refused(load_calibration, write(tmp_path / "c.json", data, HOSTILE_TEXT[hostile]), "not valid JSON")


def _entry(row: int, col: int, value):
    def change(data: dict) -> None:
        data["image_to_tool_rigid"][row][col] = value
    return change


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda d: d.pop("image_to_tool_rigid"), "image_to_tool_rigid is missing"),
        (lambda d: d.pop("pixel_spacing_mm"), "pixel_spacing_mm is missing"),
        (lambda d: d["image_to_tool_rigid"].pop(), "image_to_tool_rigid must be a 4x4"),
        (lambda d: d["image_to_tool_rigid"][1].append(0.0), "image_to_tool_rigid must be a 4x4"),
        (_entry(0, 0, "1"), "image_to_tool_rigid must be a 4x4"),
        (_entry(0, 0, [1.0]), "image_to_tool_rigid must be a 4x4"),
        (_entry(2, 3, None), "image_to_tool_rigid must be a 4x4"),
        (_entry(0, 0, 2.0), "image_to_tool_rigid is not a rigid transform"),
        (_entry(3, 0, 0.5), "image_to_tool_rigid is not a rigid transform"),
        (lambda d: d.update(image_to_tool_rigid=np.diag([1.0, 1.0, -1.0, 1.0]).tolist()), "not a rigid transform"),
        (lambda d: d.update(image_to_tool_rigid=[[0.0] * 4] * 4), "not a rigid transform"),
        (lambda d: d.update(phantom_to_base=np.diag([3.0, 3.0, 3.0, 1.0]).tolist()), "phantom_to_base is not a rigid"),
        (lambda d: d.update(pixel_spacing_mm=[0.1]), "pixel_spacing_mm must be a list of 2 finite numbers"),
        (lambda d: d.update(pixel_spacing_mm=[0.1, 0.0]), "pixel_spacing_mm must be two pixel sizes within"),
        (lambda d: d.update(pixel_spacing_mm=[0.1, -0.1]), "pixel_spacing_mm must be two pixel sizes within"),
        (lambda d: d.update(pixel_spacing_mm=[0.1, True]), "pixel_spacing_mm must be a list of 2 finite numbers"),
        (lambda d: d.update(pixel_spacing_mm=["0.1", "0.1"]), "pixel_spacing_mm must be a list of 2 finite numbers"),
        (lambda d: d.update(pixel_spacing_mm=[[0.1], [0.1]]), "pixel_spacing_mm must be a list of 2 finite numbers"),
    ],
)
def test_calibration_of_the_wrong_shape(tmp_path, change, fragment):
    data = calibration_dict()
    change(data)
    refused(load_calibration, write(tmp_path / "c.json", data), fragment)


def _bound_map(**change) -> dict:
    return {"points_px": [[[0.0, 0.0], [9.0, 0.0]], [[0.0, 9.0], [9.0, 9.0]]],
            "bound_mm": [[0.5, 0.4], [0.3, None]]} | change


@pytest.mark.parametrize(
    "bound_map, fragment",
    [
        ([], "metrics.bound_map must be a JSON object"),
        (_bound_map(bound_mm=[[0.5, 0.4]]), "metrics.bound_map.bound_mm must be a list of 2 items"),
        (_bound_map(bound_mm=[[0.5, 0.4], [0.3]]), "metrics.bound_map.bound_mm[1] must be a list of 2 items"),
        (_bound_map(bound_mm=[[0.5, "0.4"], [0.3, 0.2]]), "metrics.bound_map.bound_mm[0] must be a finite number"),
        (_bound_map(points_px=[[[0.0], [9.0, 0.0]], [[0.0, 9.0], [9.0, 9.0]]]),
         "metrics.bound_map.points_px[0] must be a list of 2 finite numbers"),
        ({"bound_mm": []}, "metrics.bound_map.points_px is missing"),
    ],
)
def test_calibration_with_a_bound_map_of_the_wrong_shape(tmp_path, bound_map, fragment):
    """The console draws a loaded calibration's bound map over its frames: a map it could not
    draw is refused as the file is read."""
    data = calibration_dict()
    data["metrics"]["bound_map"] = bound_map
    refused(load_calibration, write(tmp_path / "c.json", data), fragment)
    data["metrics"]["bound_map"] = _bound_map()
    assert load_calibration(write(tmp_path / "c.json", data)).metrics["bound_map"] == _bound_map()


@pytest.mark.parametrize(
    "metrics, fragment",
    [
        ({"pre3d_mm": "0.5"}, "metrics.pre3d_mm must be a finite number"),
        ({"arm_correction_mm": [0.2]}, "metrics.arm_correction_mm must be a finite number"),
        ({"arm_undetermined": 5}, "metrics.arm_undetermined must be a list"),
        ({"arm_undetermined": ["d1", "q7"]}, "'q7' is no DH deviation"),
        ({"objectives": {"all-wire": {"cv_pre3d_mm": 0.4}}}, "metrics.objectives.all-wire.cv_folds is missing"),
        ({"rejected_frames": {"first": "blurred"}}, "metrics.rejected_frames must be an object whose keys are whole"),
        ({"error_vs_poses": [{"poses": 6, "identity_translation_mm": None, "identity_rotation_deg": None,
                              "pre3d_mm": "x"}]}, "metrics.error_vs_poses[0].pre3d_mm"),
        ({"verdict": {"usable": "yes", "text": "Usable", "tolerance_mm": 1.0}}, "metrics.verdict.usable"),
        ({"fre_mm": 0.2}, "metrics.objective is missing"),
    ],
)
def test_calibration_with_figures_a_report_cannot_show(tmp_path, metrics, fragment):
    """``calibrate`` and the console report a loaded calibration's figures: a figure of the wrong
    type, or a report's figure missing, is refused as the file is read, not met as a crash."""
    data = calibration_dict()
    data["metrics"] = metrics
    refused(load_calibration, write(tmp_path / "c.json", data), fragment)


@pytest.mark.parametrize("top", [[], "calibration", 1.5, None])
def test_calibration_that_is_not_an_object(tmp_path, top):
    refused(load_calibration, write(tmp_path / "c.json", top), "must be a JSON object")


# Phantom definitions.


def phantom_dict() -> dict:
    return dict_from_phantom(default_phantom())


def _wire(**change):
    def apply(data: dict) -> None:
        data["layers"][1]["wires"][2].update(change)
    return apply


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda d: d.update(layers="N1"), "layers must be a list"),
        (lambda d: d.update(layers={"N1": []}), "layers must be a list"),
        (lambda d: d.update(layers=[]), "no N-wire layers"),
        (lambda d: d["layers"].__setitem__(0, "N1"), "layers[0] must be a JSON object"),
        (lambda d: d["layers"][0].update(wires="abc"), "layers[0].wires must be a list"),
        (lambda d: d["layers"][0].update(name=3), "layers[0].name must be a non-empty string"),
        (lambda d: d["layers"][0]["wires"].append(d["layers"][0]["wires"][0]), "needs 3"),
        (lambda d: d["layers"][1]["wires"].__setitem__(2, "abc"), "layers[1].wires[2] must be a JSON object"),
        (_wire(front=None), "layers[1].wires[2].front must be a list of 3"),
        (_wire(front=[1, 2]), "layers[1].wires[2].front must be a list of 3"),
        (_wire(back=[1, 2, "3"]), "layers[1].wires[2].back must be a list of 3"),
        (_wire(back=[[1, 2, 3]]), "layers[1].wires[2].back must be a list of 3"),
        (_wire(back={"x": 1}), "layers[1].wires[2].back must be a list of 3"),
        (_wire(back=[1, 2, False]), "layers[1].wires[2].back must be a list of 3"),
        (_wire(name=["w"]), "layers[1].wires[2].name must be a non-empty string"),
        (lambda d: d.pop("box"), "box is missing"),
        (lambda d: d.update(box=[0, 0, 0]), "box must be a JSON object"),
        (lambda d: d["box"].update(min="0 0 0"), "box.min must be a list of 3"),
        (lambda d: d["box"].update(max=[1e308, 1e308]), "box.max must be a list of 3"),
        (lambda d: d.update(name={"en": "x"}), "name must be a non-empty string"),
        (lambda d: d.update(format=["probecal-phantom/1"]), "not a phantom definition"),
    ],
)
def test_phantom_of_the_wrong_type_or_shape(tmp_path, change, fragment):
    data = phantom_dict()
    change(data)
    refused(load_phantom, write(tmp_path / "p.json", data), fragment)


@pytest.mark.parametrize("hostile", sorted(HOSTILE_TEXT))
def test_phantom_with_hostile_json(tmp_path, hostile):
    data = phantom_dict()
    data["layers"][0]["wires"][0]["front"][0] = RAW
    refused(load_phantom, write(tmp_path / "p.json", data, HOSTILE_TEXT[hostile]), "not valid JSON")


def test_phantom_that_is_a_list(tmp_path):
    refused(load_phantom, write(tmp_path / "p.json", [phantom_dict()]), "must be a JSON object")


# Workspace files: a safety limit that is NaN, infinite or negative would let every move through.


def workspace_dict() -> dict:
    return json.loads(DEFAULT_WORKSPACE_FILE.read_text())


LIMITS = ["max_linear_speed_mm_s", "max_linear_accel_mm_s2", "max_angular_speed_deg_s", "max_angular_accel_deg_s2"]


@pytest.mark.parametrize("key", LIMITS)
@pytest.mark.parametrize("value", [0, -250.0, "250", [250.0], None, True])
def test_workspace_limit_must_be_positive_and_finite(tmp_path, key, value):
    data = workspace_dict() | {key: value}
    refused(load_workspace, write(tmp_path / "w.json", data), key)


@pytest.mark.parametrize("key", LIMITS + ["box_min_mm"])
@pytest.mark.parametrize("hostile", ["nan", "infinity", "overflow"])
def test_workspace_with_non_finite_json(tmp_path, key, hostile):
    data = workspace_dict() | {key: RAW}
    refused(load_workspace, write(tmp_path / "w.json", data, HOSTILE_TEXT[hostile]), "not valid JSON")


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda d: d.update(box_min_mm=[0, 0]), "box_min_mm must be a list of 3"),
        (lambda d: d.update(box_max_mm="200 200 200"), "box_max_mm must be a list of 3"),
        (lambda d: d.update(box_max_mm=[[200, -150, 350]]), "box_max_mm must be a list of 3"),
        (lambda d: d.update(box_min_mm=[200, -150, 350]), "min < max"),
        (lambda d: d.pop("box_min_mm"), "box_min_mm is missing"),
        (lambda d: d.pop("max_linear_speed_mm_s"), "max_linear_speed_mm_s is missing"),
        (lambda d: d.update(max_speed=1.0), "unknown keys 'max_speed'"),
        (lambda d: d.update(description=3), "description must be a non-empty string"),
    ],
)
def test_workspace_of_the_wrong_shape(tmp_path, change, fragment):
    data = workspace_dict()
    change(data)
    refused(load_workspace, write(tmp_path / "w.json", data), fragment)


# Sweep plans (plan.json, read on --resume): poses that reach the robot.


def plan_dict() -> dict:
    return json.loads(json.dumps(SweepPlan([POSE, POSE], [0, 1], 3.5).to_dict()))


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda d: d.update(poses="all"), "poses must be a list"),
        (lambda d: d["poses"].__setitem__(1, np.eye(3).tolist()), "poses[1] must be a 4x4"),
        (lambda d: d["poses"].__setitem__(1, None), "poses[1] must be a 4x4"),
        (lambda d: d["poses"].__setitem__(1, np.diag([1.0, 1.0, 5.0, 1.0]).tolist()), "poses[1] is not a rigid"),
        (lambda d: d["poses"][0][0].__setitem__(3, "1"), "poses[0] must be a 4x4"),
        (lambda d: d.update(passes=[0]), "passes must be a list of 2 items"),
        (lambda d: d.update(passes=[0, -1]), "passes[1] must be a whole number of at least 0"),
        (lambda d: d.update(passes=[0, 1.5]), "passes[1] must be a whole number"),
        (lambda d: d.update(passes=[0, "1"]), "passes[1] must be a whole number"),
        (lambda d: d.update(duration_s="3.5"), "duration_s must be a finite number"),
        (lambda d: d.update(duration_s=-1), "duration_s must not be negative"),
        (lambda d: d.pop("duration_s"), "duration_s is missing"),
    ],
)
def test_plan_of_the_wrong_type_or_shape(tmp_path, change, fragment):
    data = plan_dict()
    change(data)
    refused(SweepPlan.load, write(tmp_path / "plan.json", data), fragment)


@pytest.mark.parametrize("hostile", sorted(HOSTILE_TEXT))
def test_plan_with_hostile_json(tmp_path, hostile):
    data = plan_dict()
    data["poses"][0][0][3] = RAW
    refused(SweepPlan.load, write(tmp_path / "plan.json", data, HOSTILE_TEXT[hostile]), "not valid JSON")


def test_valid_plan_and_workspace_still_load(tmp_path):
    plan = SweepPlan.load(write(tmp_path / "plan.json", plan_dict()))
    assert plan.passes == [0, 1] and np.allclose(plan.poses[1], POSE) and plan.duration_s == 3.5
    assert load_workspace().max_limits.linear_speed_mm_s == 250.0


# Through the command line: exit code 2, one line naming the file, nothing written.


def test_cli_validate_refuses_a_nan_calibration(tmp_path):
    data = calibration_dict()
    data["image_to_tool_rigid"][0][3] = RAW
    bad = write(tmp_path / "bad.json", data, "NaN")
    out = tmp_path / "metrics.json"
    result = run_cli("validate", tmp_path, "--calibration", bad, "--out", out)
    assert_one_line_error(result, str(bad), "NaN")
    assert not out.exists()

