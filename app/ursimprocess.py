"""URSim (``probecal ursim``) in a child process, for clients such as ur_rtde that cannot share a
process with it: how the tests and benchmarks of the real robot path start their controller."""

from __future__ import annotations

import selectors
import subprocess
import sys
import tempfile

from probecal.core.robot.ursim import DEFAULT_HOST


class URSimProcess:
    """URSim in a child process (``python -m probecal.app.ursim``), for clients such as ur_rtde
    that cannot share a process with it. ``stop`` kills it (SIGKILL): every socket drops at once."""

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        *,
        time_scale: float = 1.0,
        seed: int = 0,
        repeatability_mm: float = 0.03,
        arm_calibration_seed: int | None = None,
        fault: str | None = None,
        ready_timeout_s: float = 30.0,
    ):
        self.host = host
        self._args = ["--host", host, "--time-scale", repr(time_scale), "--seed", str(seed)]
        self._args += ["--repeatability-mm", repr(repeatability_mm)]
        self._args += [] if arm_calibration_seed is None else ["--arm-calibration-seed", str(arm_calibration_seed)]
        self._args += ["--fault", fault] if fault else []
        self._ready_timeout_s = ready_timeout_s
        self._process: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()

    def __enter__(self) -> URSimProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def start(self) -> URSimProcess:
        """Start the child and wait until it listens; RuntimeError if it does not."""
        self._process = process = subprocess.Popen(
            [sys.executable, "-m", "probecal.app.ursim", *self._args],
            stdout=subprocess.PIPE,
            stderr=self._log,
            stdin=subprocess.DEVNULL,
        )
        assert process.stdout is not None  # stdout=PIPE
        with selectors.DefaultSelector() as selector:
            selector.register(process.stdout, selectors.EVENT_READ)
            ready = selector.select(self._ready_timeout_s)
        line = process.stdout.readline().decode() if ready else ""
        if not line.startswith("URSim"):
            self.stop()
            raise RuntimeError(f"URSim on {self.host} did not start: {self.log().strip()[-500:]}")
        return self

    def stop(self) -> None:
        """Kill the child at once (SIGKILL) and reap it."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
        if self._process is not None and self._process.stdout is not None:
            self._process.wait()
            self._process.stdout.close()

    def log(self) -> str:
        """Everything the child wrote to stderr: its text messages and errors."""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")
