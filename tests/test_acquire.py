"""Acquisition under faults (design §7): stop, a robot that drops, an image stream that stalls,
resuming into the same session, and the workspace guard that never lets a bad move through."""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

from probecal.app.rigspec import make_rig
from probecal.app.ursimprocess import URSimProcess
from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.imagesource import SourceFrame
from probecal.core.acquisition.pairing import FramePairer
from probecal.core.acquisition.plan import SELF_CHECK_PASSES, PoseRanges, SweepPlan, continuous_volume_legs
from probecal.core.acquisition.rig import Recording
from probecal.core.acquisition.sweep import PLAN_FILE, SourceGrabber, Sweep, TimeLeft, record_stream
from probecal.core.calibration.result import calibration_from_matrix
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.validate import validate_session
from probecal.core.errors import InputError
from probecal.core.geometry.transforms import make_transform, transform_error
from probecal.core.io.manifest import Manifest
from probecal.core.io.plusimport import import_plus
from probecal.core.io.plusresults import read_calibration_results
from probecal.core.io.session import SessionWriter, load_session
from probecal.core.robot.contract import HOME_TOOL_TO_BASE, RobotError
from probecal.core.robot.posestream import PoseSamples
from probecal.core.robot.safety import GuardedRobot, SafetyError, Workspace, load_workspace
from probecal.core.robot.simulated import SimulatedRobot
from probecal.core.robot.ur3 import MotionLimits
from tests.support.cli import PROBECAL, run_cli
from tests.support.loopback import loopback
from tests.support.paths import FCAL_CONFIG, FCAL_RESULTS, FCAL_VALIDATION
from tests.support.refusals import assert_one_line_error
from tests.support.waiting import wait_for_frames

POSES = 8


@pytest.fixture
def rig():
    rig = make_rig("sim", "sim", seed=3, time_scale=0.0)
    rig.open()
    yield rig
    rig.close()


def _plan(rig) -> SweepPlan:
    return rig.calibration_plan(POSES, PoseRanges(), MotionLimits())


def test_stopped_sweep_keeps_its_frames_and_resumes_into_the_same_session(rig, tmp_path):
    path = tmp_path / "cal"
    recording = Recording(rig, "calibration", path, _plan(rig), MotionLimits())
    recording.sweep.show = lambda f: f.index == 2 and recording.sweep.stop()
    outcome = recording.run()
    assert outcome.stopped and outcome.recorded == 3 and outcome.remaining == POSES - 3
    assert len(load_session(path)) == 3

    resumed = Recording(rig, "calibration", path, None, MotionLimits())
    assert resumed.done == {0, 1, 2}
    outcome = resumed.run()
    assert outcome.complete and outcome.recorded == POSES - 3
    session = load_session(path)
    assert [r.extra["plan_index"] for r in session.records] == list(range(POSES))
    truth = session.truth()
    assert [f["index"] for f in truth["frames"]] == list(range(POSES))
    plan = SweepPlan.load(path / PLAN_FILE)
    for record in session.records:  # each frame was taken where the plan put it (0.03 mm repeatability)
        assert np.linalg.norm(record.tool_to_base[:3, 3] - plan.poses[record.extra["plan_index"]][:3, 3]) < 0.2


class _DroppingRobot(SimulatedRobot):
    """A robot whose link drops after ``moves`` moves, like a controller that is switched off."""

    def __init__(self, moves: int, **kwargs):
        super().__init__(**kwargs)
        self._left = moves

    def move_linear(self, target, limits=None, asynchronous=False):
        if self._left == 0:
            raise RobotError("ur:127.0.0.9: connection lost during moveL")
        self._left -= 1
        super().move_linear(target, limits, asynchronous)


def test_a_robot_that_drops_ends_the_sweep_with_every_frame_kept(rig, tmp_path):
    rig.robot.robot = _DroppingRobot(4, seed=3, time_scale=0.0)
    rig.robot.connect()
    path = tmp_path / "cal"
    outcome = Recording(rig, "calibration", path, _plan(rig), MotionLimits()).run()
    assert not outcome.complete and "connection lost" in outcome.error
    assert outcome.recorded == 4 and len(load_session(path)) == 4
    assert len(load_session(path).truth()["frames"]) == 4


