"""Dot candidates in B-mode frames: where the wire echoes are, with sub-pixel centroids.

Two finders, both pure functions of one uint8 frame:

- :func:`find_dots`, the thesis's steps (3.4): a 7x7 median filter, a disk-shaped opening, a
  threshold at a fraction of the frame's gray range, 8-connected components, a size filter and
  centroids weighted by how far each pixel rises above the threshold;
- :func:`find_plus_dots`, PLUS's (PlusFidSegmentation): for each of four bar directions the bar
  opening is subtracted (lines such as the tank floor and reverberation tails go, dot-sized
  spots stay), then a disk opening removes speckle; the cleaned region is thresholded at a
  fraction of its maximum and blobs are weighted by their cleaned gray levels.

Frames: pixels (u = column, v = row); ROIs are (x, y, width, height) pixels.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from probecal.core.geometry.fan import Fan
from probecal.core.io.imagefiles import gray_from_colour

MEDIAN_MM = 0.7  # the thesis's 7x7 median at 0.1 mm/px
DISK_RADIUS_MM = 0.2  # opening disk
THRESHOLD = 0.3  # fraction of the frame's (min..max) range
MIN_AREA_MM2 = 0.1  # the thesis's 10 px at 0.1 mm/px
MAX_AREA_MM2 = 12.0  # the thesis's 200 px (2 mm^2) is too small for deep dots (fCal 3.6, VLCUS 9.3 mm^2)
MIN_CONTRAST = 20  # gray levels between the darkest and the brightest pixel of a frame with echoes
MAX_CANDIDATES = 40  # brightest dots kept for labelling
PLUS_BAR_MM = 2.0  # PLUS's defaults: MorphologicalOpeningBarSizeMm,
PLUS_DISK_RADIUS_MM = 0.27  # MorphologicalOpeningCircleRadiusMm,
PLUS_THRESHOLD_PERCENT = 10.0  # ThresholdImagePercent,
PLUS_MAX_CANDIDATES = 20  # NumberOfMaximumFiducialPointCandidates
PLUS_EDGE_PX = 8  # PLUS drops dots whose centroid is nearer the processed region's edge
OVERLAY_LEVEL = 32  # gray level a pixel keeps in every frame of a recording to count as overlay
OVERLAY_MIN_FRAMES = 8  # frames needed before anything is called overlay
OVERLAY_MARGIN_PX = 2  # overlay grown by this much (anti-aliased text edges)



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

    def brightest(self, n: int) -> Dots:
        keep = np.sort(np.argsort(-self.intensities, kind="stable")[:n])
        return self._subset(keep)

    def without_faint(self, n: int, fraction: float) -> Dots:
        """Without the candidates under ``fraction`` of the median intensity of the ``n``
        brightest (a typical wire echo when ``n`` is the number of wires)."""
        if len(self.intensities) <= n:
            return self
        typical = np.median(np.sort(self.intensities)[-n:])
        return self._subset(np.flatnonzero(self.intensities >= fraction * typical))

    def within(self, fan: Fan) -> Dots:
        """Only the candidates whose centroids lie in ``fan`` (pixels of the same frame)."""
        return self._subset(np.flatnonzero(fan.contains(self.positions)))

    def _subset(self, keep: np.ndarray) -> Dots:
        return Dots(self.positions[keep], self.areas[keep], self.intensities[keep])

    def merged(self, groups: list[list[int]]) -> Dots:
        """The candidates with each group (indices, disjoint) made one: at the group's
        intensity-weighted centroid, with its summed area and weight; the merged ones last."""
        grouped = {i for group in groups for i in group}
        keep = self._subset(np.array([i for i in range(len(self.positions)) if i not in grouped], dtype=int))
        weights = [self.intensities[g] for g in groups]
        positions = [np.average(self.positions[g], axis=0, weights=w) for g, w in zip(groups, weights)]
        return Dots(np.vstack([keep.positions, *positions]) if groups else keep.positions,
                    np.concatenate([keep.areas, [self.areas[g].sum() for g in groups]]),
                    np.concatenate([keep.intensities, [w.sum() for w in weights]]))


NO_DOTS = Dots(np.empty((0, 2)), np.empty(0), np.empty(0))
REFINE_LEVEL = 0.1  # an echo's pixels at full resolution: this far from the background to its peak


def refined_centroids(gray: np.ndarray, points: np.ndarray, radius_px: tuple[float, float],
                      level: float = REFINE_LEVEL) -> np.ndarray:
    """Each point (u, v) px moved to the intensity-weighted centroid of the echo it lies on, at
    the frame's own resolution: within a window of twice ``radius_px`` (rx, ry) about it (0
    outside the frame), the connected pixels above ``level`` of the way from the window's median
    to the echo's peak (the brightest pixel within ``radius_px``), the blob under the point (else
    it stays), weighted by how far above. The windows are stacked, so that one connected-component
    pass serves them all."""
    points = np.asarray(points, dtype=float)
    height, width = gray.shape[:2]
    rx, ry = max(int(round(radius_px[0])), 1), max(int(round(radius_px[1])), 1)
    size_y, size_x = 4 * ry + 1, 4 * rx + 1
    stack = np.zeros((len(points), size_y + 1, size_x), np.float32)  # a row of 0 below each window
    corners = np.rint(points).astype(int) - (2 * rx, 2 * ry)
    for k, (x0, y0) in enumerate(corners):
        xa, xb, ya, yb = max(x0, 0), min(x0 + size_x, width), max(y0, 0), min(y0 + size_y, height)
        if xa < xb and ya < yb:
            stack[k, ya - y0:yb - y0, xa - x0:xb - x0] = gray[ya:yb, xa:xb]
    windows = stack[:, :size_y]
    base = np.median(windows[:, ::3, ::3].reshape(len(points), -1), axis=1)
    peak = windows[:, ry:3 * ry + 1, rx:3 * rx + 1].reshape(len(points), -1).max(axis=1)
    threshold = (base + level * (peak - base))[:, None, None]
    above = (stack > threshold) & (peak > base)[:, None, None]
    above[:, size_y] = False
    _, labels = cv2.connectedComponents(above.reshape(-1, size_x).astype(np.uint8))
    labels = labels.reshape(stack.shape)
    under = labels[:, 2 * ry, 2 * rx]
    weight = np.where((labels == under[:, None, None]) & (under > 0)[:, None, None], stack - threshold, 0.0)
    total = weight.sum(axis=(1, 2))
    found = total > 0
    out = points.copy()
    out[found, 0] = corners[found, 0] + weight[found].sum(axis=1) @ np.arange(size_x) / total[found]
    out[found, 1] = corners[found, 1] + weight[found].sum(axis=2) @ np.arange(size_y + 1) / total[found]
    return out


def _median_near(image: np.ndarray, size: int, level: int) -> np.ndarray:
    """``cv2.medianBlur(image, size)`` wherever it can reach ``level``, 0 elsewhere.

    A median of at least ``level`` needs a pixel of at least ``level`` in its window, so only the
    row bands (and within them the column span) near such pixels are filtered: a fraction of
    the frame for wire images, with the same values there as a full-frame filter.
    """
    out = np.zeros_like(image)
    pad = size // 2
    bright = image >= level
    rows = cv2.dilate(np.any(bright, axis=1).astype(np.uint8)[:, None], np.ones((size, 1), np.uint8))[:, 0]
    edges = np.flatnonzero(np.diff(np.concatenate([[0], rows, [0]]).astype(np.int8)))
    height, width = image.shape
    for top, bottom in zip(edges[::2], edges[1::2]):
        cols = np.flatnonzero(bright[max(top - pad, 0) : bottom + pad].any(axis=0))
        left, right = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, width)
        r0, c0 = max(top - pad, 0), max(left - pad, 0)
        block = np.ascontiguousarray(image[r0 : min(bottom + pad, height), c0 : min(right + pad, width)])
        out[top:bottom, left:right] = cv2.medianBlur(block, size)[top - r0 : bottom - r0, left - c0 : right - c0]
    return out


def _blobs(mask: np.ndarray, image: np.ndarray, floor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 8-connected blobs of ``mask``: pixel count, summed weight (/255) and weighted centroid
    (u, v) px of each, a pixel weighing its gray level in ``image`` above ``floor``."""
    index = np.flatnonzero(mask > 0)
    if not len(index):
        return np.empty(0), np.empty(0), np.empty((0, 2))
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    rows, cols = np.divmod(index, mask.shape[1])
    label = labels.ravel()[index]
    weight = (image[rows, cols] - float(floor)) / 255.0
    total = np.bincount(label, weight, n)[1:]
    centroid = np.column_stack([np.bincount(label, weight * c, n)[1:] for c in (cols, rows)]) / total[:, None]
    return np.bincount(label, minlength=n)[1:], total, centroid


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
    area, total, centroid = _blobs(mask, opened, level - 1)
    keep = (area >= params.min_area_px) & (area <= params.max_area_px)
    return Dots(centroid[keep] + (x0, y0), area[keep], total[keep])


