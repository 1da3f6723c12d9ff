"""The browser console, driven the way an operator drives it: headless Chromium clicks the
buttons of an in-process console on the simulator and reads the results off the page."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from probecal.app.console.panel import STRIP_WIDTH
from probecal.app.console.server import launch
from probecal.app.headless import (
    click,
    count_image_updates,
    image_updates,
    new_tab,
    open_console,
    projected_px,
    screenshot_panel_top,
    show_step,
    wait_text,
)
from probecal.core.geometry.transforms import transform_points
from probecal.core.io.session import load_session
from tests.support.waiting import wait_for_frames, wait_for_new_session, wait_until

pytest.importorskip("playwright.sync_api")

SHOTS = Path(__file__).resolve().parent.parent / "out" / "screenshots"  # git-ignored


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    console = launch(port=0, sessions_dir=tmp_path_factory.mktemp("sessions"), time_scale=0.25)
    yield console
    console.stop()
    console.server.stop()


def _open(browser, console):
    return open_console(browser, console.server.get_port())


@pytest.mark.slow
def test_console_calibrates_and_reconstructs_from_the_page(console, browser):
    page = _open(browser, console)
    click(page, "Connect")
    wait_text(page, "Connected to the simulated UR3")

    console.panel.poses.value = 12
    count_image_updates(page)
    before = set(console.sessions_dir.glob("calibration-*"))
    click(page, "Start sweep")
    session = wait_for_new_session(console.sessions_dir, "calibration", before)
    wait_text(page, r"Sweep done: 12 frames")  # a second click during a sweep: the next test, on a slow one
    assert image_updates(page) > 12  # the live frame moves between the recorded poses too
    sessions = sorted(console.sessions_dir.glob("calibration-*"))
    assert sessions == [session] and len(load_session(session)) == 12
    page.screenshot(path=str(SHOTS / "sweep.png"))

    click(page, "Calibrate")
    bound = float(wait_text(page, r"(?:Calibration usable|Not usable): image corners within ±(\d+\.\d+) mm "
                                  r"\(95 %\), (?:under|over) your 1\.0 mm tolerance").group(1))  # the verdict first
    fre = float(wait_text(page, r"FRE (\d+\.\d+) mm").group(1))
    pre3d = float(wait_text(page, r"PRE3D (\d+\.\d+) ±").group(1))
    assert fre < 0.5 and pre3d < 1.0 and bound < 3.0
    assert "image to tool, rigid" not in page.inner_text("body")  # the full report, one click away
    page.get_by_text("Full report").click()
    wait_text(page, "image to tool, rigid")
    click(page, "Check phantom")
    wait_text(page, r"Phantom checked from \d+ frames")
    wait_text(page, "wires located from")  # the table, as probecal phantom check prints it
    # The report's and the check's tables fit the side panel (the printout's rows wrapped, issue 34).
    widths = page.evaluate("() => [...document.querySelectorAll('table')].map("
                           "t => [t.getBoundingClientRect().width, t.parentElement.clientWidth])")
    assert len(widths) >= 5 and all(0 < width <= room + 0.5 for width, room in widths), widths
    curve = console.panel.curve
    assert curve.visible and len(curve.data[0]) >= 2 and np.all(np.isfinite(curve.data[2]))  # viser's own plot
    assert curve.scales["x"]["time"] is False  # counted poses, not uPlot's default of dates

    console.panel.frames_per_pass.value = 8
    click(page, "Scan volume")
    wait_text(page, r"Sweep done: 40 frames", timeout_s=90)
    click(page, "Reconstruct")
    surface = float(wait_text(page, r"surface to CAD (\d+\.\d+) mm mean", timeout_s=90).group(1))
    assert surface < 1.0
    height = console.view.scene.cloud.colors.copy()
    console.panel.cloud_colors.value = "error to CAD"
    assert not np.array_equal(console.view.scene.cloud.colors, height)
    page.wait_for_timeout(1000)  # let the point cloud reach the page before the picture
    screenshot_panel_top(page, SHOTS / "console.png")

    show_step(page, "Save session")
    wait_text(page, rf"Save writes calibration\.json, calibration\.xml, segmentation\.json, phantom_check\.json into "
                    rf"the calibration session {sessions[0].name}")  # said before the click
    click(page, "Save session")
    wait_text(page, rf"Saved calibration\.json, .* into the calibration session {re.escape(str(sessions[0]))}")
    assert (sessions[0] / "phantom_check.json").is_file() and not (console.volume_session / "calibration.json").exists()
    page.close()


def _disabled(page, names: tuple[str, ...]) -> dict[str, bool]:
    """Whether each of the buttons ``names`` (of one step's tab) is disabled on the page."""
    show_step(page, names[0])
    return {name: page.get_by_role("button", name=name, exact=True).is_disabled() for name in names}


@pytest.mark.slow
def test_impossible_steps_are_disabled_and_a_failure_notification_goes_with_its_cause(browser, tmp_path):
    """Before Connect every step but Connect is disabled, its hint saying why; a step asked for
    anyway (by a script, or a tab that has not caught up) fails in a red notification, which goes
    once its cause goes: Start sweep's at Connect, Calibrate's once a sweep is recorded."""
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.0)
    try:
        page = _open(browser, console)
        toasts = page.locator(".mantine-Notification-root")
        assert _disabled(page, ("Connect", "Measure latency")) == {"Connect": False,
                                                                              "Measure latency": True}
        assert all(_disabled(page, ("Start sweep", "Calibrate", "Check phantom")).values())
        assert all(_disabled(page, ("Scan volume", "Reconstruct")).values())
        assert _disabled(page, ("Save session", "Load session")) == {"Save session": True,
                                                                                  "Load session": False}
        assert console.panel.start.hint.startswith("Not yet: connect the robot first")
        console.start_sweep()  # not from the page: its button is disabled
        toasts.filter(has_text="Start sweep failed").wait_for()
        click(page, "Connect")
        wait_text(page, "Connected to the simulated UR3")
        toasts.filter(has_text="Start sweep failed").wait_for(state="detached")
        assert _disabled(page, ("Start sweep", "Calibrate")) == {"Start sweep": False,
                                                                                "Calibrate": True}
        console.calibrate()
        toasts.filter(has_text="Calibrate failed").wait_for()
        console.panel.poses.value = 8
        click(page, "Start sweep")
        wait_text(page, "Sweep done: 8 frames")
        toasts.filter(has_text="Calibrate failed").wait_for(state="detached")
        wait_until(lambda: not page.get_by_role("button", name="Calibrate", exact=True).is_disabled(),
                   "Calibrate enabled once a sweep is recorded")
    finally:
        console.close()


