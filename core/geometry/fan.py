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
from collections.abc import Callable
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

    def contains(self, pixels: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(...,) bool: the (..., 2) pixels (u, v) lie in the fan, at least ``margin_px`` inside
        its lines and arcs (a pixel at the origin does not)."""
        pixels = np.asarray(pixels, dtype=float)
        du, dv = pixels[..., 0] - self.origin_px[0], pixels[..., 1] - self.origin_px[1]
        left, right = (math.radians(a) for a in sorted(self.angles_deg))
        radius = np.hypot(du, dv)
        return ((dv > 0) & (du * math.cos(left) - dv * math.sin(left) >= margin_px)
                & (du * math.cos(right) - dv * math.sin(right) <= -margin_px)
                & (radius >= self.radius_start_px + margin_px) & (radius <= self.radius_stop_px - margin_px))

    def corners_px(self) -> np.ndarray:
        """(4, 2) the fan's corners (u, v px): its near arc's ends, then its far arc's, each from
        the first angle to the second."""
        angles = np.radians(self.angles_deg)
        radii = np.array([self.radius_start_px, self.radius_start_px, self.radius_stop_px, self.radius_stop_px])
        turns = np.tile(angles, 2)
        return np.column_stack([self.origin_px[0] + radii * np.sin(turns), self.origin_px[1] + radii * np.cos(turns)])

    def face_points(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) where each pixel's beam leaves the face: the point at the near radius on the
        line from the origin through it (px)."""
        d = np.asarray(pixels, dtype=float) - self.origin_px
        r = np.linalg.norm(d, axis=-1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.origin_px + np.where(r > 0, d * (self.radius_start_px / r), 0.0)

    def stretched(self, pixels: np.ndarray, stretch: float) -> np.ndarray:
        """(..., 2) where pixels lie once every beam's depth below the face is ``stretch`` times
        what the image shows (the medium's sound speed over the scanner's), in the same pixels:
        a scanner's fan converted at the wrong sound speed set right (``1 / stretch`` undoes it)."""
        face = self.face_points(pixels)
        return face + stretch * (np.asarray(pixels, dtype=float) - face)

    def samples_px(self, n: int = 31) -> np.ndarray:
        """(n * n, 2) pixels spread over the fan: ``n`` angles by ``n`` radii, edges included."""
        angles, radii = np.meshgrid(np.radians(np.linspace(*self.angles_deg, n)),
                                    np.linspace(self.radius_start_px, self.radius_stop_px, n))
        return np.column_stack([(self.origin_px[0] + radii * np.sin(angles)).ravel(),
                                (self.origin_px[1] + radii * np.cos(angles)).ravel()])

    def closest_affine(self, mapped: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(D + 1, 3) the affine map of pixels closest (least squares over :meth:`samples_px`) to
        ``mapped``, which takes (N, 2) pixels to (N, D) points."""
        pixels = self.samples_px()
        design = np.column_stack([pixels, np.ones(len(pixels))])
        solution, *_ = np.linalg.lstsq(design, mapped(pixels), rcond=None)
        out = np.zeros((solution.shape[1] + 1, 3))
        out[:-1], out[-1, 2] = solution.T, 1.0
        return out

    def to_json(self) -> dict:
        return {"angles_deg": list(self.angles_deg), "origin_px": list(self.origin_px),
                "radius_start_px": self.radius_start_px, "radius_stop_px": self.radius_stop_px}
