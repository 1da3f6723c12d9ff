"""The fan of a scan-converted ultrasound image (a convex or phased-array probe's sector), in the
image's pixels as PLUS states it (``FanAnglesDeg``, ``FanOriginPixel``, ``FanRadiusStartPixel``,
``FanRadiusStopPixel`` of a device set's ``<VolumeReconstruction>``, MF pixels).

PLUS applies it in pixels (the frame it pastes has unit spacing): from the fan's origin, a pixel
(u, v) lies in the fan when it is at or below the origin (dv >= 0), between the two fan lines
(du / dv between the tangents of the two angles, which are measured from the image's downward axis
towards +u) and between the two radii.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FAN_RADIUS_STOP_PX = 500.0  # PLUS's default FanRadiusStopPixel


@dataclass(frozen=True)
class Fan:
    """A fan in pixels (see the module docstring): angles (deg), origin (u, v) and radii (px)."""

    angles_deg: tuple[float, float]
    origin_px: tuple[float, float] = (0.0, 0.0)
    radius_start_px: float = 0.0
    radius_stop_px: float = FAN_RADIUS_STOP_PX

    def __post_init__(self) -> None:
        if not all(-90.0 < a < 90.0 for a in self.angles_deg):
            raise ValueError(f"fan angles must lie between -90 and 90 degrees, got {list(self.angles_deg)}")
        if not 0.0 <= self.radius_start_px < self.radius_stop_px:
            raise ValueError(f"the fan's radii must satisfy 0 <= start < stop, got {self.radius_start_px:g} and "
                             f"{self.radius_stop_px:g} px")

    def mask(self, width: int, height: int) -> np.ndarray:
        """(height, width) bool: the pixels in the fan (all of them when both angles are 0, as in
        PLUS, where that turns the fan off)."""
        left, right = sorted(math.tan(math.radians(a)) for a in self.angles_deg)
        if left == right == 0.0:
            return np.ones((height, width), bool)
        du = np.arange(width, dtype=float)[None, :] - self.origin_px[0]
        dv = np.arange(height, dtype=float)[:, None] - self.origin_px[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = du / dv  # NaN at the origin, which PLUS's comparisons do not reject
        distance2 = du * du + dv * dv
        return ~((dv < 0) | (ratio < left) | (ratio > right) | (distance2 < self.radius_start_px ** 2)
                 | (distance2 > self.radius_stop_px ** 2))

    def to_json(self) -> dict:
        return {"angles_deg": list(self.angles_deg), "origin_px": list(self.origin_px),
                "radius_start_px": self.radius_start_px, "radius_stop_px": self.radius_stop_px}
