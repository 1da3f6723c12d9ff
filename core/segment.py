"""Find the wire dots in B-mode frames and label them (SPEC §1 step 3, seed 3.4).

Two dot finders and labellers, chosen by the session:

- probecal's own, after the seed: a 7x7 median filter, a disk-shaped morphological clean-up, a
  threshold, 8-connected components, a size filter and intensity-weighted sub-pixel centroids,
  labelled by :func:`core.labelling.label_dots`. The disk opening is applied to the gray image
  before the threshold: for a flat disk, thresholding an opened image gives exactly the opened
  binary mask, and the opened gray levels (above the threshold) make the centroid weights. On
  the simulator the median error is under 0.03 mm. Sizes are in mm, converted with the
  approximate pixel spacing (the seed's pixel counts are for about 0.1 mm/px). When the pattern
  is not found, the frame is retried with other parameters (lower threshold, smaller kernel,
  stronger clean-up); frames that still fail are flagged with the reason.
- PLUS's (PlusFidSegmentation, PlusFidLineFinder, PlusFidLabeling), for sessions imported from
  PLUS, i.e. whenever PLUS segmentation hints are given: no median filter; for each of four bar
  directions the bar opening is subtracted, then a disk opening; a threshold at a fraction of
  the cleaned region's maximum; centroids weighted by the full gray levels of 8-connected blobs;
  the brightest candidates kept; PLUS's line finder and first-fit labelling
  (:func:`core.labelling.plus_label_dots`). On PLUS's fCal and VLCUS recordings this reproduces
  PLUS's success flags in every frame and its points to 0.001 px. One check is added: a pattern
  whose dots no affine map of the image puts on their wires is rejected (tissue frames can fool
  PLUS's line finder).

Frames: pixels (u = column, v = row), markers in the phantom definition's wire order (N by N,
within an N in definition order); distances in mm.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np

from core.errors import InputError
from core.labelling import (
    SIMULATED,
    Orientation,
    PatternModel,
    PlusLineModel,
    Tolerances,
    affine_residual_mm,
    label_dots,
    plus_label_dots,
    plus_orientation,
)
from core.phantom import Phantom
from core.session import Session

MEDIAN_MM = 0.7  # the seed's 7x7 median at 0.1 mm/px
DISK_RADIUS_MM = 0.2  # opening disk
THRESHOLD = 0.3  # fraction of the frame's (min..max) range
MIN_AREA_MM2 = 0.1  # the seed's 10 px at 0.1 mm/px
MAX_AREA_MM2 = 12.0  # the seed's 200 px (2 mm^2) is too small for deep dots (fCal 3.6, VLCUS 9.3 mm^2)
MIN_CONTRAST = 20  # gray levels between the darkest and the brightest pixel of a frame with echoes
MAX_CANDIDATES = 40  # brightest dots kept for labelling
PLUS_BAR_MM = 2.0  # PLUS's defaults: MorphologicalOpeningBarSizeMm,
PLUS_DISK_RADIUS_MM = 0.27  # MorphologicalOpeningCircleRadiusMm,
PLUS_THRESHOLD_PERCENT = 10.0  # ThresholdImagePercent,
PLUS_MAX_CANDIDATES = 20  # NumberOfMaximumFiducialPointCandidates
PLUS_EDGE_PX = 8  # PLUS drops dots whose centroid is nearer the processed region's edge


@dataclass(frozen=True)
class DotParams:
    """One parameter set of the dot finder (pixels; threshold as a fraction of the gray range)."""

    median_px: int
    disk_px: int
    threshold: float
    min_area_px: float
    max_area_px: float


@dataclass(frozen=True)
class Dots:
    """Dot candidates: sub-pixel centroids (K, 2) as (u, v), area (px) and summed weight (/255)."""

    positions: np.ndarray
    areas: np.ndarray
    intensities: np.ndarray

    def brightest(self, n: int) -> "Dots":
        keep = np.sort(np.argsort(-self.intensities, kind="stable")[:n])
        return Dots(self.positions[keep], self.areas[keep], self.intensities[keep])


NO_DOTS = Dots(np.empty((0, 2)), np.empty(0), np.empty(0))


@dataclass(frozen=True)
class FrameResult:
    """Segmentation of one frame. ``markers`` (n_wires, 2) pixels in phantom wire order when
    ``found``; ``candidates`` (K, 2) every dot candidate, for display; ``index`` the session's."""

    index: int
    found: bool
    markers: np.ndarray | None
    reason: str
    candidates: np.ndarray


