"""``probecal sweep --tracker``, run as a user runs it: a tracked probe's recording from the freehand
twin and from a PLUS-server stand-in, and every bad tracker refused in one line with exit code 2,
leaving no session behind."""

from __future__ import annotations

import time

import numpy as np
import pytest

from probecal.core.acquisition.igtl import IMAGE_DEVICE, image_message, transform_message
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.io.session import load_session
from tests.support.cli import HANG_TIMEOUT_S, run_cli

POSE = np.array([[1.0, 0, 0, 10], [0, 1, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1]])


def test_a_continuous_recording_of_the_freehand_twin(tmp_path):
    out = tmp_path / "freehand"
    done = run_cli("sweep", "calibration", out, "--tracker", "sim", "--motion", "continuous", "--frames", "20")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"{out}: 20 frames recorded"
    session = load_session(out)
    assert len(session) == 20 and session.has_pose_stream
    assert session.manifest.source["kind"] == "tracked" and session.manifest.continuous
    assert session.manifest.phantom_to_base is None  # no registered pose: the calibration solves it
    assert all(r.pose_valid for r in session.records)


def batches(n: int, probe=lambda k: POSE, stamp=lambda k, start: start + k / 50, device="ProbeToTracker"):
    """A stand-in's stream: an IMAGE and the two devices per sample."""
    start = time.time()
    for k in range(n):
        t = stamp(k, start)
        yield k / 50, [image_message(np.zeros((40, 30), np.uint8), np.eye(4), t, IMAGE_DEVICE),
                       transform_message(probe(k), t, device, "OK"),
                       transform_message(np.eye(4), t, "ReferenceToTracker", "OK")]


@pytest.mark.parametrize(("stream", "said"), [
    (dict(device="PrbToTracker"), "no TRANSFORM 'ProbeToTracker' within 3 s; the server sends 'PrbToTracker'"),
    (dict(probe=lambda k: POSE * np.array([1, 1, 1, 1])[:, None] * (3 if k > 5 else 1)),
     "TRANSFORM 'ProbeToTracker' is not a rigid pose: its rotation is not a rotation"),
    (dict(stamp=lambda k, start: start + (k if k < 10 else k - 8) / 50), "timestamps run backwards"),
])
def test_a_bad_tracker_exits_2_in_one_line(tmp_path, stream, said):
    out = tmp_path / "tracked"
    with IgtlStreamer() as streamer:
        streamer.play_batches(batches(400, **stream), wait_for_client_s=HANG_TIMEOUT_S, clients=2)
        done = run_cli("sweep", "calibration", out, "--tracker", f"igtl:127.0.0.1:{streamer.port}", "--motion",
                       "continuous", "--phantom", "fcal-2.0", "--spacing", "0.1", timeout_s=HANG_TIMEOUT_S)
    assert done.returncode == 2, done.stderr
    line = done.stderr.strip()
    assert "\n" not in line and "Traceback" not in line
    assert line.startswith("probecal: error: ") and said in line, line
    if out.exists():  # what was recorded before the tracker went wrong is kept, a session that loads
        assert f"frames kept in {out}" in line and len(load_session(out)) > 0


def test_a_tracker_that_never_sends_exits_2(tmp_path):
    with IgtlStreamer() as streamer:
        done = run_cli("sweep", "calibration", tmp_path / "t", "--tracker", f"igtl:127.0.0.1:{streamer.port}",
                       "--phantom", "fcal-2.0", timeout_s=HANG_TIMEOUT_S)
    assert done.returncode == 2
    assert done.stderr.strip().endswith("no TRANSFORM 'ProbeToTracker' or 'ReferenceToTracker' within 3 s")


@pytest.mark.parametrize(("args", "said"), [
    (("--tracker", "igtl:nowhere"), "--tracker 'igtl:nowhere': expected sim or igtl:HOST:PORT"),
    (("--tracker", "sim", "--robot", "sim"), "--robot and --resume are a robot's"),
    (("--tracker-devices", "a,b,c"), "expected PROBE or PROBE,REFERENCE device names"),
    (("--motion", "guided"), "give --tracker"),
])
def test_tracked_options_refused_in_one_line(tmp_path, args, said):
    done = run_cli("sweep", "calibration", tmp_path / "t", *args, timeout_s=HANG_TIMEOUT_S)
    assert done.returncode == 2
    assert said in done.stderr and done.stderr.count("\n") == 1
