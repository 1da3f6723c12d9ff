"""Progress on stderr: a live bar on a terminal, a few plain lines otherwise (logs, CI).

Work that finishes within ``quiet_s`` prints nothing when stderr is not a terminal, so a quick
failure leaves just its one-line error; with ``log`` false it prints nothing there at all (a
command whose result is short, unless asked to be verbose).
"""

from __future__ import annotations

import sys
import time


class Progress:
    """Callable ``progress(done, total)`` that reports long work as it goes."""

    def __init__(self, label: str, stream=None, quiet_s: float = 1.0, clock=time.monotonic, log: bool = True):
        self.label, self.log = label, log
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.clock = clock
        self.start = clock()
        self.quiet_s = quiet_s
        self._last_quarter = -1

    def __call__(self, done: int, total: int) -> None:
        total = max(total, 1)
        elapsed = self.clock() - self.start
        rate = done / max(elapsed, 1e-9)
        if self.tty:
            width = 30
            filled = int(width * done / total)
            bar = "#" * filled + "." * (width - filled)
            self.stream.write(f"\r{self.label} [{bar}] {done}/{total} ({rate:.1f}/s)")
            if done >= total:
                self.stream.write("\n")
            self.stream.flush()
            return
        quarter = 4 * done // total
        if self.log and elapsed >= self.quiet_s and quarter != self._last_quarter:
            self._last_quarter = quarter
            self.stream.write(f"{self.label}: {done}/{total} ({rate:.1f}/s)\n")
            self.stream.flush()


def clear_line(stream=None) -> None:
    """Erase an unfinished progress bar so that a message can take its place."""
    stream = stream if stream is not None else sys.stderr
    if stream.isatty():
        stream.write("\r\033[K")
        stream.flush()


class Status:
    """Callable ``status(message)`` for the steps of long work, quiet like :class:`Progress`: on a
    terminal each step takes the place of the last on one line (:func:`clear_line` ends it)."""

    def __init__(self, prefix: str, stream=None, quiet_s: float = 1.0, clock=time.monotonic, log: bool = True):
        self.prefix, self.log = prefix, log
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.start = clock()
        self.quiet_s = quiet_s

    def __call__(self, message: str) -> None:
        if self.stream.isatty():
            self.stream.write(f"\r\033[K{self.prefix}: {message}")
        elif self.log and self.clock() - self.start >= self.quiet_s:
            self.stream.write(f"{self.prefix}: {message}\n")
        self.stream.flush()
