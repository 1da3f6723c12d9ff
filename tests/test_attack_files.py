"""Hostile sessions: every manifest field, every record field and every name a session refers to,
replaced by the wrong type, the wrong shape, a non-finite or huge number, deep nesting or a path
out of the folder, is refused with InputError naming the file (and the field); through the
command line that is exit code 2, one line, nothing written."""

from __future__ import annotations

import json
import os
import shutil
import zlib
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path

import numpy as np
import pytest

from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.probe import LinearProbe
from probecal.core.geometry.transforms import make_transform
from probecal.core.io.files import open_regular, read_bytes
from probecal.core.io.manifest import Manifest, RigSpec, matrix_of
from probecal.core.io.phantomfile import default_phantom, dict_from_phantom
from probecal.core.io.session import (
    MANIFEST,
    MAX_RECORD_LINE,
    PHANTOM,
    RECORDS,
    TRUTH,
    SessionWriter,
    load_recorded_session,
    load_session,
    read_manifest,
)
from tests.support.cli import HANG_TIMEOUT_S, run_cli
from tests.support.refusals import assert_one_line_error, assert_refused

RAW = "@@raw@@"  # placeholder for JSON text that json.dumps cannot write
WRONG = {"string": "x", "list": ["x", "y"], "object": {"a": 1}, "bool": True, "number": 7.5, "negative": -3}
# JSON text refused wherever it appears, whatever the field
HOSTILE_TEXT = {
    "nan": "NaN",
    "infinity": "-Infinity",
    "overflow": "1e999",
    "5000-digit integer": "9" * 5000,
    "400-digit integer": "9" * 400,
    "deep array": "[" * 100_000 + "]" * 100_000,
    "deep object": '{"a":' * 100_000 + "1" + "}" * 100_000,
}
OUTSIDE = {"absolute": "/etc/passwd", "parent": "../outside.png", "climbing": "frames/../../outside.png"}
POSE = make_transform(np.eye(3), [1.0, 2.0, 3.0]).tolist()
NOT_RIGID = np.diag([2.0, 1.0, 1.0, 1.0]).tolist()


FAN = {"angles_deg": [-30, 30], "origin_px": [4, -2], "radius_start_px": 1, "radius_stop_px": 9}
ARM = {"model": "UR3", "theta_deg": [0.01] * 6, "d_mm": [0.2] * 6, "a_mm": [-0.3] * 6, "alpha_deg": [0.02] * 6}


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """A small valid session whose manifest holds every field the loader checks."""
    path = tmp_path_factory.mktemp("attack") / "session"
    manifest = Manifest(
        kind="calibration",
        source={"simulator": "test"},
        image_size=(8, 6),
        pixel_spacing_mm=(0.1, 0.1),
        phantom_to_base=matrix_of(np.array(POSE)),
        object_to_base=matrix_of(np.array(POSE)),
        cad_mesh="object.stl",
        plan={"poses": 2},
        workspace={"box_min_mm": [0, 0, 0]},
        rig=RigSpec(robot="sim", image="sim", seed=0, latency_s=0.0),
        dropped_frames=0,
        robot_time_s=1.5,
        fan=Fan((-30, 30), (4, -2), 1, 9),
        segmentation_hints={"ApproximateSpacingMmPerPixel": "0.1", "ClipRectangleOrigin": "1 2",
                            "ClipRectangleSize": "4 3", "MinThetaDegrees": "-70"},
    )
    with SessionWriter(path, manifest, default_phantom(), LinearProbe(), files={"object.stl": b"solid"}) as w:
        w.append(np.zeros((6, 8), np.uint8), np.array(POSE), timestamp=0.5, pose_timestamp=0.5, plan_index=0,
                 sweep=0, image_valid=True)
        w.append(np.ones((6, 8), np.uint8), None, timestamp=1.0, pose_timestamp=1.0, plan_index=1, sweep=0,
                 image_valid=True)
    session = load_session(path)
    assert len(session) == 2 and session.probe == LinearProbe() and session.phantom is not None
    return path


@pytest.fixture
def session(template, tmp_path) -> Path:
    """A fresh copy of the valid session, to spoil."""
    return Path(shutil.copytree(template, tmp_path / "s"))


def _dump(value, raw: str | None) -> str:
    text = json.dumps(value)
    return text if raw is None else text.replace(json.dumps(RAW), raw)