def _median_near(image: np.ndarray, size: int, level: int) -> np.ndarray:
    """``cv2.medianBlur(image, size)`` wherever it can reach ``level``, 0 elsewhere.

    A median of at least ``level`` needs a pixel of at least ``level`` in its window, so only the
    row bands (and within them the column span) near such pixels are filtered: a fraction of
    the frame for wire images, with the same values there as a full-frame filter.
    """
    out = np.zeros_like(image)
    pad = size // 2
    bright = image >= level
    rows = cv2.dilate(bright.any(axis=1).astype(np.uint8)[:, None], np.ones((size, 1), np.uint8))[:, 0]
    edges = np.flatnonzero(np.diff(np.concatenate([[0], rows, [0]]).astype(np.int8)))
    height, width = image.shape
    for top, bottom in zip(edges[::2], edges[1::2]):
        cols = np.flatnonzero(bright[max(top - pad, 0) : bottom + pad].any(axis=0))
        left, right = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, width)
        r0, c0 = max(top - pad, 0), max(left - pad, 0)
        block = np.ascontiguousarray(image[r0 : min(bottom + pad, height), c0 : min(right + pad, width)])
        out[top:bottom, left:right] = cv2.medianBlur(block, size)[top - r0 : bottom - r0, left - c0 : right - c0]
    return out


def find_dots(image: np.ndarray, params: DotParams, roi: tuple[int, int, int, int] | None = None) -> Dots:
    """Dot candidates of a uint8 frame, in full-frame pixels; ``roi`` is (x, y, width, height).

    The threshold is ``params.threshold`` of the way from the darkest to the brightest pixel. A
    centroid weighs each pixel of its blob by how far its cleaned-up gray level rises above the
    threshold, so pixels at the blob's edge fade in instead of snapping it to the pixel grid.
    """
    x0, y0 = (roi[0], roi[1]) if roi else (0, 0)
    crop = image[y0 : y0 + roi[3], x0 : x0 + roi[2]] if roi else image
    if not crop.size:
        return NO_DOTS
    low, high = cv2.minMaxLoc(crop)[:2]
    if high - low < MIN_CONTRAST:
        return NO_DOTS
    level = int(low + np.floor((high - low) * params.threshold + 0.5))
    filtered = _median_near(crop, params.median_px, level) if params.median_px > 1 else crop
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * params.disk_px + 1,) * 2)
    opened = cv2.morphologyEx(filtered, cv2.MORPH_OPEN, disk) if params.disk_px > 0 else filtered
    _, mask = cv2.threshold(opened, level - 1, 255, cv2.THRESH_BINARY)
    points = cv2.findNonZero(mask)
    if points is None:
        return NO_DOTS
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    cols, rows = points[:, 0, 0], points[:, 0, 1]
    label = labels[rows, cols]
    weight = opened[rows, cols].astype(np.float64) - (level - 1)
    area = np.bincount(label, minlength=n)[1:]
    total = np.bincount(label, weight, n)[1:]
    centroid = np.column_stack([np.bincount(label, weight * c, n)[1:] for c in (cols, rows)])
    keep = (area >= params.min_area_px) & (area <= params.max_area_px)
    return Dots(centroid[keep] / total[keep, None] + (x0, y0), area[keep], total[keep] / 255.0)


