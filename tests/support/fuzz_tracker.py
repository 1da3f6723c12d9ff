"""The fuzzing harness's hostile trackers in guided mode: one bad pose (NaN, mirrored, huge,
timestamps backwards), floods of device names, huge TransformStatus."""

from __future__ import annotations

from tests.support.fuzz import Case


def tracker_cases() -> list[Case]:
    return []