def edit_manifest(session: Path, change, raw: str | None = None) -> Path:
    """Apply ``change(manifest)`` to the session's manifest; ``RAW`` in it becomes ``raw`` text."""
    file = session / MANIFEST
    manifest = json.loads(file.read_text())
    change(manifest)
    file.write_text(_dump(manifest, raw))
    return file


def edit_record(session: Path, line: int, change, raw: str | None = None) -> Path:
    """Apply ``change(record)`` to line ``line`` (from 0) of the session's records."""
    file = session / RECORDS
    lines = file.read_text().splitlines()
    record = json.loads(lines[line])
    change(record)
    lines[line] = _dump(record, raw)
    file.write_text("\n".join(lines) + "\n")
    return file


def refused(session: Path, file: Path, *fragments: str) -> str:
    """Loading ``session`` raises InputError naming ``file`` and every fragment; its message."""
    return assert_refused(lambda: load_session(session), file, *fragments)


# Manifest fields and the kinds of WRONG value that are in fact valid for them.
MANIFEST_VALID_KINDS = {
    "format": set(),
    "kind": {"string"},
    "created": {"string"},
    "source": {"object"},
    "plan": {"object"},
    "workspace": {"object"},
    "image_size": set(),
    "pixel_spacing_mm": set(),
    "phantom_to_base": set(),
    "object_to_base": set(),
    "dropped_frames": set(),
    "robot_time_s": {"number", "negative"},
    "phantom": {"string"},  # refused too, as a missing file
    "cad_mesh": {"string"},
    "probe": set(),
    "rig": {"object"},  # unknown rig keys are kept
    "segmentation_hints": set(),
    "fan": set(),
    "arm": {"string"},
    "arm_kinematics": set(),
    "image_orientation_in_file": {"string"},
    "scanner_region": {"object"},
    "motion": {"string"},
    "frame_rate_hz": {"number", "negative"},
    "speed_mm_s": {"number", "negative"},
}
MANIFEST_CASES = [(key, kind) for key, valid in MANIFEST_VALID_KINDS.items() for kind in WRONG if kind not in valid]


@pytest.mark.parametrize("key, kind", MANIFEST_CASES)
def test_manifest_field_of_the_wrong_type(session, key, kind):
    file = edit_manifest(session, lambda m: m.update({key: WRONG[kind]}))
    refused(session, file, key)


@pytest.mark.parametrize("key", ["format", "pixel_spacing_mm", "phantom_to_base", "probe"])
@pytest.mark.parametrize("hostile", sorted(HOSTILE_TEXT))
def test_manifest_field_with_hostile_json(session, key, hostile):
    file = edit_manifest(session, lambda m: m.update({key: RAW}), HOSTILE_TEXT[hostile])
    refused(session, file, "not valid JSON")