def _frames(rig):
    pose = HOME_TOOL_TO_BASE
    for k in itertools.count():
        image, _ = rig.scanner.calibration_frame(pose, np.random.default_rng(k))
        yield SourceFrame(image, time.time(), k)


def test_a_stalled_image_stream_ends_the_sweep_with_a_clear_message(rig, tmp_path):
    streamer = IgtlStreamer()
    source = IgtlSource("127.0.0.1", streamer.port, transform_device=None)
    streamer.play(_frames(rig), rate_hz=30.0)
    source.open()
    try:
        grabber = SourceGrabber(source, latency_s=0.0, timeout_s=0.5)
        plan = _plan(rig)
        with SessionWriter(tmp_path / "cal", Manifest(kind="calibration")) as writer:
            sweep = Sweep(rig.robot, grabber, plan)
            sweep.show = lambda f: f.index == 1 and streamer.stall()
            started = time.monotonic()
            outcome = sweep.run(writer)
        assert time.monotonic() - started < 10.0
        assert "stalled" in outcome.error and outcome.error.startswith(f"igtl:127.0.0.1:{streamer.port}")
        # frames already queued to the client when the stream stalls still arrive: at least the
        # two shown, never all, and every one recorded is in the session
        assert 2 <= outcome.recorded < len(plan.poses) and outcome.remaining == len(plan.poses) - outcome.recorded
        assert len(load_session(tmp_path / "cal")) == outcome.recorded
    finally:
        source.close()
        streamer.close()


def test_a_scanner_that_changes_its_frame_size_stops_the_sweep_there_with_its_frames_kept(rig, tmp_path):
    """A frame of another size than the stream's (the scanner's depth changed) is held to the rule a
    session's reader applies as it arrives: the sweep stops there and says why."""
    changed = threading.Event()

    def frames():
        for frame in _frames(rig):
            yield frame if not changed.is_set() else SourceFrame(frame.image[:100, :120], frame.timestamp, frame.index)

    streamer = IgtlStreamer()
    source = IgtlSource("127.0.0.1", streamer.port, transform_device=None)
    streamer.play(frames(), rate_hz=30.0)
    source.open()
    try:
        plan = _plan(rig)
        with SessionWriter(tmp_path / "cal", Manifest(kind="calibration")) as writer:
            sweep = Sweep(rig.robot, SourceGrabber(source, latency_s=0.0, timeout_s=2.0), plan)
            sweep.show = lambda f: f.index == 1 and changed.set()
            outcome = sweep.run(writer)
        assert "is 120x100 px, the stream's frames" in outcome.error and "settings changed" in outcome.error
        assert 2 <= outcome.recorded < len(plan.poses) and len(load_session(tmp_path / "cal")) == outcome.recorded
    finally:
        source.close()
        streamer.close()


class _FrozenStreamRobot(SimulatedRobot):
    """A robot whose pose stream stops coming after the first move, like a controller whose data
    connection hangs while its command connection works."""

    def poses_since(self, after):
        samples = super().poses_since(after)
        keep = samples.timestamps <= self.frozen_at if hasattr(self, "frozen_at") else slice(None)
        return PoseSamples(samples.timestamps[keep], samples.tool_to_base[keep])

    def move_linear(self, target, limits=None, asynchronous=False):
        super().move_linear(target, limits, asynchronous)
        self.frozen_at = getattr(self, "frozen_at", time.time())


def test_frames_without_a_pose_are_refused_with_the_reason_and_noted_in_the_session(rig, tmp_path):
    rig.robot.robot = _FrozenStreamRobot(seed=3, time_scale=0.0)
    rig.robot.connect()
    streamer = IgtlStreamer()
    source = IgtlSource("127.0.0.1", streamer.port, transform_device=None)
    streamer.play(_frames(rig), rate_hz=30.0)
    source.open()
    try:
        grabber = SourceGrabber(source, timeout_s=0.5)
        with SessionWriter(tmp_path / "cal", Manifest(kind="calibration")) as writer:
            outcome = Sweep(rig.robot, grabber, _plan(rig)).run(writer)
    finally:
        source.close()
        streamer.close()
    assert outcome.recorded == 0 and outcome.refused >= 1
    assert "could be paired with a robot pose" in outcome.error and "after the newest pose" in outcome.error
    assert f"{outcome.refused} frames refused (frame " in outcome.notes() and "refused.jsonl" in outcome.notes()
    logged = [json.loads(line) for line in (tmp_path / "cal" / "refused.jsonl").read_text().splitlines()]
    assert [entry["source_index"] for entry in logged] == [r.frame_index for r in outcome.refusals]
    assert all("after the newest pose" in entry["reason"] and entry["timestamp"] > 0 for entry in logged)


