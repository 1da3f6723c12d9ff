"""The console's fields are checked on the server where they are used, with the command line's
bounds (``app.bounds``): a page can send any value over its websocket, as a buggy page or a
mistyped value could, and none may plan for minutes, break every later sweep, or print a traceback.
Stop ends a job at its next step, and says "Stopped" only once it has."""

from __future__ import annotations

import html
import socket

import msgspec.msgpack
import pytest
import viser
from websockets.sync.client import connect

from probecal.app.console.server import launch
from tests.conftest import wait_until

CAMERA = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 1.0), "fov": 1.0,
          "near": 0.01, "far": 100.0, "image_height": 800, "image_width": 1280, "look_at": (0.0, 0.0, 0.0),
          "up_direction": (0.0, 0.0, 1.0)}


@pytest.fixture
def console(tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.0)
    yield console
    console.close()


def send(console, field: viser.GuiInputHandle, value, settled=lambda: True, what: str = "the update taken") -> None:
    """What a page sends when a field changes: a GUI update over an admitted page's websocket, the
    page connected until ``settled()`` (viser runs a field's callbacks only for a page still there)."""
    before = field._impl.update_timestamp
    port = console.server.get_port()
    clients = len(console.server.get_clients())
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    with connect(f"ws://127.0.0.1:{port}/", sock=sock, origin=f"http://127.0.0.1:{port}", open_timeout=10,
                 subprotocols=[f"viser-v{viser.__version__}"]) as ws:
        ws.send(msgspec.msgpack.encode(CAMERA))  # a page's first message: viser admits it as a client then
        wait_until(lambda: len(console.server.get_clients()) > clients, "the page connected")
        ws.send(msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": field._impl.uuid,
                                        "updates": {"value": value}}))
        wait_until(lambda: field._impl.update_timestamp != before, "the update taken")
        wait_until(settled, what)
    wait_until(lambda: len(console.server.get_clients()) == clients, "the page gone")  # nothing sent to it after


def _job(console, job) -> str:
    job()
    console.wait()
    return console.panel.status.content


@pytest.mark.parametrize("field, value, said", [
    ("poses", 1e6, "Poses: 1e+06 is not within 1 to 1000 poses"),
    ("frames_per_pass", 1e6, "Frames per pass: 1e+06 is not within 1 to 1000 frames"),
    ("motion", "bogus", "Motion: 'bogus' is not one of"),
    ("speed", 1e6, "Speed: 1e+06 is not within 0.01 to 10 of the UR default"),
    ("translation", (1e9, 0.0, 0.0), "Translation ± mm: 1e+09 is not within 0 to 50 mm"),
])
def test_a_field_out_of_bounds_fails_its_job_at_once_in_one_line(console, field, value, said):
    assert "Connected" in _job(console, console.connect)
    send(console, getattr(console.panel, field), value)
    job = console.scan_volume if field == "frames_per_pass" else console.start_sweep
    job()
    console.wait(timeout=30)  # refused up front, not after minutes of planning
    assert not console.jobs.busy
    status = html.unescape(console.panel.status.content)
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
    assert "Connected" in console.panel.status.content  # and the console works on


def test_stop_ends_a_long_planning_and_says_stopped_only_then(console):
    assert "Connected" in _job(console, console.connect)
    console.panel.poses.value = 1000  # seconds of planning
    console.start_sweep()
    wait_until(lambda: "Planning" in console.panel.counter.content, "the planning under way")
    console.stop()
    status = console.panel.status.content  # the planning may have seen the request already
    assert "Stopping: Start sweep ends at its next step" in status or "Stopped: Start sweep ended" in status
    console.wait(timeout=30)
    assert "Stopped: Start sweep ended before it finished" in console.panel.status.content
    assert not list(console.sessions_dir.iterdir())
