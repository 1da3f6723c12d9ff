"""PLUS interoperability on the real fCal 1.2 recordings."""

import json
from dataclasses import replace

import numpy as np
import pytest
import SimpleITK as sitk

from probecal.core.calibration.frames import initial_spacing, observations, tracked_latency
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.validate import validate_session
from probecal.core.geometry.transforms import is_rigid
from probecal.core.io.plusdata import DEFAULT, ENV, FILES, missing_reason, plus_data_dir
from probecal.core.io.plusimport import export_plus, import_plus, tracker_samples
from probecal.core.io.plusresults import read_calibration_results
from probecal.core.io.sequence import read_sequence
from probecal.core.io.session import load_session
from tests.support.paths import FCAL_CALIBRATION, FCAL_CONFIG, FCAL_RESULTS, FCAL_VALIDATION, PLUS


@pytest.fixture(scope="module")
def fcal_sessions(plus_data, tmp_path_factory):
    root = tmp_path_factory.mktemp("fcal")
    return (
        import_plus(FCAL_CALIBRATION, FCAL_CONFIG, root / "calibration"),
        import_plus(FCAL_VALIDATION, FCAL_CONFIG, root / "validation"),
    )


def test_fcal_import_frame_counts_and_phantom(fcal_sessions):
    calibration, validation = fcal_sessions
    assert len(calibration) == 188 and len(validation) == 94
    for s in fcal_sessions:
        assert s.phantom.n_wires == 9
        assert s.manifest.image_size == (820, 616)
        assert s.image(0).shape == (616, 820) and s.image(0).dtype == np.uint8
        assert is_rigid(s.phantom_to_base, tol=1e-3)
        assert np.allclose(s.phantom_to_base[:3, 3], [9.59137, 36.0012, 87.8909])
        assert all(r.pose_valid for r in s.records)


def test_fcal_import_poses_match_plus_baseline(fcal_sessions):
    calibration, validation = fcal_sessions
    baseline = read_calibration_results(FCAL_RESULTS)
    for session, frames in ((validation, baseline.validation), (calibration, baseline.calibration)):
        expected = [f.probe_to_reference for f in frames]
        assert len(expected) == len(session)
        poses = session.poses()
        # The XML rounds to 6 significant digits, so allow that much.
        assert np.abs(poses[:, :3, 3] - np.array(expected)[:, :3, 3]).max() < 0.05
        assert np.abs(poses[:, :3, :3] - np.array(expected)[:, :3, :3]).max() < 1e-4


def test_import_uses_probe_to_reference_definition(fcal_sessions):
    calibration, _ = fcal_sessions
    seq = read_sequence(FCAL_CALIBRATION)
    expected = np.linalg.inv(seq.transforms["ReferenceToTracker"]) @ seq.transforms["ProbeToTracker"]
    assert np.allclose(calibration.poses(), expected, atol=1e-9)
    assert calibration.manifest.source["tool_pose"] == "ProbeToReference"
    assert calibration.manifest.source["tool_pose_path"] == "inv(ReferenceToTracker) @ ProbeToTracker"
    assert calibration.manifest.source["phantom_pose_path"] == "PhantomToReference"
    i = 57
    assert calibration.records[i].source_index == i
    assert calibration.records[i].timestamp == pytest.approx(seq.timestamps[i])
    assert np.array_equal(calibration.image(i), seq.frames[i])


def test_export_then_reimport_is_exact(fcal_sessions, tmp_path):
    _, validation = fcal_sessions
    out = tmp_path / "validation.igs.mha"
    export_plus(validation, out)
    # 3D Slicer and PLUS read these through ITK's MetaImage reader: so must SimpleITK.
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(out))
    reader.ReadImageInformation()
    assert reader.GetSize() == (820, 616, 94)
    assert reader.GetMetaData("Seq_Frame0000_ProbeToReferenceTransformStatus") == "OK"
    again = import_plus(out, None, tmp_path / "again")
    assert len(again) == len(validation)
    assert np.array_equal(again.poses(), validation.poses())
    for i in range(len(validation)):
        assert np.array_equal(again.image(i), validation.image(i))
    assert [r.timestamp for r in again.records] == [r.timestamp for r in validation.records]


def test_uncompressed_sequence_reads(tmp_path, fcal_sessions):
    from probecal.core.io.sequence import TrackedSequence, write_sequence

    seq = read_sequence(FCAL_VALIDATION)
    small = TrackedSequence(
        frames=seq.frames[:5],
        transforms={k: v[:5] for k, v in seq.transforms.items()},
        statuses={k: v[:5] for k, v in seq.statuses.items()},
        timestamps=seq.timestamps[:5],
    )
    out = tmp_path / "raw.igs.mha"
    write_sequence(out, small, compress=False)
    assert b"CompressedData = False" in out.read_bytes()[:2000]
    back = read_sequence(out)
    assert np.array_equal(back.frames, small.frames)
    assert np.array_equal(back.transforms["ProbeToTracker"], small.transforms["ProbeToTracker"])


def test_vlcus_sequence_without_reference_uses_default_transform(plus_data, tmp_path):
    seq_file = PLUS / "TestImages" / "SegmentationTest_VLCUS_RandomStepperMotionData2.igs.mha"
    from tests.support.paths import VLCUS_CONFIG

    session = import_plus(seq_file, VLCUS_CONFIG, tmp_path / "vlcus")
    assert len(session) == 201
    assert session.manifest.source["tool_pose"] == "ToolToTracker"
    assert session.phantom.n_wires == 6
    assert session.manifest.segmentation_hints["ClipRectangleOrigin"] == "68 145"
    loaded = load_session(tmp_path / "vlcus")
    assert loaded.image(200).shape == (480, 640)