@pytest.mark.parametrize(
    "key, value, fragment",
    [
        ("image_size", [8], "image_size"),
        ("image_size", [8, 0], "image_size (height)"),
        ("image_size", [8.5, 6], "image_size (width)"),
        ("pixel_spacing_mm", "0.1", "pixel_spacing_mm"),
        ("pixel_spacing_mm", [0.1, 0.1, 0.1], "pixel_spacing_mm"),
        ("pixel_spacing_mm", [0.1, 0], "pixel sizes within [0.001, 10] mm"),
        ("pixel_spacing_mm", [[0.1], [0.1]], "pixel_spacing_mm"),
        ("pixel_spacing_mm", [1e-300, 1e-300], "pixel sizes within [0.001, 10] mm"),
        ("pixel_spacing_mm", [0.1, 1e6], "pixel sizes within [0.001, 10] mm"),
        ("rig", {"spacing_mm": [1e-300, 0.1]}, "rig.spacing_mm must be two pixel sizes"),
        ("phantom_to_base", [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "4x4"),
        ("phantom_to_base", np.eye(3).tolist(), "4x4"),
        ("phantom_to_base", NOT_RIGID, "not a rigid transform"),
        ("phantom_to_base", [["1", 0, 0, 0]] * 4, "4x4"),
        ("object_to_base", [[0] * 4] * 4, "not a rigid transform"),
        ("dropped_frames", -1, "dropped_frames"),
        ("format", "probecal-session/0", "unknown session format"),
        ("probe", "linear", "probe"),
        ("probe", {"type": "linear", "frequency_mhz": 7}, "unknown keys 'frequency_mhz'"),
        ("probe", {"type": "phased"}, "probe.type"),
        ("probe", {"type": [1, 2, 3]}, "probe.type must be one of"),  # a traceback, found by the fuzzing harness
        ("probe", {"type": "convex", "pitch_mm": 0.3}, "unknown keys 'pitch_mm'"),
        ("probe", {"type": "convex", "fov_deg": 200}, "field of view"),
        ("probe", {"type": "convex", "radius_mm": 0}, "probe.radius_mm"),
        ("probe", {"n_elements": 128.5}, "probe.n_elements"),
        ("probe", {"n_elements": 0}, "probe.n_elements"),
        ("probe", {"pitch_mm": "0.3"}, "probe.pitch_mm"),
        ("probe", {"depth_mm": -50}, "probe.depth_mm"),
        ("probe", {"width_px": True}, "probe.width_px"),
        ("rig", {"seed": "0"}, "rig.seed"),
        ("rig", {"robot": 3}, "rig.robot"),
        ("rig", {"latency_s": [0]}, "rig.latency_s"),
        ("segmentation_hints", {"ApproximateSpacingMmPerPixel": 0.1}, "must be text"),
        ("segmentation_hints", {"ApproximateSpacingMmPerPixel": "0"}, "must lie in [0.01, 5]"),
        ("segmentation_hints", {"MorphologicalOpeningCircleRadiusMm": "1e9"}, "must lie in [0.01, 5]"),
        ("segmentation_hints", {"ApproximateSpacingMmPerPixel": "nan"}, "not finite"),
        ("segmentation_hints", {"ClipRectangleOrigin": "1.5 2"}, "whole non-negative pixels"),
        ("segmentation_hints", {"ClipRectangleOrigin": "-1 2"}, "whole non-negative pixels"),
        ("segmentation_hints", {"ClipRectangleSize": "4"}, "needs 2 numbers"),
        ("segmentation_hints", {"ThresholdImagePercent": "ten"}, "not a list of numbers"),
        ("rig", {"start_depth_mm": -1}, "rig.start_depth_mm must be 0 or more"),
        ("fan", {**FAN, "angles_deg": [-30]}, "fan.angles_deg"),
        ("fan", {**FAN, "origin_px": ["4", 0]}, "fan.origin_px"),
        ("fan", {**FAN, "radius_stop_px": None}, "fan.radius_stop_px"),
        ("fan", {**FAN, "radius_start_px": 600}, "0 <= start < stop"),
        ("fan", {**FAN, "angles_deg": [-95, 30]}, "between -90 and 90"),
        ("arm_kinematics", {k: v for k, v in ARM.items() if k != "model"}, "arm_kinematics.model is missing"),
        ("arm_kinematics", {**ARM, "d_mm": [0.2] * 5}, "arm_kinematics.d_mm must be a list of 6 finite numbers"),
        ("arm_kinematics", {**ARM, "a_mm": ["0"] * 6}, "arm_kinematics.a_mm"),
        ("arm_kinematics", {**ARM, "theta_deg": [0, 0, 400, 0, 0, 0]}, "theta_deg must be 6 deviations within ±360"),
        ("arm_kinematics", {**ARM, "d_mm": [0, 0, 0, 0, 0, 1e10]}, "arm_kinematics.d_mm must be 6 deviations within"),
        ("arm_kinematics", {**ARM, "alpha_deg": [1e300] * 6}, "arm_kinematics.alpha_deg"),
    ],
)
def test_manifest_field_of_the_wrong_shape(session, key, value, fragment):
    file = edit_manifest(session, lambda m: m.update({key: value}))
    refused(session, file, fragment)


@pytest.mark.parametrize("top", [[], [{"format": "probecal-session/1"}], "session", 3, None])
def test_manifest_that_is_not_an_object(session, top):
    (session / MANIFEST).write_text(json.dumps(top))
    refused(session, session / MANIFEST, "must be a JSON object")


@pytest.mark.parametrize("key", ["phantom", "cad_mesh"])
@pytest.mark.parametrize("where", sorted(OUTSIDE))
def test_manifest_names_outside_the_folder(session, key, where):
    file = edit_manifest(session, lambda m: m.update({key: OUTSIDE[where]}))
    refused(session, file, key, "outside")


def test_manifest_phantom_through_a_link_out(session, tmp_path):
    outside = tmp_path / "elsewhere.json"
    outside.write_text(json.dumps(dict_from_phantom(default_phantom())))
    (session / "linked.json").symlink_to(outside)
    file = edit_manifest(session, lambda m: m.update(phantom="linked.json"))
    refused(session, file, "phantom", "through a link")


def test_manifest_and_records_that_are_links_out(session, tmp_path):
    for name in (MANIFEST, RECORDS):
        copy = Path(shutil.copytree(session, tmp_path / f"linked-{name}"))
        target = tmp_path / f"outside-{name}"
        shutil.copy(copy / name, target)
        (copy / name).unlink()
        (copy / name).symlink_to(target)
        with pytest.raises(InputError, match="through a link"):
            load_session(copy)


def test_phantom_file_with_bad_content_is_refused(session):
    (session / "phantom.json").write_text('{"format": "probecal-phantom/1", "layers": [], "box": NaN}')
    refused(session, session / "phantom.json", "not valid JSON")


RECORD_VALID_KINDS = {
    "index": set(),
    "image": {"string"},  # refused too, as a missing frame
    "tool_to_base": set(),
    "timestamp": {"number", "negative"},
    "pose_timestamp": {"number", "negative"},
    "source_index": set(),
    "plan_index": set(),
    "sweep": set(),
    "image_valid": {"bool"},
}
RECORD_CASES = [(key, kind) for key, valid in RECORD_VALID_KINDS.items() for kind in WRONG if kind not in valid]


@pytest.mark.parametrize("key, kind", RECORD_CASES)
def test_record_field_of_the_wrong_type(session, key, kind):
    file = edit_record(session, 1, lambda r: r.update({key: WRONG[kind]}))
    refused(session, file, f"line 2: {key}")


@pytest.mark.parametrize("key", ["index", "tool_to_base", "timestamp"])
@pytest.mark.parametrize("hostile", sorted(HOSTILE_TEXT))
def test_record_field_with_hostile_json(session, key, hostile):
    """Refused as corrupt, or before it is parsed when the line is longer than any record's."""
    file = edit_record(session, 0, lambda r: r.update({key: RAW}), HOSTILE_TEXT[hostile])
    too_long = len(file.read_bytes().split(b"\n")[0]) > MAX_RECORD_LINE
    refused(session, file, "line 1 is" if too_long else "line 1: corrupt record")


@pytest.mark.parametrize(
    "pose, fragment",
    [
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "4x4"),
        ([[1, 0, 0, 0, 0]] * 4, "4x4"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1], [0, 0, 0, 1]], "4x4"),
        ([1] * 16, "4x4"),
        ([[[1, 0, 0, 0]]] * 4, "4x4"),
        ([[1, 0, 0, "0"]] * 4, "4x4"),
        ([[1, 0, 0, None]] * 4, "4x4"),
    ],
)
def test_record_pose_of_the_wrong_shape(session, pose, fragment):
    file = edit_record(session, 0, lambda r: r.update(tool_to_base=pose))
    refused(session, file, "line 1: tool_to_base", fragment)