@dataclass(frozen=True)
class PlusDotParams:
    """PLUS's dot finder (PlusFidSegmentation): bar half-length and disk radius (px), threshold
    (fraction of the cleaned-up region's gray range), and how many of the brightest dots are kept."""

    bar_px: int
    disk_px: int
    threshold: float
    max_candidates: int
    whole_frame: bool = False  # PLUS keeps its region a bar inside the frame; True reaches the edges

    def region(self, shape: tuple[int, ...], roi: tuple[int, int, int, int] | None) -> tuple[int, int, int, int]:
        """The processed region (x0, y0, x1, y1), exclusive ends: the clip rectangle ``roi``
        (x, y, width, height; None for the frame) kept at least a bar length plus one pixel
        inside the frame, as PLUS keeps it."""
        height, width = shape[:2]
        x, y, w, h = roi if roi else (0, 0, width, height)
        margin = self.bar_px + 1
        return (max(x, margin), max(y, margin), min(x + w, width - margin), min(y + h, height - margin))


# (rows, columns) per pixel along PLUS's bars: 0, 45, 90 and 135 degrees
_BAR_STEPS = ((0, 1), (1, -1), (1, 0), (1, 1))


def _centred_run(image: np.ndarray, step: tuple[int, int], half: int, op: np.ufunc) -> np.ndarray:
    """``op`` (``np.minimum``: erosion, ``np.maximum``: dilation) over the ``2 * half + 1`` pixels
    centred on each pixel along ``step`` = (rows, columns) per pixel, as an array of the image's
    shape; pixels whose run leaves the image hold no meaning. By doubling on the flattened image:
    log2 of the run length passes of one ufunc each, whatever the direction (a run that wraps
    past a row's end only ever lands on those meaningless pixels)."""
    if half == 0:
        return image
    rows, width = image.shape
    stride = step[0] * width + step[1]
    out = np.empty(rows * width, np.uint8)
    run, length, have = image.ravel(), 2 * half + 1, 1
    while have < length and run.size:
        shift = min(have, length - have) * stride
        run = op(run[: max(run.size - shift, 0)], run[shift:])
        have += shift // stride
    offset = half * stride
    out[offset : offset + run.size] = run
    return out.reshape(rows, width)


