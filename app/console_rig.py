"""The console's simulated lab: the digital twin's robot and scanner, one frame at a time.

:func:`core.simulation.simulate_calibration` and :func:`core.simulation.simulate_volume` run a
whole acquisition in one call; the console needs the same image formation per frame, at
whatever pose the robot is in, so these step functions call the twin's pieces directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import trimesh

from core.bmode import BModeRenderer
from core.errors import InputError
from core.plan import Plan, PoseRanges, calibration_plan, volume_plan
from core.robot import SimulatedRobot
from core.simulation import (
    OBJECT_ORIGIN_IN_BASE_MM,
    TANK_FLOOR_BELOW_WIRES_MM,
    TARGET_ROTATION_IN_BASE,
    VOLUME_STANDOFF_MM,
    Twin,
    _manifest,
    _small_transform,
    _surface_rows,
    _tank_bottom_rows,
    echo_onset_offset_px,
    make_twin,
)
from core.testobject import TEST_OBJECT_FILE, load_test_object
from core.transforms import invert_transform, make_transform
from core.ur3 import MotionLimits

NOISE = "realistic"
KINDS = ("calibration", "volume")


@dataclass
class SimRig:
    """The twin (seed-drawn mount and phantom placement), its robot and its scanner."""

    seed: int = 0
    time_scale: float = 0.25
    twin: Twin = field(init=False)
    robot: SimulatedRobot = field(init=False)
    renderer: BModeRenderer = field(init=False)

    def __post_init__(self) -> None:
        self.twin = make_twin(self.seed)
        self.robot = SimulatedRobot(seed=self.seed, time_scale=self.time_scale)
        self.renderer = BModeRenderer(self.twin.probe, NOISE, self.seed)
        rng = np.random.default_rng(self.seed + 1)
        self.nominal_object_to_base = make_transform(TARGET_ROTATION_IN_BASE, OBJECT_ORIGIN_IN_BASE_MM)
        self.object_to_base = self.nominal_object_to_base @ _small_transform(rng, 2.0, 2.0)

    @cached_property
    def mesh(self) -> trimesh.Trimesh:
        return load_test_object()

    @cached_property
    def _onset_px(self) -> float:
        return echo_onset_offset_px(self.twin.probe)

    def calibration_frame(self, tool_to_base: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The B-mode frame over the phantom at a flange pose and the true marker pixels (W, 2)."""
        twin = self.twin
        markers = twin.markers_px(tool_to_base)
        floor_z = twin.phantom.lines()[..., 2].min() - TANK_FLOOR_BELOW_WIRES_MM
        image = self.renderer.render(
            markers[np.all(np.isfinite(markers), axis=1)],
            tank_bottom_row=_tank_bottom_rows(twin, twin.image_to_phantom(tool_to_base), floor_z),
            rng=rng,
        )
        return image, markers

    def volume_frame(self, tool_to_base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The B-mode frame over the test object at a flange pose."""
        image_to_object = invert_transform(self.object_to_base) @ tool_to_base @ self.twin.image_to_tool_rigid
        return self.renderer.render(
            np.empty((0, 2)),
            surface_rows=_surface_rows(self.twin, self.mesh, image_to_object) + self._onset_px,
            tank_bottom_row=_tank_bottom_rows(self.twin, image_to_object, 0.0),
            rng=rng,
        )

    def calibration_plan(self, n_poses: int, ranges: PoseRanges, limits: MotionLimits) -> Plan:
        try:
            return calibration_plan(self.twin.nominal, n_poses, seed=self.seed, ranges=ranges, limits=limits)
        except ValueError as exc:
            raise InputError(None, f"no calibration plan: {exc}")

    def volume_plans(self, frames_per_pass: int, limits: MotionLimits) -> list[Plan]:
        lo, hi = self.mesh.bounds
        region_to_base = self.nominal_object_to_base @ make_transform(np.eye(3), [*(lo + hi)[:2] / 2, hi[2]])
        try:
            return volume_plan(region_to_base, self.twin.nominal.image_to_tool_rigid, self.twin.probe,
                               VOLUME_STANDOFF_MM, n_frames=frames_per_pass, limits=limits)
        except ValueError as exc:
            raise InputError(None, f"no volume plan: {exc}")

    def manifest(self, kind: str, plans: list[Plan]) -> dict:
        """The session manifest of a simulated acquisition (as ``probecal simulate`` writes)."""
        manifest = _manifest(kind, self.twin, self.seed, NOISE, plans[0])
        manifest["plan"] = {"passes": len(plans), "poses": sum(len(p.poses) for p in plans),
                            "estimated_robot_time_s": round(sum(p.duration_s for p in plans), 1)}
        if kind == "volume":
            manifest["cad_mesh"] = TEST_OBJECT_FILE.name
        return manifest

    def truth(self, kind: str) -> dict:
        """truth.json of a simulated session, without the per-frame part."""
        if kind == "volume":
            return {**self.twin.truth(), "object_to_base": self.object_to_base, "cad_mesh": TEST_OBJECT_FILE.name}
        return self.twin.truth()
