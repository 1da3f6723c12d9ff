"""The simulate commands and the console, run the way a user runs them."""

import json
import signal
import socket
import subprocess
import time
import urllib.request

import pytest

from probecal.core.io.session import load_session
from tests.support.cli import PROBECAL, run_cli
from tests.support.refusals import assert_one_line_error
from tests.support.waiting import recorded_frames, wait_until


def test_simulate_calibration_command(tmp_path):
    out = tmp_path / "cal"
    result = run_cli("simulate", "calibration", out, "--poses", "8", "--seed", "4", "--noise", "none")
    assert result.returncode == 0, result.stderr
    assert "8 frames" in result.stdout and "estimated UR3 time" in result.stdout
    session = load_session(out)
    assert len(session) == 8 and session.manifest.source["seed"] == 4
    truth = json.loads((out / "truth.json").read_text())
    assert len(truth["frames"]) == 8


def test_simulate_calibration_at_another_image_size(tmp_path):
    """A scanner that resamples its frames finer: the same probe (38.4 x 50 mm) in more pixels,
    dots as wide in mm, so many more pixels wide."""
    result = run_cli("simulate", "calibration", tmp_path / "fine", "--poses", "3", "--image-size", "1000", "800")
    assert result.returncode == 0, result.stderr
    session = load_session(tmp_path / "fine")
    assert session.image(0).shape == (800, 1000)
    assert session.pixel_spacing_mm == (0.0384, 0.0625)


def test_simulate_calibration_with_a_plus_phantom(plus_data, tmp_path):
    from tests.support.paths import FCAL_CONFIG

    result = run_cli("simulate", "calibration", tmp_path / "f", "--poses", "5", "--phantom", FCAL_CONFIG)
    assert result.returncode == 0, result.stderr
    assert load_session(tmp_path / "f").phantom.n_wires == 9


def test_simulate_volume_command(tmp_path):
    out = tmp_path / "vol"
    result = run_cli("simulate", "volume", out, "--seed", "1", "--frames-per-pass", "12")
    assert result.returncode == 0, result.stderr
    assert (out / "test_object.stl").is_file() and (out / "truth.json").is_file()
    assert "passes" in result.stdout and len(load_session(out)) == 5 * 12


def test_simulate_bad_arguments(tmp_path):
    assert_one_line_error(run_cli("simulate", "calibration", tmp_path / "x", "--noise", "loud"), "--noise")
    assert_one_line_error(run_cli("simulate", "calibration", tmp_path / "x", "--seed", "-3"), "--seed")
    assert_one_line_error(run_cli("simulate", "calibration", tmp_path / "x", "--phantom", tmp_path / "none.json"),
                          "none.json", "file not found")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("args, fragment", [
    (("calibration", "--motion", "continuous", "--frame-rate", "1e9"), "--frame-rate: 1e9 is not within 0.1 to 1000"),
    (("calibration", "--motion", "continuous", "--image-latency", "1e9"), "--image-latency: 1e9 is not within"),
    (("volume", "--motion", "continuous", "--speed", "1e-9"), "--speed: 1e-9 is not within 0.1 to 1000 mm/s"),
    (("volume", "--motion", "continuous", "--speed", "0.1", "--frame-rate", "100"), "at most 100000 frames and 3600 s"),
])
def test_simulate_refuses_a_sweep_too_long_before_writing(tmp_path, args, fragment):
    """A continuous sweep's frames and pose stream are bounded before they are laid out (1e9
    frames/s asked for 38 GiB): each option within what a scanner and a robot can have, and the
    sweep they make together at most 100000 frames and an hour; nothing is left, so a rerun is
    not told the folder exists."""
    out = tmp_path / "o"
    assert_one_line_error(run_cli("simulate", args[0], out, *args[1:]), fragment)
    assert list(tmp_path.iterdir()) == []


def test_an_interrupted_simulation_leaves_nothing(tmp_path):
    """The session is built beside its folder and renamed into place only when whole."""
    # A shell starts background jobs with SIGINT ignored, and a child inherits that: give it
    # Ctrl-C's default, as a terminal would, however the suite was started.
    process = subprocess.Popen([str(PROBECAL), "simulate", "volume", tmp_path / "o", "--frames-per-pass", "400"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        wait_until(lambda: any(recorded_frames(p) for p in tmp_path.glob(".o.*")), "frames in the staged session")
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130 and "interrupted" in stderr, (process.returncode, stderr)
    assert list(tmp_path.iterdir()) == []


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_starts_the_console_on_loopback():
    port = free_port()
    proc = subprocess.Popen([str(PROBECAL), "serve", "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        page = None
        while time.monotonic() < deadline and page is None:
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2).read()
            except OSError:
                time.sleep(0.5)
        assert page is not None and b"<html" in page.lower()
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.mark.slow
def test_serve_refuses_bad_backends():
    assert_one_line_error(run_cli("serve", "--robot", "kuka:10.0.0.5"), "--robot", "sim or ur:HOST")
    assert_one_line_error(run_cli("serve", "--image", "webcam"), "webcam")
