"""Hostile trackers (``tests.support.peers.TRACKERS``: PLUS servers that send valid poses, then one
thing wrong) against ``probecal sweep --tracker``, guided and continuous, and against the
console's guided mode. A pose no session may hold ends the recording in one line, with exit code 2,
keeping the frames recorded before it in a session that reads back and that ``calibrate`` refuses
for nothing but its frames; floods and huge statuses neither end it nor make it say much; frames
too small to guide are refused before any session is made."""

from __future__ import annotations

from pathlib import Path

import pytest

from probecal.app.console.server import launch
from probecal.app.tracked import TrackedSpec
from probecal.core.io.session import load_session
from tests.support.cli import HANG_TIMEOUT_S, run_cli
from tests.support.peers import SMALL_SPACING_MM, TRACKER_SPACING_MM, start_tracker
from tests.support.refusals import assert_one_line_error

PHANTOM = "thesis-4layer"


def tracked_sweep(out: Path, kind: str, motion: str, spacing: float = TRACKER_SPACING_MM):
    """``probecal sweep calibration OUT`` from the hostile tracker ``kind`` (its images too);
    continuous, 60 frames at most."""
    port = start_tracker(kind)
    frames = ("--frames", "60") if motion == "continuous" else ()
    return run_cli("sweep", "calibration", out, "--tracker", f"igtl:127.0.0.1:{port}", "--motion", motion,
                   "--phantom", PHANTOM, "--spacing", str(spacing), *frames, timeout_s=HANG_TIMEOUT_S)


def assert_kept(out: Path, at_least: int = 10) -> None:
    """The session a sweep kept reads back whole (by default with the frames of most of the second
    before the tracker went wrong): every frame, every pose and the pose stream, which reaches the
    last frame's time."""
    session = load_session(out)
    assert len(session) >= at_least
    for i in range(len(session)):
        session.image(i)
    stream = session.pose_stream()
    if len(session):
        assert stream is not None and stream[0][-1] >= session.records[-1].pose_timestamp


BAD_POSES = [
    ("nan pose", "TRANSFORM 'ProbeToTracker' is not a rigid pose: not a finite 4x4 matrix"),
    ("mirrored pose", "TRANSFORM 'ProbeToTracker' is not a rigid pose: its rotation is not a rotation (columns 1, 1, "
                      "1 long, determinant -1)"),
    ("huge pose", "TRANSFORM 'ProbeToTracker' is not a rigid pose: a value past 1e+12"),
    ("timestamps backwards", "timestamps run backwards: TRANSFORM 'ProbeToTracker' stamped"),
    ("composed huge", "TRANSFORMs 'ProbeToTracker' and 'ReferenceToTracker' compose to a pose no session may hold: a "
                      "value past 1e+12"),
    ("pose flood", "flooded: more than 1000 poses of TRANSFORM 'ProbeToTracker' in a second"),
]


@pytest.mark.parametrize(("kind", "said"), BAD_POSES)
def test_one_bad_pose_ends_a_guided_sweep_in_one_line_keeping_what_came_before(tmp_path, kind, said):
    out = tmp_path / "sw"
    done = tracked_sweep(out, kind, "guided")
    assert_one_line_error(done, "probecal: error: tracker igtl:127.0.0.1:", said, f"every frame kept is in {out}")
    assert_kept(out)


@pytest.mark.parametrize("motion", ["guided", "continuous"])
def test_composed_poses_past_the_readers_bound_end_the_sweep_and_calibrate_takes_what_it_kept(tmp_path, motion):
    """The probe at +9e11 mm and the reference at -9e11 mm compose to 1.8e12 mm: the sweep ends
    there, and calibrate reads the session it kept (its frames are blank: it finds no wires)."""
    out = tmp_path / "sw"
    done = tracked_sweep(out, "composed huge", motion)
    assert_one_line_error(done, "compose to a pose no session may hold", str(out))
    assert_kept(out)
    calibrated = run_cli("calibrate", out, timeout_s=HANG_TIMEOUT_S)
    # a guided sweep ended during its latency motion holds nothing but that motion's frames
    assert_one_line_error(calibrated, f"{out}: " + ("no usable frame among" if motion == "continuous" else
                                                    "no latency measured"))


