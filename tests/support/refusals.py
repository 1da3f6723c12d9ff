"""Bad input refused the way users are promised: one short line naming the file and the problem,
from a command (exit code 2) or from a loader (InputError)."""

from __future__ import annotations

import re
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

from probecal.core.errors import InputError

PROGRESS_LINE = re.compile(r"[a-z][a-z ]*: \d+/\d+ \(\d+\.\d/s\)")
"""What work that runs past a second reports on a stderr that is not a terminal (``app.progress``):
a command that fails only after such work (every frame read, none with a surface) has said it."""


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """Exit code 2, a single stderr line without a traceback, naming what went wrong (after any
    progress the work reported before it failed)."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = [line for line in result.stderr.strip().splitlines() if not PROGRESS_LINE.fullmatch(line)]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


def assert_refused(load: Callable[[], object], file: Path, *fragments: str) -> str:
    """``load()`` raises InputError with one short line that names ``file`` and holds every
    fragment; returns the message."""
    with pytest.raises(InputError) as caught:
        load()
    message = str(caught.value)
    assert "\n" not in message and str(file) in message, message
    assert len(message) < 400 + len(str(file)), message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message
