"""Hostile OpenIGTLink peers (``support.peers``), found by the fuzzing harness: a sweep recording
from one ends in one line that names what the peer did, keeps what it recorded whole, and takes
no more memory than the limit allows."""

from __future__ import annotations

import re

import pytest

from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.imagesource import ImageSourceError
from probecal.core.io.session import load_session
from tests.support.cli import run_cli
from tests.support.peers import start_peer

SWEEP = ("--poses", "3", "--time-scale", "0.05")


def _sweep(tmp_path, kind: str, *more: str):
    port = start_peer(kind)
    result = run_cli("sweep", "calibration", tmp_path / "sw", *SWEEP, "--image", f"igtl:127.0.0.1:{port}", *more)
    lines = result.stderr.strip().splitlines()
    assert "Traceback" not in result.stderr and "Warning" not in result.stderr, result.stderr
    return result, lines[-1] if lines else ""


def test_a_body_past_the_memory_limit_is_refused_before_it_is_read(monkeypatch):
    """A 200 MB IMAGE body sent in full: refused from its header, none of it held."""
    monkeypatch.setenv("PROBECAL_MAX_MEMORY_MB", "100")
    with IgtlSource("127.0.0.1", start_peer("huge body")) as source, \
            pytest.raises(ImageSourceError, match="'IMAGE' message of 209715200 bytes would need 600.0 MB, more "
                                                  "than the limit of 100.0 MB"):
        source.latest(10.0)


@pytest.mark.parametrize("kind", ["spacing inf", "spacing 1e+300"])
def test_a_spacing_past_float32_is_refused_without_a_warning(tmp_path, kind):
    result, line = _sweep(tmp_path, kind)
    assert result.returncode == 2 and "states a pixel spacing of inf x inf mm" in line


def test_a_stream_faster_than_the_sweep_ends_it_naming_the_rate(tmp_path):
    """A peer that sends as fast as it can (how fast depends on the machine): the continuous sweep
    ends in one line, named a flood past 1000 frames/s or a reader that fell behind the stream's
    rate below that, and not with a --resume that cannot work."""
    result, line = _sweep(tmp_path, "flood", "--motion", "continuous")
    assert result.returncode == 1, line
    assert re.search(r"flooded|fell behind the stream \(\d+ frames/s\)", line), line
    assert "a continuous sweep is not resumed: record a new one" in line


@pytest.mark.parametrize("kind, motion, said", [
    ("epoch timestamps", (), "s before the robot settled"),
    ("future timestamps", (), "s ahead of this computer's clock"),
    ("epoch timestamps", ("--motion", "continuous"), "none of the"),
])
def test_frames_stamped_by_another_clock_are_named_so(tmp_path, kind, motion, said):
    """A scanner whose clock is not this computer's: every frame stamped out of reach of the
    robot's poses. The sweep says so, not "stream stalled" (the frames keep coming) nor "done"."""
    result, line = _sweep(tmp_path, kind, *motion)
    assert result.returncode == 1, line
    assert said in line and "the scanner's clock is not this computer's, or the image latency is wrong" in line
    assert "stalled" not in line


@pytest.mark.parametrize("kind", ["huge poses", "nan poses"])
def test_tracker_poses_a_reader_would_refuse_are_not_recorded(tmp_path, kind):
    """A peer's ProbeToReference of 1e30 mm (or NaN) pairs as no pose: the robot's is recorded, and
    the session reads back."""
    result, _ = _sweep(tmp_path, kind)
    assert result.returncode == 0, result.stderr
    session = load_session(tmp_path / "sw")
    assert len(session) == 3 and abs(session.poses()).max() < 1e4