def _disk_boxes(radius: int) -> list[tuple[int, int]]:
    """PLUS's disk (the pixels within ``radius`` of the centre) as the union of centred boxes,
    each given by its half-height and half-width."""
    half_widths = [int(np.floor(np.sqrt(radius**2 - v**2) + 1e-9)) for v in range(radius + 1)]
    return [(v, u) for v, u in enumerate(half_widths) if v == radius or half_widths[v + 1] < u]


def _disk_op(image: np.ndarray, radius: int, op: np.ufunc) -> np.ndarray:
    """``op`` over PLUS's disk around each pixel (a box is a row run then a column run); pixels
    within ``radius`` of the edge hold no meaning."""
    boxes = (_centred_run(_centred_run(image, (0, 1), u, op), (1, 0), v, op) for v, u in _disk_boxes(radius))
    return op.reduce(list(boxes))


def _padded(image: np.ndarray, rows: int, columns: int) -> np.ndarray:
    """``image`` inside a black border (for dilations, which must not see past the image)."""
    return cv2.copyMakeBorder(image, rows, rows, columns, columns, cv2.BORDER_CONSTANT, value=0)


def _plus_cleaned(image: np.ndarray, params: PlusDotParams, region: tuple[int, int, int, int]) -> np.ndarray:
    """PLUS's morphology on ``region``: for each bar direction in turn the bar opening is
    subtracted (only dot-sized bright spots survive), then a disk opening. Erosions read the
    frame around the region; dilations see only the region's eroded values (OpenCV's erode and
    dilate with PLUS's kernels, computed by runs)."""
    x0, y0, x1, y1 = region
    pad, height, width = params.bar_px, y1 - y0, x1 - x0
    work = image[y0 - pad : y1 + pad, x0 - pad : x1 + pad].copy()
    inside = (slice(pad, pad + height), slice(pad, pad + width))
    inner = work[inside]
    for dy, dx in _BAR_STEPS:
        eroded = _padded(_centred_run(work, (dy, dx), pad, np.minimum)[inside], pad * dy, pad * abs(dx))
        opened = _centred_run(eroded, (dy, dx), pad, np.maximum)
        cv2.subtract(inner, opened[pad * dy : pad * dy + height, pad * abs(dx) : pad * abs(dx) + width], dst=inner)
    radius = params.disk_px
    extra = max(radius - pad, 0)  # a disk reaching past the bar's margin sees nothing there
    source = cv2.copyMakeBorder(work, extra, extra, extra, extra, cv2.BORDER_CONSTANT, value=255) if extra else work
    start = pad + extra - radius  # the region and the disk's reach around it
    source = np.ascontiguousarray(source[start : start + height + 2 * radius, start : start + width + 2 * radius])
    inside = (slice(radius, radius + height), slice(radius, radius + width))
    return _disk_op(_padded(_disk_op(source, radius, np.minimum)[inside], radius, radius), radius, np.maximum)[inside]


