"""The dead-man rule: when the last console page closes during a sweep, the robot stops at its
next pose and the sweep can be resumed; a page reopened in time (a reload) lets it go on, and
``serve --unattended`` lets a sweep run on with no page open."""

from __future__ import annotations

import pytest

from probecal.app.console.server import launch
from probecal.app.headless import click, open_console, wait_text
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


@pytest.mark.slow
def test_closing_the_only_page_stops_the_sweep_at_its_next_pose_and_start_sweep_resumes(browser, tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.25)
    try:
        page, session = _sweep_started(browser, console, POSES, 0.2)  # slow: closed mid-sweep on a busy machine
        sweep = console._sweep
        page.close()
        wait_until(lambda: sweep.hold.is_set(), "the sweep held when its only page closed")
        held_at = recorded_frames(session)
        console.wait()
        kept = recorded_frames(session)
        assert kept <= held_at + 1 and kept < POSES, (held_at, kept)  # the pose under way, and no other
        assert not console.rig.robot.is_moving()
        assert "Stopped: no console page was open" in console.panel.status.text

        page = open_console(browser, console.server.get_port())
        wait_text(page, "Stopped: no console page was open")
        console.panel.speed.value = 1.0
        click(page, "Start sweep")
        wait_text(page, r"Sweep done: \d+ frames")
        assert recorded_frames(session) == POSES  # resumed into the same session
        page.close()
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
