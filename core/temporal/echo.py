"""Where a flat reflector (a water tank's floor) lies in each frame: the echo signal of a
temporal calibration (PLUS fCal's "line segmentation", done our way).

Pixels: x = column, y = row, as in design §2. A frame's echo position is the row, at the frame's
centre column, of the straight line fitted through the floor's echo on every sampled scanline.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

SCANLINES = 40
"""Columns sampled across the frame (PLUS samples 40 too)."""
MIN_SCANLINES = 5
"""A frame whose line rests on fewer inlying scanlines than this has no echo position."""
PEAK_FRACTION = 0.5
"""An echo spans the rows around a scanline's peak that stay above this fraction of it."""
MIN_PEAK_FRACTION = 0.3
"""A scanline whose peak is under this fraction of the frame's brightest scanline sees no floor."""
INLIER_PX = 3.0
"""Scanlines this far (px) off the line, or 3 robust deviations if more, are not on the floor."""


def _scanline_echo(column: np.ndarray) -> float:
    """Centre of gravity (row, px) of the bright run around the scanline's peak."""
    peak = int(np.argmax(column))
    dim = column < PEAK_FRACTION * column[peak]
    before, after = np.flatnonzero(dim[:peak]), np.flatnonzero(dim[peak:])
    start = int(before[-1]) + 1 if len(before) else 0
    stop = peak + int(after[0]) if len(after) else len(column)
    run = column[start:stop]
    return float(start + (run * np.arange(len(run))).sum() / run.sum())


def _line_row(columns: np.ndarray, rows: np.ndarray, at: float) -> float:
    """Row at column ``at`` of the line fitted through (columns, rows), refitted without the
    scanlines off it; NaN when too few stay on it."""
    keep = np.ones(len(columns), bool)
    design = np.column_stack([columns - at, np.ones(len(columns))])
    for _ in range(4):
        if keep.sum() < MIN_SCANLINES:
            return float("nan")
        coef = np.linalg.lstsq(design[keep], rows[keep], rcond=None)[0]
        off = np.abs(design @ coef - rows)
        limit = max(INLIER_PX, 3 * 1.4826 * float(np.median(off[keep])))
        if np.array_equal(off <= limit, keep):
            break
        keep = off <= limit
    return float(coef[1]) if keep.sum() >= MIN_SCANLINES else float("nan")


def floor_echo_row(frame: np.ndarray, scanlines: int = SCANLINES) -> float:
    """The row (px) at the centre column of a flat reflector's echo in one uint8 frame, NaN
    when the frame shows none."""
    height, width = frame.shape
    smooth = cv2.GaussianBlur(frame, (5, 5), 0).astype(np.float32)
    columns = np.linspace(0, width - 1, scanlines).round().astype(int)
    profiles = smooth[:, columns]
    peaks = profiles.max(axis=0)
    seen = peaks > max(MIN_PEAK_FRACTION * peaks.max(), 1.0)
    if seen.sum() < MIN_SCANLINES:
        return float("nan")
    rows = np.array([_scanline_echo(profiles[:, k]) for k in np.flatnonzero(seen)])
    return _line_row(columns[seen].astype(float), rows, (width - 1) / 2)


STATIC_SAMPLE = 25
"""Frames looked at (evenly spread) to find what does not move."""
STATIC_FRACTION = 0.9
"""A pixel bright in this fraction of them is an overlay (text, scales), not an echo."""


class Frames(Protocol):
    """Frames of one size by index: an (N, H, W) array, or frames read as they are asked for."""

    def __len__(self) -> int: ...

    def __getitem__(self, k: int, /) -> np.ndarray: ...


def static_mask(frames: Frames) -> np.ndarray:
    """(H, W) True where the frames are bright whatever the probe does: a frame grabber's
    overlays, which a moving echo never is. Bright: at least half the frames' typical peak. Only
    :data:`STATIC_SAMPLE` frames are held at once."""
    pick = np.stack([frames[int(k)] for k in np.linspace(0, len(frames) - 1, min(len(frames), STATIC_SAMPLE)).round()])
    level = max(0.5 * float(np.median(pick.max(axis=(1, 2)))), 1.0)
    return np.mean(pick >= level, axis=0) >= STATIC_FRACTION


def floor_echo_rows(frames: Frames) -> np.ndarray:
    """(N,) :func:`floor_echo_row` of every frame of N (H, W) uint8 frames (an array, or frames
    read one at a time as they are asked for), with what stays bright in nearly every frame
    (:func:`static_mask`) left out."""
    mask = static_mask(frames) if len(frames) >= STATIC_SAMPLE else np.zeros(frames[0].shape, bool)
    keep = (~mask).astype(np.uint8)
    return np.array([floor_echo_row(frames[k] * keep if mask.any() else frames[k]) for k in range(len(frames))])