@dataclass(frozen=True)
class Cleaned:
    """PLUS's cleaned-up frame (:func:`_plus_cleaned`) over a box, and where centroids may fall."""

    image: np.ndarray  # the cleaned box (uint8)
    origin: tuple[int, int]  # frame px (u, v) of its top-left pixel
    keep: tuple[int, int, int, int]  # (x0, y0, x1, y1) frame px, exclusive ends: a centroid must lie inside


def plus_cleaned(image: np.ndarray, params: PlusDotParams, roi: tuple[int, int, int, int] | None = None
                 ) -> Cleaned | None:
    """PLUS's morphology for :func:`find_plus_dots`; None when nothing can be found (an empty
    region, a black frame). With ``params.whole_frame`` the frame is padded with black and only
    the box around its non-zero pixels is processed: the cleaned frame is zero wherever the
    frame is, and the box holds everything the morphology reads, so the result is the same."""
    if not params.whole_frame:
        x0, y0, x1, y1 = region = params.region(image.shape, roi)
        if x1 <= x0 or y1 <= y0:
            return None
        edge = PLUS_EDGE_PX
        return Cleaned(_plus_cleaned(image, params, region), (x0, y0), (x0 + edge, y0 + edge, x1 - edge, y1 - edge))
    edge = params.bar_px + 1 + PLUS_EDGE_PX
    padded = cv2.copyMakeBorder(image, edge, edge, edge, edge, cv2.BORDER_CONSTANT, value=0)
    x, y, w, h = roi or (0, 0, image.shape[1], image.shape[0])
    inner = PLUS_EDGE_PX
    x0, y0, x1, y1 = params.region(padded.shape, (x + edge - inner, y + edge - inner, w + 2 * inner, h + 2 * inner))
    if x1 <= x0 or y1 <= y0:
        return None
    bx, by, bw, bh = cv2.boundingRect(padded[y0:y1, x0:x1])
    if bw == 0:
        return None
    margin = params.disk_px + 1
    box = (max(x0 + bx - margin, x0), max(y0 + by - margin, y0),
           min(x0 + bx + bw + margin, x1), min(y0 + by + bh + margin, y1))
    keep = (x0 + inner - edge, y0 + inner - edge, x1 - inner - edge, y1 - inner - edge)
    return Cleaned(_plus_cleaned(padded, params, box), (box[0] - edge, box[1] - edge), keep)


def plus_dots(cleaned: Cleaned | None, params: PlusDotParams) -> Dots:
    """The dot candidates of a cleaned-up frame at ``params.threshold``, brightest first (see
    :func:`find_plus_dots`)."""
    if cleaned is None:
        return NO_DOTS
    level = int(np.floor(int(cleaned.image.max()) * params.threshold + 0.5))
    _, mask = cv2.threshold(cleaned.image, max(level - 1, 0), 255, cv2.THRESH_BINARY)
    area, total, centroid = _blobs(mask, cleaned.image, 0)
    centroid = centroid + cleaned.origin
    x0, y0, x1, y1 = cleaned.keep
    inside = ((centroid >= (x0, y0)) & (centroid < (x1, y1))).all(axis=1)
    order = np.argsort(-total[inside], kind="stable")[: params.max_candidates]
    return Dots(centroid[inside][order], area[inside][order], total[inside][order])


def find_plus_dots(image: np.ndarray, params: PlusDotParams, roi: tuple[int, int, int, int] | None = None) -> Dots:
    """PLUS's dot candidates, brightest first: the cleaned-up region thresholded at
    ``params.threshold`` of its maximum (PLUS's range starts at the zeros outside the region),
    8-connected blobs weighted by their gray levels, centroids at least 8 px inside the region,
    intensity the summed gray level / 255; ``roi`` is (x, y, width, height). With
    ``params.whole_frame`` the frame is padded with black first, so dots up to its edges count."""
    return plus_dots(plus_cleaned(image, params, roi), params)


