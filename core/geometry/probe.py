"""Probe geometry and pixel spacing (design §4): a linear array's rectangular image, or a convex
(curvilinear) array's scan-converted fan.

The image frame has x = column, y = row (depth), z = normal; pixel (u, v) is the point (u, v, 0)
scaled by the spacing. The scanner converts echo time to depth assuming ``nominal_sound_speed``;
in a medium with another sound speed every echo lies ``medium / nominal`` as far from the face as
the image shows it. For a linear probe that scales the axial spacing; for a convex probe it scales
each beam's depth below the curved face, which no affine map of the pixels does exactly
(:attr:`ConvexProbe.affine_px_to_mm` is the closest one over the fan).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np

from probecal.core.geometry.fan import Fan


@dataclass(frozen=True)
class Span:
    """The values a probe's field may take: from ``low`` to ``high`` ``unit``, both included."""

    low: float
    high: float
    unit: str = ""

    def holds(self, value: float) -> bool:
        """``value`` lies within the span (NaN does not)."""
        return self.low <= value <= self.high

    def __str__(self) -> str:
        return f"{self.low:g} to {self.high:g}{self.unit}"


IMAGE_PX = Span(8, 8192, " px")
"""A frame's width and height: a scanner's frames are a few hundred to about two thousand pixels
each way; 8192 leaves room for any resampling, and a frame of 100000 px a side is 10 GB."""
DEPTH_MM = Span(0.1, 1000.0, " mm")
"""How deep a probe images: ultrasound reaches about 300 mm into tissue, and a metre leaves room
(the bound of every depth option, ``app.bounds``)."""
START_DEPTH_MM = Span(0.0, 1000.0, " mm")
"""How far below the face a depth preset's first row lies."""
SOUND_SPEED = Span(1000.0, 4000.0, " m/s")
"""A scanner's assumed and a medium's true sound speeds: water, gels and soft tissue lie within
1400-1650 m/s, bone below 4000."""
PROBE_FIELDS: dict[str, Span] = {
    "n_elements": Span(1, 8192),
    "pitch_mm": Span(0.01, 10.0, " mm"),
    "depth_mm": DEPTH_MM,
    "width_px": IMAGE_PX,
    "height_px": IMAGE_PX,
    "nominal_sound_speed": SOUND_SPEED,
    "medium_sound_speed": SOUND_SPEED,
    "start_depth_mm": START_DEPTH_MM,
    "radius_mm": Span(1.0, 1000.0, " mm"),
    "fov_deg": Span(1.0, 179.0, " deg"),
}
"""The bounds of every field a probe has (a probe file's, a session's, the twin's): what a real
array can be, with room, so that no field asks for more than a scanner images. An element pitch of
0.01-10 mm, at most as many elements as pixels across, a convex face's radius of 1 mm to 1 m."""


@dataclass(frozen=True)
class LinearProbe:
    """A linear probe and the B-mode image it produces (lengths in mm, speeds in m/s)."""

    n_elements: int = 128
    pitch_mm: float = 0.3
    depth_mm: float = 50.0
    width_px: int = 384
    height_px: int = 500
    nominal_sound_speed: float = 1540.0
    medium_sound_speed: float = 1480.0
    start_depth_mm: float = 0.0  # how far below the face the first row lies, as the scanner labels depth

    kind = "linear"
    face_below_first_row_mm = 0.0  # the face lies the start depth above the first row

    @property
    def fan(self) -> Fan | None:
        """None: a linear probe's image is its whole rectangle."""
        return None

    @property
    def width_mm(self) -> float:
        return self.n_elements * self.pitch_mm

    @property
    def nominal_spacing_mm(self) -> tuple[float, float]:
        """(sx, sy) mm/pixel as the scanner reports it."""
        return self.width_mm / self.width_px, self.depth_mm / self.height_px

    @property
    def true_spacing_mm(self) -> tuple[float, float]:
        """(sx, sy) mm/pixel in the medium: the axial spacing scales with the sound speed."""
        sx, sy = self.nominal_spacing_mm
        return sx, sy * self.medium_sound_speed / self.nominal_sound_speed

    @property
    def true_start_depth_mm(self) -> float:
        """How far below the face the first row lies in the medium (mm): it scales with the sound
        speed as the axial spacing does."""
        return self.start_depth_mm * self.medium_sound_speed / self.nominal_sound_speed

    def scale_matrix(self, spacing_mm: tuple[float, float] | None = None) -> np.ndarray:
        """diag(sx, sy, 1, 1): pixel coordinates to image mm (true spacing by default)."""
        sx, sy = spacing_mm if spacing_mm is not None else self.true_spacing_mm
        return np.diag([sx, sy, 1.0, 1.0])

    def pixels_from_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """(..., 2) pixels (u, v) where the scanner shows (..., 2+) true image-frame points (mm)."""
        points = np.asarray(points_mm, dtype=float)
        return points[..., :2] / self.true_spacing_mm

    def mm_from_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) true image-frame points (x, y mm) of (..., 2) pixels (u, v)."""
        return np.asarray(pixels, dtype=float) * self.true_spacing_mm

    def beam_at(self, u: np.ndarray | float, v: np.ndarray | float) -> tuple[float, np.ndarray | float]:
        """The beam through pixel (u, v): its angle (rad, from the image's downward axis toward +u;
        0 for a linear array) and the pixel's true depth below the face along it (mm); for arrays
        of pixels, the depths' array."""
        return 0.0, self.true_start_depth_mm + v * self.true_spacing_mm[1]

    def to_dict(self) -> dict:
        return {"type": self.kind, **asdict(self)}


