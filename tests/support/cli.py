"""Running the installed ``probecal`` entry point the way a user would, with a guard against hangs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

PROBECAL = Path(sys.executable).parent / "probecal"
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