def plus_dot_sets(image: np.ndarray, attempts: tuple[PlusDotParams, ...],
                  roi: tuple[int, int, int, int] | None = None) -> Iterator[Dots]:
    """:func:`find_plus_dots` for each parameter set in turn, lazily; sets that differ only in
    threshold or count share one cleaned-up frame."""
    cleaned: dict[tuple, Cleaned | None] = {}
    for params in attempts:
        key = (params.bar_px, params.disk_px, params.whole_frame)
        if key not in cleaned:
            cleaned[key] = plus_cleaned(image, params, roi)
        yield plus_dots(cleaned[key], params)


def overlay_keep(frames: list[np.ndarray]) -> np.ndarray | None:
    """What a scanner or frame grabber draws over its images (text, scales, tick marks, the probe
    outline), found as the pixels that stay at or above :data:`OVERLAY_LEVEL` in every one of
    ``frames`` (uint8 gray, one recording, the probe moving between them): a uint8 mask, 0 on the
    overlay grown by :data:`OVERLAY_MARGIN_PX` and 255 elsewhere, to AND with each frame. None
    with fewer than :data:`OVERLAY_MIN_FRAMES` frames of one size, or when nothing stays bright."""
    if len(frames) < OVERLAY_MIN_FRAMES or len({f.shape for f in frames}) > 1:
        return None
    overlay = np.where(np.minimum.reduce(frames) >= OVERLAY_LEVEL, 255, 0).astype(np.uint8)
    if not overlay.any():
        return None
    grow = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * OVERLAY_MARGIN_PX + 1,) * 2)
    return cv2.bitwise_not(cv2.dilate(overlay, grow))


ECHO_HALF_DEPTH_MM = 1.0  # axial reach around a dot in which its echo's peak is looked for
ECHO_HALF_WIDTH_MM = 0.5  # lateral reach whose rows are summed into the axial profile


def echo_peak_rows(image: np.ndarray, markers_px: np.ndarray, spacing_mm: tuple[float, float]) -> np.ndarray:
    """The row (sub-pixel) where each dot's echo is brightest, for markers ``markers_px`` (N, 2)
    (u, v) px of a frame with pixel spacing ``spacing_mm`` (x, y): the frame's rows summed over
    the dot's lateral reach, smoothed by [1 2 1], the maximum within the axial reach refined by a
    parabola. A wire echo rings on below the wire, so a dot's centroid sits deeper than its
    peak, and deeper the larger the echo; NaN where a marker is missing or its reach leaves
    the frame."""
    gray = as_gray(image)
    height, width = gray.shape
    half_u = max(int(round(ECHO_HALF_WIDTH_MM / spacing_mm[0])), 1)
    half_v = max(int(round(ECHO_HALF_DEPTH_MM / spacing_mm[1])), 2)
    rows = np.full(len(markers_px), np.nan)
    for k, (u, v) in enumerate(np.asarray(markers_px, float)):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        u0, v0 = int(round(u)), int(round(v))
        top, bottom = v0 - half_v - 1, v0 + half_v + 2
        if u0 - half_u < 0 or u0 + half_u >= width or top < 0 or bottom > height:
            continue
        profile = gray[top:bottom, u0 - half_u : u0 + half_u + 1].sum(axis=1, dtype=np.float64)
        profile = np.convolve(profile, (0.25, 0.5, 0.25), mode="valid")  # rows top + 1 .. bottom - 2
        i = int(np.clip(np.argmax(profile), 1, len(profile) - 2))
        before, peak, after = profile[i - 1 : i + 2]
        curvature = before - 2 * peak + after
        rows[k] = top + 1 + i + (0.5 * (before - after) / curvature if curvature < 0 else 0.0)
    return rows


def as_gray(image: np.ndarray) -> np.ndarray:
    """A uint8 single-channel view of a frame (colour frames are converted)."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = gray_from_colour(image)
    if image.dtype != np.uint8:
        # OpenCV's stub makes dst required; None has OpenCV allocate it
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)  # type: ignore[call-overload]
    return image


def plus_dot_params(hints: dict[str, str], pixel: float) -> PlusDotParams:
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


def odd(x: float) -> int:
    return 2 * int(round((x - 1) / 2)) + 1