@pytest.mark.slow
@pytest.mark.timeout(900)  # three tabs in software WebGL: 90 s alone, over 200 s beside another worker
def test_tabs_share_state_and_stop_halts_a_sweep(console, browser):
    tabs = [_open(browser, console) for _ in range(3)]
    click(tabs[0], "Connect")
    for tab in tabs:
        wait_text(tab, "Connected to the simulated UR3")
    for tab in tabs:
        show_step(tab, "Calibrate")
    texts = [re.search(r"FRE \d+\.\d+ mm", tab.inner_text("body")) for tab in tabs]
    if console.calibration is not None:  # the state of the first test, when it ran
        assert len({t.group(0) for t in texts if t}) == 1 and all(texts)

    before = set(console.sessions_dir.glob("calibration-*"))
    console.panel.poses.value = 120
    console.panel.speed.value = 0.1  # a sweep of two minutes or more: Stop lands in it, however slow the page
    # is (three tabs rendering in software WebGL may take 10-25 s to answer a click)
    click(tabs[2], "Start sweep")
    session = wait_for_new_session(console.sessions_dir, "calibration", before)
    wait_for_frames(session, 3)
    click(tabs[1], "Start sweep")  # a second sweep while one runs does nothing
    click(tabs[1], "Stop")
    stopped = rf"Stopped: (\d+) frames kept in {re.escape(str(session))}"  # this sweep's report, never stale
    kept = {int(wait_text(tab, stopped).group(1)) for tab in tabs}
    assert not console.rig.robot.is_moving()
    assert set(console.sessions_dir.glob("calibration-*")) - before == {session}
    assert kept == {len(load_session(session))} and 3 <= kept.pop() < 120
    console.panel.speed.value = 1.0
    for k, tab in enumerate(tabs):
        tab.screenshot(path=str(SHOTS / f"tab{k}.png"))
        tab.close()


def _in_view(page, locator) -> bool:
    box = locator.bounding_box()
    size = page.viewport_size
    return box is not None and box["y"] >= 0 and box["y"] + box["height"] <= size["height"] and box["x"] >= 0


