"""Error measures, defined once (design §5): segmentation errors, hand-eye errors without truth,
PRE3D (FRE is ``core.calibration.register.Registration.fre_mm``).

Markers are pixels (u, v); ``image_to_tool`` includes the pixel spacing; poses are
``tool_to_base``; everything else is mm and degrees.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.transforms import invert_transform, rotation_angle_deg, transform_points

if TYPE_CHECKING:
    from probecal.core.calibration.segment import FrameResult

PLUS_CONFIDENCE = 0.95  # PLUS reports mean and std over the lowest 95 % of errors


def trimmed_mean_std(errors: ArrayLike, fraction: float = PLUS_CONFIDENCE) -> tuple[float, float]:
    """Mean and population standard deviation of the lowest ``fraction`` of the errors, counted
    as PLUS does (the lowest round(n * fraction) values)."""
    values = np.sort(np.asarray(errors, dtype=float).ravel())
    values = values[np.isfinite(values)]
    if values.size == 0:
        return float("nan"), float("nan")
    keep = max(1, int(values.size * fraction + 0.5))
    kept = values[:keep]
    return float(kept.mean()), float(kept.std())


def middle_wire_points(phantom: Phantom, markers_px: np.ndarray) -> np.ndarray:
    """(..., L, 3) phantom-frame points of the diagonal crossings from the dot ratios of (..., W, 2)
    markers (thesis eq. 3.6-3.9): ``alpha = |p2 - p1| / |p3 - p1|`` and ``M = X12 + alpha (X32 - X12)``,
    exact for any plane because the outer wires are parallel. NaN for a layer with a missing dot."""
    markers_px = np.asarray(markers_px, dtype=float)
    out = np.empty(markers_px.shape[:-2] + (len(phantom.layers), 3))
    for k, layer in enumerate(phantom.layers):
        p1, p2, p3 = (markers_px[..., 3 * k + j, :] for j in range(3))
        with np.errstate(invalid="ignore", divide="ignore"):
            alpha = np.linalg.norm(p2 - p1, axis=-1) / np.linalg.norm(p3 - p1, axis=-1)
        x12, x32 = layer.diagonal_anchors
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


def pre3d(phantom: Phantom, markers_px: np.ndarray, tool_to_base: np.ndarray, image_to_tool: np.ndarray,
          phantom_to_base: np.ndarray) -> tuple[float, float]:
    """PRE3D (mean, std) over the lowest 95 % of errors, exactly as PLUS reports it."""
    return trimmed_mean_std(pre3d_errors(phantom, markers_px, tool_to_base, image_to_tool, phantom_to_base))


@dataclass(frozen=True)
class PoseError:
    translation_mm: float
    rotation_deg: float


def identity_error(
    image_to_tool_rigid: np.ndarray, phantom_to_base: np.ndarray, tool_to_base: np.ndarray, image_to_phantom: np.ndarray
) -> PoseError:
    """The thesis's eq. 4.1 without its typo: ``I = X^-1 M^-1 Y N`` should be the identity; the
    translation error is the plain Euclidean norm of I's translation."""
    i = invert_transform(image_to_tool_rigid) @ invert_transform(tool_to_base) @ phantom_to_base @ image_to_phantom
    return PoseError(float(np.linalg.norm(i[:3, 3])), rotation_angle_deg(i[:3, :3]))


@dataclass(frozen=True)
class SegmentationScore:
    """Segmentation against ground truth (design §5): frame counts and centroid errors (mm).

    A found frame is ``correct`` when every marker is nearest its own wire's true position and
    within the tolerance, ``mislabelled`` when some marker is nearer another wire's (or its wire
    is not in view), else ``inaccurate`` (right labels, a centroid beyond the tolerance).
    """

    frames: int
    complete: int  # frames whose truth shows every wire
    found: int
    correct: int
    mislabelled: int
    inaccurate: int
    errors_mm: np.ndarray  # every marker's distance from its true position, frames with right labels

    @property
    def correct_rate(self) -> float:
        return self.correct / max(self.frames, 1)

    @property
    def median_error_mm(self) -> float:
        return float(np.median(self.errors_mm)) if len(self.errors_mm) else float("nan")


def segmentation_error_mm(results: list[FrameResult], truth_frames: list[dict], spacing_mm: tuple[float, float],
                          tolerance_mm: float = 1.0) -> SegmentationScore:
    """Score results against a simulated session's ``truth.json`` frames (``index``,
    ``markers_px`` with null for wires out of view); ``spacing_mm`` the true (sx, sy) mm/px."""
    truth = {f["index"]: np.array([[np.nan] * 2 if m is None else m for m in f["markers_px"]], float)
             for f in truth_frames}
    scale = np.asarray(spacing_mm, float)
    complete = found = correct = mislabelled = inaccurate = 0
    errors = []
    for r in results:
        true = truth[r.index]
        complete += bool(np.isfinite(true).all())
        if r.markers is None:  # not found
            continue
        found += 1
        distance = np.linalg.norm((r.markers[:, None, :] - true[None, :, :]) * scale, axis=-1)  # (W, W)
        own = np.diagonal(distance)
        if not np.isfinite(own).all() or (np.nanargmin(distance, axis=1) != np.arange(len(own))).any():
            mislabelled += 1
            continue
        errors.append(own)
        if own.max() <= tolerance_mm:
            correct += 1
        else:
            inaccurate += 1
    return SegmentationScore(len(results), complete, found, correct, mislabelled, inaccurate,
                             np.concatenate(errors) if errors else np.empty(0))


@dataclass(frozen=True)
class ThesisSegmentationError:
    """The thesis's measure (eq. 3.1-3.5): phantom distance minus the mean measured distance (mm)
    between the outer dots of a layer (lateral) and between outer dots of adjacent layers (axial)."""

    lateral_mm: float
    axial_mm: float
    frames: int


def _wire_distance(phantom: Phantom, a: int, b: int) -> float:
    """Distance (mm) between two parallel wires of the phantom."""
    wa, wb = phantom.wires[a], phantom.wires[b]
    return float(np.linalg.norm(np.cross(wa.direction, wb.front - wa.front)))


def thesis_segmentation_error(results: list[FrameResult], phantom: Phantom,
                            spacing_mm: tuple[float, float]) -> ThesisSegmentationError:
    """Thesis eq. 3.4/3.5 over the found frames, for any phantom: every layer's outer-dot distance
    against its outer-wire separation (30 mm in the seed) and the same outer wire of adjacent
    layers against their distance (10 mm); ``spacing_mm`` (sx, sy) mm/px."""
    n_layers = len(phantom.layers)
    lateral = [(3 * k, 3 * k + 2) for k in range(n_layers)]
    axial = [(3 * k + w, 3 * k + 3 + w) for k in range(n_layers - 1) for w in (0, 2)]
    markers = np.array([r.markers for r in results if r.found]).reshape(-1, phantom.n_wires, 2)
    markers = markers * np.asarray(spacing_mm, float)

    def deviation(pairs: list[tuple[int, int]]) -> float:
        if not pairs or not len(markers):
            return float("nan")
        expected = np.array([_wire_distance(phantom, a, b) for a, b in pairs])
        measured = np.stack([np.linalg.norm(markers[:, a] - markers[:, b], axis=1) for a, b in pairs], axis=1)
        return float(np.mean(expected - measured))

    return ThesisSegmentationError(deviation(lateral), deviation(axial), len(markers))
