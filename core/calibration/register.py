"""Per-frame registration: where was the image plane in the phantom? (``image_to_phantom``)

Input: one frame's labelled markers in pixels (phantom wire order, NaN where missing) and a pixel
spacing (sx, sy) in mm. Output: a rigid ``image_to_phantom`` (image frame in mm, i.e. pixels
scaled by the spacing) and the FRE.

Two methods:

- ``thesis`` (thesis 3.5): the N-wire ratios give the diagonal crossings in the phantom, which place
  the frame; ICP against the virtual point cloud (open3d) refines it.
- ``point-to-wire``: exact point-to-wire least squares from the same start.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from probecal.core.calibration.metrics import middle_wire_points
from probecal.core.geometry.phantom import NLayer, Phantom, wire_axes
from probecal.core.geometry.probe import image_mm_from_pixels
from probecal.core.geometry.transforms import (
    make_transform,
    nearest_rotation,
    rotation_from_rotvec,
    skew,
    transform_points,
)

METHODS = ("thesis", "point-to-wire")
ICP_MAX_DISTANCE_MM = 3.0


@dataclass(frozen=True)
class Registration:
    """``image_to_phantom`` (rigid, image mm) and how far each registered marker lies from its wire."""

    image_to_phantom: np.ndarray
    residuals_mm: np.ndarray  # per used marker, distance to its wire (mm)
    wire_indices: np.ndarray  # which wires the residuals belong to

    @property
    def fre_mm(self) -> float:
        """The fiducial registration error (design §5): the markers' mean distance to their wires (mm)."""
        return float(self.residuals_mm.mean())


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (4x4) mapping source points (N, 3) onto target points
    (N, 3); for a stack of targets (..., N, 3), one transform (..., 4, 4) per target."""
    cs, ct = source.mean(axis=0), target.mean(axis=-2)
    rotation = nearest_rotation(np.swapaxes(target - ct[..., None, :], -1, -2) @ (source - cs))
    out = np.zeros(rotation.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = ct - rotation @ cs
    out[..., 3, 3] = 1.0
    return out


def _point_on_wire_at_distance(start: np.ndarray, end: np.ndarray, centre: np.ndarray,
                               distance: float) -> list[np.ndarray]:
    d = (end - start) / np.linalg.norm(end - start)
    w = start - centre
    b, c = d @ w, w @ w - distance**2
    disc = b * b - c
    if disc < 0:
        return [start - b * d]  # closest point: the best we can say
    root = np.sqrt(disc)
    return [start + (-b - root) * d, start + (-b + root) * d]


def _layer_candidates(layer: NLayer, middle: np.ndarray, p1: np.ndarray, p2: np.ndarray,
                      p3: np.ndarray) -> list[np.ndarray]:
    """Phantom positions (3, 3) for one N's dots: M from the ratio, the outer crossings on wires
    1 and 3 at the measured distances from M and on one line with it. Two mirror-image
    configurations fit one N; both are returned."""
    w1, _, w3 = layer.wires
    options = []
    for left in _point_on_wire_at_distance(w1.front, w1.back, middle, float(np.linalg.norm(p1 - p2))):
        for right in _point_on_wire_at_distance(w3.front, w3.back, middle, float(np.linalg.norm(p3 - p2))):
            bend = np.linalg.norm(np.cross(left - middle, right - middle))
            options.append((bend, np.array([left, middle, right])))
    options.sort(key=lambda o: o[0])
    return [triple for _, triple in options[:2]]


def ratio_registration(phantom: Phantom, points_mm: np.ndarray, markers_px: np.ndarray) -> np.ndarray | None:
    """Place the frame from the dot ratios alone (thesis eq. 3.6-3.9): for every complete N the
    diagonal crossing comes from the ratio and the outer crossings follow; of the mirror-image
    choices per N, the combination that one rigid transform fits best wins. None with fewer
    than two complete Ns."""
    middles = middle_wire_points(phantom, markers_px)
    layers = [k for k in range(len(phantom.layers)) if np.all(np.isfinite(middles[k]))]
    if len(layers) < 2:
        return None
    source = np.concatenate([points_mm[3 * k : 3 * k + 3] for k in layers])
    choices = [_layer_candidates(phantom.layers[k], middles[k], *points_mm[3 * k : 3 * k + 3]) for k in layers]
    # Each N gives one or two candidates, so there is at least one combination.
    targets = np.array([np.concatenate(combination) for combination in itertools.product(*choices)])
    fits = kabsch(source, targets)
    misfit = np.sum((source @ np.swapaxes(fits[:, :3, :3], 1, 2) + fits[:, None, :3, 3] - targets) ** 2, axis=(1, 2))
    return fits[int(np.argmin(misfit))]


def refine_on_wires(phantom: Phantom, image_to_phantom: np.ndarray, points_mm: np.ndarray, wires: np.ndarray,
                    iterations: int = 30) -> np.ndarray:
    """Exact point-to-line least squares over the rigid transform, from a starting estimate."""
    return _on_wires(phantom, image_to_phantom, points_mm, wires, False, iterations)[0]


def refine_with_depth_scale(phantom: Phantom, image_to_phantom: np.ndarray, points_mm: np.ndarray,
                            wires: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, float]:
    """:func:`refine_on_wires` with the image's depth scale fitted too: ``(image_to_phantom,
    scale)`` for the points with their y (depth, mm) times ``scale``. A rigid fit makes up for a
    nominal spacing that is off in depth (the sound speed) by tilting the plane about the image's
    x, several degrees for a few per cent."""
    return _on_wires(phantom, image_to_phantom, points_mm, wires, True, iterations)


def _on_wires(phantom: Phantom, image_to_phantom: np.ndarray, points_mm: np.ndarray, wires: np.ndarray,
              fit_scale: bool, iterations: int) -> tuple[np.ndarray, float]:
    """Gauss-Newton on SE(3) (and the depth scale) with the analytic Jacobian: each residual is
    the point's offset perpendicular to its wire, ``P (R p + t - a)`` with ``P = I - d d^T``; a
    rotation step ``R <- exp(w) R`` moves it by ``-P [R p]x w``, a scale step on p's y by
    ``P R (0, p_y, 0)``."""
    a, _, _, project = wire_axes(phantom.lines()[wires])  # front ends (n, 3), projections (n, 3, 3)
    rotation, translation = image_to_phantom[:3, :3].copy(), image_to_phantom[:3, 3].copy()
    scale = 1.0
    for _ in range(iterations):
        scaled = points_mm * np.array([1.0, scale, 1.0])
        q = scaled @ rotation.T
        residual = np.einsum("nij,nj->ni", project, q + translation - a).ravel()
        blocks = [-project @ skew(q), project]
        if fit_scale:
            blocks.append(project @ (rotation[:, 1][None, :, None] * points_mm[:, 1, None, None]))
        jacobian = np.concatenate(blocks, axis=2).reshape(len(points_mm) * 3, -1)
        step = np.linalg.lstsq(jacobian, -residual, rcond=None)[0]
        rotation = rotation_from_rotvec(step[:3]) @ rotation
        translation = translation + step[3:6]
        if fit_scale:
            scale += step[6]
        if np.abs(step).max() < 1e-10:
            break
    return make_transform(rotation, translation), scale


def refine_by_icp(phantom: Phantom, image_to_phantom: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """The thesis's refinement: point-to-point ICP of the markers against the virtual phantom."""
    import open3d as o3d  # heavy import, needed by the thesis's method only

    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_mm))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(phantom.point_cloud()))
    result = o3d.pipelines.registration.registration_icp(
        source, target, ICP_MAX_DISTANCE_MM, image_to_phantom,
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50),
    )
    return np.asarray(result.transformation)


def register_frame(phantom: Phantom, markers_px: np.ndarray, spacing_mm: Sequence[float] | np.ndarray,
                   method: str = "point-to-wire") -> Registration | None:
    """Register one frame; None when fewer than two complete N patterns are visible."""
    if method not in METHODS:
        raise ValueError(f"unknown registration method {method!r}")
    markers_px = np.asarray(markers_px, dtype=float)
    points_mm = image_mm_from_pixels(markers_px, spacing_mm)
    image_to_phantom = ratio_registration(phantom, points_mm, markers_px)
    if image_to_phantom is None:
        return None
    valid = np.flatnonzero(np.all(np.isfinite(markers_px), axis=1))
    if method == "thesis":
        image_to_phantom = refine_by_icp(phantom, image_to_phantom, points_mm[valid])
    else:
        image_to_phantom = refine_on_wires(phantom, image_to_phantom, points_mm[valid], valid)
    residuals = phantom.wire_distances(transform_points(image_to_phantom, points_mm[valid]), valid)
    return Registration(image_to_phantom, residuals, valid)
