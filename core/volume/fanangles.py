"""PLUS's fan-angle auto-detection (``EnableFanAnglesAutoDetect``, vtkFanAngleDetectorAlgo): the
angles of a frame's fan that hold image content, within the configured fan, so that the dark
sectors where the probe lost contact with the skin are left out of the volume.

Pixels (MF, PLUS's in-memory orientation) are sampled one pixel apart along four arcs about the
fan's origin, at 15, 30, 50 and 70 % of the way from the start radius to the stop radius. Along each
arc a window of ``2 * filter_radius_px`` samples opens a bright run when at least half of it is
at or above ``brightness`` and closes it when at most half is; the widest run of any arc, narrowed
by the margin (PLUS's 3 degrees each side) and kept within the configured angles, is the frame's
fan. A frame without a run is empty, and PLUS leaves it out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ARC_FRACTIONS = (0.15, 0.30, 0.50, 0.70)  # PLUS's EvaluatedDepthsRadiusPercentage
MARGIN_DEG = -3.0  # PLUS's FanAngleMarginDeg: negative narrows the detected fan


@dataclass(frozen=True)
class FanAutoDetect:
    """The detection's settings (``FanAnglesAutoDetectBrightnessThreshold``,
    ``FanAnglesAutoDetectFilterRadiusPixel``, PLUS's defaults)."""

    brightness: float = 30.0
    filter_radius_px: int = 10


def _round(values: np.ndarray) -> np.ndarray:
    """vtkMath::Round: halves away from zero."""
    return np.where(values >= 0, np.floor(values + 0.5), np.ceil(values - 0.5)).astype(int)


def _widest_run(angles: np.ndarray, bright: np.ndarray, window: int, last_angle: float) -> tuple[float, float]:
    """The widest bright run (left, right) in rad along one arc (see the module docstring); (0, 0)
    when there is none."""
    counts = np.concatenate([[0], np.cumsum(bright)])
    best, valid, left = (0.0, 0.0), False, 0.0
    runs = []
    for j in range(window, len(angles)):
        count = counts[j] - counts[j - window]
        if not valid and count >= window / 2:
            left, valid = float(angles[j - window]), True
        elif valid and count <= window / 2:
            runs.append((left, float(angles[j - 1])))
            valid = False
    if valid:  # a run that reaches the fan's edge
        runs.append((left, last_angle))
    for run in runs:
        if run[1] - run[0] > best[1] - best[0]:
            best = run
    return best


def detected_fan_angles(image: np.ndarray, origin_px: tuple[float, float], radius_start_px: float,
                        radius_stop_px: float, max_angles_deg: tuple[float, float],
                        settings: FanAutoDetect) -> tuple[float, float] | None:
    """The fan angles (deg) of ``image`` (uint8 (H, W), MF) that hold content, within
    ``max_angles_deg``; None for an empty frame."""
    height, width = image.shape
    x0, y0 = int(origin_px[0]), int(origin_px[1])  # PLUS takes the origin's whole pixels
    low, high = (math.radians(a) for a in max_angles_deg)
    window = 2 * settings.filter_radius_px
    widest = (0.0, 0.0)
    for fraction in ARC_FRACTIONS:
        radius = radius_start_px + (radius_stop_px - radius_start_px) * fraction
        step = 1.0 / radius
        angles = low + np.arange(int((high - low) / step)) * step
        u, v = _round(x0 + radius * np.sin(angles)), _round(y0 + radius * np.cos(angles))
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        angles = angles[inside]
        bright = image[v[inside], u[inside]] >= settings.brightness
        run = _widest_run(angles, bright, window, high)
        if run[1] - run[0] > widest[1] - widest[0]:
            widest = run
    if widest == (0.0, 0.0):
        return None
    left = max(math.degrees(widest[0]) - MARGIN_DEG, max_angles_deg[0])
    right = min(math.degrees(widest[1]) + MARGIN_DEG, max_angles_deg[1])
    return left, right
