"""Temporal calibration (issue 17): the lag between the images and the pose stream, on synthetic
signals, on PLUS's water-tank recording, and on the twin's continuous sweep."""

from __future__ import annotations

import json
import shutil
import tracemalloc
import xml.etree.ElementTree as ET
from dataclasses import replace

import cv2
import numpy as np
import pytest

from probecal.core.acquisition.pairing import paired_again
from probecal.core.acquisition.plan import THESIS_RANGES
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.latency import TooFewEchoes, session_latency, temporal_frames
from probecal.core.calibration.result import load_calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session, segment_and_calibrate
from probecal.core.errors import InputError
from probecal.core.io.sequence import read_sequence
from probecal.core.io.session import load_session
from probecal.core.temporal.echo import floor_echo_row, floor_echo_rows
from probecal.core.temporal.lag import estimate_latency, principal_motion
from probecal.core.temporal.plusbuffers import plus_latency
from probecal.core.volume.cad import session_cad_target
from probecal.core.volume.reconstruct import reconstruct_session
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error

VIDEO = "TestImages/WaterTankBottomTranslationVideoBuffer.igs.mha"
TRACKER = "TestImages/WaterTankBottomTranslationTrackerBuffer-trimmed.igs.mha"


def _signals(latency_s: float, jitter_s: float = 0.002, seed: int = 0):
    """A probe bobbing up and down (pose stream at 125 Hz, mm) and the echo's row it makes in
    frames taken at 20 Hz, stamped ``latency_s`` late with jitter (px, 12.5 px/mm, moving the
    other way)."""
    rng = np.random.default_rng(seed)
    pose_times = np.arange(0.0, 8.0, 1 / 125)
    motion = 5 * np.sin(2 * np.pi * 0.7 * pose_times) + 2 * np.sin(2 * np.pi * 1.9 * pose_times)
    acquired = np.arange(1.0, 7.0, 1 / 20)
    truth = np.interp(acquired, pose_times, motion)
    echo = 200 - 12.5 * truth + rng.normal(0, 0.3, len(acquired))
    return acquired + latency_s + rng.normal(0, jitter_s, len(acquired)), echo, pose_times, motion


def test_the_lag_that_lines_the_echo_up_with_the_motion_is_the_image_latency():
    for latency in (0.0, 0.037, 0.12, -0.05):
        frame_times, echo, pose_times, motion = _signals(latency)
        found = estimate_latency(frame_times, echo, pose_times, motion)
        assert found.image_latency_s == pytest.approx(latency, abs=0.001)
        assert found.correlation < -0.99  # the echo moves against the motion's axis here
        assert 0 < found.std_error_s < 0.001 and found.peak_halfwidth_s < 0.02
        assert found.frames_used + found.frames_rejected == len(echo) and found.frames_rejected <= 2


def test_frames_whose_echo_is_off_the_motion_are_dropped_and_missing_echoes_skipped():
    frame_times, echo, pose_times, motion = _signals(0.08)
    echo[[10, 40, 70]] += 60.0  # a reverberation taken for the floor
    echo[[20, 21]] = np.nan  # no floor found
    found = estimate_latency(frame_times, echo, pose_times, motion)
    assert found.image_latency_s == pytest.approx(0.08, abs=0.001)
    assert 3 <= found.frames_rejected <= 5 and found.frames_used + found.frames_rejected == len(echo) - 2


def test_a_still_probe_or_a_lag_beyond_the_search_measures_nothing():
    frame_times, echo, pose_times, motion = _signals(0.3)
    with pytest.raises(ValueError, match="edge of the lags searched"):
        estimate_latency(frame_times, echo, pose_times, motion, max_lag_s=0.1)
    with pytest.raises(ValueError, match="the probe moved 0.00 mm"):
        estimate_latency(frame_times, echo, pose_times, np.zeros_like(motion))
    with pytest.raises(ValueError, match="at least 10 are needed"):
        estimate_latency(frame_times, np.full_like(echo, np.nan), pose_times, motion)


def test_principal_motion_follows_the_main_axis_of_the_selected_samples():
    t = np.linspace(0, 1, 400)
    positions = np.outer(np.sin(40 * t), [0.0, 0.6, 0.8]) + np.outer(t, [6.0, 0.0, 0.0])
    along = principal_motion(positions)
    assert abs(np.corrcoef(along, t)[0, 1]) > 0.9  # the drift is the main axis of all samples
    first = principal_motion(positions, axis_from=t < 0.2)
    assert abs(np.corrcoef(first, np.sin(40 * t))[0, 1]) > 0.9  # the bobbing is that of the first stretch


