"""What the console shows is the session in front of it, judged (issue 52): in headless Chromium at
1280 x 800 and 1920 x 1080, a user's flow checks each thing that was seen wrong in turn. Stop
stays put through a sweep; every result leads with its verdict and names its session; a stopped
scan shows no time left and its reconstruction warns that it is partial; loading an uncalibrated
session after a calibrated one leaves nothing of the first; loading a reconstructed volume session
shows its volume and slices; Frame the work after a load puts the phantom in view; a wide screen
gets a wide side panel. benchmarks/make_console_screenshots.py puts these tests' pictures in
docs/img."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from probecal.app.console.panel import STRIP_WIDTH, WIDE_PANEL_PX
from probecal.app.console.server import launch
from probecal.app.headless import SCREENSHOTS_ENV, click, new_tab, projected_px, show_step, wait_text
from probecal.core.geometry.transforms import transform_points
from tests.support.waiting import wait_for_frames, wait_for_new_session, wait_until

pytest.importorskip("playwright.sync_api")

SHOTS = Path(os.environ.get(SCREENSHOTS_ENV, Path(__file__).resolve().parent.parent / "out" / "screenshots"))
SIZES = ({"width": 1280, "height": 800}, {"width": 1920, "height": 1080})


def _stop_top(page) -> float:
    return page.get_by_role("button", name="Stop", exact=True).bounding_box()["y"]


def _side_panel_left(page) -> float:
    return page.get_by_role("tab", name="1 Connect").bounding_box()["x"]


def _phantom_in_view(console, page, size) -> bool:
    """Whether every corner of the phantom's box lies between the status column and the side
    panel, within the page's height, under the camera of some tab."""
    phantom = console.rig.twin.phantom
    placed = console.calibration.phantom_to_base if console.calibration else console.rig.twin.nominal.phantom_to_base
    lo, hi = phantom.box_min, phantom.box_max
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    points = transform_points(placed, corners) * 1e-3
    right = _side_panel_left(page)
    for client in console.server.get_clients().values():
        px = projected_px(client, points, size)
        if (np.all(np.isfinite(px)) and px[:, 0].min() >= STRIP_WIDTH and px[:, 0].max() <= right
                and px[:, 1].min() >= 0 and px[:, 1].max() <= size["height"]):
            return True
    return False


def _load(console, page, folder: str) -> None:
    console.panel.session_path.value = folder  # the Folder field, as typed
    click(page, "Load session")


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s['width']}x{s['height']}")
def test_the_console_shows_the_session_in_front_of_it_with_its_verdict(browser, tmp_path, size):
    name = f"{size['width']}x{size['height']}"
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.25)
    try:
        SHOTS.mkdir(parents=True, exist_ok=True)
        page = new_tab(browser, size)
        page.goto(f"http://127.0.0.1:{console.server.get_port()}")
        wide = size["width"] >= 1700
        assert (size["width"] - _side_panel_left(page) > WIDE_PANEL_PX) == wide  # a wide screen, a wide panel
        click(page, "Connect")
        wait_text(page, "Connected to the simulated UR3")
        stop_at = _stop_top(page)

        # A sweep: Stop stays where it was, whatever the status says.
        console.panel.poses.value = 8
        before = set(tmp_path.glob("calibration-*"))
        click(page, "Start sweep")
        calibration_session = wait_for_new_session(tmp_path, "calibration", before)
        tops = []
        while "Sweep done" not in page.inner_text("body"):
            tops.append(_stop_top(page))
            page.wait_for_timeout(100)
        tops.append(_stop_top(page))
        assert max(abs(t - stop_at) for t in tops) < 1.0, tops

        # Calibrate: the verdict first, naming the session.
        click(page, "Calibrate")
        wait_text(page, r"(Calibration usable|Not usable): image corners within ±\d+\.\d+ mm \(95 %\)")
        assert calibration_session.name in page.inner_text("body")
        assert abs(_stop_top(page) - stop_at) < 1.0

        # A whole scan, reconstructed: its verdict counts every planned pose.
        console.panel.frames_per_pass.value = 4
        before = set(tmp_path.glob("volume-*"))
        click(page, "Scan volume")
        whole = wait_for_new_session(tmp_path, "volume", before)
        wait_text(page, r"Sweep done: \d+ frames")
        click(page, "Reconstruct")
        wait_text(page, r"(Volume usable|Not usable|Partial volume): .*of \d+ planned poses")

        # A scan stopped early: no time left shown, and its reconstruction warns first.
        console.panel.frames_per_pass.value = 40
        before = set(tmp_path.glob("volume-*"))
        console.panel.speed.value = 0.2
        click(page, "Scan volume")
        partial = wait_for_new_session(tmp_path, "volume", before)
        wait_for_frames(partial, 3)
        click(page, "Stop")
        wait_text(page, rf"Stopped: \d+ frames kept in .*{re.escape(partial.name)}")
        assert not re.search(r"about \d+ s left", page.inner_text("body"))
        console.panel.speed.value = 1.0
        click(page, "Reconstruct")
        partial_verdict = wait_text(page, r"Partial volume: (\d+) of 200 planned poses scanned, so parts of the "
                                          r"object are missing")
        assert 3 <= int(partial_verdict.group(1)) < 200
        page.screenshot(path=str(SHOTS / f"console-partial-scan-{name}.png"))

        # An uncalibrated calibration session, loaded after the calibrated one: nothing of it stays.
        uncalibrated = tmp_path / "uncalibrated"
        shutil.copytree(calibration_session, uncalibrated, ignore=shutil.ignore_patterns("calibration.*", "segm*"))
        _load(console, page, uncalibrated.name)
        wait_text(page, "Loaded calibration session")
        wait_text(page, "No calibration yet")
        body = page.inner_text("body")
        assert "image corners within" not in body and "Reconstruction:" not in body and "Partial volume" not in body
        show_step(page, "Save session")
        wait_text(page, "Nothing to save yet")
        click(page, "Frame the work")
        wait_until(lambda: _phantom_in_view(console, page, size), "the phantom in view after a load")

        # A reconstructed volume session: its volume, its verdict naming it, and its slices.
        _load(console, page, whole.name)
        wait_text(page, "Loaded volume session")
        show_step(page, "Reconstruct")
        wait_text(page, r"(Volume usable|Not usable|Partial volume)")
        wait_text(page, "Volume slices")
        assert whole.name in page.inner_text("body") and console.view.scene.cloud is not None
        wait_text(page, r"across x \(\+z up, \+y right\)")  # slices labelled, placed in mm
        wait_text(page, r"x \(mm, base frame\)")
        page.screenshot(path=str(SHOTS / f"console-loaded-volume-{name}.png"))
        assert abs(_stop_top(page) - stop_at) < 1.0
        page.close()
    finally:
        console.close()
