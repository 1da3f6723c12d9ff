"""The console's job runner: long work (a sweep, a calibration, a reconstruction) runs in one
background thread at a time, so the page and Stop stay live; a second request while one runs is
refused, and whatever a job raises is reported, never lost and never fatal to the console."""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable

from probecal.core.acquisition.imagesource import ImageSourceError
from probecal.core.acquisition.tracker import TrackerError
from probecal.core.errors import InputError, Interrupted
from probecal.core.robot.contract import RobotError

EXPECTED = (InputError, RobotError, ImageSourceError, TrackerError, ValueError, OSError)
"""What a job may fail with in the normal run of things: reported by its message alone."""


class JobRunner:
    """Runs one job at a time. ``on_busy(name of the running job)`` hears of a refused request,
    ``on_failure(job name, message)`` of a job that raised, ``on_success(job name, when it
    started (time.monotonic))`` of one that did not, ``on_stopped(job name)`` of one that Stop
    ended (it raised Interrupted). ``stop_requested`` is set by Stop and cleared when a job starts."""

    def __init__(self, on_busy: Callable[[str], None], on_failure: Callable[[str, str], None],
                 on_success: Callable[[str, float], None] | None = None,
                 on_stopped: Callable[[str], None] | None = None):
        self.on_busy, self.on_failure, self.on_success = on_busy, on_failure, on_success
        self.on_stopped = on_stopped
        self.started = 0  # jobs started so far
        self.stop_requested = threading.Event()
        self.interrupted = threading.Event()  # the running job ended at Stop's request
        self._job: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def busy(self) -> bool:
        return self._job is not None and self._job.is_alive()

    def start(self, name: str, work: Callable[[], None]) -> bool:
        """Run ``work`` in the background unless a job is running (then refuse, and say so)."""
        with self._lock:
            if self._job is not None and self._job.is_alive():
                self.on_busy(self._job.name)
                return False
            self.stop_requested.clear()
            self.interrupted.clear()
            job = threading.Thread(target=self._run, args=(name, work), name=name, daemon=True)
            job.start()
            self._job = job  # started: a waiting thread may join it
            self.started += 1
            return True

    @property
    def current(self) -> str | None:
        """The running job's name (None when none runs)."""
        job = self._job
        return job.name if job is not None and job.is_alive() else None

    def _run(self, name: str, work: Callable[[], None]) -> None:
        started = time.monotonic()
        try:
            work()
            if self.on_success is not None:
                self.on_success(name, started)
        except Interrupted:
            self.interrupted.set()
            if self.on_stopped is not None:
                self.on_stopped(name)
        except EXPECTED as exc:
            self.on_failure(name, str(exc))
        except Exception as exc:  # the console must survive anything a job throws
            traceback.print_exc()  # a bug: its whole story goes to the log, for a report
            self.on_failure(name, f"{type(exc).__name__}: {exc}")

    def check_stop(self) -> None:
        """Raise Interrupted once Stop was asked for: long work calls it at each step (its
        progress), so that Stop ends it there."""
        if self.stop_requested.is_set():
            raise Interrupted()

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the running job (for scripts and tests)."""
        job = self._job
        if job is not None:
            job.join(timeout)
