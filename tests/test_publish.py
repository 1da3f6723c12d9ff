"""OpenIGTLink output for 3D Slicer: the console sends the calibration and every tracked frame it
shows, received here by pyigtl's own client over loopback."""

from __future__ import annotations

import socket

import numpy as np
import pyigtl

from probecal.app.console.server import launch


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_console_publishes_the_calibration_and_tracked_frames(tmp_path):
    port = _free_port()
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.0, publish=port)
    client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
    try:
        assert console.publisher.wait_for_client(10.0)
        console.connect()
        console.wait()
        frame = client.wait_for_message("Image", timeout=5)
        pose = client.wait_for_message("ProbeToReference", timeout=5)
        assert frame is not None and frame.image.shape[-2:] == (500, 384)
        assert np.allclose(pose.matrix, console.rig.robot.tool_to_base(), atol=1e-3)

        console.panel.poses.value = 8
        console.start_sweep()
        console.wait()
        console.calibrate()
        console.wait()
        calibration = client.wait_for_message("ImageToProbe", timeout=5)
        assert np.allclose(calibration.matrix, console.calibration.image_to_tool, atol=1e-3)

        console.connect()  # a frame shown after the calibration is placed by it
        console.wait()
        tool_to_base = console.rig.robot.tool_to_base()
        expected = tool_to_base @ console.calibration.image_to_tool
        for _ in range(10):
            frame = client.wait_for_message("Image", timeout=5)
            if not np.allclose(frame.ijk_to_world_matrix, np.eye(4)):
                break
        # The base frame goes out as Slicer's world unchanged, as PLUS sends its Reference.
        assert np.allclose(frame.ijk_to_world_matrix, expected, atol=1e-2)
    finally:
        client.stop()
        console.close()
