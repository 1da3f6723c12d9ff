"""Driving the console in headless Chromium the way an operator would (Debian ``chromium`` and
Playwright): for the end-to-end tests, the console benchmark and the README screenshots. It needs
the test extra's Playwright, imported only when a browser starts."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
# Without the background-networking flags Chromium keeps dialling out of a closed network.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--disable-quic"]
VIEWPORT = {"width": 1600, "height": 1000}
SCREENSHOTS_ENV = "PROBECAL_SCREENSHOTS"
"""Where the browser tests put their pictures (default ``out/screenshots``, git-ignored;
``benchmarks/make_console_screenshots.py`` points it at docs/img)."""

# Counts every update of an <img> on the page (in a sweep, the live frame is the one changing).
_COUNT_IMAGES = """() => {
  window.__frames = 0;
  if (window.__countingImages) return;
  window.__countingImages = true;
  new MutationObserver((records) => {
    for (const r of records) {
      if (r.type === 'attributes' && r.target.tagName === 'IMG') window.__frames++;
      for (const n of r.addedNodes || []) if (n.tagName === 'IMG') window.__frames++;
    }
  }).observe(document.body, {subtree: true, childList: true, attributes: true, attributeFilter: ['src']});
}"""


@contextmanager
def chromium() -> Iterator:
    """A headless Debian Chromium under Playwright (never a downloaded browser)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


PAGE_TIMEOUT_MS = 120_000
"""How long a tab may take to answer (Playwright's default is 30 s): software WebGL on a machine
whose other core runs another test's calibration has taken longer to load the page or a tab."""


def new_tab(browser, viewport: dict[str, int] = VIEWPORT):
    """A new tab that waits up to ``PAGE_TIMEOUT_MS`` for what it is asked to find."""
    page = browser.new_page(viewport=viewport)
    page.set_default_timeout(PAGE_TIMEOUT_MS)
    return page


def open_console(browser, port: int, host: str = "127.0.0.1", token: str | None = None):
    """A new tab on the console, once its controls are on the page."""
    page = new_tab(browser)
    page.goto(f"http://{host}:{port}" + (f"/?token={token}" if token else ""))
    page.get_by_role("button", name="Connect").wait_for()
    return page


def wait_text(page, pattern: str, timeout_s: float = 60.0) -> re.Match:
    """Wait until the page's text matches ``pattern``; returns the match."""
    deadline = time.monotonic() + timeout_s
    while True:
        match = re.search(pattern, page.inner_text("body"))
        if match:
            return match
        if time.monotonic() > deadline:
            raise AssertionError(f"{pattern!r} never appeared; the page says:\n{page.inner_text('body')[:2000]}")
        time.sleep(0.05)


STEPS = {"Connect": "1 Connect", "Measure latency": "1 Connect", "Start sweep": "2 Calibrate",
         "Calibrate": "2 Calibrate", "Check phantom": "2 Calibrate", "Add poses and check again": "2 Calibrate",
         "Scan volume": "3 Scan", "Reconstruct": "3 Scan", "Self-check": "3 Scan",
         "Save session": "4 Session", "Load session": "4 Session", "Frame the work": "View", "Whole robot": "View"}
"""The step (tab of the side panel) each button is in; Stop is in the status strip, always in sight."""


def show_step(page, label: str) -> None:
    """Open the side panel's step that holds the button ``label``."""
    if label in STEPS:
        page.get_by_role("tab", name=STEPS[label]).click()


def click(page, label: str) -> None:
    show_step(page, label)
    page.get_by_role("button", name=label, exact=True).click()


def count_image_updates(page) -> None:
    """Start counting image updates on the page (read them with :func:`image_updates`)."""
    page.evaluate(_COUNT_IMAGES)


def image_updates(page) -> int:
    return int(page.evaluate("window.__frames"))


def watch_text(page, pattern: str) -> None:
    """Note on the page's own clock (ms since the epoch) when its text first matches ``pattern``
    (a JavaScript regular expression); read it with :func:`text_seen_at`."""
    page.evaluate("""(pattern) => {
      window.__seenAt = window.__seenAt || {};
      window.__seenAt[pattern] = null;
      const re = new RegExp(pattern);
      const check = () => {
        if (window.__seenAt[pattern] === null && re.test(document.body.innerText)) {
          window.__seenAt[pattern] = Date.now();
        }
      };
      new MutationObserver(check).observe(document.body, {subtree: true, childList: true, characterData: true});
      check();
    }""", pattern)


def text_seen_at(page, pattern: str) -> float | None:
    """Seconds since the epoch at which the text watched with ``pattern`` appeared, or None."""
    seen = page.evaluate("(pattern) => window.__seenAt[pattern]", pattern)
    return None if seen is None else seen / 1000.0


def click_at(page, label: str) -> float:
    """Click a button from inside the page; returns the page's time of the click (s since the epoch)."""
    show_step(page, label)
    page.get_by_role("button", name=label, exact=True).wait_for()
    return page.evaluate("""(label) => {
      const button = [...document.querySelectorAll('button')].find((b) => b.innerText.trim() === label);
      const at = Date.now();
      button.click();
      return at / 1000.0;
    }""", label)


def screenshot_panel_top(page, path: Path) -> None:
    """A picture of the whole console with the side panel scrolled to its top."""
    for close in page.locator(".mantine-Notification-closeButton").all():
        close.click()
    page.mouse.move(VIEWPORT["width"] - 200, 400)
    page.mouse.wheel(0, -5000)
    page.wait_for_timeout(500)
    path.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(path))


def projected_px(client, points_m, viewport: dict[str, int] = VIEWPORT):
    """(N, 2) pixels of the page where a tab's camera (``client.camera``: OpenCV axes, vertical fov,
    the size of its 3D view, which fills the page's height right of the status column) puts (N, 3)
    scene points (m) in a viewport of that size; NaN behind the camera. The view's size is reported
    in the canvas's own pixels, which viser's adaptive resolution shrinks while rendering is slow
    (a busy machine): it is scaled to the page's."""
    import numpy as np
    import viser.transforms as vtf

    camera = client.camera
    height = viewport["height"]
    width = camera.image_width * height / camera.image_height if camera.image_height else viewport["width"]
    rotation = vtf.SO3(np.asarray(camera.wxyz)).as_matrix()
    in_camera = (np.asarray(points_m, float) - np.asarray(camera.position)) @ rotation
    focal = height / 2 / np.tan(camera.fov / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = focal * in_camera[:, :2] / in_camera[:, 2:3] + [viewport["width"] - width / 2, height / 2]
    pixels[in_camera[:, 2] <= 0] = np.nan
    return pixels