@pytest.mark.parametrize("key", ["index", "image"])
def test_record_without_a_required_field(session, key):
    file = edit_record(session, 0, lambda r: r.pop(key))
    refused(session, file, f"line 1: {key} is missing")


@pytest.mark.parametrize("line", ["[1, 2]", '"frame"', "3", "null", "true"])
def test_record_line_that_is_not_an_object(session, line):
    file = session / RECORDS
    lines = file.read_text().splitlines()
    file.write_text("\n".join([lines[0], line]) + "\n")
    refused(session, file, "line 2 must be a JSON object")


@pytest.mark.parametrize("where", sorted(OUTSIDE))
def test_record_image_outside_the_folder(session, tmp_path, where):
    (tmp_path / "outside.png").write_bytes((session / "frames" / "000000.png").read_bytes())
    file = edit_record(session, 0, lambda r: r.update(image=OUTSIDE[where]))
    refused(session, file, "line 1: image", "outside")


def test_record_image_through_a_link_out(session, tmp_path):
    outside = tmp_path / "outside.png"
    outside.write_bytes((session / "frames" / "000000.png").read_bytes())
    (session / "frames" / "link.png").symlink_to(outside)
    file = edit_record(session, 0, lambda r: r.update(image="frames/link.png"))
    refused(session, file, "line 1: image", "through a link")


