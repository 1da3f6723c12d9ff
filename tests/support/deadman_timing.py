"""How soon the console notices a page gone during a sweep (the dead-man rule), and how soon the
robot then stands still: for a page closed cleanly, a close frame followed by silence, a page that
stops reading, and one whose network freezes (``tests/support/vanishing.py``), each from a raw
page (``tests/support/page.py``) that started a stop-and-go sweep on the simulator; ``--browser``
adds Chromium tabs closed and frozen. Prints, per way of going, the median and worst time from
the page's last word to the sweep held and to the robot still, against the heartbeat's bound
(``app/console/heartbeat.py``: BEAT_S + ANSWER_S).

``benchmarks/bench_deadman.py`` runs it (``python -m tests.support.deadman_timing`` from the
checkout's root).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from probecal.app.console.heartbeat import ANSWER_S, BEAT_S
from probecal.app.console.server import launch
from tests.support.page import RawPage
from tests.support.vanishing import FreezingRelay
from tests.support.waiting import recorded_frames, wait_until

WAYS = ("closed", "close frame, then silence", "stops reading", "network frozen")
BROWSER_WAYS = ("closed", "network frozen")


def _timed(console, vanish: Callable[[], object]) -> tuple[float, float]:
    """Once a sweep has recorded 2 frames, ``vanish`` the page; seconds from then to the sweep
    held, and to the robot still."""
    sweep = wait_until(lambda: console._sweep, "the sweep", 120)
    wait_until(lambda: recorded_frames(Path(console.panel.session_path.value)) >= 2, "frames", 120)
    last_word = time.monotonic()
    vanish()
    wait_until(lambda: sweep.hold.is_set(), "the sweep held", 60)
    held = time.monotonic() - last_word
    wait_until(lambda: not console.rig.robot.is_moving(), "the robot still", 60)
    still = time.monotonic() - last_word
    console.wait(60)
    return held, still


def raw_trial(way: str, sessions: Path) -> tuple[float, float]:
    """A raw page (the test suite's) that started a sweep, then goes ``way``."""
    console = launch(port=0, sessions_dir=sessions, time_scale=0.25)
    console.panel.poses.value, console.panel.speed.value = 40, 0.3
    try:
        with FreezingRelay(("127.0.0.1", console.server.get_port())) as relay:
            page = RawPage(console, via=relay.address).__enter__()  # not left through __exit__: it vanishes
            page.click(console.panel.connect)
            wait_until(lambda: console.rig.robot.connected and not console.busy, "connected", 60)
            page.click(console.panel.start)
            return _timed(console, {"closed": page._ws.close,
                                    "close frame, then silence": lambda: (page.send_close_frame(), relay.freeze()),
                                    "stops reading": relay.deafen, "network frozen": relay.freeze}[way])
    finally:
        console.close()


def browser_trial(way: str, sessions: Path) -> tuple[float, float]:
    """A Chromium tab that started a sweep, then is closed or its network freezes."""
    from probecal.app.headless import chromium, click, open_console, wait_text

    console = launch(host="127.0.0.2", port=0, sessions_dir=sessions, time_scale=0.25)
    console.panel.poses.value, console.panel.speed.value = 40, 0.3
    port = console.server.get_port()
    try:
        with FreezingRelay(("127.0.0.2", port), ("127.0.0.1", port)) as relay, chromium() as browser:
            page = open_console(browser, port)
            click(page, "Connect")
            wait_text(page, "Connected to the simulated UR3")
            click(page, "Start sweep")
            return _timed(console, page.close if way == "closed" else relay.freeze)
    finally:
        console.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--browser", action="store_true", help="also Chromium tabs, closed and frozen")
    args = parser.parse_args()
    runs = [(f"raw page {way}", way, raw_trial) for way in WAYS]
    if args.browser:
        runs += [(f"Chromium tab {way}", way, browser_trial) for way in BROWSER_WAYS]
    print(f"heartbeat: a ping every {BEAT_S:g} s, answered within {ANSWER_S:g} s: a vanished page is gone "
          f"{BEAT_S + ANSWER_S:g} s after its last answer at worst; {args.trials} trials each")
    print(f"{'the page':40s} {'held: median':>13s} {'worst':>7s} {'robot still: median':>20s} {'worst':>7s}")
    for name, way, trial in runs:
        times = []
        for _ in range(args.trials):
            with tempfile.TemporaryDirectory() as tmp:
                times.append(trial(way, Path(tmp)))
        held, still = zip(*times)
        print(f"{name:40s} {statistics.median(held):11.2f} s {max(held):5.2f} s {statistics.median(still):18.2f} s "
              f"{max(still):5.2f} s")


if __name__ == "__main__":
    main()
