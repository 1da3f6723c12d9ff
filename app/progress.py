"""Progress on stderr: a live bar on a terminal, a few plain lines otherwise (logs, CI)."""

from __future__ import annotations

import sys
import time


class Progress:
    """Callable ``progress(done, total)`` that reports long work as it goes."""

    def __init__(self, label: str, stream=None):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.start = time.monotonic()
        self._last_quarter = -1

    def __call__(self, done: int, total: int) -> None:
        total = max(total, 1)
        rate = done / max(time.monotonic() - self.start, 1e-9)
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
        if quarter != self._last_quarter:
            self._last_quarter = quarter
            self.stream.write(f"{self.label}: {done}/{total} ({rate:.1f}/s)\n")
            self.stream.flush()