@dataclass(frozen=True)
class PlusDotParams:
    """PLUS's dot finder (PlusFidSegmentation): bar half-length and disk radius (px), threshold
    (fraction of the cleaned-up region's gray range), and how many of the brightest dots are kept."""

    bar_px: int
    disk_px: int
    threshold: float
    max_candidates: int

    def region(self, shape: tuple[int, ...], roi: tuple[int, int, int, int] | None) -> tuple[int, int, int, int]:
        """The processed region (x0, y0, x1, y1), exclusive ends: the clip rectangle ``roi``
        (x, y, width, height; None for the frame) kept at least a bar length plus one pixel
        inside the frame, as PLUS keeps it."""
        height, width = shape[:2]
        x, y, w, h = roi if roi else (0, 0, width, height)
        margin = self.bar_px + 1
        return (max(x, margin), max(y, margin), min(x + w, width - margin), min(y + h, height - margin))


def _bars(half: int) -> tuple[np.ndarray, ...]:
    """Line structuring elements of 2 * half + 1 pixels at 0, 45, 90 and 135 degrees."""
    n = 2 * half + 1
    return (np.ones((1, n), np.uint8), np.fliplr(np.eye(n, dtype=np.uint8)), np.ones((n, 1), np.uint8),
            np.eye(n, dtype=np.uint8))


def _plus_disk(radius: int) -> np.ndarray:
    """PLUS's disk: the pixels within ``radius`` of the centre."""
    v, u = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return (np.hypot(u, v) <= radius).astype(np.uint8)


def _plus_cleaned(image: np.ndarray, params: PlusDotParams, region: tuple[int, int, int, int]) -> np.ndarray:
    """PLUS's morphology on ``region``: for each bar direction in turn the bar opening is
    subtracted (only dot-sized bright spots survive), then a disk opening. Erosions read the
    frame around the region; dilations see only the region's eroded values."""
    x0, y0, x1, y1 = region
    pad = params.bar_px
    work = image[y0 - pad : y1 + pad, x0 - pad : x1 + pad].copy()
    inside = (slice(pad, pad + y1 - y0), slice(pad, pad + x1 - x0))
    inner = work[inside]
    for bar in _bars(pad):
        cv2.subtract(inner, cv2.dilate(cv2.erode(work, bar)[inside], bar), dst=inner)
    disk = _plus_disk(params.disk_px)
    return cv2.dilate(cv2.erode(work, disk)[inside], disk)


def find_plus_dots(image: np.ndarray, params: PlusDotParams, roi: tuple[int, int, int, int] | None = None) -> Dots:
    """PLUS's dot candidates, brightest first: the cleaned-up region thresholded at
    ``params.threshold`` of its maximum (PLUS's range starts at the zeros outside the region),
    8-connected blobs weighted by their gray levels, centroids at least 8 px inside the region,
    intensity the summed gray level / 255; ``roi`` is (x, y, width, height)."""
    x0, y0, x1, y1 = region = params.region(image.shape, roi)
    if x1 <= x0 or y1 <= y0:
        return NO_DOTS
    cleaned = _plus_cleaned(image, params, region)
    level = int(np.floor(int(cleaned.max()) * params.threshold + 0.5))
    _, mask = cv2.threshold(cleaned, max(level - 1, 0), 255, cv2.THRESH_BINARY)
    points = cv2.findNonZero(mask)
    if points is None:
        return NO_DOTS
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    cols, rows = points[:, 0, 0], points[:, 0, 1]
    label = labels[rows, cols]
    weight = cleaned[rows, cols] / 255.0
    total = np.bincount(label, weight, n)[1:]
    centroid = np.column_stack([np.bincount(label, weight * c, n)[1:] for c in (cols, rows)]) / total[:, None]
    centroid += (x0, y0)
    edge = PLUS_EDGE_PX
    inside = ((centroid >= (x0 + edge, y0 + edge)) & (centroid < (x1 - edge, y1 - edge))).all(axis=1)
    order = np.argsort(-total[inside], kind="stable")[: params.max_candidates]
    return Dots(centroid[inside][order], np.bincount(label, minlength=n)[1:][inside][order], total[inside][order])


