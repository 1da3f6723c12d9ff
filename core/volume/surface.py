"""Surface extraction for volume scanning (thesis 3.7): the bright echo of an object's top surface.

As in the seed, the frame is median filtered and thresholded; then, per scan line (image
column), the first bright run from the probe down is the surface, and its depth is where the
echo's leading edge crosses the threshold, interpolated to a fraction of a pixel. The leading
edge is where the interface is: the echo starts there and rings on below it.

A fixed threshold is crossed later by a weaker echo, and a surface echoes weaker the more
obliquely the beam meets it: seen through a beam tilted 20 deg, the twin's surfaces come out
0.35 mm deeper along it. ``SurfaceParams.edge="steepest"`` instead places the edge where the
echo rises most steeply before its peak, the classic edge of a blurred step, which moves least
with the echo's strength, saturated or not (``benchmarks/bench_selfcheck.py --edge``).

Pixels: u = column, v = row (depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

EDGES = ("threshold", "steepest")
"""Where a scan line's surface edge is placed (:class:`SurfaceParams`)."""


@dataclass(frozen=True)
class SurfaceParams:
    """Median kernel (px, odd), threshold (gray level), the shortest bright run that counts as
    a surface (px) and the near-field rows to skip under the probe face (px). ``edge``:
    "threshold", the edge is where the echo crosses the threshold; "steepest", where it rises most
    steeply within ``echo_px`` rows above the crossing, before its peak (the most over
    ``echo_px`` rows from it)."""

    median_px: int = 5
    threshold: int = 128
    min_run_px: int = 3
    skip_top_px: int = 20
    edge: str = "threshold"
    echo_px: int = 12

    def __post_init__(self) -> None:
        if self.edge not in EDGES:
            raise ValueError(f"edge must be one of {', '.join(EDGES)}, not {self.edge!r}")


def extract_surface(image: np.ndarray, params: SurfaceParams = SurfaceParams()) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of the surface's leading edge, one per scan line that has one (float pixels)."""
    filtered = cv2.medianBlur(np.ascontiguousarray(image, dtype=np.uint8), params.median_px).astype(np.float32)
    filtered[: params.skip_top_px] = 0
    bright = filtered >= params.threshold
    # A run counts only if it lasts min_run_px rows: erode the mask along the columns.
    kernel = np.ones((params.min_run_px, 1), np.uint8)
    anchor = (0, 0)  # keep a run's first row where it starts
    solid = cv2.erode(bright.astype(np.uint8), kernel, anchor=anchor, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    has = solid.any(axis=0)
    cols = np.flatnonzero(has)
    rows = solid[:, cols].argmax(axis=0)
    if params.edge == "threshold":
        return cols.astype(float), _crossing(filtered, cols, rows, float(params.threshold))
    return cols.astype(float), _steepest(filtered, cols, rows, params.echo_px)


def _crossing(filtered: np.ndarray, cols: np.ndarray, rows: np.ndarray, level: float) -> np.ndarray:
    """Where each column rises through ``level`` between ``rows - 1`` and ``rows`` (rows, float)."""
    above = np.maximum(rows - 1, 0)
    lo, hi = filtered[above, cols], filtered[rows, cols]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(hi > lo, (level - lo) / (hi - lo), 1.0)
    return above + np.clip(fraction, 0.0, 1.0)


def _steepest(filtered: np.ndarray, cols: np.ndarray, rows: np.ndarray, echo_px: int) -> np.ndarray:
    """Where each column's echo, first bright at ``rows``, rises most steeply before its peak
    (rows, float): the largest step between neighbouring rows, placed between them to a fraction
    of a row by a parabola through it and its neighbours."""
    offsets = np.arange(-echo_px, echo_px)
    window = filtered[np.clip(rows[None, :] + offsets[:, None], 0, len(filtered) - 1), cols[None, :]]
    peak_at = echo_px + window[echo_px:].argmax(axis=0)
    steps = np.diff(window, axis=0)  # steps[k]: from the window's row k to row k + 1
    steps[np.arange(len(steps))[:, None] >= peak_at[None, :]] = -np.inf
    at = steps.argmax(axis=0)
    line = np.arange(len(cols))
    here = steps[at, line]
    before = steps[np.maximum(at - 1, 0), line]
    after = steps[np.minimum(at + 1, len(steps) - 1), line]
    bend = before - 2 * here + after
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(np.isfinite(bend) & (bend < 0), 0.5 * (before - after) / bend, 0.0)
    return rows + offsets[at] + 0.5 + np.clip(shift, -0.5, 0.5)