def test_the_workspace_guard_refuses_before_anything_is_sent():
    robot = SimulatedRobot(time_scale=0.0)
    guarded = GuardedRobot(robot, load_workspace())
    guarded.connect()
    start = robot.tool_to_base()
    outside = HOME_TOOL_TO_BASE.copy()
    outside[2, 3] = -50.0  # below the box floor, into the tank
    with pytest.raises(SafetyError, match="outside the workspace box"):
        guarded.move_linear(outside)
    with pytest.raises(SafetyError, match="linear speed 1000 mm/s is above"):
        guarded.move_linear(HOME_TOOL_TO_BASE, MotionLimits(linear_speed_mm_s=1000.0))
    assert robot.elapsed_motion_s == 0.0 and np.allclose(robot.tool_to_base(), start)
    # A robot that is somehow outside may not be moved either: it has to be brought back by hand.
    lower = HOME_TOOL_TO_BASE.copy()
    lower[2, 3] = 150.0
    below_home = Workspace((-100.0, -400.0, 100.0), (100.0, -200.0, 200.0))
    with pytest.raises(SafetyError, match="current flange position"):
        GuardedRobot(robot, below_home).move_linear(lower)
    assert robot.elapsed_motion_s == 0.0
    # A path is refused whole when any of its poses is outside, or its speed too high.
    outside = HOME_TOOL_TO_BASE.copy()
    outside[2, 3] = 5000.0
    with pytest.raises(SafetyError, match="outside the workspace box"):
        guarded.move_path([HOME_TOOL_TO_BASE, outside, HOME_TOOL_TO_BASE])
    with pytest.raises(SafetyError, match="linear speed 1000 mm/s is above"):
        guarded.move_path([HOME_TOOL_TO_BASE], MotionLimits(linear_speed_mm_s=1000.0))
    assert robot.elapsed_motion_s == 0.0 and np.allclose(robot.tool_to_base(), start)


def test_a_plan_leaving_the_workspace_is_refused_whole(tmp_path):
    small = Workspace((-200.0, -450.0, 150.0), (200.0, -150.0, 350.0))  # the scanning height is below it
    rig = make_rig("sim", "sim", seed=3, time_scale=0.0, workspace=small)
    rig.open()
    with pytest.raises(Exception, match="leave the workspace box"):
        _plan(rig)
    rig.close()