def test_huge_index_is_refused_as_out_of_order(session):
    file = edit_record(session, 0, lambda r: r.update(index=10**300))
    refused(session, file, "records out of order")


def test_valid_session_still_loads_with_a_torn_last_line(session):
    with open(session / RECORDS, "ab") as f:
        f.write(b'{"index": 2, "image": "/etc/pas')
    loaded = load_session(session)
    assert len(loaded) == 2 and loaded.records[1].extra == {"plan_index": 1, "sweep": 0, "image_valid": True}
    assert loaded.pixel_spacing_mm == (0.1, 0.1) and np.allclose(loaded.phantom_to_base, POSE)


def test_truth_file_is_checked(session):
    (session / TRUTH).write_text(json.dumps({"object_to_base": "here"}))
    with pytest.raises(InputError, match="object_to_base must be a 4x4"):
        load_session(session).truth()
    (session / TRUTH).write_text("[1]")
    with pytest.raises(InputError, match="must be a JSON object"):
        load_session(session).truth()
    # A placement that is not rigid made a reconstruction's report NaN (the fuzzing harness, issue 35).
    (session / TRUTH).write_text(json.dumps({"object_to_base": [[1e-300, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                               [0, 0, 0, 1]]}))
    with pytest.raises(InputError, match="object_to_base is not a rigid transform"):
        load_session(session).truth()


def test_a_record_whose_pose_is_not_rigid_is_refused(session):
    """A pose of zeros reached calibrate and failed in scipy (the fuzzing harness, issue 35)."""
    file = edit_record(session, 0, lambda r: r.update(tool_to_base=[[0.0] * 4] * 3 + [[0, 0, 0, 1]]))
    refused(session, file, "line 1: tool_to_base is not a rigid transform")


def test_read_manifest_checks_the_rig(session):
    assert read_manifest(session).rig.robot == "sim"
    edit_manifest(session, lambda m: m["rig"].update(seed=-1))
    with pytest.raises(InputError, match="rig.seed"):
        read_manifest(session)


def test_resume_refuses_a_bad_session(session):
    edit_record(session, 0, lambda r: r.update(timestamp="noon"))
    with pytest.raises(InputError, match="line 1: timestamp"):
        SessionWriter(session, Manifest(), resume=True)


# Through the command line: exit code 2, one line naming the file, nothing written.


def test_cli_export_plus_refuses_an_outside_frame(session, tmp_path):
    (tmp_path / "outside.png").write_bytes((session / "frames" / "000000.png").read_bytes())
    file = edit_record(session, 0, lambda r: r.update(image="../outside.png"))
    out = tmp_path / "out.igs.mha"
    assert_one_line_error(run_cli("export-plus", session, out), str(file), "outside")
    assert not out.exists()


def test_cli_calibrate_refuses_a_list_manifest(session):
    (session / MANIFEST).write_text("[]")
    before = sorted(p.name for p in session.iterdir())
    assert_one_line_error(run_cli("calibrate", session), str(session / MANIFEST), "JSON object")
    assert sorted(p.name for p in session.iterdir()) == before


@pytest.mark.parametrize("command", ["segment", "calibrate"])
def test_cli_refuses_a_pixel_spacing_no_scanner_has(session, command):
    """1e-300 mm/px passed as positive and divided by zero downstream."""
    file = edit_manifest(session, lambda m: m.update(pixel_spacing_mm=[1e-300, 1e-300]))
    before = sorted(p.name for p in session.iterdir())
    assert_one_line_error(run_cli(command, session), str(file), "pixel_spacing_mm", "within [0.001, 10] mm")
    assert sorted(p.name for p in session.iterdir()) == before


def test_cli_sweep_resume_refuses_a_list_manifest(session):
    (session / MANIFEST).write_text('[{"format": "probecal-session/1"}]')
    before = (session / RECORDS).read_bytes()
    assert_one_line_error(run_cli("sweep", "calibration", session, "--resume", "--time-scale", "0"),
                          str(session / MANIFEST), "JSON object")
    assert (session / RECORDS).read_bytes() == before


def test_a_frame_whose_png_header_asks_for_too_much_is_refused_before_decoding(session):
    loaded = load_session(session)
    frame = session / loaded.records[0].image
    data = bytearray(frame.read_bytes())
    data[16:24] = (100_000).to_bytes(4, "big") * 2  # IHDR: 100000 x 100000 px
    frame.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"frame 0 \(100000 x 100000 px\) would need .* limit") as caught:
        loaded.image(0)
    assert caught.value.path == frame
    assert loaded.image(1).shape == (6, 8)


