"""Console figures (issue targets) in headless Chromium on the simulator, the robot in real time:
live frame updates per second on the page during a sweep, the time from the solve to a visible
result after a click on Calibrate, and how three tabs keep up (the README's pictures of the console
come from make_console_screenshots.py).

Run: .venv/bin/python benchmarks/bench_console.py [--poses 30]
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from pathlib import Path

from probecal.app.console.server import launch
from probecal.app.headless import (
    chromium,
    click,
    click_at,
    count_image_updates,
    image_updates,
    open_console,
    show_step,
    text_seen_at,
    wait_text,
    watch_text,
)


def sweep_rate(tabs, console, poses: int) -> None:
    console.panel.poses.value = poses
    for tab in tabs:
        count_image_updates(tab)
    started = time.monotonic()
    click(tabs[0], "Start sweep")
    wait_text(tabs[0], rf"Sweep done: {poses} frames", timeout_s=poses * 3.0)
    elapsed = time.monotonic() - started
    rates = [image_updates(tab) / elapsed for tab in tabs]
    print(f"{len(tabs)} tab(s), {poses}-pose sweep in {elapsed:.1f} s (robot in real time): live frame updates on "
          f"the page {', '.join(f'{r:.1f}' for r in rates)} frames/s (target >= 15); "
          f"{console.view.frames_shown} frames sent so far")


def calibrate(page) -> None:
    result = r"PRE3D \d+\.\d+ ±"
    watch_text(page, result)
    clicked = click_at(page, "Calibrate")
    wait_text(page, result)
    visible = text_seen_at(page, result) - clicked
    solve = float(wait_text(page, r"Calibrated from \d+ frames in (\d+\.\d+) s").group(1))
    print(f"Calibrate: result on the page {visible:.2f} s after the click, the solve took {solve:.1f} s, so "
          f"~{max(visible - solve, 0.0):.2f} s from the solve to the page (target <= 2 s)")


def shared_state(tabs, console) -> None:
    for tab in tabs:
        show_step(tab, "Calibrate")
    texts = [re.search(r"FRE \d+\.\d+ mm.*", tab.inner_text("body")) for tab in tabs]
    same = all(texts) and len({t.group(0) for t in texts}) == 1
    print(f"3 tabs show the same calibration result: {same}")
    console.panel.poses.value = 40
    click(tabs[2], "Start sweep")
    wait_text(tabs[0], r"Frames recorded: [3-9]")
    stopped = r"Stopped: \d+ frames kept"
    for tab in tabs:
        watch_text(tab, stopped)
    clicked = click_at(tabs[1], "Stop")
    for tab in tabs:
        wait_text(tab, stopped, timeout_s=10)
    seen = [text_seen_at(tab, stopped) - clicked for tab in tabs]
    print(f"Stop clicked in tab 2: 'Stopped' on the three pages {', '.join(f'{s:.2f}' for s in seen)} s after the "
          f"click; robot still moving: {console.rig.robot.is_moving()}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--poses", type=int, default=30)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp, chromium() as browser:
        console = launch(port=0, sessions_dir=Path(tmp), time_scale=1.0)
        try:
            port = console.server.get_port()
            page = open_console(browser, port)
            click(page, "Connect")
            wait_text(page, "Connected")
            sweep_rate([page], console, args.poses)
            calibrate(page)
            tabs = [page] + [open_console(browser, port) for _ in range(2)]
            sweep_rate(tabs, console, 12)
            shared_state(tabs, console)
            console.panel.frames_per_pass.value = 8
            click(page, "Scan volume")
            wait_text(page, r"Sweep done: 40 frames", timeout_s=120)
            click(page, "Reconstruct")
            wait_text(page, r"Surface error mean", timeout_s=120)
        finally:
            console.stop()
            console.server.stop()


if __name__ == "__main__":
    main()
