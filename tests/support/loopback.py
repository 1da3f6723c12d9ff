"""Loopback addresses of this test run's own, so that simulated controllers binding ur_rtde's
fixed ports never meet another run's (or another xdist worker's) on one machine."""

from __future__ import annotations

import os
import random

_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID")  # the same in every worker of one parallel run
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
_LOOPBACK_BASE = ((random.Random(_RUN) if _RUN else random.SystemRandom()).randrange(16, 200) + _WORKER) % 256
"""This test run's own 127.B.0.0/16 (each of a parallel run's workers its own B)."""


def loopback(group: int, n: int) -> str:
    """A loopback address of this test run's own, 127.B.group.n: simulated controllers bind
    ur_rtde's fixed ports on it, so two test runs on one machine never meet."""
    return f"127.{_LOOPBACK_BASE}.{group}.{n}"
