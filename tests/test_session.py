"""Sessions survive a crash and refuse corruption with a clear message."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from probecal.core.errors import InputError
from probecal.core.geometry.probe import LinearProbe
from probecal.core.io.manifest import Manifest
from probecal.core.io.phantomfile import default_phantom
from probecal.core.io.session import MAX_REFUSALS_LOGGED, REFUSAL_CHARS, REFUSED, SessionWriter, load_session
from tests.support.paths import ROOT

WRITER = """
import sys, numpy as np
from core.io.manifest import Manifest
from core.io.session import SessionWriter
from core.geometry.probe import LinearProbe
rng = np.random.default_rng(0)
with SessionWriter(sys.argv[1], Manifest(kind="calibration"), probe=LinearProbe()) as w:
    i = 0
    while True:
        pose = np.eye(4); pose[0, 3] = i
        w.append(rng.integers(0, 255, (500, 384), dtype=np.uint8), pose, timestamp=float(i))
        print(i, flush=True)
        i += 1
"""


def write_frames(path, n):
    with SessionWriter(path, Manifest(kind="calibration"), default_phantom(), LinearProbe()) as w:
        for i in range(n):
            pose = np.eye(4)
            pose[:3, 3] = [i, 2 * i, 3 * i]
            w.append(np.full((50, 40), i, np.uint8), pose, timestamp=i * 0.1, pose_timestamp=i * 0.1 + 0.01)
    return load_session(path)


def test_round_trip(tmp_path):
    s = write_frames(tmp_path / "s", 5)
    assert len(s) == 5 and s.phantom.n_wires == 12 and s.probe == LinearProbe()
    assert np.array_equal(s.image(3), np.full((50, 40), 3, np.uint8))
    assert np.allclose(s.poses()[4][:3, 3], [4, 8, 12])
    assert s.records[2].timestamp == pytest.approx(0.2) and s.records[2].pose_timestamp == pytest.approx(0.21)


def test_no_pose_recorded_as_missing(tmp_path):
    with SessionWriter(tmp_path / "s", Manifest(kind="imported")) as w:
        w.append(np.zeros((4, 4), np.uint8), None)
    s = load_session(tmp_path / "s")
    assert [r.pose_valid for r in s.records] == [False]
    assert np.isnan(s.poses()).all()


def test_the_refused_frames_log_is_bounded(tmp_path):
    """A source refused at every frame, with a long reason each time, cannot fill the disk: the
    log keeps the first MAX_REFUSALS_LOGGED refusals, each reason cut to REFUSAL_CHARS."""
    with SessionWriter(tmp_path / "s", Manifest(kind="calibration")) as w:
        for k in range(MAX_REFUSALS_LOGGED + 5):
            w.refuse({"source_index": k, "timestamp": None, "reason": "x" * 100_000})
    lines = (tmp_path / "s" / REFUSED).read_text().splitlines()
    assert len(lines) == MAX_REFUSALS_LOGGED
    assert json.loads(lines[-1]) == {"source_index": MAX_REFUSALS_LOGGED - 1, "timestamp": None,
                                     "reason": "x" * REFUSAL_CHARS}


def test_resume_appends_to_the_same_session(tmp_path):
    write_frames(tmp_path / "s", 3)
    with SessionWriter(tmp_path / "s", Manifest(), resume=True) as w:
        assert w.append(np.zeros((50, 40), np.uint8), np.eye(4)) == 3
    assert len(load_session(tmp_path / "s")) == 4


def test_torn_last_record_is_ignored(tmp_path):
    write_frames(tmp_path / "s", 4)
    with open(tmp_path / "s" / "records.jsonl", "ab") as f:
        f.write(b'{"index": 4, "image": "frames/0000')
    assert len(load_session(tmp_path / "s")) == 4


def test_missing_frame_is_refused(tmp_path):
    write_frames(tmp_path / "s", 4)
    (tmp_path / "s" / "frames" / "000002.png").unlink()
    with pytest.raises(InputError, match="frame 2 is missing"):
        load_session(tmp_path / "s")


def test_corrupt_record_in_the_middle_is_refused(tmp_path):
    write_frames(tmp_path / "s", 4)
    lines = (tmp_path / "s" / "records.jsonl").read_bytes().split(b"\n")
    lines[1] = b"{garbage"
    (tmp_path / "s" / "records.jsonl").write_bytes(b"\n".join(lines))
    with pytest.raises(InputError, match="line 2: corrupt record"):
        load_session(tmp_path / "s")


def test_killed_writer_leaves_a_loadable_session(tmp_path):
    """SIGKILL a writer at several moments: each time everything it reported is on disk."""
    for attempt in range(3):
        path = tmp_path / f"s{attempt}"
        proc = subprocess.Popen(
            [sys.executable, "-c", WRITER, str(path)], cwd=ROOT, stdout=subprocess.PIPE, text=True
        )
        reported = -1
        deadline = time.monotonic() + 30
        while reported < 5 + 7 * attempt and time.monotonic() < deadline:
            reported = int(proc.stdout.readline())
        time.sleep(0.013 * attempt)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        session = load_session(path)
        assert len(session) >= reported + 1
        for i in (0, len(session) - 1):
            assert session.image(i).shape == (500, 384)
            assert session.records[i].tool_to_base[0, 3] == i


def _stream(n: int, start: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    times = start + np.arange(n) * 0.008
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = np.arange(n) * 0.5
    return times, poses


def test_a_kept_pose_stream_round_trips_in_batches_and_a_torn_line_is_ignored(tmp_path):
    session = write_frames(tmp_path / "s", 2)
    assert session.pose_stream() is None
    with SessionWriter(tmp_path / "s", Manifest(), resume=True) as w:
        w.append_poses(*_stream(5))
        w.append_poses(*_stream(3, start=1.0))
    times, poses = load_session(tmp_path / "s").pose_stream()
    assert np.allclose(times, np.r_[_stream(5)[0], _stream(3, 1.0)[0]])
    assert np.allclose(poses[:5], _stream(5)[1]) and poses.shape == (8, 4, 4)
    with open(tmp_path / "s" / "posestream.jsonl", "ab") as f:
        f.write(b"[2.0, 1, 0")  # a write cut short
    assert len(load_session(tmp_path / "s").pose_stream()[0]) == 8


@pytest.mark.parametrize("line, problem", [
    (b"[1.0, 1, 0, 0]\n", "line 6 must be a list of 13 finite numbers"),
    (b"[0.001, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]\n", "line 6: timestamp"),
    (b"[9.0, 2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]\n", "line 6: the pose is not a rigid transform"),
    (b"not json\n", "line 6: corrupt pose sample"),
])
def test_a_corrupt_pose_stream_is_refused_naming_the_line(tmp_path, line, problem):
    write_frames(tmp_path / "s", 1)
    with SessionWriter(tmp_path / "s", Manifest(), resume=True) as w:
        w.append_poses(*_stream(5))
    with open(tmp_path / "s" / "posestream.jsonl", "ab") as f:
        f.write(line)
    with pytest.raises(InputError, match="posestream.jsonl") as error:
        load_session(tmp_path / "s").pose_stream()
    assert problem in str(error.value)