def _as_gray(image: np.ndarray) -> np.ndarray:
    """A uint8 single-channel view of a frame (colour frames are converted)."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if image.dtype != np.uint8:
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)
    return image


def _plus_dot_params(hints: dict[str, str], pixel: float) -> PlusDotParams:
    """PLUS's dot-finder settings from its ``<Segmentation>`` attributes (PLUS's defaults)."""
    spacing = float(hints.get("ApproximateSpacingMmPerPixel") or pixel)

    def px(key: str, default_mm: float) -> int:
        return int(np.floor(float(hints.get(key) or default_mm) / spacing + 0.5))

    return PlusDotParams(
        bar_px=px("MorphologicalOpeningBarSizeMm", PLUS_BAR_MM),
        disk_px=px("MorphologicalOpeningCircleRadiusMm", PLUS_DISK_RADIUS_MM),
        threshold=float(hints.get("ThresholdImagePercent") or PLUS_THRESHOLD_PERCENT) / 100,
        max_candidates=int(float(hints.get("NumberOfMaximumFiducialPointCandidates") or PLUS_MAX_CANDIDATES)),
    )


def _odd(x: float) -> int:
    return 2 * int(round((x - 1) / 2)) + 1


@dataclass(frozen=True)
class Segmenter:
    """Finds and labels the wire dots of one phantom in frames of one scanner set-up.

    ``spacing_mm`` is the approximate (sx, sy) mm/px used for sizes and geometry checks;
    ``attempts`` the dot-finder parameter sets tried in turn; ``roi`` (x, y, width, height) px.
    With ``plus_dots`` and ``plus_lines`` set, PLUS's dot finder and labelling run instead of
    ``attempts`` and :func:`core.labelling.label_dots`.
    """

    n_wires: int
    model: PatternModel
    tolerances: Tolerances
    spacing_mm: tuple[float, float]
    attempts: tuple[DotParams, ...]
    roi: tuple[int, int, int, int] | None = None
    max_candidates: int = MAX_CANDIDATES
    plus_dots: PlusDotParams | None = None
    plus_lines: PlusLineModel | None = None

    @classmethod
    def create(
        cls,
        phantom: Phantom,
        spacing_mm: tuple[float, float],
        orientation: Orientation = SIMULATED,
        hints: dict[str, str] | None = None,
        use_roi: bool = True,
    ) -> "Segmenter":
        """A segmenter for ``phantom`` at an approximate spacing. ``hints`` are a PLUS
        ``<Segmentation>`` element's attributes; given, PLUS's dot finder and labelling run with
        their settings (ROI, bar, disk, threshold, candidates, line limits)."""
        hints = hints or {}
        sx, sy = spacing_mm
        pixel = float(np.sqrt(sx * sy))
        base = DotParams(
            median_px=max(_odd(MEDIAN_MM / pixel), 3),
            disk_px=max(int(round(DISK_RADIUS_MM / pixel)), 1),
            threshold=THRESHOLD,
            min_area_px=MIN_AREA_MM2 / (sx * sy),
            max_area_px=MAX_AREA_MM2 / (sx * sy),
        )
        attempts = (
            base,
            replace(base, threshold=base.threshold / 2),  # dim dots
            replace(base, median_px=max(base.median_px - 2, 1)),  # small dots
            replace(base, median_px=base.median_px + 2, disk_px=base.disk_px + 1,  # noisy frames
                    threshold=min(2 * base.threshold, 0.6)),
        )
        roi = None
        if use_roi and hints.get("ClipRectangleOrigin") and hints.get("ClipRectangleSize"):
            corner, size = hints["ClipRectangleOrigin"].split(), hints["ClipRectangleSize"].split()
            roi = tuple(int(v) for v in (*corner, *size))
        return cls(
            n_wires=phantom.n_wires,
            model=PatternModel.from_phantom(phantom, orientation),
            tolerances=Tolerances.from_plus_hints(hints),
            spacing_mm=(float(sx), float(sy)),
            attempts=tuple(dict.fromkeys(attempts)),
            roi=roi,
            plus_dots=_plus_dot_params(hints, pixel) if hints else None,
            plus_lines=PlusLineModel.from_plus_hints(phantom, hints) if hints else None,
        )

    @classmethod
    def for_session(cls, session: Session, orientation: Orientation | None = None,
                    use_roi: bool = True) -> "Segmenter":
        """The segmenter a session calls for: its phantom, spacing and PLUS hints.

        The orientation defaults to PLUS's convention (:func:`core.labelling.plus_orientation`)
        for sessions imported from PLUS recordings, else to probecal's
        (:data:`core.labelling.SIMULATED`).
        The spacing is PLUS's ApproximateSpacingMmPerPixel, else the session's nominal spacing,
        else its probe's. Raises InputError without a phantom or a spacing.
        """
        if session.phantom is None:
            raise InputError(session.path, "session has no phantom definition to label the markers with")
        hints = session.manifest.get("segmentation_hints") or {}
        if hints.get("ApproximateSpacingMmPerPixel"):
            spacing = (float(hints["ApproximateSpacingMmPerPixel"]),) * 2
        elif session.pixel_spacing_mm is not None:
            spacing = session.pixel_spacing_mm
        elif session.probe is not None:
            spacing = session.probe.nominal_spacing_mm
        else:
            raise InputError(session.path, "no pixel spacing known (no probe, spacing or PLUS segmentation hints)")
        if orientation is None:
            imported = session.manifest.get("kind") == "imported"
            orientation = plus_orientation(session.phantom) if imported else SIMULATED
        return cls.create(session.phantom, spacing, orientation, hints, use_roi)

    def __call__(self, image: np.ndarray, index: int = 0) -> FrameResult:
        """Segment one frame (uint8 gray, or colour).

        A pattern that fits its wires within half the residual limit is taken at once; otherwise
        every parameter set is tried and the best-fitting pattern wins. An ambiguous frame is
        rejected: other parameters would only pick one of the rival patterns.
        """
        gray = _as_gray(image)
        if self.plus_dots is not None:
            return self._plus_segment(gray, index)
        best, failure = None, None
        for params in self.attempts:
            dots = find_dots(gray, params, self.roi).brightest(self.max_candidates)
            labelling = label_dots(dots.positions, self.spacing_mm, self.model, self.tolerances)
            if labelling.ambiguous:
                return FrameResult(index, False, None, labelling.reason, dots.positions)
            if labelling.dots is None:
                failure = failure or (dots, labelling.reason)
            elif best is None or labelling.residual_mm < best[1].residual_mm:
                best = (dots, labelling)
            if best and best[1].residual_mm <= self.tolerances.max_residual_mm / 2:
                break
        if best is None:
            dots, reason = failure
            if gray.max() - gray.min() < MIN_CONTRAST:
                reason = "no echoes: the frame is blank"
            return FrameResult(index, False, None, reason, dots.positions)
        dots, labelling = best
        markers = np.empty((self.n_wires, 2))
        markers[self.model.wire_index.ravel()] = dots.positions[labelling.dots.ravel()]
        return FrameResult(index, True, markers, "ok", dots.positions)

    def _plus_segment(self, gray: np.ndarray, index: int) -> FrameResult:
        """PLUS's dot finder and labelling; a pattern whose dots an affine map cannot put on
        their wires (RMS beyond the residual limit) is rejected, which PLUS does not check."""
        dots = find_plus_dots(gray, self.plus_dots, self.roi)
        found, reason = plus_label_dots(dots.positions, dots.intensities, self.plus_lines)
        if found is None:
            if gray.max() - gray.min() < MIN_CONTRAST:
                reason = "no echoes: the frame is blank"
            return FrameResult(index, False, None, reason, dots.positions)
        markers = dots.positions[found]
        points_mm = markers[self.model.wire_index] * np.asarray(self.spacing_mm)
        residual = float(affine_residual_mm(points_mm[None], self.model)[0])
        if residual > self.tolerances.max_residual_mm:
            return FrameResult(index, False, None, f"dots off their wires by {residual:.2f} mm RMS", dots.positions)
        return FrameResult(index, True, markers, "ok", dots.positions)


Progress = Callable[[int, int], None]


def segment_session(session: Session, progress: Progress | None = None,
                    segmenter: Segmenter | None = None) -> list[FrameResult]:
    """Segment every frame of a session (two threads: decoding and OpenCV release the GIL)."""
    segmenter = segmenter or Segmenter.for_session(session)

    def one(i: int) -> FrameResult:
        if not session.records[i].extra.get("image_valid", True):
            return FrameResult(i, False, None, "frame marked invalid in the recording", NO_DOTS.positions)
        return segmenter(session.image(i), i)

    results = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        for result in pool.map(one, range(len(session))):
            results.append(result)
            if progress:
                progress(len(results), len(session))
    return results


def results_to_json(results: list[FrameResult], session: Session) -> dict:
    """SPEC §6 ``segment --out``: index is the source file's frame index for imported recordings."""
    frames = []
    for r in results:
        source = session.records[r.index].source_index
        frames.append({
            "index": int(source if source is not None else r.index),
            "found": bool(r.found),
            "markers": None if r.markers is None else np.round(r.markers, 3).tolist(),
            "reason": r.reason,
        })
    return {"frames": frames}