def test_cli_sweep_killed_then_resumed(tmp_path):
    """A sweep killed mid-way resumes with its own rig, the nominal spacing it was given included."""
    out = tmp_path / "cal"
    proc = subprocess.Popen([str(PROBECAL), "sweep", "calibration", str(out), "--poses", "12", "--time-scale", "0.5",
                             "--spacing", "0.1", "0.098"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    wait_for_frames(out, 3)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    kept = len(load_session(out))
    assert 3 <= kept < 12
    result = run_cli("sweep", "calibration", out, "--resume", "--time-scale", "0")
    assert result.returncode == 0, result.stderr
    assert f"({12 - kept} in this run)" in result.stdout
    session = load_session(out)
    assert sorted(r.extra["plan_index"] for r in session.records) == list(range(12))
    assert session.pixel_spacing_mm == (0.1, 0.098) and session.manifest.rig.spacing_mm == (0.1, 0.098)
    assert run_cli("calibrate", out).returncode == 0


@pytest.mark.slow
def test_cli_sweep_bad_input(tmp_path):
    assert_one_line_error(run_cli("sweep", "calibration", tmp_path / "none", "--resume"), "no session to resume")
    not_a_sweep = tmp_path / "sim"
    assert run_cli("simulate", "calibration", not_a_sweep, "--poses", "6").returncode == 0
    assert_one_line_error(run_cli("sweep", "calibration", not_a_sweep, "--resume"), "plan.json")
    assert_one_line_error(run_cli("sweep", "volume", tmp_path / "v", "--robot", "abb"), "--robot")
    assert_one_line_error(run_cli("sweep", "calibration", tmp_path / "d", "--start-depth-mm", "3"),
                          "--start-depth-mm is a live scanner's")
    for image, problem in (("video:/nonexistent.mp4", "no such video file"), ("replay:/nonexistent", "not found"),
                           ("igtl:127.0.0.1:1", "connection refused")):
        assert_one_line_error(run_cli("sweep", "calibration", tmp_path / "i", "--image", image), image, problem)
        assert not (tmp_path / "i").exists()
    workspace = tmp_path / "workspace.json"
    workspace.write_text('{"box_min_mm": [0, 0, 0]}')
    assert_one_line_error(run_cli("sweep", "calibration", tmp_path / "w", "--workspace", workspace), str(workspace),
                          "box_max_mm is missing")


def test_a_sweep_over_openigtlink_pairs_each_frame_with_the_settled_pose(tmp_path):
    """A scanner streaming what the probe sees at 30 frames/s, as a PLUS server would; the sweep
    pairs every frame with the robot's pose by timestamp."""
    rig = make_rig("sim", "sim", seed=3, time_scale=0.2)
    rig.open()
    plan = _plan(rig)  # planned on the twin, which knows where the phantom is

    def scanner():
        rng = np.random.default_rng(0)
        for k in itertools.count():
            image, _ = rig.scanner.calibration_frame(rig.robot.tool_to_base(), rng)
            yield SourceFrame(image, time.time(), k)

    streamer = IgtlStreamer()
    streamer.play(scanner(), rate_hz=30.0)
    rig.source = IgtlSource("127.0.0.1", streamer.port, transform_device=None)
    rig.start_depth_mm = 2.5  # the scanner's preset, as --start-depth-mm gives it
    try:
        rig.source.open()
        outcome = Recording(rig, "calibration", tmp_path / "cal", plan, MotionLimits()).run()
        assert outcome.complete, outcome.error
        session = load_session(tmp_path / "cal")
        assert len(session) == POSES and session.truth() is None
        assert session.start_depth_mm == 2.5 and session.manifest.rig.start_depth_mm == 2.5
        assert session.manifest.arm == "UR3"  # named by its joints and poses: calibrate fits it
        for record in session.records:
            assert record.pose_timestamp <= record.timestamp + 1e-6
            assert np.linalg.norm(record.tool_to_base[:3, 3] - plan.poses[record.extra["plan_index"]][:3, 3]) < 0.2
        assert run_cli("segment", tmp_path / "cal", "--out", tmp_path / "seg.json").returncode == 0
        assert all(f["found"] for f in json.loads((tmp_path / "seg.json").read_text())["frames"])
    finally:
        streamer.close()  # before the rig: its frames are rendered at the robot's pose
        rig.close()


def test_a_continuous_stream_is_recorded_frame_by_frame_with_the_moving_robots_pose(rig, tmp_path):
    """Frames streamed at 30 frames/s while the robot moves at 20 mm/s: every one is recorded, in
    order, with the pose the robot had when it was imaged (kept beside the stream as truth)."""
    robot = SimulatedRobot(seed=3, time_scale=1.0)
    robot.connect()
    truth = {}

    def scanner():  # each frame stamped in the middle of the time its pose took to read
        rng = np.random.default_rng(0)
        for k in itertools.count():
            before = time.time()
            pose = robot.tool_to_base()
            after = time.time()
            truth[k] = pose, after - before
            yield SourceFrame(rig.scanner.calibration_frame(pose, rng)[0], (before + after) / 2, k)

    start = robot.tool_to_base()
    robot.move_linear(start @ make_transform(np.eye(3), [40.0, 0.0, 0.0]), MotionLimits(linear_speed_mm_s=20.0),
                      asynchronous=True)
    with IgtlStreamer() as streamer, IgtlSource("127.0.0.1", streamer.port, transform_device=None) as source, \
            SessionWriter(tmp_path / "stream", Manifest(kind="volume")) as writer:
        streamer.play(scanner(), rate_hz=30.0)
        outcome = record_stream(source, FramePairer(robot), writer, frames=45)
    robot.stop()
    assert outcome.error is None and outcome.refused == 0 and outcome.recorded == 45
    session = load_session(tmp_path / "stream")
    assert [r.source_index for r in session.records] == list(range(45))  # none lost, in order
    travelled = np.linalg.norm(session.records[-1].tool_to_base[:3, 3] - session.records[0].tool_to_base[:3, 3])
    assert travelled > 20.0  # the robot moved through the stream
    for record in session.records:  # as exact as the truth: 20 mm/s times half its reading time
        pose, reading_s = truth[record.source_index]
        dt, dr = transform_error(record.tool_to_base, pose)
        assert dt < 0.01 + 20.0 * reading_s / 2 and dr < 0.001


def test_real_plus_frames_streamed_over_openigtlink_validate_like_the_recording(plus_data, tmp_path):
    """PLUS's fCal validation frames and ProbeToReference poses, played as a PLUS server plays
    them and recorded from the stream, score PLUS's own calibration exactly as the file does."""
    recorded = import_plus(FCAL_VALIDATION, FCAL_CONFIG, tmp_path / "file")
    streamer = IgtlStreamer()
    streamer.play(SourceFrame(recorded.image(i), 1000.0 + i, i, r.tool_to_base, 1000.0 + i)
                  for i, r in enumerate(recorded.records))
    with IgtlSource("127.0.0.1", streamer.port) as source, \
            SessionWriter(tmp_path / "stream", recorded.manifest, recorded.phantom, recorded.probe) as writer:
        for frame in itertools.islice(source.frames(5.0), len(recorded)):
            writer.append(frame.image, frame.tool_to_base, frame.timestamp, frame.pose_timestamp)
    streamer.close()
    received = load_session(tmp_path / "stream")
    assert len(received) == len(recorded) == 94
    for i in range(len(received)):
        assert np.array_equal(received.image(i), recorded.image(i))
    assert np.allclose(received.poses(), recorded.poses(), atol=1e-3)  # OpenIGTLink carries float32

    baseline = read_calibration_results(FCAL_RESULTS)
    plus = calibration_from_matrix(baseline.image_to_probe, FCAL_RESULTS)
    metrics = validate_session(received, plus, segment_session(received))
    assert metrics["frames_used"] == 94
    assert metrics["pre3d_mm"] == pytest.approx(baseline.pre3d_validation_mm[0], abs=2e-3)


def test_a_continuous_sweep_moves_without_stopping_records_every_frame_and_keeps_the_pose_stream(tmp_path):
    # In real time: the simulated scanner images as fast as the CPU lets it, and a busy machine
    # still records more than 40 frames of the motion.
    rig = make_rig("sim", "sim", seed=3, time_scale=1.0)
    rig.open()
    try:
        path = tmp_path / "cont"
        recording = Recording(rig, "calibration", path, _plan(rig), MotionLimits(), motion="continuous")
        outcome = recording.run()
        assert outcome.complete and outcome.recorded == len(load_session(path)) > 40
        session = load_session(path)
        phases = [r.extra["phase"] for r in session.records]
        assert phases[0] == "temporal" and phases[-1] == "calibration" and phases == sorted(phases, reverse=True)
        assert session.manifest.motion == "continuous" and session.has_pose_stream
        times, _ = session.pose_stream()
        assert times[0] < session.records[0].timestamp - 0.5 and times[-1] > session.records[-1].timestamp - 0.1
        # Paired by time with the rig's latency (0): each pose is the stream's at the frame's stamp.
        assert all(r.pose_timestamp == r.timestamp for r in session.records)
        assert len(session.truth()["frames"]) == len(session)
        with pytest.raises(InputError, match="cannot be resumed"):
            Recording(rig, "calibration", path, None, MotionLimits())
    finally:
        rig.close()


@pytest.mark.slow
def test_cli_continuous_sweep_through_ur_rtde_then_calibrate_measures_the_latency(tmp_path):
    """The real ur_rtde client drives URSim through a blended path (moveL with a path); the
    twin's scanner images at the flange's pose; calibrate measures the latency on the up-and-down
    motion against the pose stream ur_rtde delivered."""
    host, out = loopback(10, 1), tmp_path / "cal"
    with URSimProcess(host, time_scale=0.5):
        result = run_cli("sweep", "calibration", out, "--robot", f"ur:{host}", "--motion", "continuous",
                         "--poses", "12")
    assert result.returncode == 0, result.stderr
    assert "UR3 time" in result.stdout
    assert load_session(out).manifest.arm == "UR3"  # named from what the controller streamed
    calibrated = run_cli("calibrate", out, "--out", tmp_path / "cal.json")
    assert calibrated.returncode == 0, calibrated.stderr
    truth = json.loads((out / "truth.json").read_text())["setup"]["image_latency_s"]
    measured = json.loads((tmp_path / "cal.json").read_text())["image_latency_s"]
    # Within 10 ms: the twin's scanner takes the flange pose from the controller's stream, and with
    # the simulated controller sharing two cores with another test worker that pose arrives a few
    # ms late (alone, 1-2 ms off the truth).
    assert measured == pytest.approx(truth, abs=0.010)


def test_the_time_a_sweep_has_left_is_its_plan_steps_to_go_at_the_pace_of_those_done():
    """Steps planned at 2, 1 and 1 robot seconds; the first took 1 wall second (a robot twice as
    fast as real time): 2 planned seconds are left, 1 wall second at that pace."""
    now = [0.0]
    left = TimeLeft(np.array([2.0, 1.0, 1.0]), clock=lambda: now[0])
    assert left.left_s() is None and left.fraction() == 0.0  # no pace before a step ends
    now[0] = 1.0
    left.step_done()
    assert left.left_s() == pytest.approx(1.0) and left.fraction() == pytest.approx(0.5)
    now[0] = 1.25  # halfway through the second step
    assert left.left_s() == pytest.approx(0.75) and left.fraction() == pytest.approx(0.625)
    now[0] = 2.0
    left.step_done()
    left.step_done()
    assert left.left_s() == 0.0 and left.fraction() == 1.0
    # From three steps on, each step's own time is told from the pace: here 0.5 s a step (its
    # frame grabbed and shown) and half the robot's planned time.
    now[0] = 0.0
    left = TimeLeft(np.array([4.0, 1.0, 1.0, 1.0, 1.0]), clock=lambda: now[0])
    for now[0] in (2.5, 3.5, 4.5):
        left.step_done()
    assert left.left_s() == pytest.approx(2.0)


def test_a_self_check_sweep_records_each_frames_view_and_pass_and_its_plan_keeps_them(rig, tmp_path):
    """Each pass of the self-check's plan from every view, inside the workspace; a stop-and-go
    sweep records every frame's view and pass over all views, its plan.json keeps the views, and
    driven without stopping each pass's frames carry them too."""
    frames = 3
    plan = rig.self_check_plan(frames, MotionLimits())
    n = frames * len(SELF_CHECK_PASSES)
    assert plan.views == [0] * n + [1] * n and plan.passes == [k // frames for k in range(2 * n)]
    outcome = Recording(rig, "volume", tmp_path / "check", plan, MotionLimits()).run()
    assert outcome.complete
    session = load_session(tmp_path / "check")
    assert [(r.extra["view"], r.extra["sweep"]) for r in session.records] == list(zip(plan.views, plan.passes))
    assert session.manifest.plan["views"] == 2
    loaded = SweepPlan.load(tmp_path / "check" / PLAN_FILE)
    assert loaded.views == plan.views and loaded.passes == plan.passes
    assert np.allclose(np.array(loaded.poses), np.array(plan.poses))
    legs = continuous_volume_legs(plan, MotionLimits())
    each = len(SELF_CHECK_PASSES)
    assert [leg.record for leg in legs if leg.record is not None] == [{"sweep": k, "view": k // each}
                                                                      for k in range(2 * each)]


def test_a_plan_file_without_views_loads_as_one_view_and_bad_views_are_refused(tmp_path):
    path = tmp_path / PLAN_FILE
    old = {"poses": [np.eye(4).tolist()] * 2, "passes": [0, 1], "duration_s": 1.0}  # written before views were
    path.write_text(json.dumps(old))
    plan = SweepPlan.load(path)
    assert plan.views is None and plan.passes == [0, 1] and plan.view_of_pass(1) is None
    assert "views" not in plan.to_dict() and "views" not in plan.summary()
    for views, field in (([0], "views"), ([0, -1], r"views\[1\]"), ([0, 0.5], r"views\[1\]"), ("0,1", "views")):
        path.write_text(json.dumps({**old, "views": views}))
        with pytest.raises(InputError, match=field):
            SweepPlan.load(path)
