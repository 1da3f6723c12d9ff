"""The dead-man rule for a page that vanishes without closing: a page that stops reading (its
network gone, a client that clicked and then went silent) counts as gone within the heartbeat's
time, and the sweep it started stops at its next pose (one without stops, at once); a live page
beside it keeps the sweep going. The page here is a raw websocket (``tests.support.page``)
behind a relay that freezes (``tests.support.vanishing``); ``test_console_deadman`` does the
same with Chromium."""

from __future__ import annotations

import pytest
from websockets.protocol import State

from probecal.app.console.heartbeat import ANSWER_S, BEAT_S
from probecal.app.console.server import launch
from tests.support.page import RawPage
from tests.support.vanishing import FreezingRelay
from tests.support.waiting import recorded_frames, wait_for_frames, wait_for_new_session, wait_until

NOTICED_S = 10 * (BEAT_S + ANSWER_S)
"""The most a test waits for the console to notice a vanished page: the heartbeat's worst case
(``benchmarks/bench_deadman.py`` prints the time taken) with room for a busy machine; without
the heartbeat a frozen page is never noticed before websockets' own 40 s."""


@pytest.fixture
def console(tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.25)
    yield console
    console.close()


def _started(console, page: RawPage, button: str, frames: int = 3):
    """``button``'s sweep started from ``page``, and its session once it holds ``frames``."""
    page.click(console.panel.connect)
    wait_until(lambda: console.rig.robot.connected and not console.busy, "connected")
    kind = "volume" if button == "scan" else "calibration"
    before = set(console.sessions_dir.glob(f"{kind}-*"))
    page.click(getattr(console.panel, button))
    session = wait_for_new_session(console.sessions_dir, kind, before, timeout_s=300)  # planning, on a busy machine
    wait_for_frames(session, frames)
    return session


@pytest.mark.parametrize("button, how", [("start", "freeze"), ("scan", "freeze"), ("start", "deafen")])
def test_a_page_that_stops_answering_stops_the_sweep_it_started(console, button, how):
    """Its network frozen, or the page no longer reading what it is sent (while it may still send)."""
    console.panel.poses.value = 40
    console.panel.speed.value = 0.3
    with FreezingRelay(("127.0.0.1", console.server.get_port())) as relay, RawPage(console, via=relay.address) as page:
        session = _started(console, page, button)
        sweep = console._sweep
        getattr(relay, how)()
        wait_until(lambda: sweep.hold.is_set(), "the page noticed gone", timeout_s=NOTICED_S)
        held_at = recorded_frames(session)
        console.wait(60)
        relay.close()
    assert "Stopped: no console page was open" in console.panel.status.text
    kept = recorded_frames(session)
    assert kept <= held_at + 1 and kept < sweep.total, (held_at, kept)
    assert not console.rig.robot.is_moving()


def test_a_sweep_without_stops_halts_at_once_when_its_page_vanishes(console):
    console.panel.motion.value = "continuous"
    with FreezingRelay(("127.0.0.1", console.server.get_port())) as relay, RawPage(console, via=relay.address) as page:
        session = _started(console, page, "start", frames=1)
        sweep = console._sweep
        relay.freeze()
        wait_until(lambda: sweep.halt.is_set(), "the sweep halted", timeout_s=NOTICED_S)
        console.wait(60)
        relay.close()
    status = console.panel.status.text
    assert "Stopped: no console page was open" in status and "record a new one" in status, status
    assert not console.rig.robot.is_moving() and recorded_frames(session) >= 1


def test_a_page_that_closes_and_then_goes_silent_is_gone_at_once(console):
    """A close frame, then nothing: the console does not wait out the closing handshake (10 s)."""
    websock = console.server._websock_server
    with FreezingRelay(("127.0.0.1", console.server.get_port())) as relay, RawPage(console, via=relay.address) as page:
        session = _started(console, page, "start")
        sweep = console._sweep
        connection = next(iter(websock._live_connections.values()))
        page.send_close_frame()
        wait_until(lambda: connection.state is not State.OPEN, "the close frame received")
        relay.freeze()
        wait_until(lambda: sweep.hold.is_set(), "the page noticed gone", timeout_s=NOTICED_S)
        console.wait(60)
        relay.close()
    assert "Stopped: no console page was open" in console.panel.status.text
    assert recorded_frames(session) < sweep.total


def test_a_live_page_keeps_the_sweep_going_when_another_vanishes(console):
    console.panel.poses.value = 8
    relay = FreezingRelay(("127.0.0.1", console.server.get_port()))
    with relay, RawPage(console, via=relay.address) as lost, RawPage(console) as live:
        session = _started(console, lost, "start", frames=1)
        relay.freeze()
        wait_until(lambda: len(console.server.get_clients()) == 1, "the frozen page cut off", timeout_s=NOTICED_S)
        console.wait(120)
        relay.close()
        assert "Sweep done: 8 frames" in console.panel.status.text, console.panel.status.text
        assert recorded_frames(session) == 8
        live.click(console.panel.connect)  # the live page is still heard
        wait_until(lambda: "Connected" in console.panel.status.text, "the live page's click taken")