@dataclass(frozen=True)
class SegmentationScore:
    """Segmentation against ground truth (SPEC §5): frame counts and centroid errors (mm).

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


def segmentation_error_mm(results: list[FrameResult], truth_frames: list[dict], spacing: tuple[float, float],
                          tolerance_mm: float = 1.0) -> SegmentationScore:
    """Score results against a simulated session's ``truth.json`` frames (``index``,
    ``markers_px`` with null for wires out of view); ``spacing`` the true (sx, sy) mm/px."""
    truth = {f["index"]: np.array([[np.nan] * 2 if m is None else m for m in f["markers_px"]], float)
             for f in truth_frames}
    scale = np.asarray(spacing, float)
    complete = found = correct = mislabelled = inaccurate = 0
    errors = []
    for r in results:
        true = truth[r.index]
        complete += bool(np.isfinite(true).all())
        if not r.found:
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
class SeedSegmentationError:
    """The seed's measure (eq. 3.1-3.5): phantom distance minus the mean measured distance (mm)
    between the outer dots of a layer (lateral) and between outer dots of adjacent layers (axial)."""

    lateral_mm: float
    axial_mm: float
    frames: int


def _wire_distance(phantom: Phantom, a: int, b: int) -> float:
    """Distance (mm) between two parallel wires of the phantom."""
    wa, wb = phantom.wires[a], phantom.wires[b]
    return float(np.linalg.norm(np.cross(wa.direction, wb.front - wa.front)))


def seed_segmentation_error(results: list[FrameResult], phantom: Phantom,
                            spacing: tuple[float, float]) -> SeedSegmentationError:
    """Seed eq. 3.4/3.5 over the found frames, for any phantom: every layer's outer-dot distance
    against its outer-wire separation (30 mm in the seed) and the same outer wire of adjacent
    layers against their distance (10 mm); ``spacing`` (sx, sy) mm/px."""
    n_layers = len(phantom.layers)
    lateral = [(3 * k, 3 * k + 2) for k in range(n_layers)]
    axial = [(3 * k + w, 3 * k + 3 + w) for k in range(n_layers - 1) for w in (0, 2)]
    markers = np.array([r.markers for r in results if r.found]).reshape(-1, phantom.n_wires, 2)
    markers = markers * np.asarray(spacing, float)

    def deviation(pairs: list[tuple[int, int]]) -> float:
        if not pairs or not len(markers):
            return float("nan")
        expected = np.array([_wire_distance(phantom, a, b) for a, b in pairs])
        measured = np.stack([np.linalg.norm(markers[:, a] - markers[:, b], axis=1) for a, b in pairs], axis=1)
        return float(np.mean(expected - measured))

    return SeedSegmentationError(deviation(lateral), deviation(axial), len(markers))
