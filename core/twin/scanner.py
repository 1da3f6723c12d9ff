"""The twin's scanner: the B-mode frame a flange pose sees of the N-wire phantom (calibration) or
of the test object (volume), rendered from the true set-up (``core.twin.twin``)."""

from __future__ import annotations

from dataclasses import replace
from functools import cached_property

import numpy as np
import trimesh

from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Probe
from probecal.core.geometry.transforms import invert_transform, make_transform, transform_points
from probecal.core.twin.bmode import BModeRenderer
from probecal.core.twin.levels import Level, level
from probecal.core.twin.testobject import TEST_OBJECT_FILE, load_test_object
from probecal.core.twin.twin import TARGET_ROTATION_IN_BASE, Twin, make_twin, random_offset

# The tank floor sits this far below the lowest wire layer.
TANK_FLOOR_BELOW_WIRES_MM = 10.0


FAN_COLUMN_STEP_PX = 8
"""A fan image's columns bend in the medium when the sound speeds differ; they are followed in
steps of this many rows (a linear image's columns are straight: its first and last rows do)."""


def _tank_bottom_rows(twin: Twin, image_to_target: np.ndarray, floor_z_mm: float) -> np.ndarray:
    """Per-column row where the plane z = floor_z (target frame) meets the image, NaN if none."""
    probe = twin.probe
    last = probe.height_px - 1
    rows = np.append(np.arange(0, last, FAN_COLUMN_STEP_PX), last) if probe.fan is not None else np.array([0, last])
    grid = np.stack(np.broadcast_arrays(np.arange(probe.width_px, dtype=float)[:, None], rows[None, :]), axis=-1)
    points = np.concatenate([probe.mm_from_pixels(grid), np.zeros((*grid.shape[:2], 1))], axis=-1)
    height = transform_points(image_to_target, points.reshape(-1, 3))[:, 2].reshape(grid.shape[:2]) - floor_z_mm
    above = height > 0
    out = np.full(probe.width_px, np.nan)
    crossed = above[:, :-1] != above[:, 1:]
    columns = np.nonzero(crossed.any(axis=1))[0]
    step = np.argmax(crossed[columns], axis=1)
    h0, h1 = height[columns, step], height[columns, step + 1]
    out[columns] = rows[step] + (rows[step + 1] - rows[step]) * h0 / (h0 - h1)
    return out


# Volume scene: the test object sits on the tank floor in front of the robot, the probe face
# 12 mm above its highest point.
OBJECT_ORIGIN_IN_BASE_MM = np.array([30.0, -280.0, -80.0])
VOLUME_STANDOFF_MM = 12.0


