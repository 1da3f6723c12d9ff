"""Remakes the README's pictures of the console (docs/img/console-*.png): each step of the work on
the simulator, in headless Chromium at 1280 x 800 (and the calibrated and reconstructed steps at
1920 x 1080), the self-check last, the status column on the left, the steps on the right, the
camera on the work; then
the browser test that checks what the console shows (tests/test_console_trust.py) at both sizes,
its pictures into docs/img too; then the guided acquisition of a tracked probe on the freehand twin
(``serve --tracker sim``), as it goes and paused by a marker out of the tracker's view.

Run: .venv/bin/python benchmarks/make_console_screenshots.py [--guided]  (--guided: its pictures alone)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from probecal.app.console.panel import DEFAULT_POSES
from probecal.app.console.server import launch
from probecal.app.headless import SCREENSHOTS_ENV, chromium, click, show_step, wait_text
from probecal.app.tracked import TrackedSpec

IMAGES = Path(__file__).resolve().parent.parent / "docs" / "img"
SMALL, LARGE = {"width": 1280, "height": 800}, {"width": 1920, "height": 1080}


def shoot(page, name: str, step: str, scroll_to: str | None = None) -> None:
    """A picture of the page with ``step`` shown, the side panel scrolled to the text ``scroll_to``,
    and no notifications."""
    show_step(page, step)
    if scroll_to is not None:
        page.get_by_text(scroll_to).scroll_into_view_if_needed()
    for close in page.locator(".mantine-Notification-closeButton").all():
        close.click()
    page.wait_for_timeout(1200)  # the camera glides and the clouds arrive
    size = page.viewport_size
    path = IMAGES / f"console-{name}-{size['width']}x{size['height']}.png"
    page.screenshot(path=str(path))
    print(f"wrote {path}")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp, chromium() as browser:
        console = launch(port=0, sessions_dir=Path(tmp), time_scale=0.25)
        try:
            address = f"http://127.0.0.1:{console.server.get_port()}"
            page = browser.new_page(viewport=SMALL)
            page.goto(address)
            click(page, "Connect")
            wait_text(page, "Connected to the simulated UR3")
            shoot(page, "1-connect", "Connect")
            click(page, "Start sweep")
            wait_text(page, r"Frames recorded: (1[2-9]|2\d)")
            shoot(page, "2-sweep", "Start sweep")
            wait_text(page, rf"Sweep done: {DEFAULT_POSES} frames", timeout_s=120)
            click(page, "Calibrate")
            wait_text(page, r"Calibrated in \d+\.\d s", timeout_s=120)
            shoot(page, "3-calibrated", "Calibrate")
            large = browser.new_page(viewport=LARGE)
            large.goto(address)
            wait_text(large, "Calibrated in")
            shoot(large, "3-calibrated", "Calibrate")
            click(page, "Check phantom")
            wait_text(page, r"Phantom checked from \d+ frames", timeout_s=120)
            shoot(page, "3-phantom-check", "Check phantom", scroll_to="Wire offsets")
            click(page, "Scan volume")
            wait_text(page, r"Live volume: [1-9]\d+ frames", timeout_s=120)
            shoot(page, "4-scan", "Scan volume")
            wait_text(page, r"Sweep done: 200 frames", timeout_s=240)
            click(page, "Reconstruct")
            wait_text(page, r"surface to CAD", timeout_s=120)
            console.panel.cloud_colors.value = "error to CAD"
            shoot(page, "5-results", "Reconstruct")
            shoot(large, "5-results", "Reconstruct")
            click(page, "Self-check")
            wait_text(page, r"Self-checked selfcheck-", timeout_s=600)
            shoot(page, "6-self-check", "Self-check")
        finally:
            console.stop()
            console.server.stop()


def trust_pictures() -> None:
    """The browser test of what the console shows, at both sizes, its screenshots into docs/img."""
    root = IMAGES.parent.parent
    subprocess.run([sys.executable, "-m", "pytest", "tests/test_console_trust.py", "-q", "-n", "0"], cwd=root,
                   env={**os.environ, SCREENSHOTS_ENV: str(IMAGES)}, check=True)


def guided_pictures() -> None:
    """The guided acquisition at 1280 x 800: following the targets once the bound is measured, and
    paused by the probe's marker out of the tracker's view."""
    with tempfile.TemporaryDirectory() as tmp, chromium() as browser:
        console = launch(port=0, sessions_dir=Path(tmp), tracked=TrackedSpec("sim"))
        assert console.guided is not None
        try:
            page = browser.new_page(viewport=SMALL)
            page.goto(f"http://127.0.0.1:{console.server.get_port()}")
            click(page, "Connect")
            wait_text(page, "Connected to tracker")
            click(page, "Start sweep")
            wait_text(page, r"corner bound: ±", timeout_s=300)
            shoot(page, "7-guided", "Start sweep")
            server = console.guided.streams.server if console.guided.streams else None
            assert server is not None
            server.fault = "missing"
            wait_text(page, "Paused: ")
            shoot(page, "7-guided-paused", "Start sweep")
            server.fault = None
        finally:
            console.close()


if __name__ == "__main__":
    if "--guided" not in sys.argv:
        main()
        trust_pictures()
    guided_pictures()
