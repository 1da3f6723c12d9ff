"""PLUS's labeller (FidLineFinder and FidLabeling), cloned for comparison: lines through the dot
candidates, N patterns from pairs of parallel lines at the hinted distances, the first compatible
clique. Pixels: x = column, y = row."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from probecal.core.geometry.phantom import Phantom

PLUS_END_TOLERANCE_MM = 4.0  # PLUS's allowance on the outer-dot distance of a line
PLUS_MIDDLE_TOLERANCE_MM = 15.0  # and on the distance from a line's start to its middle dot


def _plus_px(mm: ArrayLike, spacing_mm: float) -> np.ndarray:
    """mm to whole pixels, rounded half up as PLUS does."""
    return np.floor(np.asarray(mm, float) / spacing_mm + 0.5).astype(int)


@dataclass(frozen=True)
class PlusLineModel:
    """PLUS's line and pattern limits for a phantom (pixels, radians); patterns in definition order.

    ``end_px`` / ``middle_px`` are each pattern's expected distance from a line's start dot to its
    end dot / middle dot (PLUS takes the outer distance from the wires' back ends in x-y).
    """

    end_px: np.ndarray  # (P,)
    end_tolerance_px: int
    middle_px: np.ndarray  # (P,)
    middle_tolerance_px: int
    theta_rad: tuple[float, float]
    collinear_px: float
    angle_tolerance_rad: float
    pair_distance_px: tuple[int, int]  # allowed distance between parallel lines
    pair_angle_rad: tuple[float, float]  # angles between the pattern planes
    max_shift_px: int

    @property
    def n_patterns(self) -> int:
        return len(self.end_px)

    @classmethod
    def from_plus_hints(cls, phantom: Phantom, hints: dict[str, str]) -> PlusLineModel:
        """The limits a PLUS ``<Segmentation>`` element sets (PLUS's defaults where it is silent)."""
        def value(key: str, default: float) -> float:
            return float(hints.get(key) or default)

        spacing = value("ApproximateSpacingMmPerPixel", 0.078)
        ends, middles, planes = [], [], []
        for layer in phantom.layers:
            first, diagonal, last = layer.wires
            across = (last.front - first.front) / np.linalg.norm(last.front - first.front)
            middles.append(abs(np.dot((diagonal.front + diagonal.back) / 2 - first.front, across)))
            ends.append(np.linalg.norm((first.back - last.back)[:2]))
            normal = np.cross(first.back - first.front, last.front - first.front)
            planes.append((normal / np.linalg.norm(normal), first.front))
        pairs = [(planes[i], planes[j]) for i in range(len(planes)) for j in range(i)]
        pairs = pairs or [(planes[0], planes[0])]  # one pattern: no pairs to check
        gaps = [abs(np.dot(a[0], b[1] - a[1])) for a, b in pairs]
        angles = [np.arccos(min(abs(np.dot(a[0], b[0])), 1.0)) for a, b in pairs]
        error = value("MaxLinePairDistanceErrorPercent", 10.0) / 100
        return cls(
            end_px=_plus_px(ends, spacing),
            end_tolerance_px=int(_plus_px(PLUS_END_TOLERANCE_MM, spacing)),
            middle_px=_plus_px(middles, spacing),
            middle_tolerance_px=int(_plus_px(PLUS_MIDDLE_TOLERANCE_MM, spacing)),
            theta_rad=(np.radians(value("MinThetaDegrees", -70.0)), np.radians(value("MaxThetaDegrees", 70.0))),
            collinear_px=value("CollinearPointsMaxDistanceFromLineMm", 0.6) / spacing,
            angle_tolerance_rad=np.radians(value("AngleToleranceDegrees", 10.0)),
            pair_distance_px=(int(_plus_px(min(gaps) * (1 - error), spacing)),
                              int(_plus_px(max(gaps) * (1 + error), spacing))),
            pair_angle_rad=(min(angles), max(angles)),
            max_shift_px=int(_plus_px(value("MaxLineShiftMm", 10.0), spacing)),
        )


def _accept_theta(angle: np.ndarray, theta: tuple[float, float]) -> np.ndarray:
    """PLUS's test of a line's angle (atan2, -pi..pi) against its allowed range, either direction."""
    lo, hi = theta
    ok = (angle > lo) & (angle < hi)
    if lo > -np.pi / 2 and hi < np.pi / 2:
        return ok | (angle < hi - np.pi) | (angle > lo + np.pi)
    if hi > np.pi / 2:
        return ok | ((angle < hi - np.pi) & (angle > lo - np.pi))
    if lo < -np.pi / 2:
        return ok | ((angle < hi + np.pi) & (angle > lo + np.pi))
    return ok


def _segment_length(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between points in single precision, as PLUS measures line lengths."""
    return np.sqrt(((b - a) ** 2).sum(-1).astype(np.float32)).astype(float)


def _farthest(points: np.ndarray, lines: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Each line's dot farthest from its ``origin`` dot, PLUS's way: the running maximum is kept
    as an integer, so a later dot less than a pixel farther still wins."""
    longest, far = np.zeros(len(lines)), origin.copy()
    for k in range(lines.shape[1]):
        d = np.linalg.norm(points[lines[:, k]] - points[origin], axis=-1)
        better = d > longest
        longest, far = np.where(better, np.trunc(d), longest), np.where(better, lines[:, k], far)
    return far


def _line_ends(points: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PLUS's start and end dots of lines (L, k) of dot indices: the start is first the dot with
    the largest u (compared against a truncated running maximum, as PLUS does), the end the dot
    farthest from it, then the start the dot farthest from the end."""
    u = points[lines, 0]
    best, start = np.trunc(u[:, 0]), lines[:, 0].copy()
    for k in range(lines.shape[1]):
        better = u[:, k] > best
        best, start = np.where(better, np.trunc(u[:, k]), best), np.where(better, lines[:, k], start)
    end = _farthest(points, lines, start)
    return _farthest(points, lines, end), end


def _distance_from_lines(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Distance of points from the infinite lines through start and end (broadcasting, (..., 2))."""
    u = end - start
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = points - start
    return np.abs(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0])


def _plus_pairs(points: np.ndarray, model: PlusLineModel) -> np.ndarray:
    """PLUS's two-point lines (T, 2), lower dot index first: the dots as far apart as some
    pattern's outer dots, on a line within the angle range."""
    i, j = np.triu_indices(len(points), 1)
    length = _segment_length(points[i], points[j])
    fits = (np.abs(length[:, None] - model.end_px[None, :]) < model.end_tolerance_px).any(axis=1)
    step = points[j] - points[i]
    fits &= _accept_theta(np.arctan2(step[:, 1], step[:, 0]), model.theta_rad)
    return np.column_stack([i[fits], j[fits]])


def _principal_directions(points: np.ndarray) -> np.ndarray:
    """Unit direction (L, 2) of the least-squares line through each set of points (L, k, 2)."""
    centred = points - points.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("lki,lkj->lij", centred, centred))[1][..., 1]


@dataclass(frozen=True)
class PlusLines:
    """PLUS's three-point lines, brightest first: dot indices (L, 3) ascending, start and end dot
    indices (L,), unit directions (L, 2)."""

    dots: np.ndarray
    start: np.ndarray
    end: np.ndarray
    direction: np.ndarray


def plus_lines(points: np.ndarray, intensities: np.ndarray, model: PlusLineModel) -> PlusLines:
    """PLUS's line finder: every two-point line grows by each dot near its line, on the side of
    its end and at some pattern's middle-dot distance from its start; the three-point lines
    within the angle range are kept, ordered by summed dot intensity."""
    pairs = _plus_pairs(points, model)
    start, end = _line_ends(points, pairs)
    near = _distance_from_lines(points[None], points[start][:, None], points[end][:, None]) <= model.collinear_px
    near[np.arange(len(pairs))[:, None], pairs] = False
    t, k = np.nonzero(near)
    length = _segment_length(points[start[t]], points[k])
    fits = (np.abs(length[:, None] - model.middle_px[None, :]) < model.middle_tolerance_px).any(axis=1)
    fits &= np.einsum("ti,ti->t", points[end[t]] - points[start[t]], points[k] - points[start[t]]) >= 0
    dots = np.unique(np.sort(np.column_stack([pairs[t[fits]], k[fits]]), axis=1), axis=0).reshape(-1, 3)
    direction = _principal_directions(points[dots]) if len(dots) else np.empty((0, 2))
    keep = _accept_theta(np.arctan2(direction[:, 1], direction[:, 0]), model.theta_rad)
    dots, direction = dots[keep], direction[keep]
    order = np.argsort(-intensities[dots].sum(axis=1), kind="stable")
    dots, direction = dots[order], direction[order]
    start, end = _line_ends(points, dots)
    return PlusLines(dots, start, end, direction)


def _plus_compatible(points: np.ndarray, lines: PlusLines, model: PlusLineModel) -> np.ndarray:
    """(L, L) whether two lines may belong to one pattern, PLUS's test with the dimmer line first:
    parallel lines (within the angle tolerance) at an allowed distance and shift, other lines
    at an angle the pattern planes allow."""
    cos = np.clip(lines.direction @ lines.direction.T, -1.0, 1.0)
    angle = np.arccos(cos)
    angle = np.abs(np.where(angle > np.pi / 2, angle - np.pi, angle))
    start, end = points[lines.start], points[lines.end]
    distance = _distance_from_lines(start[:, None], start[None], end[None])  # [a, b]: a's start from b's line
    lo, hi = model.pair_distance_px
    middle = (start + end) / 2
    axis = (end - start) / np.linalg.norm(end - start, axis=1, keepdims=True)
    shift = np.einsum("ai,abi->ab", axis, middle[None] - middle[:, None])
    parallel = (distance >= lo) & (distance <= hi) & (np.abs(shift) <= model.max_shift_px)
    low, high = model.pair_angle_rad
    tol = model.angle_tolerance_rad
    ok = np.where(angle < tol, parallel, (angle >= low - tol) & (angle <= high + tol))
    dimmer_first = np.arange(len(ok))[:, None] > np.arange(len(ok))[None, :]
    return np.where(dimmer_first, ok, ok.T)


def _first_clique(ok: np.ndarray, size: int, chosen: tuple[int, ...] = ()) -> tuple[int, ...] | None:
    """The first ``size`` lines, in lexicographic order of ascending index tuples, that are all
    pairwise compatible (PLUS's enumeration order: brightest combinations first)."""
    if len(chosen) == size:
        return chosen
    first = chosen[-1] + 1 if chosen else 0
    for c in np.flatnonzero(ok[first:, list(chosen)].all(axis=1)) + first:  # all of no columns: True
        found = _first_clique(ok, size, chosen + (int(c),))
        if found:
            return found
    return None


def plus_label_dots(points: np.ndarray, intensities: np.ndarray,
                    model: PlusLineModel) -> tuple[np.ndarray | None, str]:
    """PLUS's labelling: the first compatible set of three-point lines, one per pattern, the
    shallowest line (by its ends' mean v) for the first pattern; within a line the dots from the
    largest u down are the pattern's wires in definition order. Returns the dot indices in
    phantom wire order, or None with the reason."""
    lines = plus_lines(points, intensities, model)
    if len(lines.dots) < model.n_patterns:
        return None, f"{len(lines.dots)} collinear dot triples, the pattern needs {model.n_patterns}"
    chosen = _first_clique(_plus_compatible(points, lines, model), model.n_patterns)
    if chosen is None:
        return None, "no set of dot lines at the pattern's distances and angles"
    index = np.array(chosen)
    depth = (points[lines.start[index], 1] + points[lines.end[index], 1]) / 2
    dots = lines.dots[index[np.argsort(depth, kind="stable")]]
    order = np.argsort(-points[dots, 0], axis=1, kind="stable")
    return np.take_along_axis(dots, order, axis=1).ravel(), "ok"