def test_the_floor_echo_is_found_at_the_centre_column_of_a_tilted_line():
    frame = np.zeros((300, 400), np.uint8)
    cv2.line(frame, (20, 120), (380, 192), 230, 3)  # row 156 at the centre column
    for x in range(0, 400, 37):  # speckle and a reverberation fragment below
        cv2.circle(frame, (x, 40 + x % 50), 1, 60, -1)
    cv2.line(frame, (300, 260), (340, 268), 120, 2)
    assert floor_echo_row(frame) == pytest.approx(156.0 + 72 * (199.5 - 200) / 360, abs=0.5)
    assert np.isnan(floor_echo_row(np.zeros((300, 400), np.uint8)))


def test_a_frame_grabbers_overlay_is_not_taken_for_the_floor():
    rows = 150 + 40 * np.sin(np.linspace(0, 6, 40))
    frames = np.zeros((40, 300, 400), np.uint8)
    for frame, row in zip(frames, rows):
        cv2.line(frame, (0, int(round(row)) - 10), (399, int(round(row)) + 10), 200, 3)
        frame[20:30, :] = 255  # a text band as bright as anything, across the whole width
    found = floor_echo_rows(frames)
    assert np.abs(found - np.round(rows)).max() < 1.0


def test_plus_water_tank_latency_matches_plus_and_follows_moved_timestamps(plus_data):
    baseline = ET.parse(plus_data / "TestImages" / "TemporalCalibrationResultsBaseline.xml").getroot()
    plus_image_latency = -float(baseline.get("TrackerLagSec"))  # PLUS's sign: the tracker's lag
    found = plus_latency(plus_data / VIDEO, plus_data / TRACKER)
    assert found.image_latency_s == pytest.approx(plus_image_latency, abs=0.002)
    moved = plus_latency(plus_data / VIDEO, plus_data / TRACKER, video_shift_s=0.05)
    assert moved.image_latency_s - found.image_latency_s == pytest.approx(0.05, abs=0.002)


def test_a_tracker_buffer_reads_as_poses_without_images_and_is_no_video(plus_data):
    tracker = read_sequence(plus_data / TRACKER, images=False)
    assert tracker.frames.shape == (801, 0, 0) and tracker.transform("Probe", "Tracker") is not None
    with pytest.raises(InputError, match="a tracker buffer"):
        read_sequence(plus_data / TRACKER)


def test_temporal_calibrate_command_on_plus_buffers(plus_data, tmp_path):
    out = tmp_path / "lag.json"
    result = run_cli("temporal-calibrate", "--video", plus_data / VIDEO, "--tracker", plus_data / TRACKER,
                     "--out", out)
    assert result.returncode == 0, result.stderr
    assert "image latency 64." in result.stdout and "TrackerLagSec" in result.stdout
    data = json.loads(out.read_text())
    assert data["image_latency_s"] == pytest.approx(0.0648, abs=0.002)
    assert data["plus_tracker_lag_s"] == -data["image_latency_s"] and data["frames_used"] > 150
    assert_one_line_error(run_cli("temporal-calibrate", "--video", plus_data / VIDEO, "--tracker",
                                  plus_data / TRACKER, "--out", out), str(out), "--force")
    swapped = run_cli("temporal-calibrate", "--video", plus_data / TRACKER, "--tracker", plus_data / VIDEO,
                      "--out", tmp_path / "swapped.json")
    assert_one_line_error(swapped, TRACKER.split("/")[1], "tracker buffer")
    assert_one_line_error(run_cli("temporal-calibrate", "--video", plus_data / VIDEO, "--out", tmp_path / "x.json"),
                          "both --video and --tracker")
    assert not (tmp_path / "swapped.json").exists() and not (tmp_path / "x.json").exists()


@pytest.fixture(scope="module")
def continuous(tmp_path_factory):
    return simulate_calibration(tmp_path_factory.mktemp("cont") / "s", n_poses=16, seed=6, noise="realistic",
                                motion="continuous", image_latency_s=0.11, ranges=THESIS_RANGES)


