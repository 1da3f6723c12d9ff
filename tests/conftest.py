"""Fixtures, for every test: the real PLUS data (skipped without it), headless Chromium, and a
watchdog that ends a hung run. Helpers the tests import live in tests/support."""

from __future__ import annotations

import faulthandler
import os
from pathlib import Path

import pytest

from probecal.core.io.plusdata import missing_reason
from tests.support.paths import PLUS

HUNG_TEST_S = 1200.0
"""A test still running after this long (beyond every test's own timeout) is hung: its threads'
stacks are dumped and the run ends."""


@pytest.fixture(scope="module")
def browser():
    """Headless Debian Chromium for a module's browser tests (skipped where it is not installed)."""
    from probecal.app.headless import CHROMIUM, chromium

    if not CHROMIUM.is_file():
        pytest.skip("Debian chromium is not installed")
    with chromium() as browser:
        yield browser


@pytest.fixture(scope="session")
def terminal_stderr(pytestconfig):
    """The run's own stderr, which pytest's output capture does not swallow."""
    capture = pytestconfig.pluginmanager.getplugin("capturemanager")
    with capture.global_and_fixture_disabled():
        fd = os.dup(2)
    with os.fdopen(fd, "w") as stream:
        yield stream


@pytest.fixture(autouse=True)
def end_a_hung_run(terminal_stderr):
    """pytest-timeout's alarm is Python code, which never runs while a C call (ur_rtde's, which
    keeps the GIL while it waits on the network) holds the interpreter; faulthandler's watchdog is
    a C thread, so a hang there ends the run with every thread's stack instead of stalling it."""
    faulthandler.dump_traceback_later(HUNG_TEST_S, exit=True, file=terminal_stderr)
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.fixture(scope="session")
def plus_data() -> Path:
    reason = missing_reason()
    if reason is not None:
        pytest.skip(reason)
    return PLUS


MARKERS_BY_FIXTURE = {"browser": "browser", "plus_data": "real_data"}
"""A test that uses one of these fixtures, directly or through another fixture, gets its marker:
the fixture is what makes it need Chromium or the real recordings, so the mark cannot be forgotten."""


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects by marker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        for fixture, marker in MARKERS_BY_FIXTURE.items():
            if fixture in getattr(item, "fixturenames", ()):
                item.add_marker(marker)
