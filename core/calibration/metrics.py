"""Error measures, defined once (SPEC §5): FRE, hand-eye errors with and without truth, PRE3D.

Markers are pixels (u, v); ``image_to_tool`` includes the pixel spacing; poses are
``tool_to_base``; everything else is mm and degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from probecal.core.geometry.phantom import NLayer, Phantom
from probecal.core.geometry.transforms import invert_transform, rotation_angle_deg, transform_points

PLUS_CONFIDENCE = 0.95  # PLUS reports mean and std over the lowest 95 % of errors


def trimmed_mean_std(errors, fraction: float = PLUS_CONFIDENCE) -> tuple[float, float]:
    """Mean and population standard deviation of the lowest ``fraction`` of the errors, counted
    as PLUS does (the lowest round(n * fraction) values)."""
    values = np.sort(np.asarray(errors, dtype=float).ravel())
    values = values[np.isfinite(values)]
    if values.size == 0:
        return float("nan"), float("nan")
    keep = max(1, int(values.size * fraction + 0.5))
    kept = values[:keep]
    return float(kept.mean()), float(kept.std())


def _line_intersection(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Where two coplanar lines meet (the point on line a closest to line b)."""
    d1, d2, w = a1 - a0, b1 - b0, a0 - b0
    m = np.array([[d1 @ d1, -(d1 @ d2)], [d1 @ d2, -(d2 @ d2)]])
    s, _ = np.linalg.solve(m, [-(w @ d1), -(w @ d2)])
    return a0 + s * d1


def diagonal_anchors(layer: NLayer) -> tuple[np.ndarray, np.ndarray]:
    """Where the diagonal's line meets the lines of outer wire 1 and outer wire 3 (phantom, mm)."""
    w1, w2, w3 = layer.wires
    return (
        _line_intersection(w2.front, w2.back, w1.front, w1.back),
        _line_intersection(w2.front, w2.back, w3.front, w3.back),
    )


def middle_wire_points(phantom: Phantom, markers_px: np.ndarray) -> np.ndarray:
    """(..., L, 3) phantom-frame points of the diagonal crossings from the dot ratios of (..., W, 2)
    markers (seed eq. 3.6-3.9): ``alpha = |p2 - p1| / |p3 - p1|`` and ``M = X12 + alpha (X32 - X12)``,
    exact for any plane because the outer wires are parallel. NaN for a layer with a missing dot."""
    markers_px = np.asarray(markers_px, dtype=float)
    out = np.empty(markers_px.shape[:-2] + (len(phantom.layers), 3))
    for k, layer in enumerate(phantom.layers):
        p1, p2, p3 = (markers_px[..., 3 * k + j, :] for j in range(3))
        with np.errstate(invalid="ignore", divide="ignore"):
            alpha = np.linalg.norm(p2 - p1, axis=-1) / np.linalg.norm(p3 - p1, axis=-1)
        x12, x32 = diagonal_anchors(layer)
        out[..., k, :] = x12 + alpha[..., None] * (x32 - x12)
    return out


def pre3d_errors(
    phantom: Phantom,
    markers_px: np.ndarray,
    tool_to_base: np.ndarray,
    image_to_tool: np.ndarray,
    phantom_to_base: np.ndarray,
) -> np.ndarray:
    """PLUS's 3D point reconstruction error per frame and N (mm), shape (F, L).

    The diagonal crossing found from the dot ratio is taken to the tool frame with the known
    poses and compared with the calibrated image point of the middle dot.
    """
    markers_px = np.asarray(markers_px, dtype=float)
    errors = np.full((len(markers_px), len(phantom.layers)), np.nan)
    for f, (markers, pose) in enumerate(zip(markers_px, tool_to_base)):
        if not np.all(np.isfinite(pose)):
            continue
        phantom_to_tool = invert_transform(pose) @ phantom_to_base
        expected = transform_points(phantom_to_tool, middle_wire_points(phantom, markers))
        middles = markers[1::3]
        calibrated = transform_points(image_to_tool, np.column_stack([middles, np.zeros(len(middles))]))
        errors[f] = np.linalg.norm(calibrated - expected, axis=1)
    return errors


def pre3d(phantom, markers_px, tool_to_base, image_to_tool, phantom_to_base) -> tuple[float, float]:
    """PRE3D (mean, std) over the lowest 95 % of errors, exactly as PLUS reports it."""
    return trimmed_mean_std(pre3d_errors(phantom, markers_px, tool_to_base, image_to_tool, phantom_to_base))


def fre(phantom: Phantom, points_phantom: np.ndarray, wire_indices: np.ndarray) -> float:
    """Fiducial registration error: mean distance (mm) of registered markers to their wires."""
    return float(phantom.distance_to_wires(points_phantom, wire_indices).mean())


@dataclass(frozen=True)
class PoseError:
    translation_mm: float
    rotation_deg: float


def identity_error(
    image_to_tool_rigid: np.ndarray, phantom_to_base: np.ndarray, tool_to_base: np.ndarray, image_to_phantom: np.ndarray
) -> PoseError:
    """The seed's eq. 4.1 without its typo: ``I = X^-1 M^-1 Y N`` should be the identity; the
    translation error is the plain Euclidean norm of I's translation."""
    i = invert_transform(image_to_tool_rigid) @ invert_transform(tool_to_base) @ phantom_to_base @ image_to_phantom
    return PoseError(float(np.linalg.norm(i[:3, 3])), rotation_angle_deg(i[:3, :3]))