@pytest.mark.parametrize("kind", ["device names flood", "huge status"])
def test_floods_and_huge_statuses_do_not_end_a_guided_sweep_nor_fill_its_line(tmp_path, kind):
    """The sweep runs until the server closes (exit 1, as a stream that ends), saying so in one
    short line, and keeps what it recorded."""
    out = tmp_path / "sw"
    done = tracked_sweep(out, kind, "guided")
    assert done.returncode == 1, done.stderr
    line = done.stderr.strip()
    assert line.startswith("probecal: sweep ended early (") and "connection closed by the server" in line, line
    assert "\n" not in line and len(line) < 500, line[:1000]
    assert_kept(out)


def test_a_huge_status_in_a_continuous_sweep_is_logged_short(tmp_path):
    out = tmp_path / "sw"
    done = tracked_sweep(out, "huge status", "continuous")
    assert done.returncode == 0, done.stderr
    assert len(done.stdout) < 500 and not done.stderr
    assert_kept(out)
    refused = out / "refused.jsonl"
    assert not refused.exists() or max(map(len, refused.read_text().splitlines())) < 1000


def test_frames_too_small_to_guide_are_refused_before_a_session_is_made(tmp_path):
    """64 x 48 px at 0.1 mm cannot show every wire of the phantom at any guided pose: refused in one
    line naming the frames' size, and nothing is written."""
    done = tracked_sweep(tmp_path / "sw", "small frames", "guided", spacing=SMALL_SPACING_MM)
    assert_one_line_error(done, "frames of 64 x 48 px (6.4 x 4.8 mm) are too small to guide over the phantom: only 0 "
                                "of 16 targets keep every wire in view")
    assert not list(tmp_path.iterdir())


def test_the_console_ends_a_guided_acquisition_on_a_bad_pose_and_says_why(tmp_path):
    """The console's guided mode ends at the NaN pose, says why in its status line, keeps the
    session, and takes the next job."""
    port = start_tracker("nan pose", bad_at=150)  # 5 s after Connect: the acquisition is running by then
    spec = TrackedSpec(f"igtl:127.0.0.1:{port}", phantom=PHANTOM, spacing_mm=(TRACKER_SPACING_MM,) * 2)
    console = launch(port=0, sessions_dir=tmp_path, tracked=spec)
    try:
        assert console.connect()
        console.wait(60)
        assert "Connected to tracker" in console.panel.status.text, console.panel.status.text
        assert console.start_sweep()
        console.wait(60)
        status = console.panel.status.text
        assert status.startswith(f"Guided acquisition failed: tracker igtl:127.0.0.1:{port}: TRANSFORM "
                                 "'ProbeToTracker' is not a rigid pose: not a finite 4x4 matrix."), status
        assert "\n" not in status
        session = Path(console.panel.session_path.value)
        assert f"frames kept in {session}" in status
        assert_kept(session, at_least=0)
        assert not console.busy
    finally:
        console.close()


def test_the_console_refuses_frames_too_small_to_guide_in_one_line(tmp_path):
    port = start_tracker("small frames")
    spec = TrackedSpec(f"igtl:127.0.0.1:{port}", phantom=PHANTOM, spacing_mm=(SMALL_SPACING_MM,) * 2)
    console = launch(port=0, sessions_dir=tmp_path, tracked=spec)
    try:
        assert console.connect()
        console.wait(60)
        assert console.start_sweep()
        console.wait(60)
        assert console.panel.status.text == (f"Start sweep failed: igtl:127.0.0.1:{port}: frames of 64 x 48 px (6.4 x "
                                             "4.8 mm) are too small to guide over the phantom: only 0 of 16 targets "
                                             "keep every wire in view")
        assert not list(tmp_path.iterdir()) and not console.busy
        assert console.panel.session_path.value == ""  # no folder named that was not made
    finally:
        console.close()
