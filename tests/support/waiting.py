"""Waiting on state (a condition, a session's frames, a robot standing still), never on sleeps:
each wait ends in an AssertionError naming what did not come, a guard against hanging."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

T = TypeVar("T")


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
