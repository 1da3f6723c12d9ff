"""Surface extraction for volume scanning (thesis 3.7): the bright echo of an object's top surface.

As in the seed, the frame is median filtered and thresholded; then, per scan line (image
column), the first bright run from the probe down is the surface, and its depth is where the
echo's leading edge crosses the threshold, interpolated to a fraction of a pixel. The leading
edge is where the interface is: the echo starts there and rings on below it.

A fixed threshold is crossed later by a weaker echo, and a surface echoes weaker the more
obliquely the beam meets it: seen through a beam tilted 20 deg, the twin's surfaces come out
0.35 mm deeper along it. ``SurfaceParams.edge_fraction`` instead places the edge where the echo
has risen that fraction of the way from the background above it to its peak, which does not move
with the echo's strength.

Pixels: u = column, v = row (depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SurfaceParams:
    """Median kernel (px, odd), threshold (gray level), the shortest bright run that counts as
    a surface (px) and the near-field rows to skip under the probe face (px). ``edge_fraction``:
    None, the edge is where the echo crosses the threshold; a fraction, where it has risen that far
    from the background (the least over ``echo_px`` rows above the crossing) to its peak (the most
    over ``echo_px`` rows from it)."""

    median_px: int = 5
    threshold: int = 128
    min_run_px: int = 3
    skip_top_px: int = 20
    edge_fraction: float | None = None
    echo_px: int = 12


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
    if params.edge_fraction is None:
        return cols.astype(float), _crossing(filtered, cols, rows, np.full(len(cols), float(params.threshold)))
    return cols.astype(float), _rise(filtered, cols, rows, params.edge_fraction, params.echo_px)


def _crossing(filtered: np.ndarray, cols: np.ndarray, rows: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Where each column rises through ``level`` between ``rows - 1`` and ``rows`` (rows, float)."""
    above = np.maximum(rows - 1, 0)
    lo, hi = filtered[above, cols], filtered[rows, cols]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(hi > lo, (level - lo) / (hi - lo), 1.0)
    return above + np.clip(fraction, 0.0, 1.0)


def _rise(filtered: np.ndarray, cols: np.ndarray, rows: np.ndarray, edge_fraction: float, echo_px: int) -> np.ndarray:
    """Where each column's echo, first bright at ``rows``, last rises through ``edge_fraction`` of
    the way from the background above it to its peak before that peak (rows, float)."""
    offsets = np.arange(-echo_px, echo_px)
    window = filtered[np.clip(rows[None, :] + offsets[:, None], 0, len(filtered) - 1), cols[None, :]]
    peak_at = echo_px + window[echo_px:].argmax(axis=0)
    level = window[:echo_px].min(axis=0) + edge_fraction * (window[echo_px:].max(axis=0) - window[:echo_px].min(axis=0))
    below = (window < level[None, :]) & (np.arange(2 * echo_px)[:, None] < peak_at[None, :])
    last_below = 2 * echo_px - 1 - below[::-1].argmax(axis=0)  # the last row under the level before the peak
    return _crossing(filtered, cols, np.clip(rows + offsets[last_below] + 1, 0, len(filtered) - 1), level)
