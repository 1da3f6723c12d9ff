"""Markup from outside never runs in the console: every text that comes from a file, a folder's
name or a peer (session folder names, a manifest's fields, a frame's file name quoted in an error,
a tracker's device names and TransformStatus) is pushed through the console as a user would meet
it, with a script payload, and real Chromium shows it as typed while nothing runs.

A payload is checked to run when put on the page raw (the control), so that "nothing ran" means
something; and no code of the console but its text boundary (``app/console/text.py``) puts
content on the page."""

from __future__ import annotations

import ast
import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from probecal.app.console.server import launch
from probecal.app.headless import click, new_tab, wait_text
from probecal.app.tracked import TrackedSpec
from probecal.core.acquisition.igtl import IMAGE_DEVICE, image_message, transform_message
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.acquisition.tracker import TrackerDevices

pytestmark = pytest.mark.browser

RAN = "window.__pwned === 1 || window.__p === 1 || document.title === 'PWNED'"
"""What any payload does when it runs."""
IMG = "<img src=x onerror=window.__pwned=1>"
IFRAME = "<iframe srcdoc=\"<script>top.document.title='PWNED'<&#47;script>\">"
SHORT = "<img src onerror=X>"
"""Payloads: an image whose error runs script, an inline frame holding a script (a session folder
name that ran in the console), and an image whose error runs a getter the page defines
(:data:`TRAP`), within the 20 bytes an OpenIGTLink device name holds."""
TRAP = "Object.defineProperty(window, 'X', {get() { window.__p = 1; }});"
PAYLOAD_ELEMENTS = "img[onerror], iframe[srcdoc]"
"""What the payloads would put on the page."""
APP = Path(__file__).resolve().parent.parent / "app"


def open_console(browser, port: int):
    """A tab on the console, once its controls are on it, with :data:`TRAP` set."""
    page = new_tab(browser)
    page.add_init_script(TRAP)
    page.goto(f"http://127.0.0.1:{port}")
    page.get_by_role("button", name="Connect").wait_for()
    return page


def _nothing_ran(page) -> None:
    """No element a payload makes is on the page (innerHTML would have made it with the text
    shown), and nothing a payload does has happened."""
    assert page.locator(PAYLOAD_ELEMENTS).count() == 0, "markup from outside is on the page"
    assert not page.evaluate(RAN), "markup from outside ran in the console"


def _shows(page, text: str) -> None:
    wait_text(page, re.escape(text))


def _load(console, page, folder: str) -> None:
    console.panel.session_path.value = folder
    page.get_by_role("tab", name="4 Session").click()
    click(page, "Load session")


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> Path:
    """A calibration session named IFRAME with its calibration saved, a volume session named IMG,
    a calibration session whose manifest's kind is IMG and one whose first frame is named IMG."""
    root = tmp_path_factory.mktemp("sessions")
    cal = simulate_calibration(root / IFRAME, n_poses=3, seed=5, noise="none")
    shutil.copy(cal.path / "truth.json", cal.path / "calibration.json")
    simulate_volume(root / IMG, seed=5, noise="none", n_frames=4)
    shutil.copytree(cal.path, root / "kind", ignore=shutil.ignore_patterns("calibration.json"))
    manifest = json.loads((root / "kind" / "manifest.json").read_text())
    (root / "kind" / "manifest.json").write_text(json.dumps({**manifest, "kind": IMG}))
    shutil.copytree(cal.path, root / "frame")
    records = (root / "frame" / "records.jsonl").read_text()
    (root / "frame" / "records.jsonl").write_text(records.replace("frames/000000.png", f"frames/{IMG}.png", 1))
    return root


def test_the_payloads_run_when_put_on_the_page_raw(browser, sessions):
    """The control: unescaped, each payload runs in this browser."""
    console = launch(port=0, sessions_dir=sessions, time_scale=0.0)
    try:
        for payload in (IMG, IFRAME, SHORT):
            page = open_console(browser, console.server.get_port())
            console.view.panel.status._handle.content = payload  # past the text boundary, on purpose
            page.wait_for_function(RAN, timeout=30_000)
            console.view.status("Not connected.")
            page.close()
    finally:
        console.close()


