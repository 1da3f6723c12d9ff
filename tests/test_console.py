"""The browser console, driven the way an operator drives it: headless Chromium clicks the
buttons of an in-process console on the simulator and reads the results off the page."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from app.console import launch
from core.session import load_session

sync_api = pytest.importorskip("playwright.sync_api")

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]
README_SHOT = Path(__file__).resolve().parent.parent / "docs" / "img" / "console.png"
VIEWPORT = {"width": 1600, "height": 1000}

# Counts every update of an <img> on the page (the live frame is the only one changing in a sweep).
COUNT_IMAGES = """() => {
  window.__frames = 0;
  new MutationObserver((records) => {
    for (const r of records) {
      if (r.type === 'attributes' && r.target.tagName === 'IMG') window.__frames++;
      for (const n of r.addedNodes || []) if (n.tagName === 'IMG') window.__frames++;
    }
  }).observe(document.body, {subtree: true, childList: true, attributes: true, attributeFilter: ['src']});
}"""


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    console = launch(port=0, sessions_dir=tmp_path_factory.mktemp("sessions"), time_scale=0.25)
    yield console
    console.stop()
    console.server.stop()


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.is_file():
        pytest.skip("Debian chromium is not installed")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield browser
        browser.close()


def _open(browser, console):
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(f"http://127.0.0.1:{console.server.get_port()}")
    page.get_by_role("button", name="Connect").wait_for(timeout=30_000)
    return page


def _wait_text(page, pattern: str, timeout_s: float = 60.0) -> re.Match:
    """Wait until the page text matches ``pattern``; returns the match."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        match = re.search(pattern, page.inner_text("body"))
        if match:
            return match
        time.sleep(0.1)
    raise AssertionError(f"{pattern!r} never appeared; page says:\n{page.inner_text('body')[:2000]}")


def _click(page, label: str) -> None:
    page.get_by_role("button", name=label, exact=True).click()


def test_console_calibrates_and_reconstructs_from_the_page(console, browser, tmp_path):
    page = _open(browser, console)
    _click(page, "Connect")
    _wait_text(page, "Connected to the simulated UR3")

    console.panel.poses.value = 12
    page.evaluate(COUNT_IMAGES)
    started = time.monotonic()
    _click(page, "Start sweep")
    _wait_text(page, r"Frames recorded: [1-9]")
    _click(page, "Start sweep")  # a second click while sweeping does nothing
    _wait_text(page, r"Sweep done: 12 frames")
    elapsed = time.monotonic() - started
    rate = page.evaluate("window.__frames") / elapsed
    print(f"\nlive frame updates on the page during a 12-pose sweep: {rate:.1f} frames/s "
          f"({console.frames_shown} frames sent in {elapsed:.1f} s)")
    assert rate >= 10.0  # software WebGL on 2 cores; the console streams at 20 frames/s
    sessions = sorted(console.sessions_dir.glob("calibration-*"))
    assert len(sessions) == 1 and len(load_session(sessions[0])) == 12
    page.screenshot(path=str(tmp_path / "sweep.png"))

    clicked = time.monotonic()
    _click(page, "Calibrate")
    fre = float(_wait_text(page, r"FRE (\d+\.\d+) mm").group(1))
    pre3d = float(_wait_text(page, r"PRE3D (\d+\.\d+) ±").group(1))
    print(f"calibration on the page {time.monotonic() - clicked:.1f} s after the click: FRE {fre:.3f} mm, "
          f"PRE3D {pre3d:.3f} mm")
    assert fre < 0.5 and pre3d < 1.0
    _wait_text(page, "image_to_tool_rigid")

    console.panel.frames_per_pass.value = 8
    _click(page, "Scan volume")
    _wait_text(page, r"Sweep done: 40 frames", timeout_s=90)
    _click(page, "Reconstruct")
    surface = float(_wait_text(page, r"Surface error mean (\d+\.\d+) mm", timeout_s=90).group(1))
    print(f"surface error to the CAD model: mean {surface:.3f} mm")
    assert surface < 1.0
    page.wait_for_timeout(1500)  # let the point cloud and scene settle before the picture
    for close in page.locator(".mantine-Notification-closeButton").all():
        close.click()
    page.mouse.move(VIEWPORT["width"] - 200, 400)
    page.mouse.wheel(0, -5000)  # the panel from the top: controls and the live frame
    page.wait_for_timeout(500)
    README_SHOT.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(README_SHOT))

    _click(page, "Save session")
    _wait_text(page, r"Saved .*calibration\.json")
    assert (sessions[0] / "calibration.json").is_file()


def test_tabs_share_state_and_stop_halts_a_sweep(console, browser, tmp_path):
    tabs = [_open(browser, console) for _ in range(3)]
    _click(tabs[0], "Connect")
    for tab in tabs:
        _wait_text(tab, "Connected to the simulated UR3")
    texts = [re.search(r"FRE \d+\.\d+ mm", tab.inner_text("body")) for tab in tabs]
    if console.calibration is not None:  # the state of the first test, when it ran
        assert len({t.group(0) for t in texts if t}) == 1 and all(texts)

    before = set(console.sessions_dir.glob("calibration-*"))
    console.panel.poses.value = 40
    _click(tabs[2], "Start sweep")
    _wait_text(tabs[0], r"Frames recorded: [3-9]")
    _click(tabs[1], "Start sweep")
    clicked = time.monotonic()
    _click(tabs[1], "Stop")
    for tab in tabs:
        _wait_text(tab, r"Stopped: \d+ frames kept", timeout_s=10)
    print(f"\nstop shown in all three tabs {time.monotonic() - clicked:.2f} s after the click")
    assert not console.rig.robot.is_moving()
    new = set(console.sessions_dir.glob("calibration-*")) - before
    assert len(new) == 1
    kept = len(load_session(new.pop()))
    assert 3 <= kept < 40
    for k, tab in enumerate(tabs):
        tab.screenshot(path=str(tmp_path / f"tab{k}.png"))
        tab.close()
