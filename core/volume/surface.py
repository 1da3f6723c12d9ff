"""Surface extraction for volume scanning (thesis 3.7): the bright echo of an object's top surface.

As in the seed, the frame is median filtered and thresholded; then, per scan line (image
column), the first bright run from the probe down is the surface, and its depth is where the
echo's leading edge crosses the threshold, interpolated to a fraction of a pixel. The leading
edge is where the interface is: the echo starts there and rings on below it.

Pixels: u = column, v = row (depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SurfaceParams:
    """Median kernel (px, odd), threshold (gray level), the shortest bright run that counts as
    a surface (px) and the near-field rows to skip under the probe face (px)."""

    median_px: int = 5
    threshold: int = 128
    min_run_px: int = 3
    skip_top_px: int = 20


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
    above = np.maximum(rows - 1, 0)
    lo, hi = filtered[above, cols], filtered[rows, cols]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(hi > lo, (params.threshold - lo) / (hi - lo), 1.0)
    v = above + np.clip(fraction, 0.0, 1.0)
    return cols.astype(float), v
