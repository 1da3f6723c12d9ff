"""The console with a tracked probe, in headless Chromium at 1280 x 800, as a user runs it: the
freehand twin streamed by the PLUS-server stand-in on loopback, its hand following the guidance."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest

from probecal.app.console.server import launch
from probecal.app.headless import new_tab, wait_text
from probecal.app.tracked import TrackedSpec
from probecal.core.acquisition.igtl import IMAGE_DEVICE, image_message, transform_message
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.tracker import TrackerDevices
from probecal.core.calibration.guided import GuideSettings
from probecal.core.io.session import load_session
from tests.support.waiting import recorded_frames, wait_until

SIZE = {"width": 1280, "height": 800}


def in_view(page, selector: str) -> bool:
    """Whether the element is on screen without scrolling (False while it is being redrawn)."""
    box = page.locator(selector).first.bounding_box()
    return box is not None and box["y"] >= 0 and box["y"] + box["height"] <= SIZE["height"]


def held_still(page) -> int:
    return int(wait_text(page, r"(\d+) frames held still").group(1))


@pytest.fixture
def console(tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, tracked=TrackedSpec("sim"))
    assert console.guided is not None
    console.guided.settings = GuideSettings(first_bound=15, bound_every=15)  # a bound soon, and again
    yield console
    console.close()


def test_guided_acquisition_coverage_bound_pause_and_stop(browser, console):
    page = new_tab(browser, viewport=SIZE)
    page.goto(f"http://127.0.0.1:{console.server.get_port()}")
    page.get_by_role("button", name="Connect").click()
    wait_text(page, "Connected to tracker igtl:127.0.0.1")
    page.get_by_role("tab", name="2 Calibrate").click()
    page.get_by_role("button", name="Start sweep").click()
    wait_text(page, "No calibration yet: the image is drawn where its wire dots place it")
    wait_text(page, "Move the probe slowly up and down over the wires")
    wait_text(page, r"Guided acquisition: \d+ frames recorded while the latency is measured")
    first = held_still(page)
    bound = wait_text(page, r"corner bound: ±(\d+\.\d+) mm", timeout_s=180).group(1)
    wait_text(page, r"Guided acquisition: \d+ frames recorded, \d+ kept")
    # the coverage display and the bound are in view, and change as frames arrive
    wait_until(lambda: in_view(page, ".probecal-guide") and in_view(page, "text=corner bound"),
               "the coverage and the bound in view")
    wait_until(lambda: held_still(page) > first + 5, "more frames held still", timeout_s=120)
    wait_until(lambda: re.search(r"corner bound: ±(\d+\.\d+) mm", page.inner_text("body")).group(1) != bound,
               "the bound measured again", timeout_s=180)
    # a dropped tracker pauses with its reason, and what is recorded stays
    server = console.guided.streams.server
    for fault, said in (("missing", "the tracker marks 'ProbeToTracker' MISSING"), ("silent", "no pose for")):
        server.fault = fault
        wait_text(page, f"Paused: tracker igtl:127.0.0.1:\\d+: {said}")
        session = Path(console.panel.session_path.value)
        kept = recorded_frames(session)
        wait_until(lambda: in_view(page, "text=Paused:"), "the pause's reason in view")
        server.fault = None
        wait_until(lambda: "Paused" not in page.inner_text("body"), "the pause over")
        assert recorded_frames(session) >= kept
    page.get_by_role("button", name="Stop").click()
    said = wait_text(page, r"Stopped: (\d+) frames kept in (\S+); Calibrate calibrates them")
    assert len(load_session(said.group(2))) == int(said.group(1)) >= kept


def test_a_bad_tracker_fails_connect_in_one_line_and_the_console_stays_usable(tmp_path):
    """Unknown device names: Connect says so in one line, naming what the server sends; the
    steps that need the probe stay refused, and the console takes the next job."""
    with IgtlStreamer() as streamer:
        spec = TrackedSpec(f"igtl:127.0.0.1:{streamer.port}", TrackerDevices("PrbToTracker", "ReferenceToTracker"),
                           phantom="fcal-2.0", spacing_mm=(0.1, 0.1))
        console = launch(port=0, sessions_dir=tmp_path, tracked=spec)
        try:
            streamer.play_batches(tracker_batches(4000, "ProbeToTracker"), wait_for_client_s=60.0)
            assert console.connect()
            console.wait(60)
            status = console.panel.status.text
            assert "Connect failed: tracker igtl:127.0.0.1:" in status and "no TRANSFORM 'PrbToTracker'" in status
            assert "the server sends 'ProbeToTracker'" in status
            assert console.panel.start.disabled and not console.busy
            assert console.connect()  # the console is still there to be asked
            console.wait(60)
            assert "Connect failed" in console.panel.status.text
        finally:
            console.close()


def tracker_batches(n: int, device: str):
    """A stand-in's images and tracker poses, 50 a second."""
    start = time.time()
    for k in range(n):
        t = start + k / 50
        yield k / 50, [image_message(np.zeros((40, 30), np.uint8), np.eye(4), t, IMAGE_DEVICE),
                       transform_message(np.eye(4), t, device, "OK"),
                       transform_message(np.eye(4), t, "ReferenceToTracker", "OK")]
