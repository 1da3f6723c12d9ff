"""The tracked probe's pose source (core.acquisition.tracker) against a PLUS-server stand-in over
loopback: poses composed as PLUS composes them, and every way a tracker stream goes wrong."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.igtl import transform_message
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.tracker import (
    MAX_NAMES_SEEN,
    MAX_RATE_HZ,
    BadTrackerData,
    IgtlTracker,
    TrackerDevices,
    TrackerError,
    parse_devices,
    rigidity_problem,
)
from probecal.core.errors import QUOTED_CHARS
from probecal.core.geometry.transforms import invert_transform, make_transform
from tests.support.waiting import wait_until

PLUS = TrackerDevices("ProbeToTracker", "ReferenceToTracker")
RATE_HZ = 100.0


def probe_to_reference(k: int) -> np.ndarray:
    """The probe's true pose in the reference's frame at sample k (mm)."""
    return make_transform(Rotation.from_euler("xyz", [10 + 0.2 * k, -5, 30], degrees=True).as_matrix(),
                          [10.0 + 0.5 * k, -20.0, 150.0])


def reference_to_tracker(k: int) -> np.ndarray:
    """The reference moves too (the camera was bumped): composition must follow it."""
    return make_transform(Rotation.from_euler("xyz", [170, 5 + 0.1 * k, -20], degrees=True).as_matrix(),
                          [40.0, -60.0 + 0.2 * k, -900.0])


def plus_batches(n: int, start: float, status=lambda k, device: "OK", matrix=None, stamp=None):
    """What a PLUS server sends for n tracker samples: ProbeToTracker then ReferenceToTracker, both
    stamped with the sample's time (s after ``start``, on this machine's clock)."""
    for k in range(n):
        t = start + k / RATE_HZ if stamp is None else stamp(k)
        probe = reference_to_tracker(k) @ probe_to_reference(k) if matrix is None else matrix(k)
        yield k / RATE_HZ, [transform_message(probe, t, "ProbeToTracker", status(k, "ProbeToTracker")),
                            transform_message(reference_to_tracker(k), t, "ReferenceToTracker",
                                              status(k, "ReferenceToTracker"))]


def test_plus_poses_are_composed_at_their_times_and_mapped_to_this_clock():
    start = time.time()
    with IgtlStreamer() as streamer:
        streamer.play_batches(plus_batches(50, start))
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0)
        tracker.connect()
        try:
            samples = wait_until(lambda: (s := tracker.poses_since(start - 1.0)) and len(s) == 50 and s,
                                 "50 composed poses")
            assert tracker.paused is None
        finally:
            tracker.disconnect()
    expected = np.array([probe_to_reference(k) for k in range(50)])
    assert np.allclose(samples.tool_to_base, expected, atol=1e-3)  # float32 on the wire
    # stamped by the sender, moved onto this machine's clock as one: never earlier than sent
    assert np.allclose(np.diff(samples.timestamps), 1 / RATE_HZ, atol=1e-6)
    assert samples.timestamps[0] >= start


def test_a_single_device_in_the_references_frame():
    start = time.time()
    batches = ((k / RATE_HZ, [transform_message(probe_to_reference(k), start + k / RATE_HZ, "StylusToRef")])
               for k in range(20))
    with IgtlStreamer() as streamer:
        streamer.play_batches(batches)
        tracker = IgtlTracker("127.0.0.1", streamer.port, parse_devices("StylusToRef"), first_pose_s=5.0)
        tracker.connect()
        try:
            samples = wait_until(lambda: (s := tracker.poses_since(0.0)) and len(s) == 20 and s, "20 poses")
        finally:
            tracker.disconnect()
    assert np.allclose(samples.tool_to_base, [probe_to_reference(k) for k in range(20)], atol=1e-3)
    assert np.allclose(tracker.tool_to_base(), probe_to_reference(19), atol=1e-3)


def test_unknown_device_names_are_refused_naming_what_the_server_sends():
    with IgtlStreamer() as streamer:
        streamer.play_batches(plus_batches(1000, time.time()))
        tracker = IgtlTracker("127.0.0.1", streamer.port, TrackerDevices("PrbToTrk", "ReferenceToTracker"),
                              first_pose_s=0.5)
        with pytest.raises(TrackerError) as caught:
            tracker.connect()
    said = str(caught.value)
    assert said == (f"tracker igtl:127.0.0.1:{streamer.port}: no TRANSFORM 'PrbToTrk' within 0.5 s; the server "
                    "sends 'ProbeToTracker'")
    assert not tracker.connected


def test_a_tracker_that_never_sends_is_refused_in_time():
    with IgtlStreamer() as streamer:
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=0.3)
        started = time.monotonic()
        with pytest.raises(TrackerError, match=r"no TRANSFORM 'ProbeToTracker' or 'ReferenceToTracker' within 0.3 s$"):
            tracker.connect()
        assert time.monotonic() - started < 5.0


def test_no_server_is_refused_in_one_line():
    with IgtlStreamer() as streamer:
        port = streamer.port
    with pytest.raises(TrackerError, match=r"^tracker igtl:127.0.0.1:\d+: connection refused"):
        IgtlTracker("127.0.0.1", port, PLUS).connect()


@pytest.mark.parametrize(("matrix", "said"), [
    (np.diag([2.0, 1.0, 1.0, 1.0]), "its rotation is not a rotation (columns 2, 1, 1 long, determinant 2)"),
    (np.diag([-1.0, 1.0, 1.0, 1.0]), "determinant -1"),
    (np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "columns 1, 1.02, 1 long"),
    # orthonormal within the tolerance, but its determinant is not: a session's reader refuses it
    (np.diag([1.0004, 1.0004, 1.0004, 1.0]), "determinant 1.001"),
])
def test_a_matrix_that_is_not_a_rigid_pose_ends_the_stream(matrix, said):
    bad = lambda k: matrix if k == 30 else reference_to_tracker(k) @ probe_to_reference(k)  # noqa: E731
    with IgtlStreamer() as streamer:
        streamer.play_batches(plus_batches(40, time.time(), matrix=bad))
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0)
        tracker.connect()
        error = wait_until(lambda: tracker.error, "the tracker's error")
    assert error.startswith(f"tracker igtl:127.0.0.1:{streamer.port}: TRANSFORM 'ProbeToTracker' is not a rigid pose: ")
    assert said in error
    with pytest.raises(BadTrackerData) as ended:  # ended, not paused: it does not come back
        tracker.paused  # noqa: B018
    assert str(ended.value) == error
    assert "\n" not in error
    assert len(tracker.poses_since(0.0)) >= 29  # what came before is kept
    tracker.disconnect()


def test_poses_that_compose_past_the_readers_bound_end_the_stream():
    """The probe at +9e11 mm and the reference at -9e11 mm are each a pose; composed, the probe
    lies 1.8e12 mm from the reference, which no session may hold: the stream ends there."""
    far = lambda x: make_transform(np.eye(3), [x, 0.0, 0.0])  # noqa: E731
    start = time.time()
    batches = ((k / RATE_HZ, [transform_message(far(9e11) if k >= 20 else probe_to_reference(k), start + k / RATE_HZ,
                                                "ProbeToTracker"),
                              transform_message(far(-9e11) if k >= 20 else np.eye(4), start + k / RATE_HZ,
                                                "ReferenceToTracker")])
               for k in range(40))
    with IgtlStreamer() as streamer:
        streamer.play_batches(batches)
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0)
        tracker.connect()
        error = wait_until(lambda: tracker.error, "the tracker's error")
    assert error == (f"tracker igtl:127.0.0.1:{streamer.port}: TRANSFORMs 'ProbeToTracker' and 'ReferenceToTracker' "
                     "compose to a pose no session may hold: a value past 1e+12")
    kept = tracker.poses_since(0.0)
    assert len(kept) >= 19 and all(rigidity_problem(pose) is None for pose in kept.tool_to_base)
    tracker.disconnect()


def test_a_flood_of_device_names_is_counted_within_a_bound():
    """A server that sends a new device name in every message: the tracker keeps a bounded number of
    them, and says what the server sends in a short line."""
    start = time.time()
    batches = ((k / RATE_HZ, [transform_message(np.eye(4), start + k / RATE_HZ, f"N{k:05d}x{j:03d}")
                              for j in range(200)])
               for k in range(50))
    with IgtlStreamer() as streamer:
        streamer.play_batches(batches)
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=1.0)
        with pytest.raises(TrackerError) as caught:
            tracker.connect()
    said = str(caught.value)
    assert "the server sends 'N00000x000', 'N00000x001', 'N00000x002', 'N00000x003', 'N00000x004' and at least " \
           f"{MAX_NAMES_SEEN - 5} more" in said, said
    assert len(said) < 300 and "\n" not in said


def test_a_huge_status_is_quoted_short():
    """A TransformStatus of 5 MB pauses the stream like any other, its reason one short line."""
    huge = "<b>" + "X" * (5 << 20)
    status = lambda k, device: huge if 10 <= k < 15 and device == "ProbeToTracker" else "OK"  # noqa: E731
    with IgtlStreamer() as streamer:
        streamer.play_batches(plus_batches(100, time.time(), status=status))
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0, dropout_s=5.0)
        tracker.connect()
        paused = wait_until(lambda: tracker.paused, "the tracker paused")
        assert paused == (f"tracker igtl:127.0.0.1:{streamer.port}: the tracker marks 'ProbeToTracker' "
                          f"{huge[:QUOTED_CHARS]!r}...")
        wait_until(lambda: len(tracker.poses_since(0.0)) == 95, "the poses after it")
        assert tracker.paused is None
        tracker.disconnect()


def test_a_flood_of_poses_ends_the_stream():
    start = time.time()
    flood = ((k / RATE_HZ, [transform_message(probe_to_reference(0), start + k / RATE_HZ + j * 1e-5, "StylusToRef")
                            for j in range(40)])
             for k in range(100))
    with IgtlStreamer() as streamer:
        streamer.play_batches(flood)
        tracker = IgtlTracker("127.0.0.1", streamer.port, parse_devices("StylusToRef"), first_pose_s=5.0)
        tracker.connect()
        error = wait_until(lambda: tracker.error, "the tracker's error")
    assert error.endswith(f"flooded: more than {MAX_RATE_HZ} poses of TRANSFORM 'StylusToRef' in a second, more "
                          "than any tracker sends")
    tracker.disconnect()


def test_timestamps_running_backwards_end_the_stream():
    start = time.time()
    stamp = lambda k: start + (k if k < 20 else k - 10) / RATE_HZ  # noqa: E731
    with IgtlStreamer() as streamer:
        streamer.play_batches(plus_batches(30, start, stamp=stamp))
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0)
        tracker.connect()
        error = wait_until(lambda: tracker.error, "the tracker's error")
    assert "timestamps run backwards: TRANSFORM 'ProbeToTracker' stamped" in error
    with pytest.raises(BadTrackerData):
        tracker.paused  # noqa: B018
    tracker.disconnect()


def test_a_marker_out_of_view_pauses_with_the_reason_and_resumes():
    gone = range(20, 60)
    status = lambda k, device: "MISSING" if k in gone and device == "ProbeToTracker" else "OK"  # noqa: E731
    with IgtlStreamer() as streamer:
        streamer.stall()
        streamer.play_batches(plus_batches(100, time.time(), status=status))
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0, dropout_s=5.0)
        streamer.resume()
        tracker.connect()
        paused = wait_until(lambda: tracker.paused, "the tracker paused")
        assert paused == f"tracker igtl:127.0.0.1:{streamer.port}: the tracker marks 'ProbeToTracker' MISSING"
        wait_until(lambda: len(tracker.poses_since(0.0)) == 60, "the poses after it came back")
        assert tracker.paused is None
        tracker.disconnect()


def test_a_silent_tracker_pauses_after_the_dropout():
    with IgtlStreamer() as streamer:
        streamer.play_batches(plus_batches(10, time.time()))
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=5.0, dropout_s=0.2)
        tracker.connect()
        paused = wait_until(lambda: tracker.paused, "the tracker paused")
        assert paused.startswith(f"tracker igtl:127.0.0.1:{streamer.port}: no pose for ")
        tracker.disconnect()


def test_parse_devices():
    assert parse_devices("ProbeToTracker,ReferenceToTracker") == PLUS
    assert parse_devices(" ProbeToReference ") == TrackerDevices("ProbeToReference", None)
    for bad in ("", "a,b,c", "a,a", "a,", "x" * 21):
        with pytest.raises(ValueError):
            parse_devices(bad)


def test_rigidity():
    pose = probe_to_reference(3)
    assert rigidity_problem(pose) is None
    assert rigidity_problem(invert_transform(pose)) is None
    assert rigidity_problem(np.full((4, 4), np.nan)) == "not a finite 4x4 matrix"
    assert rigidity_problem(pose - np.outer([0, 0, 0, 1], [0, 0, 0.5, 0])).startswith("its last row is")
    assert rigidity_problem(pose * np.array([1, 1, 1, 1e12])[:, None]) is not None
    # as a session's reader checks a pose: its determinant within 1e-3 of +1, every value within 1e12
    assert rigidity_problem(np.diag([1.0004, 1.0004, 1.0004, 1.0])) is not None
    assert rigidity_problem(make_transform(np.eye(3), [1e12, 0, 0])) is None
    assert rigidity_problem(make_transform(np.eye(3), [1.1e12, 0, 0])) == "a value past 1e+12"


def test_a_plus_recording_streamed_through_the_stand_in_records_what_its_import_holds(plus_data, tmp_path):
    """fCal 1.2's validation recording streamed as a PLUS server streams it and recorded live is the
    session its import is (the same frames, poses, phantom pose and PLUS settings), so it
    calibrates the same: benchmarks/bench_playback.py calibrates both."""
    from probecal.core.acquisition.igtlsource import IgtlSource
    from probecal.core.acquisition.igtlstreamer import recording_batches
    from probecal.core.acquisition.tracked import TrackedRecording, setup_from_device_set
    from probecal.core.io.plusimport import import_plus
    from probecal.core.io.sequence import read_sequence
    from probecal.core.io.session import load_session
    from tests.support.paths import FCAL_CONFIG, FCAL_VALIDATION

    sequence = read_sequence(FCAL_VALIDATION)
    with IgtlStreamer() as streamer:
        streamer.play_batches(recording_batches(sequence, time.time()), wait_for_client_s=60.0, clients=2)
        source = IgtlSource("127.0.0.1", streamer.port, transform_device=None)
        source.open()
        tracker = IgtlTracker("127.0.0.1", streamer.port, PLUS, first_pose_s=10.0, device_clock=True)
        try:
            tracker.connect()
            recording = TrackedRecording(tracker, source, tmp_path / "live", setup=setup_from_device_set(FCAL_CONFIG))
            outcome = recording.run(frames=len(sequence), timeout_s=10.0)
        finally:
            tracker.disconnect()
            source.close()
    assert outcome.error is None and not outcome.refusals and outcome.recorded == len(sequence)
    live, imported = load_session(tmp_path / "live"), import_plus(FCAL_VALIDATION, FCAL_CONFIG, tmp_path / "imported")
    assert np.allclose(live.manifest.phantom_to_base, imported.manifest.phantom_to_base)
    assert live.manifest.segmentation_hints == imported.manifest.segmentation_hints
    assert live.manifest.image_orientation_in_file is not None and live.manifest.source["kind"] == "tracked"
    offsets = [a.timestamp - b.timestamp for a, b in zip(live.records, imported.records)]
    assert np.ptp(offsets) < 1e-6  # the recording's own times, moved as one by the stand-in
    for i in range(len(imported)):
        assert np.array_equal(live.image(i), imported.image(i))
    assert np.allclose(live.poses(), imported.poses(), atol=2e-3)  # OpenIGTLink carries float32
    assert np.allclose(live.pose_stream()[1], imported.pose_stream()[1], atol=2e-3)
