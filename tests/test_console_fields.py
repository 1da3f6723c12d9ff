"""The console's fields are checked on the server where they are used, with the command line's
bounds (``app.bounds``): a page can send any value over its websocket, as a buggy page or a
mistyped value could, and none may plan for minutes, break every later sweep, or print a traceback.
Stop ends a job at its next step, and says "Stopped" only once it has."""

from __future__ import annotations

import pytest
import viser

from probecal.app.console.server import launch
from tests.support.page import RawPage
from tests.support.waiting import wait_until


@pytest.fixture
def console(tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.0)
    yield console
    console.close()


def send(console, field: viser.GuiInputHandle, value, settled=lambda: True, what: str = "the update taken") -> None:
    """What a page sends when a field changes, the page connected until ``settled()`` (viser runs
    a field's callbacks only for a page still there)."""
    with RawPage(console) as page:
        page.set(field, value)
        wait_until(settled, what)


def _job(console, job) -> str:
    job()
    console.wait()
    return console.panel.status.text


@pytest.mark.parametrize("field, value, said", [
    ("poses", 1e6, "Poses: 1e+06 is not within 1 to 1000 poses"),
    ("frames_per_pass", 1e6, "Frames per pass: 1e+06 is not within 1 to 1000 frames"),
    ("translation", (1e9, 0.0, 0.0), "Translation ± mm: 1e+09 is not within 0 to 50 mm"),
])
def test_a_field_out_of_bounds_fails_its_job_at_once_in_one_line(console, field, value, said):
    assert "Connected" in _job(console, console.connect)
    send(console, getattr(console.panel, field), value)
    job = console.scan_volume if field == "frames_per_pass" else console.start_sweep
    job()
    console.wait(timeout=30)  # refused up front, not after minutes of planning
    assert not console.jobs.busy
    status = console.panel.status.text
    assert "failed: " + said in status and "Traceback" not in status, status
    assert not list(console.sessions_dir.iterdir())  # no session begun


@pytest.mark.parametrize("field, value", [
    ("latency_ms", float("nan")), ("latency_ms", float("inf")), ("latency_ms", 1e300),
    ("spacing", (0.0, 0.0)), ("spacing", (-1.0, -1.0)), ("tolerance", 1e9), ("tolerance", float("nan")),
])
def test_a_field_the_console_uses_at_once_goes_back_when_out_of_bounds(console, field, value):
    handle = getattr(console.panel, field)
    kept = handle.value
    latency, spacing, tolerance = console.rig.latency_s, console.nominal_spacing_mm, console.tolerance_mm
    send(console, handle, value, lambda: handle.value == kept, f"{field} back to {kept}")
    assert (console.rig.latency_s, console.nominal_spacing_mm, console.tolerance_mm) == (latency, spacing, tolerance)
    console.connect()
    console.wait()
    assert "Connected" in console.panel.status.text  # and the console works on


@pytest.mark.parametrize("field, job, name", [("poses", "start_sweep", "Start sweep"),
                                              ("frames_per_pass", "scan_volume", "Scan volume")])
def test_stop_ends_a_long_planning_and_says_stopped_only_then(console, field, job, name):
    assert "Connected" in _job(console, console.connect)
    getattr(console.panel, field).value = 1000  # seconds of planning
    getattr(console, job)()
    wait_until(lambda: "Planning" in console.panel.counter.text, "the planning under way")
    console.stop()
    status = console.panel.status.text  # the planning may have seen the request already
    assert f"Stopping: {name} ends at its next step" in status or f"Stopped: {name} ended" in status
    console.wait(timeout=30)
    assert f"Stopped: {name} ended before it finished" in console.panel.status.text
    assert not list(console.sessions_dir.iterdir())


@pytest.mark.parametrize("field, updates", [
    ("poses", {"value": "x"}), ("poses", {"value": float("nan")}), ("speed", {"value": None}),
    ("spacing", {"value": [0.2, 0.2, 0.2]}), ("translation", {"value": "abc"}), ("tolerance", {"value": [1.0]}),
    ("poses", {"bogus": 1}), ("poses", {"value": 5, "min": 1000}), ("start", {"disabled": False}),
    ("motion", {"value": "bogus"}), ("cloud_colors", {"value": None}), ("window", {"value": float("nan")}),
    ("level", {"value": 1e300}), ("speed", {"value": 1e6}),
])
def test_an_update_viser_cannot_take_is_dropped_without_a_traceback(console, capfd, field, updates):
    """A value that is not of the field's type, a vector of another length, a property a page
    never sets, a dropdown's value not among its options or a slider's out of its range: dropped
    before viser casts it (which would print a traceback), the field as it was."""
    handle = getattr(console.panel, field)
    kept, stamp, disabled = handle.value, handle._impl.update_timestamp, console.panel.start.disabled
    with RawPage(console) as page:
        page.update(handle, updates)
        page.set(console.panel.frames_per_pass, 7)  # taken after the hostile update: a page's come in order
    assert handle.value == kept and handle._impl.update_timestamp == stamp
    assert console.panel.poses.min == 1 and console.panel.start.disabled == disabled
    assert "Traceback" not in capfd.readouterr().err