def test_names_fields_and_errors_from_session_files_show_as_typed_and_never_run(browser, sessions):
    console = launch(port=0, sessions_dir=sessions, time_scale=0.0)
    try:
        page = open_console(browser, console.server.get_port())
        _load(console, page, IFRAME)  # the folder's name: status, counter, results and Save's note
        _shows(page, f"Loaded calibration session {sessions / IFRAME} (3 frames)")
        _shows(page, f"Calibration: saved in {IFRAME}")
        page.get_by_role("tab", name="2 Calibrate").click()
        _shows(page, f"session {IFRAME}")
        _nothing_ran(page)
        _load(console, page, IMG)  # a volume session's
        _shows(page, f"Loaded volume session {sessions / IMG} (")
        _shows(page, "Volume session: ")
        _nothing_ran(page)
        _load(console, page, "kind")  # a manifest's field
        _shows(page, f"Loaded {IMG} session")
        _nothing_ran(page)
        _load(console, page, "frame")  # an error quoting a file's name, in the status and the notification
        _shows(page, f"Load session failed: {sessions / 'frame' / 'frames' / IMG}.png")
        assert page.get_by_text(f"{IMG}.png").count() >= 2  # the status line and the notification
        _nothing_ran(page)
    finally:
        console.close()


def _tracker(state: dict[str, str], n: int = 6000):
    """A PLUS server stand-in's frames (640 x 480 px) and both poses, 50 a second, the probe's
    device name and status as ``state`` holds them when each is sent."""
    start = time.time()
    for k in range(n):
        t = start + k / 50
        yield k / 50, [image_message(np.zeros((480, 640), np.uint8), np.diag([0.1, 0.1, 1.0, 1.0]), t, IMAGE_DEVICE),
                       transform_message(np.eye(4), t, state["device"], state["status"]),
                       transform_message(np.eye(4), t, "ReferenceToTracker", "OK")]


def _tracked_console(sessions: Path, streamer: IgtlStreamer):
    spec = TrackedSpec(f"igtl:127.0.0.1:{streamer.port}", TrackerDevices("ProbeToTracker", "ReferenceToTracker"),
                       phantom="fcal-2.0", spacing_mm=(0.1, 0.1))
    return launch(port=0, sessions_dir=sessions, tracked=spec)


@pytest.mark.parametrize("device, status", [(SHORT, "OK"), ("ProbeToTracker", IMG)])
def test_what_a_tracker_sends_at_connect_shows_as_typed_and_never_runs(browser, sessions, device, status):
    """A device name the server sends, named when the wanted one never comes; a status, named
    when no valid pose comes."""
    with IgtlStreamer() as streamer:
        console = _tracked_console(sessions, streamer)
        try:
            streamer.play_batches(_tracker({"device": device, "status": status}), wait_for_client_s=60.0)
            page = open_console(browser, console.server.get_port())
            click(page, "Connect")
            _shows(page, "Connect failed: tracker igtl:127.0.0.1:")
            _shows(page, device if status == "OK" else status)
            _nothing_ran(page)
        finally:
            console.close()


def test_a_tracker_status_that_pauses_a_guided_run_shows_as_typed_and_never_runs(browser, sessions):
    state = {"device": "ProbeToTracker", "status": "OK"}
    with IgtlStreamer() as streamer:
        console = _tracked_console(sessions, streamer)
        try:
            streamer.play_batches(_tracker(state), wait_for_client_s=60.0)
            page = open_console(browser, console.server.get_port())
            click(page, "Connect")
            wait_text(page, "Connected to tracker igtl:127.0.0.1")
            page.get_by_role("tab", name="2 Calibrate").click()
            click(page, "Start sweep")
            wait_text(page, "Move the probe slowly up and down over the wires")
            state["status"] = IMG
            _shows(page, f"Paused: tracker igtl:127.0.0.1:{streamer.port}: the tracker marks 'ProbeToTracker'")
            _shows(page, IMG)
            _nothing_ran(page)
            click(page, "Stop")
            wait_text(page, "Stopped:")
        finally:
            console.close()


def test_only_the_text_boundary_puts_content_on_the_page():
    """No module of the app but ``console/text.py`` calls viser's add_html or add_markdown, or sets
    an element's content: what any other shows passes through TextBox."""
    offenders = []
    for path in APP.rglob("*.py"):
        if path.name == "text.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            called = isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr
            assigned = isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Attribute) and t.attr == "content" for t in node.targets)
            if called in ("add_html", "add_markdown") or assigned:
                offenders.append(f"{path.relative_to(APP)}:{node.lineno}")
    assert not offenders, offenders
