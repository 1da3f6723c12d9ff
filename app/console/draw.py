"""Pictures for the console's side panel (annotated frames, colour bars) and the
geometry of what the 3D scene draws. Pure functions: arrays in, arrays out (mm unless noted)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import griddata

from probecal.core.calibration.result import BoundMap
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import wire_label
from probecal.core.geometry.transforms import transform_points
from probecal.core.volume.grid import Volume
from probecal.core.volume.pointcloud import error_colors

FOUND = (60, 200, 90)
MISSED = (230, 70, 60)
CANDIDATE = (240, 190, 40)
FAN_EDGE = (110, 110, 110)
LABEL_COLOUR = (255, 200, 40)  # a slice's axis labels and its outline in 3D: readable on black and white echoes


BOUND_OPACITY = 0.4
"""How much of a pixel the bound map's colour takes over the live frame: the echoes still show."""


@dataclass(frozen=True)
class Overlay:
    """Colours laid over a frame: ``rgb`` (height, width, 3) where ``alpha`` (height, width, 1,
    0-1) says how much, and the values (``low`` to ``high``, mm) the colours run between."""

    rgb: np.ndarray
    alpha: np.ndarray
    low: float
    high: float


def bound_overlay(bound_map: BoundMap, size_px: tuple[int, int], fan: Fan | None = None) -> Overlay | None:
    """The bound map (pixels as the image shows them) over a (width, height) frame: each pixel's
    bound interpolated linearly between the map's points, blue at the map's least through green to
    red at its largest, over the map's extent (a fan image's: within its fan); None for a map
    with no bound to draw."""
    points = np.array(bound_map["points_px"], dtype=float).reshape(-1, 2)
    values = np.array(bound_map["bound_mm"], dtype=float).ravel()
    known = np.isfinite(values)
    if known.sum() < 3 or len(points) != len(values):
        return None
    width, height = size_px
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    field = griddata(points[known], values[known], (u, v), method="linear")
    inside = np.isfinite(field)
    if fan is not None:
        inside &= fan.mask(width, height)
    low, high = float(values[known].min()), float(values[known].max())
    colours = error_colors(np.nan_to_num(field - low).ravel(), max(high - low, 1e-9)).reshape(height, width, 3)
    return Overlay(colours, np.where(inside, BOUND_OPACITY, 0.0)[..., None], low, high)


def annotate_frame(image: np.ndarray, markers: np.ndarray | None, candidates: np.ndarray, scale: int = 1,
                   fan: Fan | None = None, overlay: Overlay | None = None) -> np.ndarray:
    """The frame in RGB under the ``overlay`` (one of its size; the bound map), enlarged ``scale``
    times, with a fan image's fan outlined in grey, dot candidates ringed in amber and labelled
    markers circled in green with their layer and wire."""
    rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if overlay is not None and overlay.rgb.shape == rgb.shape:
        rgb = (rgb * (1.0 - overlay.alpha) + overlay.rgb * overlay.alpha).astype(np.uint8)
    rgb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
    if fan is not None:
        edges = np.round(fan_outline_px(fan) * scale).astype(np.int32)
        cv2.polylines(rgb, list(edges), False, FAN_EDGE, 1, cv2.LINE_AA)
    for u, v in np.asarray(candidates).reshape(-1, 2):
        cv2.circle(rgb, (int(u * scale), int(v * scale)), 5 * scale, CANDIDATE, 1, cv2.LINE_AA)
    if markers is not None:
        for wire, (u, v) in enumerate(markers):
            if not np.isfinite(u):
                continue
            centre = (int(u * scale), int(v * scale))
            cv2.circle(rgb, centre, 6 * scale, FOUND, 2, cv2.LINE_AA)
            cv2.putText(rgb, wire_label(wire), (centre[0] + 7 * scale, centre[1] - 4 * scale),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale, FOUND, 1, cv2.LINE_AA)
    return rgb


SLICE_AXES = ("z", "y", "x")
"""The three orthogonal slices through a volume, by the axis each is across (voxels are (z, y, x))."""


SLICE_VIEW = {"z": ("y", "x"), "y": ("z", "x"), "x": ("z", "y")}
"""Each slice's axes as drawn: the one pointing up, the one pointing right (base frame)."""


def slice_index(volume: Volume, axis: str, at_mm: float) -> int:
    """The voxel index across ``axis`` nearest to ``at_mm`` (base frame, mm), within the volume."""
    k = "xyz".index(axis)
    n = volume.voxels.shape[SLICE_AXES.index(axis)]
    return int(np.clip(round((at_mm - volume.origin_mm[k]) / volume.spacing_mm[k]), 0, n - 1))


def slice_range_mm(volume: Volume, axis: str) -> tuple[float, float, float]:
    """The first and last voxel centres across ``axis`` and the voxel size (base frame, mm)."""
    k = "xyz".index(axis)
    n = volume.voxels.shape[SLICE_AXES.index(axis)]
    return volume.origin_mm[k], volume.origin_mm[k] + (n - 1) * volume.spacing_mm[k], volume.spacing_mm[k]