# A FIFO (or a device) where a file is expected: opening it would wait for a writer for ever.


def refused_at_once(load, fifo: Path, *fragments: str) -> str:
    """``load()`` refuses ``fifo`` (:func:`assert_refused`) without blocking on it; were it to block,
    the FIFO is opened for writing and closed, which lets the reader go, and the test fails."""
    with ThreadPoolExecutor(1) as pool:
        future = pool.submit(assert_refused, load, fifo, *fragments)
        try:
            return future.result(timeout=HANG_TIMEOUT_S)
        except FutureTimeout:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
            raise AssertionError(f"{fifo}: blocked on the FIFO") from None


def replaced_by_fifo(file: Path) -> Path:
    file.unlink()
    os.mkfifo(file)
    return file


@pytest.mark.parametrize("name", [MANIFEST, RECORDS, PHANTOM])
def test_a_fifo_in_place_of_a_session_file_is_refused_at_once(session, name):
    fifo = replaced_by_fifo(session / name)
    refused_at_once(lambda: load_session(session), fifo, "not a regular file")


def test_a_fifo_in_place_of_a_frame_is_refused_at_once(session):
    loaded = load_session(session)
    fifo = replaced_by_fifo(session / loaded.records[0].image)
    refused_at_once(lambda: loaded.image(0), fifo, "not a regular file")


def test_files_are_opened_only_when_regular(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    refused_at_once(lambda: read_bytes(fifo), fifo, "not a regular file")
    refused_at_once(lambda: open_regular(fifo), fifo, "not a regular file")
    refused_at_once(lambda: read_bytes(Path("/dev/zero")), Path("/dev/zero"), "not a regular file")
    refused_at_once(lambda: read_bytes(tmp_path), tmp_path, "file not found")


@pytest.mark.parametrize("fifo", [False, True])
def test_cli_refuses_a_session_without_frames(session, fifo):
    records = session / RECORDS
    if fifo:
        replaced_by_fifo(records)
    else:
        records.write_bytes(b"")
    assert_refused(lambda: load_recorded_session(session), records)
    for command in (("segment", session), ("export-plus", session, session / "out.igs.mha")):
        result = run_cli(*command, timeout_s=HANG_TIMEOUT_S)
        assert_one_line_error(result, str(records), "not a regular file" if fifo else "holds no frames")
    assert not (session / "segmentation.json").exists() and not (session / "out.igs.mha").exists()


def _forged_ihdr(data: bytes, at: int, value: bytes, fix_crc: bool) -> bytes:
    """A PNG's bytes with IHDR's field at byte ``at`` (of the file) set to ``value``, its CRC made
    right again when ``fix_crc``."""
    forged = bytearray(data)
    forged[at:at + len(value)] = value
    if fix_crc:
        forged[29:33] = zlib.crc32(forged[12:29]).to_bytes(4, "big")
    return bytes(forged)


@pytest.mark.parametrize("at, value, fix_crc, fragment", [
    (16, (500).to_bytes(4, "big"), False, "corrupt (CRC)"),
    (16, (0).to_bytes(4, "big"), True, "header is invalid (0 x 6 px"),
    (24, bytes([3]), True, "bit depth 3"),
    (25, bytes([5]), True, "colour type 5"),
])
def test_cli_a_frame_with_a_forged_png_header_is_one_line(session, at, value, fix_crc, fragment):
    """libpng would print its complaint on stderr before ours: the header is checked first."""
    frame = session / "frames" / "000000.png"
    frame.write_bytes(_forged_ihdr(frame.read_bytes(), at, value, fix_crc))
    assert_one_line_error(run_cli("segment", session), str(frame), "frame 0", fragment)
    assert not (session / "segmentation.json").exists()