@pytest.mark.slow
def test_the_status_stays_in_view_during_a_sweep_and_the_camera_frames_the_phantom(console, browser):
    others = set(console.server.get_clients())  # the earlier tests' tabs (closed, but maybe not yet gone)
    page = new_tab(browser, viewport=SMALL)
    page.goto(f"http://127.0.0.1:{console.server.get_port()}")
    click(page, "Connect")
    wait_text(page, "Connected to the simulated UR3")
    console.panel.poses.value = 10
    console.panel.resume.value = False  # a new sweep, whatever an earlier test left unfinished
    click(page, "Start sweep")
    counter = page.get_by_text(re.compile(r"Frames recorded: [1-9]"))
    counter.wait_for(timeout=60_000)
    for _ in range(3):  # while the sweep runs, on the page of the smaller screen (the counter is drawn anew
        # with each frame: in view once drawn)
        wait_until(lambda: _in_view(page, counter), "the counter in view", timeout_s=10)
        assert _in_view(page, page.get_by_role("button", name="Stop", exact=True))
        assert _in_view(page, page.get_by_role("button", name="Calibrate", exact=True))
        page.wait_for_timeout(200)
    wait_text(page, r"Sweep done: 10 frames")
    click(page, "Calibrate")
    wait_text(page, r"Calibrated in \d+\.\d s")
    calibration = console.calibration
    centre = calibration.phantom_to_base @ np.append(console.rig.twin.phantom.center(), 1.0)
    # The page moves its camera smoothly and reports where it is: wait until the phantom is in the
    # middle of what the status column and the side panel leave of the view.
    seen: list[tuple[np.ndarray, float]] = []

    def this_tab() -> list:
        """This tab's client, found anew: a tab whose websocket drops on a busy machine comes back
        as a new client."""
        return [c for key, c in console.server.get_clients().items() if key not in others]

    def framed():
        middle = (STRIP_WIDTH + _side_panel_left(page)) / 2  # read anew: the page may still be laying out
        for client in this_tab():
            seen.append((projected_px(client, centre[None, :3] / 1000.0, SMALL)[0], middle))
            if np.allclose(seen[-1][0], [middle, SMALL["height"] / 2], atol=40):
                return client
        return None

    try:
        client = wait_until(framed, "the camera on the phantom")
    except AssertionError as error:
        clients = {key: (c.camera.image_width, c.camera.image_height, np.round(c.camera.look_at, 3))
                   for key, c in console.server.get_clients().items()}
        raise AssertionError(f"{error}: the phantom (px) and the middle's x last {seen[-1:]}; clients {clients} "
                             f"(earlier {sorted(others)}); framed on {console.server.initial_camera.look_at}") from None
    assert np.linalg.norm(client.camera.position - client.camera.look_at) < 0.8
    assert _in_view(page, page.get_by_text(re.compile(r"PRE3D \d+\.\d+ ± \d+\.\d+ mm \(consistency\)")))
    click(page, "Whole robot")
    wait_until(lambda: any(np.linalg.norm(c.camera.position - c.camera.look_at) > 0.5 for c in this_tab()),
               "the whole robot in view")
    page.close()


SMALL = {"width": 1280, "height": 800}


def _side_panel_left(page) -> float:
    """Where the side panel begins on the page (px): its first tab's left edge."""
    return page.get_by_role("tab", name="1 Connect").bounding_box()["x"]


