"""The dead-man rule: when the last console page closes during a sweep, or vanishes without a
close, the robot stops at its next pose and the sweep can be resumed; a page reopened in time (a
reload) lets it go on, and ``serve --unattended`` lets a sweep run on with no page open."""

from __future__ import annotations

import contextlib

import pytest

from probecal.app.console.heartbeat import ANSWER_S, BEAT_S
from probecal.app.console.server import launch
from probecal.app.headless import click, open_console, wait_text
from tests.support.loopback import loopback
from tests.support.vanishing import FreezingRelay
from tests.support.waiting import recorded_frames, wait_for_frames, wait_for_new_session, wait_until

pytest.importorskip("playwright.sync_api")

POSES = 24


def _sweep_started(browser, console, poses: int, speed: float):
    """A page that connected and started a sweep of ``poses`` poses at ``speed``, and the sweep's
    session once it holds 3 frames."""
    page = open_console(browser, console.server.get_port())
    click(page, "Connect")
    wait_text(page, "Connected to the simulated UR3")
    console.panel.poses.value = poses
    console.panel.speed.value = speed
    before = set(console.sessions_dir.glob("calibration-*"))
    click(page, "Start sweep")
    session = wait_for_new_session(console.sessions_dir, "calibration", before)
    wait_for_frames(session, 3)
    return page, session


def _held_then_resumed(browser, console, session, host: str = "127.0.0.1") -> None:
    """Once the sweep's hold is set: the robot stops at its next pose (the pose under way, and no
    other, is recorded), the status says why, and Start sweep on a page opened at ``host``
    resumes it into the same session."""
    held_at = recorded_frames(session)
    console.wait()
    kept = recorded_frames(session)
    assert kept <= held_at + 1 and kept < POSES, (held_at, kept)
    assert not console.rig.robot.is_moving()
    assert "Stopped: no console page was open" in console.panel.status.text
    page = open_console(browser, console.server.get_port(), host=host)
    wait_text(page, "Stopped: no console page was open")
    console.panel.speed.value = 1.0
    click(page, "Start sweep")
    wait_text(page, r"Sweep done: \d+ frames")
    assert recorded_frames(session) == POSES
    page.close()


@pytest.mark.slow
def test_closing_the_only_page_stops_the_sweep_at_its_next_pose_and_start_sweep_resumes(browser, tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.25)
    try:
        page, session = _sweep_started(browser, console, POSES, 0.2)  # slow: closed mid-sweep on a busy machine
        sweep = console._sweep
        page.close()
        wait_until(lambda: sweep.hold.is_set(), "the sweep held when its only page closed")
        _held_then_resumed(browser, console, session)
    finally:
        console.close()


@pytest.mark.slow
def test_an_unattended_console_sweeps_on_with_no_page_open(browser, tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.25, unattended=True)
    try:
        page, session = _sweep_started(browser, console, 12, 0.3)
        sweep = console._sweep
        page.close()
        console.wait()
        assert not sweep.hold.is_set() and recorded_frames(session) == 12
        assert "Sweep done" in console.panel.status.text
    finally:
        console.close()


@contextlib.contextmanager
def _behind_a_relay(tmp_path):
    """A console on a loopback address of this run's own and a relay to it at 127.0.0.1 on the
    same port, where the browser opens it (the console's own address and port in its Host)."""
    for attempt in range(1, 6):
        console = launch(host=loopback(12, attempt), port=0, sessions_dir=tmp_path, time_scale=0.25)
        port = console.server.get_port()
        try:
            relay = FreezingRelay((loopback(12, attempt), port), ("127.0.0.1", port))
        except OSError:  # the port is taken on 127.0.0.1: another address, another port
            console.close()
            continue
        try:
            yield console, relay, loopback(12, attempt)
        finally:
            relay.close()
            console.close()
        return
    raise AssertionError("no port free on both loopback addresses")


@pytest.mark.slow
def test_a_page_that_vanishes_without_a_close_stops_the_sweep_at_its_next_pose(browser, tmp_path):
    """Its network gone: the tab neither reads nor closes. The heartbeat notices within
    BEAT_S + ANSWER_S (``benchmarks/bench_deadman.py`` prints the time; the bound here leaves room
    for a busy machine), and Start sweep resumes once a page is back."""
    with _behind_a_relay(tmp_path) as (console, relay, host):
        page, session = _sweep_started(browser, console, POSES, 0.2)
        sweep = console._sweep
        relay.freeze()
        wait_until(lambda: sweep.hold.is_set(), "the sweep held when its page vanished",
                   timeout_s=10 * (BEAT_S + ANSWER_S))
        page.close()
        _held_then_resumed(browser, console, session, host)  # the page back, on another way in