def test_seq_nrrd_round_trip(fcal_sessions, tmp_path):
    _, validation = fcal_sessions
    out = tmp_path / "validation.seq.nrrd"
    export_plus(validation, out)
    assert out.read_bytes().startswith(b"NRRD")
    again = import_plus(out, None, tmp_path / "again")
    assert np.array_equal(again.poses(), validation.poses())
    assert np.array_equal(again.image(93), validation.image(93))


def test_one_setting_names_the_plus_data_and_a_skip_says_what_is_missing(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV, str(tmp_path))
    assert plus_data_dir() == tmp_path
    assert missing_reason() == f"real PLUS data: {ENV}={tmp_path} has none of its files; see the README, 'Real data'"
    for name in FILES[1:]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    assert f"lacks 1 files ({FILES[0]} first)" in missing_reason()
    (tmp_path / FILES[0]).write_bytes(b"")
    assert missing_reason() is None
    monkeypatch.delenv(ENV)
    assert plus_data_dir() == DEFAULT and DEFAULT.name == "plus"


NWIRE_FREEHAND = PLUS / "TestImages" / "NwirePhantomFreehand.igs.mha"
NWIRE_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"


def test_plus1_nwire_recording_imports_calibrates_and_beats_plus_matrix(plus_data, tmp_path):
    """PLUS 1's device set: ``<NWire>`` elements and the phantom registration in
    ``<Geometry><Registration>`` (its Phantom->Reference definition is an identity placeholder).
    Without segmentation hints the nominal spacing comes from ``--spacing``."""
    from tests.support.cli import run_cli
    from tests.support.refusals import assert_one_line_error

    bare = tmp_path / "bare"
    assert run_cli("import-plus", "--config", NWIRE_CONFIG, NWIRE_FREEHAND, bare).returncode == 0
    assert_one_line_error(run_cli("calibrate", bare), str(bare), "no pixel spacing known", "--spacing")

    out = tmp_path / "nwire"
    result = run_cli("import-plus", NWIRE_FREEHAND, "--config", NWIRE_CONFIG, "--spacing", "0.077", out)
    assert result.returncode == 0, result.stderr
    session = load_session(out)
    assert [layer.name for layer in session.phantom.layers] == ["N1", "N2"] and session.phantom.n_wires == 6
    assert session.pixel_spacing_mm == (0.077, 0.077)
    assert session.phantom_to_base[0, 3] == pytest.approx(-35.8004)

    result = run_cli("calibrate", out, "--out", tmp_path / "cal.json")
    assert result.returncode == 0, result.stderr
    metrics = json.loads((tmp_path / "cal.json").read_text())["metrics"]
    assert metrics["frames_used"] >= 70  # the pattern is whole in about three quarters of the sweep
    plus = run_cli("validate", out, "--calibration", NWIRE_CONFIG, "--out", tmp_path / "plus.json")
    assert plus.returncode == 0, plus.stderr
    plus_pre3d = json.loads((tmp_path / "plus.json").read_text())["metrics"]["pre3d_mm"]
    # Our calibration on frames held out of its fit, against PLUS's matrix on the same recording.
    assert metrics["cv_pre3d_mm"] < plus_pre3d < 1.0


def test_a_tracked_recording_keeps_its_tracker_samples_as_its_pose_stream(fcal_sessions):
    calibration, _ = fcal_sessions
    times, poses = calibration.pose_stream()
    assert np.array_equal(times, [r.timestamp for r in calibration.records])
    np.testing.assert_allclose(poses, calibration.poses(), atol=1e-9)  # every frame's pose, valid and in order
    stamps = np.array([0.0, 0.1, 0.1, 0.05, 0.3, np.nan, 0.4])
    kept, _ = tracker_samples(stamps, np.repeat(np.eye(4)[None], 7, axis=0), np.array([1, 1, 1, 1, 0, 1, 1], bool))
    assert kept.tolist() == [0.0, 0.1, 0.4]  # invalid, unstamped and out-of-order samples are not a stream


@pytest.fixture(scope="module")
def fcal_segmented(fcal_sessions):
    """Both fCal 1.2 recordings segmented the robot's way (no PLUS hints but the spacing)."""
    return [(s, segment_session(s, segmenter=session_segmenter(s, use_hints=False))) for s in fcal_sessions]


def test_the_calibration_measures_the_same_tracker_latency_on_both_fcal_recordings(fcal_segmented):
    found = []
    for session, results in fcal_segmented:
        obs, _ = observations(session, results)
        spacing = initial_spacing(session, obs, session.phantom)
        latency = tracked_latency(session, obs, session.phantom, spacing, session.phantom_to_base)
        # The tracked poses run about 0.4 s behind the images: paired at the right time, the
        # markers sit half as far from their wires.
        assert -0.55 < latency.image_latency_s < -0.3 and latency.applied
        assert latency.residual_mm < 0.7 * latency.residual_at_zero_mm
        found.append(latency.image_latency_s)
    assert abs(found[0] - found[1]) < 0.1  # a property of the bench, found on each recording alone


def test_validation_pairs_the_frames_with_the_calibrations_latency(fcal_segmented):
    (calibration, cal_results), (validation, val_results) = fcal_segmented
    report = calibrate_session(calibration, cal_results, "middle-wire", with_validation=False)
    latency = report.calibration.image_latency_s
    assert latency is not None and report.calibration.metrics["temporal"]["applied"]
    at_latency = validate_session(validation, report.calibration, val_results)
    as_recorded = validate_session(validation, replace(report.calibration, image_latency_s=None), val_results)
    assert at_latency["image_latency_s"] == latency and as_recorded["image_latency_s"] is None
    assert at_latency["pre3d_mm"] < 0.8 < as_recorded["pre3d_mm"]  # PLUS's own calibration: 1.247 mm