def volume_slice(volume: Volume, axis: str, at_mm: float, window: float, level: float,
                 height_px: int = 220) -> np.ndarray:
    """The volume cut across ``axis`` at ``at_mm`` (base frame), gray levels windowed (``level``
    at mid-gray, ``window`` wide, 0-255), as an RGB picture ``height_px`` tall with square
    millimetres, its axes labelled: z up in the y and x slices, y up in the z slice."""
    k = SLICE_AXES.index(axis)
    cut = np.take(volume.voxels, slice_index(volume, axis, at_mm), axis=k).astype(float)
    rows_mm, cols_mm = [s for i, s in enumerate(volume.spacing_mm[::-1]) if i != k]
    low = level - window / 2.0
    gray = np.clip((cut - low) / max(window, 1e-6) * 255.0, 0, 255).astype(np.uint8)[::-1]
    width_px = max(1, round(height_px * gray.shape[1] * cols_mm / max(gray.shape[0] * rows_mm, 1e-9)))
    picture = cv2.cvtColor(cv2.resize(gray, (width_px, height_px), interpolation=cv2.INTER_NEAREST),
                           cv2.COLOR_GRAY2RGB)
    up, right = SLICE_VIEW[axis]
    for text, corner in ((f"+{up}", (4, 14)), (f"+{right}", (max(0, width_px - 24), height_px - 6))):
        cv2.putText(picture, text, corner, cv2.FONT_HERSHEY_SIMPLEX, 0.45, LABEL_COLOUR, 1, cv2.LINE_AA)
    return picture


def slice_outline(volume: Volume, axis: str, at_mm: float) -> np.ndarray:
    """(4, 2, 3) edges of the slice's rectangle across ``axis`` at ``at_mm`` (base frame, mm),
    spanning the volume in the other two axes."""
    k = "xyz".index(axis)
    lo = np.asarray(volume.origin_mm, float)
    hi = lo + (np.array(volume.voxels.shape[::-1]) - 1) * np.asarray(volume.spacing_mm, float)
    a, b = (i for i in range(3) if i != k)
    corners = []
    for u, v in ((lo[a], lo[b]), (hi[a], lo[b]), (hi[a], hi[b]), (lo[a], hi[b])):
        point = np.zeros(3)
        point[k], point[a], point[b] = at_mm, u, v
        corners.append(point)
    return np.array([[corners[i], corners[(i + 1) % 4]] for i in range(4)])


def box_edges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12, 2, 3) edges of an axis-aligned box."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pairs = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return np.array([[corners[a], corners[b]] for a, b in pairs])


FAN_ARC_STEPS = 24  # straight pieces per arc of a fan's outline


def fan_outline_px(fan: Fan) -> np.ndarray:
    """(2 * FAN_ARC_STEPS + 2, 2, 2) the edges of a fan in pixels: its near and far arcs in
    pieces, then its two side lines."""
    angles = np.radians(np.linspace(*fan.angles_deg, FAN_ARC_STEPS + 1))
    edges = []
    for radius in (fan.radius_start_px, fan.radius_stop_px):
        arc = np.column_stack([fan.origin_px[0] + radius * np.sin(angles), fan.origin_px[1] + radius * np.cos(angles)])
        edges.append(np.stack([arc[:-1], arc[1:]], axis=1))
    near_left, near_right, far_left, far_right = fan.corners_px()
    edges.append(np.array([[near_left, far_left], [near_right, far_right]]))
    return np.concatenate(edges)


def image_outline(image_to_tool: np.ndarray, width_px: int, height_px: int, fan: Fan | None = None) -> np.ndarray:
    """(N, 2, 3) edges of the image in the tool frame (``image_to_tool`` with spacing): its
    rectangle, or a fan image's fan."""
    if fan is not None:
        edges = fan_outline_px(fan)
        points = np.concatenate([edges.reshape(-1, 2), np.zeros((edges.size // 2, 1))], axis=1)
        return transform_points(image_to_tool, points).reshape(-1, 2, 3)
    corners = np.array([[0, 0, 0], [width_px, 0, 0], [width_px, height_px, 0], [0, height_px, 0]], float)
    corners = transform_points(image_to_tool, corners)
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


def fan_texture(image: np.ndarray, fan: Fan | None) -> np.ndarray:
    """A frame for the scene's image plane: a fan image's transparent outside its fan (RGBA)."""
    if fan is None:
        return image
    alpha = np.where(fan.mask(image.shape[1], image.shape[0]), 255, 0).astype(np.uint8)
    return np.dstack([image, image, image, alpha])


def image_centre_pose(image_to_tool: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """Pose (tool frame) of a scene image of the frame: centred on it, x along the columns and
    y up the rows (a scene image shows its first row at +y)."""
    centre = image_to_tool @ np.array([width_px / 2, height_px / 2, 0.0, 1.0])
    axes = image_to_tool[:3, :3] / np.linalg.norm(image_to_tool[:3, :3], axis=0)
    pose = np.eye(4)
    pose[:3, :3] = axes @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = centre[:3]
    return pose


def cylinder_pose(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotation (3x3, z along the segment) and length of a cylinder from ``start`` to ``end``."""
    axis = end - start
    length = float(np.linalg.norm(axis))
    z = axis / length
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z]), length


def colour_bar(what: str, low: float, high: float, unit: str, width: int = 420) -> np.ndarray:
    """A colour scale (RGB uint8) for values from ``low`` to ``high`` in ``unit``: the blue-green-
    red ramp the scene colours points with, labelled at both ends and in the middle."""
    bar = np.full((46, width, 3), 255, np.uint8)
    left, right = 8, width - 8
    ramp = error_colors(np.linspace(0.0, 1.0, right - left), 1.0)
    bar[4:20, left:right] = ramp[None, :, :]
    for fraction in (0.0, 0.5, 1.0):
        x = int(left + fraction * (right - left - 1))
        text = f"{low + fraction * (high - low):.3g}"
        size = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.38, 1)[0][0]
        cv2.putText(bar, text, (int(np.clip(x - size / 2, 0, width - size)), 33), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                    (60, 60, 60), 1, cv2.LINE_AA)
    caption = f"{what} ({unit})"
    size = cv2.getTextSize(caption, cv2.FONT_HERSHEY_SIMPLEX, 0.38, 1)[0][0]
    cv2.putText(bar, caption, ((width - size) // 2, 44), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (60, 60, 60), 1, cv2.LINE_AA)
    return bar