def test_a_continuous_sweep_keeps_its_pose_stream_and_marks_its_temporal_frames(continuous):
    times, poses = continuous.pose_stream()
    assert np.all(np.diff(times) > 0) and poses.shape == (len(times), 4, 4)
    frames = temporal_frames(continuous)
    assert 20 <= len(frames) < len(continuous) and frames == list(range(len(frames)))
    truth = continuous.truth()
    assert truth["setup"]["image_latency_s"] == 0.11
    # Paired as the rig pairs a frame that does not know the latency: at its timestamp.
    record = continuous.records[len(frames) + 5]
    assert record.pose_timestamp == record.timestamp


def test_the_latency_measured_on_a_continuous_sweep_and_its_frames_paired_again(continuous):
    found = session_latency(continuous)
    assert found.image_latency_s == pytest.approx(0.11, abs=0.002)
    truth = continuous.truth()["frames"]
    again = paired_again(continuous, found.image_latency_s)
    k = len(temporal_frames(continuous)) + 10
    acquired = again.records[k].pose_timestamp
    assert acquired == pytest.approx(truth[k]["acquired_s"], abs=0.01)  # within the timestamp jitter
    moved = np.linalg.norm(again.records[k].tool_to_base[:3, 3] - continuous.records[k].tool_to_base[:3, 3])
    assert moved > 0.5  # 110 ms of motion


def test_calibrate_measures_the_latency_before_pairing_and_keeps_it(continuous, tmp_path):
    report = segment_and_calibrate(continuous)
    calibration = report.calibration
    assert calibration.image_latency_s == pytest.approx(0.11, abs=0.002)
    assert calibration.metrics["image_latency_s"] == pytest.approx(calibration.image_latency_s, abs=1e-6)
    assert calibration.metrics["frames_total"] == len(continuous) - len(temporal_frames(continuous))
    truth = np.array(continuous.truth()["image_to_tool_rigid"])
    assert np.linalg.norm(calibration.image_to_tool_rigid[:3, 3] - truth[:3, 3]) < 0.1
    calibration.write(tmp_path / "cal.json")
    assert load_calibration(tmp_path / "cal.json").image_latency_s == pytest.approx(calibration.image_latency_s)
    assert load_calibration(continuous.path / "truth.json").image_latency_s == 0.11


def test_a_temporal_motion_that_showed_too_few_echoes_leaves_the_latency_to_the_sweeps_own_frames(continuous):
    """A slow image stream may catch the echo too seldom during the temporal motion; the sweep's
    frames, fitted at every lag against the pose stream, still measure the latency."""
    temporal = set(temporal_frames(continuous))
    results = [replace(r, found=False, markers=None, reason="blanked") if r.index in temporal else r
               for r in segment_session(continuous)]
    with pytest.raises(TooFewEchoes):
        session_latency(continuous, results)
    said: list[str] = []
    calibration = calibrate_session(continuous, results, progress=said.append).calibration
    assert any("fitting it on the sweep's frames instead" in line for line in said), said
    assert calibration.image_latency_s == pytest.approx(0.11, abs=0.01)
    assert calibration.metrics["frames_total"] == len(continuous) - len(temporal)
    truth = np.array(continuous.truth()["image_to_tool_rigid"])
    assert np.linalg.norm(calibration.image_to_tool_rigid[:3, 3] - truth[:3, 3]) < 0.2


def test_a_session_of_nothing_but_a_temporal_motion_too_short_is_refused_saying_so(continuous, tmp_path):
    """Its few frames show the echo too seldom, and no sweep follows to fit the latency on: the
    refusal says both, not that no frame is usable for no reason."""
    short = tmp_path / "short"
    shutil.copytree(continuous.path, short)
    records = (short / "records.jsonl").read_text().splitlines()[:6]
    (short / "records.jsonl").write_text("\n".join(records) + "\n")
    result = run_cli("calibrate", short, "--out", tmp_path / "cal.json")
    assert_one_line_error(result, str(short), "no latency measured", "every frame is of that motion")
    assert not (tmp_path / "cal.json").exists()


