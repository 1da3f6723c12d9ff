"""Shared fixtures: paths to the real PLUS data and the probecal entry point."""

from __future__ import annotations

import faulthandler
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest

from probecal.core.io.plusdata import missing_reason, plus_data_dir

ROOT = Path(__file__).resolve().parent.parent
PLUS = plus_data_dir()
FCAL_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
FCAL_CALIBRATION = PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha"
FCAL_VALIDATION = PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha"
FCAL_RESULTS = PLUS / "TestImages" / "FreehandCalibration3NWires.results.xml"
VLCUS_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber.xml"
PROBECAL = Path(sys.executable).parent / "probecal"
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID")  # the same in every worker of one parallel run
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
_LOOPBACK_BASE = ((random.Random(_RUN) if _RUN else random.SystemRandom()).randrange(16, 200) + _WORKER) % 256
"""This test run's own 127.B.0.0/16 (each of a parallel run's workers its own B)."""
HUNG_TEST_S = 1200.0
"""A test still running after this long (beyond every test's own timeout) is hung: its threads'
stacks are dumped and the run ends."""


@pytest.fixture(scope="module")
def browser():
    """Headless Debian Chromium for a module's browser tests (skipped where it is not installed)."""
    from support.headless import CHROMIUM, chromium

    if not CHROMIUM.is_file():
        pytest.skip("Debian chromium is not installed")
    with chromium() as browser:
        yield browser


@pytest.fixture(scope="session")
def terminal_stderr(pytestconfig):
    """The run's own stderr, which pytest's output capture does not swallow."""
    capture = pytestconfig.pluginmanager.getplugin("capturemanager")
    with capture.global_and_fixture_disabled():
        fd = os.dup(2)
    with os.fdopen(fd, "w") as stream:
        yield stream


@pytest.fixture(autouse=True)
def end_a_hung_run(terminal_stderr):
    """pytest-timeout's alarm is Python code, which never runs while a C call (ur_rtde's, which
    keeps the GIL while it waits on the network) holds the interpreter; faulthandler's watchdog is
    a C thread, so a hang there ends the run with every thread's stack instead of stalling it."""
    faulthandler.dump_traceback_later(HUNG_TEST_S, exit=True, file=terminal_stderr)
    yield
    faulthandler.cancel_dump_traceback_later()


def loopback(group: int, n: int) -> str:
    """A loopback address of this test run's own, 127.B.group.n: simulated controllers bind
    ur_rtde's fixed ports on it, so two test runs on one machine never meet."""
    return f"127.{_LOOPBACK_BASE}.{group}.{n}"


@pytest.fixture(scope="session")
def plus_data() -> Path:
    reason = missing_reason()
    if reason is not None:
        pytest.skip(reason)
    return PLUS


CLI_TIMEOUT_S = 300.0
HANG_TIMEOUT_S = 60.0
"""How long a command tested not to hang (on a FIFO, an address that does not answer) may take."""


def run_cli(*args, cwd: Path | None = None, timeout_s: float = CLI_TIMEOUT_S) -> subprocess.CompletedProcess:
    """Run the installed ``probecal`` entry point the way a user would. One that hangs is ended
    after ``timeout_s`` (shorter where a hang is what is tested, so that it fails fast) with
    SIGABRT, on which Python's faulthandler prints where every thread stood; the AssertionError
    carries it. A test ended otherwise (pytest's own timeout) takes the process with it."""
    process = subprocess.Popen([str(PROBECAL), *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, cwd=cwd, env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    with process:
        try:
            stdout, stderr = process.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGABRT)
            stdout, stderr = process.communicate()
            raise AssertionError(f"probecal {' '.join(map(str, args))} hung for {timeout_s:g} s; its threads:\n"
                                 f"{stderr[-6000:]}")
        except BaseException:
            process.kill()
            raise
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """Exit code 2, a single stderr line without a traceback, naming what went wrong."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


T = TypeVar("T")


def assert_refused(load: Callable[[], object], file: Path, *fragments: str) -> str:
    """``load()`` raises InputError with one short line that names ``file`` and holds every
    fragment; returns the message."""
    from probecal.core.errors import InputError

    with pytest.raises(InputError) as caught:
        load()
    message = str(caught.value)
    assert "\n" not in message and str(file) in message, message
    assert len(message) < 400 + len(str(file)), message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


def wait_until(condition: Callable[[], T], what: str = "the awaited state", timeout_s: float = 60.0,
               poll_s: float = 0.005) -> T:
    """Poll ``condition`` until it returns something true and return that; an AssertionError naming
    ``what`` after ``timeout_s`` (a guard against hanging, not a speed target)."""
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:g} s")
        time.sleep(poll_s)
    return value


def assert_still(robot, pose, since: float, for_s: float = 0.3) -> None:
    """The robot's own pose stream shows it at ``pose`` (4x4 mm) for ``for_s`` of controller time
    after ``since`` (s)."""
    stream = wait_until(lambda: (s := robot.poses_since(since)) and s.timestamps[-1] - since >= for_s and s,
                        f"{for_s} s of the robot's pose stream")
    assert np.allclose(stream.tool_to_base, pose, atol=1e-3)


def recorded_frames(session: Path) -> int:
    """Frames whose records are complete in a session folder being written."""
    records = session / "records.jsonl"
    return records.read_bytes().count(b"\n") if records.is_file() else 0


def wait_for_frames(session: Path, count: int, timeout_s: float = 60.0) -> None:
    wait_until(lambda: recorded_frames(session) >= count, f"{count} frames in {session}", timeout_s)


def wait_for_new_session(sessions_dir: Path, kind: str, before: set[Path], timeout_s: float = 60.0) -> Path:
    """The session folder of ``kind`` that appears in ``sessions_dir`` beside those ``before``."""
    return wait_until(lambda: next(iter(set(sessions_dir.glob(f"{kind}-*")) - before), None),
                      f"a new {kind} session in {sessions_dir}", timeout_s)
