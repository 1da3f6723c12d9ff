"""Linear-array probe geometry and pixel spacing (SPEC §4).

The image frame has x = column, y = row (depth), z = normal; pixel (u, v) is the point (u, v, 0).
The scanner converts echo time to depth assuming ``nominal_sound_speed``; in a medium with another
sound speed the true axial spacing scales by ``medium / nominal``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


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

    def to_dict(self) -> dict:
        return {"type": "linear", **asdict(self)}

    @classmethod
    def from_dict(cls, data: dict) -> LinearProbe:
        fields = {k: v for k, v in data.items() if k != "type"}
        return cls(**fields)


def image_mm_from_pixels(pixels: np.ndarray, spacing_mm) -> np.ndarray:
    """(..., 3) image-frame points (mm) of (..., 2) pixels (u, v) at ``spacing_mm`` (sx, sy):
    (u sx, v sy, 0)."""
    pixels = np.asarray(pixels, dtype=float)
    return np.stack([pixels[..., 0] * spacing_mm[0], pixels[..., 1] * spacing_mm[1], np.zeros(pixels.shape[:-1])],
                    axis=-1)