class TwinScanner:
    """The twin's scanner: the B-mode frame a flange pose sees of the phantom (calibration) or
    of the test object (volume). The object's true placement is drawn from ``seed`` like the
    phantom's; ``nominal_object_to_base`` is where it was meant to go."""

    def __init__(self, twin: Twin, noise: str | Level = "realistic", seed: int = 0):
        self.level = level(noise)
        self.twin, self.noise = twin, self.level.name
        self.renderer = BModeRenderer(twin.probe, self.level.noise, seed, self.level.imaging)
        self.nominal_object_to_base = make_transform(TARGET_ROTATION_IN_BASE, OBJECT_ORIGIN_IN_BASE_MM)
        self.object_to_base = self.nominal_object_to_base @ random_offset(np.random.default_rng(seed + 1), 2.0, 2.0)
        self._floor_z = twin.phantom.lines()[..., 2].min() - TANK_FLOOR_BELOW_WIRES_MM

    @cached_property
    def mesh(self) -> trimesh.Trimesh:
        """The test object's CAD mesh (object frame, mm)."""
        return load_test_object()

    @cached_property
    def _onset_px(self) -> float:
        return echo_onset_offset_px(self.twin.probe)

    def region_to_base(self) -> np.ndarray:
        """The volume scan's region of interest: the top centre of the object where it was meant
        to sit (z up, mm)."""
        lo, hi = self.mesh.bounds
        return self.nominal_object_to_base @ make_transform(np.eye(3), [*(lo + hi)[:2] / 2, hi[2]])

    def calibration_frame(self, tool_to_base: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The frame over the phantom at a flange pose, and the true marker pixels (W, 2; NaN
        where a wire is out of view)."""
        twin = self.twin
        markers = twin.markers_px(tool_to_base)
        seen = np.all(np.isfinite(markers), axis=1)
        image = self.renderer.render(
            markers[seen],
            tank_bottom_row=_tank_bottom_rows(twin, twin.image_to_phantom(tool_to_base), self._floor_z),
            rng=rng,
            directions=twin.wire_directions(tool_to_base)[seen],
            along_mm=twin.along_wires_mm(tool_to_base)[seen],
        )
        return image, markers

    def image_delay_s(self, rng: np.random.Generator) -> float:
        """How late (s) the scanner stamps a frame: the twin's latency plus its jitter."""
        jitter = self.twin.timestamp_jitter_s
        return self.twin.image_latency_s + (float(rng.normal(0.0, jitter)) if jitter else 0.0)

    def _image_to_object(self, tool_to_base: np.ndarray) -> np.ndarray:
        return invert_transform(self.object_to_base) @ tool_to_base @ self.twin.image_to_tool_rigid

    def surface_image_mm(self, tool_to_base: np.ndarray) -> np.ndarray:
        """(n, 3) image-frame points (mm) where the test object's surface meets the beams at a
        true flange pose, one per column that meets it: what a noise-free frame shows."""
        rows = _surface_rows(self.twin, self.mesh, self._image_to_object(tool_to_base))
        columns = np.flatnonzero(np.isfinite(rows))
        xy = self.twin.probe.mm_from_pixels(np.column_stack([columns, rows[columns]]))
        return np.column_stack([xy, np.zeros(len(xy))])

    def volume_frame(self, tool_to_base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The frame over the test object at a flange pose."""
        image_to_object = self._image_to_object(tool_to_base)
        return self.renderer.render(
            np.empty((0, 2)),
            surface_rows=_surface_rows(self.twin, self.mesh, image_to_object) + self._onset_px,
            tank_bottom_row=_tank_bottom_rows(self.twin, image_to_object, 0.0),
            rng=rng,
        )

    def volume_truth(self) -> dict:
        return {**self.twin.truth(), "object_to_base": self.object_to_base, "cad_mesh": TEST_OBJECT_FILE.name}


def twin_scanner(seed: int = 0, noise: str | Level = "realistic", phantom: Phantom | None = None,
                 image_latency_s: float | None = None, built_phantom: Phantom | None = None,
                 probe: Probe | None = None) -> TwinScanner:
    """The twin of ``seed`` with the set-up errors of level ``noise``, and its scanner;
    ``image_latency_s`` (s) replaces the latency the level draws, ``built_phantom`` (the same
    wires, placed as built) the phantom the level's tolerance draws, ``probe`` the default probe
    (another image size: a scanner that resamples its frames finer or coarser)."""
    lvl = level(noise)
    twin = make_twin(seed, phantom, probe, setup=lvl.setup)
    if image_latency_s is not None:
        twin = replace(twin, image_latency_s=float(image_latency_s))
    if built_phantom is not None:
        if built_phantom.n_wires != twin.phantom.n_wires:
            raise ValueError(f"the phantom as built has {built_phantom.n_wires} wires, its definition "
                             f"{twin.phantom.n_wires}")
        twin = replace(twin, built_phantom=built_phantom)
    return TwinScanner(twin, lvl, seed)


def json_from_markers(markers: np.ndarray) -> list:
    """truth.json's per-frame ``markers_px``: [u, v] per wire, null where out of view."""
    return [None if np.isnan(m[0]) else m.tolist() for m in markers]


DISPLAY_HALF_LEVEL = 128
"""The gray level halfway up the display: where a surface extractor sees an echo's leading edge."""


def echo_onset_offset_px(probe: Probe) -> float:
    """How far (px) a specular echo's centre lies below the edge where it rises through the
    display's half gray level. The twin puts that leading edge on the interface, because a real
    echo begins where the sound meets the surface and rings on below it. Measured on a flat,
    noiseless echo: the first row at or over the level, less the fraction of a row the level lies
    above it (linear between the two rows); 0 when the echo rises through no row of the image's
    middle column (a fan too shallow to show it)."""
    centre = probe.height_px / 2.0
    image = BModeRenderer(probe, "none", 0).render(np.empty((0, 2)), surface_rows=np.full(probe.width_px, centre))
    column = image[:, probe.width_px // 2].astype(np.float32)
    row = int(np.argmax(column >= DISPLAY_HALF_LEVEL))
    if row == 0 or column[row] < DISPLAY_HALF_LEVEL:
        return 0.0
    below, above = column[row - 1], column[row]
    return centre - (row - 1) - float((DISPLAY_HALF_LEVEL - below) / (above - below))


def _surface_rows(twin: Twin, mesh: trimesh.Trimesh, image_to_object: np.ndarray) -> np.ndarray:
    """Per-column row of the first surface the beam meets in the image plane, NaN where none."""
    origin, normal = image_to_object[:3, 3], image_to_object[:3, 2]
    segments = trimesh.intersections.mesh_plane(mesh, normal, origin)
    rows = np.full(twin.probe.width_px, np.nan)
    if len(segments) == 0:
        return rows
    seg = twin.probe.pixels_from_mm(transform_points(invert_transform(image_to_object), segments))  # pixels
    x0, x1, y0, y1 = seg[:, 0, 0], seg[:, 1, 0], seg[:, 0, 1], seg[:, 1, 1]
    x = np.arange(twin.probe.width_px)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (x - x0) / (x1 - x0)
    hit = (t >= 0) & (t <= 1) & np.isfinite(t)
    depth = np.where(hit, y0 + t * (y1 - y0), np.inf).min(axis=1)
    valid = np.isfinite(depth) & (depth >= 0)
    rows[valid] = depth[valid]
    rows[rows > twin.probe.height_px - 1] = np.nan
    return rows
