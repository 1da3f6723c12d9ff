"""Robot pose streams stamped by the controller's clock, and frames paired with them: exact on
the twin's clock however busy the caller is, refused only when the robot moved in a gap."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.pairing import FramePairer, stream_buffer
from probecal.core.geometry.transforms import make_transform, transform_error
from probecal.core.robot.contract import HOME_TOOL_TO_BASE
from probecal.core.robot.posestream import ClockSync, PoseBuffer, PoseSamples
from probecal.core.robot.simulated import STREAM_HZ, SimulatedRobot
from probecal.core.robot.ur3 import MotionLimits
from tests.test_robot import shifted

HANG_GUARD_S = 10.0  # generous bound on anything that must not hang; not a speed target


def two_poses() -> tuple[np.ndarray, np.ndarray]:
    return make_transform(np.eye(3), [0.0, 0.0, 0.0]), make_transform(
        Rotation.from_euler("z", 20, degrees=True), [10.0, -4.0, 2.0]
    )


class _ListRobot:
    """A robot whose pose stream is a list of (timestamp, pose) given by the test."""

    def __init__(self, samples=()):
        self.samples = list(samples)

    def poses_since(self, after: float) -> PoseSamples:
        newer = [(t, p) for t, p in self.samples if t > after]
        if not newer:
            return PoseSamples.empty()
        return PoseSamples(np.array([t for t, _ in newer]), np.array([p for _, p in newer]))


def test_buffer_interpolates_between_samples():
    start, end = two_poses()
    buffer = PoseBuffer(max_gap_s=0.05)
    assert buffer.add(start, 1.00) and buffer.add(end, 1.04)
    pose, reason = buffer.pose_at(1.03)  # three quarters of the way
    assert reason == ""
    np.testing.assert_allclose(pose[:3, 3], [7.5, -3.0, 1.5], atol=1e-9)
    angle = Rotation.from_matrix(pose[:3, :3]).as_euler("xyz", degrees=True)
    np.testing.assert_allclose(angle, [0.0, 0.0, 15.0], atol=1e-9)
    assert np.array_equal(buffer.pose_at(1.04)[0], end)  # exactly on a sample


def test_a_gap_is_refused_only_when_the_robot_moved_in_it():
    start, end = two_poses()
    buffer = PoseBuffer(max_gap_s=0.05)
    assert buffer.pose_at(1.0) == (None, "no robot poses yet")
    buffer.add(start, 1.0)
    buffer.add(end, 1.5)  # moved 11 mm in half a second nobody saw
    buffer.add(end, 3.0)  # then stood still for 1.5 s
    (before, why_before), (after, why_after) = buffer.pose_at(0.9), buffer.pose_at(3.1)
    assert before is None and "before the oldest" in why_before
    assert after is None and "after the newest" in why_after
    moving, why = buffer.pose_at(1.2)
    assert moving is None and "moved 10.95 mm in a 0.500 s gap" in why
    still, why = buffer.pose_at(2.2)
    assert why == "" and np.allclose(still, end)
    assert not buffer.add(end, 3.0)  # not after the newest: ignored
    with pytest.raises(ValueError, match="finite"):
        buffer.add(np.full((4, 4), np.nan), 4.0)
    assert len(buffer) == 3 and buffer.span() == (1.0, 3.0)


def test_a_whole_stream_is_looked_up_at_once_as_one_pose_at_a_time():
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.01, 0.12, 60))
    poses = np.array([make_transform(Rotation.from_rotvec(rng.normal(0, 0.3, 3)), rng.normal(0, 5, 3))
                      for _ in times])
    poses[20] = poses[19]  # standing still across a long gap: interpolated all the same
    times[20:] += 1.0
    buffer = PoseBuffer(max_gap_s=0.1)
    buffer.extend(PoseSamples(times, poses))
    queries = np.concatenate([rng.uniform(times[0] - 0.5, times[-1] + 0.5, 400), times[:5], times[-1:]])
    looked_up = buffer.poses_at(queries)
    for t, pose in zip(queries, looked_up):
        expected, _ = buffer.pose_at(t)
        if expected is None:
            assert np.isnan(pose).all()
        else:
            np.testing.assert_allclose(pose, expected, atol=1e-9)
    assert 0 < np.isnan(looked_up[:, 0, 0]).sum() < len(queries)  # moving gaps and the ends refused
    assert np.isnan(PoseBuffer().poses_at(np.array([1.0]))).all()


def test_a_slow_kept_stream_is_interpolated_across_its_own_sample_interval():
    start, end = two_poses()
    times = np.arange(0.0, 1.0, 0.08)  # a tracker sampled at the frames' 12.5 Hz
    poses = np.array([start if i % 2 == 0 else end for i in range(len(times))])
    buffer = stream_buffer(times, poses)
    assert buffer.max_gap_s == pytest.approx(0.2)
    assert np.isfinite(buffer.poses_at(np.array([0.04]))).all()
    assert stream_buffer(np.arange(0.0, 1.0, 0.008), np.repeat(start[None], 125, axis=0)).max_gap_s == 0.05


def test_buffer_is_bounded_and_returns_what_came_after():
    start, _ = two_poses()
    buffer = PoseBuffer(capacity=3)
    for i in range(5):
        buffer.add(start, i * 0.01)
    assert len(buffer) == 3 and buffer.span() == (0.02, 0.04)
    np.testing.assert_allclose(buffer.since(0.025).timestamps, [0.03, 0.04])
    later = buffer.since(100.025, offset=100.0)  # on a clock 100 s ahead of the samples'
    np.testing.assert_allclose(later.timestamps, [100.03, 100.04])


def test_clock_sync_takes_the_fastest_delivery_and_follows_drift():
    sync = ClockSync(window_s=10.0)
    assert sync.offset is None
    rng = np.random.default_rng(0)
    for k in range(2000):  # a controller clock 1000 s behind ours, seen 0.1..20 ms late
        device = 5.0 + k * 0.002
        sync.observe(device, device + 1000.0 + rng.uniform(0.0001, 0.02))
    assert sync.offset == pytest.approx(1000.0, abs=0.0005)
    for k in range(2000, 12000):  # the controller's clock now runs 1 ms behind per 10 s
        device = 5.0 + k * 0.002
        sync.observe(device, device + 1000.0 + 0.0001 * (k - 2000) * 0.002 + 0.0001)
    assert sync.offset == pytest.approx(1000.0 + 0.002 - 0.001 + 0.0001, abs=0.0003)


def test_pairer_applies_the_latency_and_waits_for_the_stream():
    start, end = two_poses()
    robot = _ListRobot([(1.00, start), (1.04, end)])
    pairer = FramePairer(robot, latency_s=0.02)
    pairing = pairer.pair(1.05)  # shows the probe at 1.03 s
    assert pairing.frame_timestamp == 1.05 and pairing.pose_timestamp == pytest.approx(1.03)
    np.testing.assert_allclose(pairing.tool_to_base[:3, 3], [7.5, -3.0, 1.5], atol=1e-9)
    late = threading.Timer(0.1, robot.samples.append, args=((1.08, end),))
    late.start()
    pairing = pairer.pair(1.09, wait_s=HANG_GUARD_S)  # 1.07 s: the stream gets there later
    late.join()
    assert np.allclose(pairing.tool_to_base, end)
    refused = pairer.pair(5.0, wait_s=0.0)
    assert refused.tool_to_base is None and "after the newest pose" in refused.reason


def _gil_hog(stop: threading.Event) -> None:
    while not stop.is_set():
        sum(range(20_000))  # pure-Python work: holds the GIL in long stretches


def test_the_twin_streams_exact_poses_to_a_starved_reader():
    """While the robot moves and two threads hog the interpreter, the pose stream still has a
    sample every 1/STREAM_HZ s and each is where the motion profile puts the flange."""
    robot = SimulatedRobot(seed=1, time_scale=1.0, repeatability_mm=0.0)
    robot.connect()
    target = shifted(HOME_TOOL_TO_BASE, dx=30.0, dz=-10.0, rot_deg=(0.0, 0.0, 10.0))
    started = time.time()
    stop = threading.Event()
    hogs = [threading.Thread(target=_gil_hog, args=(stop,), daemon=True) for _ in range(2)]
    for hog in hogs:
        hog.start()
    try:
        robot.move_linear(target, MotionLimits(linear_speed_mm_s=60.0), asynchronous=True)
        assert robot.wait(HANG_GUARD_S)
    finally:
        stop.set()
    stream = robot.poses_since(started - 0.1)
    steps = np.diff(stream.timestamps)
    np.testing.assert_allclose(steps, 1.0 / STREAM_HZ, atol=1e-6)
    dt, dr = transform_error(stream.tool_to_base[-1], target)
    assert dt < 1e-6 and dr < 0.02  # the rotation's repeatability error stays
    moves = np.linalg.norm(np.diff(stream.tool_to_base[:, :3, 3], axis=0), axis=1)
    assert moves.max() < 60.0 / STREAM_HZ * 1.01  # no jump: the speed limit holds sample to sample
    assert stream.timestamps[0] > started - 0.1 and stream.timestamps[-1] <= time.time()


def test_a_halted_twin_rests_where_the_stream_last_showed_it():
    robot = SimulatedRobot(seed=1, time_scale=1.0, repeatability_mm=0.0)
    robot.connect()
    started = time.time()
    # 3 s to the target: the stop lands short of it even if this thread stalls on a busy machine
    robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=60.0), MotionLimits(linear_speed_mm_s=20.0), asynchronous=True)
    deadline = time.monotonic() + HANG_GUARD_S
    while robot.tool_to_base()[0, 3] - HOME_TOOL_TO_BASE[0, 3] < 5.0:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    robot.stop()
    stopped = time.time()
    rest = robot.tool_to_base()
    assert 5.0 < rest[0, 3] - HOME_TOOL_TO_BASE[0, 3] < 60.0
    stream = robot.poses_since(started)
    while stream.timestamps[-1] <= stopped:  # the twin's clock moves on; so does its stream
        stream = robot.poses_since(started)
    assert np.allclose(stream.tool_to_base[-1], rest, atol=1e-9)
    steps = np.diff(stream.tool_to_base[:, 0, 3])
    assert np.all(steps > -1e-9) and np.sum(steps > 1e-6) > 5  # it moved on up to the stop, then rested