@dataclass(frozen=True)
class ConvexProbe:
    """A convex (curvilinear) probe and the scan-converted fan it produces: the face an arc of
    ``radius_mm`` spanning ``fov_deg``, beams from the arc's centre (the apex) down to
    ``depth_mm`` below the face; square pixels, ``width_px`` across the fan's widest extent; the
    first row touches the arc's two ends (lengths in mm, angles in degrees, speeds in m/s)."""

    radius_mm: float = 50.0
    fov_deg: float = 60.0
    n_elements: int = 128
    depth_mm: float = 70.0
    width_px: int = 600
    nominal_sound_speed: float = 1540.0
    medium_sound_speed: float = 1480.0
    start_depth_mm: float = 0.0  # a fan starts at the face; kept for the presets' interface

    kind = "convex"

    def __post_init__(self) -> None:
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"a convex probe's field of view must lie between 0 and 180 degrees, got {self.fov_deg:g}")
        if self.start_depth_mm != 0.0:
            raise ValueError("a convex probe's fan starts at its face: its start depth must be 0")

    @property
    def _half(self) -> float:
        return math.radians(self.fov_deg / 2)

    @property
    def width_mm(self) -> float:
        """The fan's widest extent (mm, nominal): across its deep arc's two ends."""
        return 2.0 * (self.radius_mm + self.depth_mm) * math.sin(self._half)

    @property
    def pitch_mm(self) -> float:
        """The elements' spacing along the arc (mm)."""
        return self.radius_mm * math.radians(self.fov_deg) / self.n_elements

    @property
    def height_px(self) -> int:
        s = self.width_mm / self.width_px
        return math.ceil((self.radius_mm + self.depth_mm - self.radius_mm * math.cos(self._half)) / s)

    @property
    def nominal_spacing_mm(self) -> tuple[float, float]:
        s = self.width_mm / self.width_px
        return s, s

    @property
    def face_below_first_row_mm(self) -> float:
        """How far the face's middle (its lowest point) lies below the first row (mm)."""
        return self.radius_mm * (1.0 - math.cos(self._half))

    @property
    def apex_px(self) -> tuple[float, float]:
        """The beams' common origin (u, v px), above the image."""
        s = self.nominal_spacing_mm[0]
        return self.width_px / 2, -self.radius_mm * math.cos(self._half) / s

    @property
    def fan(self) -> Fan:
        """The image's fan in pixels (PLUS's semantics, :class:`~probecal.core.geometry.fan.Fan`)."""
        s = self.nominal_spacing_mm[0]
        angle = self.fov_deg / 2
        return Fan((-angle, angle), self.apex_px, self.radius_mm / s, (self.radius_mm + self.depth_mm) / s)

    @property
    def true_start_depth_mm(self) -> float:
        return 0.0

    @property
    def stretch(self) -> float:
        """How much deeper than shown every echo lies below the face (medium / nominal speed)."""
        return self.medium_sound_speed / self.nominal_sound_speed

    def pixels_from_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """(..., 2) pixels (u, v) where the scanner shows (..., 2+) true image-frame points (mm):
        each point's depth below the face along its beam is shown shrunk by the sound speeds."""
        s = self.nominal_spacing_mm[0]
        return self.fan.stretched(np.asarray(points_mm, dtype=float)[..., :2] / s, 1.0 / self.stretch)

    def mm_from_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) true image-frame points (x, y mm) of (..., 2) pixels (u, v)."""
        return self.fan.stretched(pixels, self.stretch) * self.nominal_spacing_mm[0]

    @cached_property
    def affine_px_to_mm(self) -> np.ndarray:
        """(3, 3) the affine map of pixels to true image mm closest (least squares) to
        :meth:`mm_from_pixels` over the fan: exact when the sound speeds agree."""
        return self.fan.closest_affine(self.mm_from_pixels)

    @property
    def true_spacing_mm(self) -> tuple[float, float]:
        """(sx, sy) mm/pixel of :attr:`affine_px_to_mm`."""
        return float(self.affine_px_to_mm[0, 0]), float(self.affine_px_to_mm[1, 1])

    def scale_matrix(self, spacing_mm: tuple[float, float] | None = None) -> np.ndarray:
        """Pixel coordinates to image mm: diag(sx, sy, 1, 1) at ``spacing_mm``, else the closest
        affine map over the fan (:attr:`affine_px_to_mm`)."""
        if spacing_mm is not None:
            return np.diag([spacing_mm[0], spacing_mm[1], 1.0, 1.0])
        out = np.eye(4)
        out[:2, :2], out[:2, 3] = self.affine_px_to_mm[:2, :2], self.affine_px_to_mm[:2, 2]
        return out

    def beam_at(self, u: np.ndarray | float,
                v: np.ndarray | float) -> tuple[np.ndarray | float, np.ndarray | float]:
        """The beam through pixel (u, v): its angle (rad, from the image's downward axis toward +u)
        and the pixel's true depth below the face along it (mm); for arrays of pixels, arrays."""
        du, dv = u - self.apex_px[0], v - self.apex_px[1]
        shown = np.hypot(du, dv) * self.nominal_spacing_mm[0] - self.radius_mm
        return np.arctan2(du, dv), shown * self.stretch

    def to_dict(self) -> dict:
        return {"type": self.kind, **asdict(self)}


Probe = LinearProbe | ConvexProbe

BUILTIN_PROBES: dict[str, Probe] = {"linear-38": LinearProbe(), "convex-50": ConvexProbe()}
DEFAULT_PROBE = "linear-38"
"""The twin's probes by name (``--probe``): a 38.4 mm linear array imaging 50 mm deep (the
default), and a convex array of 50 mm radius and 60 degrees imaging 70 mm below its face."""


def probe_from_dict(data: dict) -> Probe:
    """A probe from its dict form (``to_dict``; a missing ``type`` is linear). Raises ValueError
    or TypeError on a field the probe does not have or a value it refuses."""
    kinds: dict[str, type[LinearProbe] | type[ConvexProbe]] = {"linear": LinearProbe, "convex": ConvexProbe}
    kind = data.get("type", "linear")
    if kind not in kinds:
        raise ValueError(f"probe type must be one of {sorted(kinds)}, got {kind!r}")
    return kinds[kind](**{k: v for k, v in data.items() if k != "type"})


def in_view(probe: Probe, pixels: np.ndarray) -> np.ndarray:
    """(...,) bool: the (..., 2) pixels lie on ``probe``'s image, and in its fan if it has one."""
    pixels = np.asarray(pixels, dtype=float)
    u, v = pixels[..., 0], pixels[..., 1]
    inside = (u >= 0) & (u <= probe.width_px - 1) & (v >= 0) & (v <= probe.height_px - 1)
    return inside if probe.fan is None else inside & probe.fan.contains(pixels)


Spacing = Sequence[float] | np.ndarray
"""A pixel spacing (sx, sy), mm/px: a pair, or an array of two."""


def image_mm_from_pixels(pixels: np.ndarray, spacing_mm: Sequence[float] | np.ndarray) -> np.ndarray:
    """(..., 3) image-frame points (mm) of (..., 2) pixels (u, v) at ``spacing_mm`` (sx, sy):
    (u sx, v sy, 0)."""
    pixels = np.asarray(pixels, dtype=float)
    return np.stack([pixels[..., 0] * spacing_mm[0], pixels[..., 1] * spacing_mm[1], np.zeros(pixels.shape[:-1])],
                    axis=-1)