def test_a_motion_without_a_phantom_is_read_a_frame_at_a_time(continuous, tmp_path):
    """Without a phantom the latency follows the floor's echo in every frame of the motion; the
    frames are read as they are needed, so the memory it takes does not grow with them."""
    peaks = []
    for count in (len(temporal_frames(continuous)) // 2, len(temporal_frames(continuous))):
        folder = tmp_path / f"first{count}"
        shutil.copytree(continuous.path, folder)
        (folder / "phantom.json").unlink()
        manifest = json.loads((folder / "manifest.json").read_text())
        (folder / "manifest.json").write_text(json.dumps({**manifest, "phantom": None}))
        records = (folder / "records.jsonl").read_text().splitlines()[:count]
        (folder / "records.jsonl").write_text("\n".join(records) + "\n")
        session = load_session(folder)
        tracemalloc.start()
        try:
            session_latency(session)
        except InputError:
            pass  # the twin's wires are no floor: what is measured here is what reading them takes
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    frame = continuous.image(0).nbytes
    assert peaks[1] - peaks[0] < 5 * frame, (peaks, frame)  # not the other half of the frames (64 and more)


def test_temporal_calibrate_command_on_a_session(continuous, tmp_path):
    result = run_cli("temporal-calibrate", continuous.path, "--out", tmp_path / "lag.json")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "lag.json").read_text())["image_latency_s"] == pytest.approx(0.11, abs=0.002)


def test_a_session_without_a_pose_stream_has_no_latency_to_measure(tmp_path):
    session = simulate_calibration(tmp_path / "stop", n_poses=3, seed=1, noise="none")
    result = run_cli("temporal-calibrate", session.path, "--out", tmp_path / "lag.json")
    assert_one_line_error(result, str(session.path), "no pose stream", "continuous motion",
                          "--motion continuous records one")  # the option named by the command line
    assert not (tmp_path / "lag.json").exists()


def test_a_continuous_volume_sweep_is_paired_again_with_the_calibrations_latency(tmp_path):
    sweep = simulate_volume(tmp_path / "v", seed=2, noise="realistic", motion="continuous", image_latency_s=0.08)
    assert sweep.has_pose_stream and sweep.manifest.speed_mm_s == 20.0
    assert {r.extra["sweep"] for r in sweep.records} == set(range(sweep.manifest.plan["passes"]))
    truth = load_calibration(sweep.path / "truth.json")  # the twin's calibration and its 80 ms
    assert truth.image_latency_s == 0.08
    cad = session_cad_target(sweep)
    paired = reconstruct_session(sweep, truth, tmp_path / "paired", cad=cad).report
    ignored = reconstruct_session(sweep, replace(truth, image_latency_s=None), tmp_path / "ignored", cad=cad).report
    assert paired["image_latency_s"] == 0.08 and ignored["image_latency_s"] is None
    assert paired["surface_mean_mm"] < 0.06
    assert ignored["surface_p95_mm"] > paired["surface_p95_mm"] + 0.3  # 1.6 mm along the sweep


def test_a_sweep_takes_its_latency_from_a_measurement(continuous, tmp_path):
    lag = tmp_path / "lag.json"
    assert run_cli("temporal-calibrate", continuous.path, "--out", lag).returncode == 0
    out = tmp_path / "sweep"
    result = run_cli("sweep", "calibration", out, "--poses", "6", "--time-scale", "0", "--latency-from", lag)
    assert result.returncode == 0, result.stderr
    recorded = json.loads((out / "manifest.json").read_text())["rig"]["latency_s"]
    assert recorded == pytest.approx(json.loads(lag.read_text())["image_latency_s"])
    stop = simulate_calibration(tmp_path / "stop", n_poses=3, seed=1, noise="none")
    (tmp_path / "cal.json").write_text((stop.path / "truth.json").read_text().replace('"image_latency_s"', '"x"'))
    assert_one_line_error(run_cli("sweep", "calibration", tmp_path / "s2", "--latency-from", tmp_path / "cal.json"),
                          "cal.json", "records no image_latency_s")
    assert_one_line_error(run_cli("serve", "--latency", "0.1", "--latency-from", lag, "--port", "0"),
                          "not both")
    # A calibration's latency is refused for another scanner's images.
    other = json.loads((stop.path / "truth.json").read_text())
    other["valid_for"] = {"image_size": [820, 616], "nominal_spacing_mm": [0.078, 0.078], "depth_mm": 48.0,
                          "source": "PLUS recording"}
    (tmp_path / "fcal.json").write_text(json.dumps(other))
    refused = run_cli("sweep", "calibration", tmp_path / "s3", "--time-scale", "0", "--latency-from",
                      tmp_path / "fcal.json")
    assert_one_line_error(refused, "fcal.json", "made for other images", "384 x 500", "--force")
    assert not (tmp_path / "s3").exists()