def _work_on_screen(console, page, points_m) -> tuple[float, float]:
    """The width and height (px) at 1280 x 800 of the box around ``points_m`` (m, base frame) as
    the tab's camera sees it, once the tab has the camera the console framed; asserted whole,
    between the status column and the side panel."""
    console.jobs.wait(timeout=120)  # the step that framed it has run through: its status comes before its framing
    assert console.jobs.current is None
    look_at = np.asarray(console.server.initial_camera.look_at)
    client = wait_until(lambda: next((c for c in console.server.get_clients().values()
                                      if np.allclose(c.camera.look_at, look_at, atol=1e-3)), None),
                        "the tab's camera on the work")
    lo, hi = np.min(points_m, axis=0), np.max(points_m, axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    px = projected_px(client, corners, SMALL)
    assert np.all(np.isfinite(px)), px
    assert px[:, 0].min() >= STRIP_WIDTH and px[:, 0].max() <= _side_panel_left(page), px
    assert px[:, 1].min() >= 0 and px[:, 1].max() <= SMALL["height"], px
    return float(np.ptp(px[:, 0])), float(np.ptp(px[:, 1]))


@pytest.mark.slow
def test_each_step_shows_what_it_produced_in_view_and_hides_what_is_in_the_way(browser, tmp_path):
    """At 1280 x 800: after Calibrate the phantom, its wires and every frame's markers, large enough
    to read, the robot and probe faded and the image plane down to its outline, and the
    calibration's bound map over the live frame (grey before but for its markers; the same frame,
    drawn again) with its legend in mm, from the map's least bound to its largest; while scanning
    and after Reconstruct the test object, then its cloud, and nothing of the calibration; and the
    View step's switches show and hide a layer."""
    from probecal.app.console.panel import BOUND_LABEL
    from probecal.app.console.scene import FADED_OPACITY

    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.0)
    try:
        page = new_tab(browser, SMALL)
        page.goto(f"http://127.0.0.1:{console.server.get_port()}")
        click(page, "Connect")
        wait_text(page, "Connected to the simulated UR3")
        console.panel.poses.value = 8
        click(page, "Start sweep")
        wait_text(page, "Sweep done: 8 frames")
        legend = page.get_by_text(BOUND_LABEL, exact=True)
        assert not legend.is_visible()
        grey = page.evaluate(_FRAME_COLOURED, STRIP_WIDTH)
        assert grey < 0.1, grey
        click(page, "Calibrate")
        wait_text(page, "Calibrated in")
        legend.wait_for(state="visible")
        overlay = console.view.bound_overlay
        assert overlay is not None
        bounds = np.array(console.calibration.metrics["bound_map"]["bound_mm"], dtype=float)
        assert (overlay.low, overlay.high) == (bounds.min(), bounds.max())
        wait_until(lambda: page.evaluate(_FRAME_COLOURED, STRIP_WIDTH) > 0.9, "the bound map over the live frame")
        scene = console.view.scene
        assert scene.phantom_box.visible and scene.wires.visible and scene.registration.visible
        assert len(scene.registration.points) > 8 * 9  # every frame's markers, not the last frame's
        assert all(h.opacity == FADED_OPACITY for h in scene.arm) and scene.probe.opacity == FADED_OPACITY
        assert scene.outline.visible and not scene.plane_image.visible
        assert not any(console.panel.layers[layer].value for layer in ("cloud", "CAD model", "volume"))
        page.screenshot(path=str(SHOTS / "calibrated-1280x800.png"))
        phantom = console.rig.twin.phantom
        box = transform_points(console.calibration.phantom_to_base, np.array([phantom.box_min, phantom.box_max]))
        width, height = _work_on_screen(console, page, box * 1e-3)
        assert min(width, height) > 250, (width, height)  # the phantom: about 130 x 100 px before (issue 34)
        _work_on_screen(console, page, scene.registration.points)  # and every marker on it

        console.panel.frames_per_pass.value = 4
        click(page, "Scan volume")
        wait_text(page, r"Sweep done: \d+ frames")
        assert scene.object is not None and scene.object.visible
        assert not (scene.phantom_box.visible or scene.wires.visible or scene.registration.visible)
        lo, hi = console.mesh.bounds
        width, height = _work_on_screen(console, page, transform_points(console.rig.scanner.object_to_base,
                                                                  np.array([lo, hi])) * 1e-3)
        assert min(width, height) > 150, (width, height)  # the test object, framed while scanning
        click(page, "Reconstruct")
        wait_text(page, "surface to CAD")
        assert scene.cloud is not None and scene.cloud.visible and scene.object.visible
        assert not any(h.visible for h in (*scene.arm, scene.probe, scene.outline, scene.plane_image,
                                           scene.phantom_box, scene.wires, scene.registration))
        wait_text(page, "Volume slices")  # and the volume, three slices with window and level
        page.screenshot(path=str(SHOTS / "reconstructed-1280x800.png"))
        width, height = _work_on_screen(console, page, scene.cloud.points.astype(float))
        assert min(width, height) > 150, (width, height)

        page.get_by_role("tab", name="View").click()
        page.get_by_label("Robot", exact=True).check()
        wait_until(lambda: all(h.visible for h in scene.arm), "the arm shown by its switch")
        page.get_by_label("Cloud", exact=True).uncheck()
        wait_until(lambda: not scene.cloud.visible, "the cloud hidden by its switch")
        assert scene.object.visible  # the other layers as they were
    finally:
        console.close()


_FRAME_COLOURED = """(stripWidth) => {
  // The share of the live frame's pixels (the largest picture in the status column) that carry a
  // colour: the grey echoes carry none, the markers little, the bound map all of it.
  const frame = [...document.querySelectorAll('img')]
    .filter((img) => img.getBoundingClientRect().right <= stripWidth && img.naturalWidth > 0)
    .sort((a, b) => b.naturalWidth * b.naturalHeight - a.naturalWidth * a.naturalHeight)[0];
  if (!frame) return 0;
  const canvas = document.createElement('canvas');
  [canvas.width, canvas.height] = [frame.naturalWidth, frame.naturalHeight];
  const context = canvas.getContext('2d');
  context.drawImage(frame, 0, 0);
  const pixels = context.getImageData(0, 0, canvas.width, canvas.height).data;
  let coloured = 0;
  for (let i = 0; i < pixels.length; i += 4) {
    const [r, g, b] = [pixels[i], pixels[i + 1], pixels[i + 2]];
    if (Math.max(r, g, b) - Math.min(r, g, b) > 24) coloured++;
  }
  return coloured / (pixels.length / 4);
}"""
