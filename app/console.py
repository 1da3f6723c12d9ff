"""The browser console (viser). For now a live view of the digital twin: the UR3 at its home
pose, the phantom where the twin put it, and the simulated ultrasound frame at the centred pose.

The scene is in metres (viser's unit); core works in mm, converted here at the edge.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import viser

from core.bmode import BModeRenderer
from core.errors import InputError
from core.robot import HOME_JOINTS
from core.simulation import make_twin
from core.transforms import transform_points
from core.ur3 import link_frames

MM = 1e-3
FRAME_PERIOD_S = 0.1


def _box_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12, 2, 3) edges of an axis-aligned box."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pairs = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return np.array([[corners[a], corners[b]] for a, b in pairs])


def build_scene(server: viser.ViserServer, seed: int = 0) -> None:
    """Draw the twin: robot links, phantom box and wires (base frame), and start the live frame."""
    twin = make_twin(seed)
    joints = np.array([f[:3, 3] for f in link_frames(HOME_JOINTS)]) * MM
    server.scene.add_frame("/base", axes_length=0.1, axes_radius=0.003)
    server.scene.add_line_segments(
        "/robot/links", np.stack([joints[:-1], joints[1:]], axis=1), colors=(90, 140, 200), thickness=0.02
    )
    server.scene.add_point_cloud("/robot/joints", joints, colors=(230, 230, 230), point_size=0.02)
    phantom_to_base = twin.nominal.phantom_to_base
    box = transform_points(phantom_to_base, _box_edges(twin.phantom.box_min, twin.phantom.box_max)) * MM
    server.scene.add_line_segments("/phantom/box", box, colors=(160, 160, 160), thickness=0.002)
    wires = transform_points(phantom_to_base, twin.phantom.lines()) * MM
    server.scene.add_line_segments("/phantom/wires", wires, colors=(40, 90, 230), thickness=0.002)

    server.gui.add_markdown(
        "**probecal** — digital twin preview.\n\n"
        "The operator controls (Connect, Start sweep, Calibrate, Scan volume) arrive with the "
        "console issue; every step already runs from the `probecal` command line."
    )
    renderer = BModeRenderer(twin.probe, "realistic", seed)
    centred = twin.nominal.tool_to_base(twin.nominal.image_to_phantom)
    markers = twin.markers_px(centred)
    markers = markers[np.all(np.isfinite(markers), axis=1)]
    image = server.gui.add_image(renderer.render(markers), label="live ultrasound (simulated)", format="png")

    def stream() -> None:
        rng = np.random.default_rng(seed)
        while True:
            time.sleep(FRAME_PERIOD_S)
            image.image = renderer.render(markers, rng=rng)

    threading.Thread(target=stream, daemon=True, name="probecal-live-frame").start()


def serve(host: str = "127.0.0.1", port: int = 8080, robot: str = "sim", image: str = "sim") -> None:
    """Start the console and block until interrupted."""
    if robot != "sim" or image != "sim":
        raise InputError(None, "only the built-in simulator (--robot sim --image sim) is available so far")
    server = viser.ViserServer(host=host, port=port, label="probecal")
    build_scene(server)
    print(f"probecal console on http://{host}:{server.get_port()} (Ctrl+C to stop)", flush=True)
    while True:
        time.sleep(1.0)
