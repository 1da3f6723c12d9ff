"""What the twin's scanner images with: the imaging model (point-spread widths, echo shapes, the
elevational slice), the noise levels, and the wire-dot point-spread function whose core sigmas give
the displayed widths the model asks for (design §4 "Image formation").

Amplitudes are linear, 1.0 just saturates the display; levels are dB re that amplitude; offsets
and widths are mm (x lateral, z axial, + deeper)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class ImagingModel:
    """Scanner and point-spread-function parameters (dB re saturation, mm).

    ``*_fwhm_*`` widths are *displayed* full widths at half the maximum gray level, as measured
    on the 8-bit image. Displayed lateral FWHM(d) = sqrt(w0^2 + (slope * (d - d0))^2).
    """

    dynamic_range_db: float = 45.0
    gray_gamma: float = 1.6
    dot_db: float = 9.0
    lateral_fwhm_min_mm: float = 0.55
    lateral_fwhm_slope: float = 0.0745
    lateral_fwhm_depth0_mm: float = 9.2
    axial_fwhm_mm: float = 0.7
    sidelobe_db: float = -30.0
    sidelobe_width: float = 2.0  # side-lobe skirt sigma / main-lobe sigma
    smile_per_mm: float = 0.05  # arc rise (mm) = smile_per_mm * (lateral offset in mm)^2
    tail_db: float = -8.0
    tail_length_mm: float = 0.22
    tail_width: float = 0.8  # tail sigma / main-lobe sigma
    surface_db: float = 6.0
    surface_shadow_db: float = -25.0
    tank_db: float = -16.0
    tank_shadow_db: float = -40.0
    tank_ringing_db: tuple[float, ...] = (-22.0,)
    tank_ringing_mm: float = 1.2
    tank_double_db: float = -14.0
    attenuation_db_per_mm: float = 0.05  # round trip
    tgc_db_per_mm: float = 0.05
    # Elevational beam (two-way FWHM of the slice, mm): 0 is an infinitely thin slice. A wire
    # crossing it obliquely echoes from every elevation inside it, so its dot smears in-plane.
    elevation_fwhm_mm: float = 0.0
    elevation_focus_mm: float = 20.0
    elevation_divergence: float = 0.0  # FWHM growth per mm of depth away from the focus
    # A wire tilted toward the beam (angle t between the wire and the plane normal to the beam
    # axis) echoes less and longer: loss and axial widening scale with sin^2 t, given at 30 deg.
    incidence_loss_db: float = 0.0
    incidence_widening: float = 0.0  # relative axial widening
    wire_roughness: float = 0.0  # 0..1: share of a smeared echo that adds with random phase
    wire_diameter_mm: float = 0.0  # > 0: echoes come from random points of the wire's cross-section
    ringdown_db: float = -np.inf  # reverberation ringing on below each wire, re its echo
    ringdown_mm: float = 1.5

    def elevation_fwhm_at(self, depth_mm: float) -> float:
        """Two-way elevational slice thickness (FWHM, mm) at a depth (mm); 0 for a thin slice."""
        if self.elevation_fwhm_mm <= 0.0:
            return 0.0
        return float(np.hypot(self.elevation_fwhm_mm, self.elevation_divergence * (depth_mm - self.elevation_focus_mm)))

    def lateral_fwhm_mm(self, depth_mm: np.ndarray | float) -> np.ndarray:
        """Displayed lateral FWHM (mm) of a wire dot at a depth (mm)."""
        d = np.asarray(depth_mm, dtype=float) - self.lateral_fwhm_depth0_mm
        return np.hypot(self.lateral_fwhm_min_mm, self.lateral_fwhm_slope * d)

    @property
    def half_level_db(self) -> float:
        """Amplitude (dB re saturation) that is shown at half the maximum gray level."""
        return -self.dynamic_range_db * (1.0 - 0.5 ** (1.0 / self.gray_gamma))


@dataclass(frozen=True)
class NoiseModel:
    """Artefacts of one noise level: levels in dB re saturation, rates in mean counts per frame.

    With ``speckle_db = reverb_db = -inf`` and every rate, jitter and texture zero (``none``),
    rendering draws no random numbers.
    """

    speckle_db: float = -np.inf
    tgc_jitter_db: float = 0.0
    dot_jitter_db: float = 0.0
    dot_texture: float = 0.0  # depth of the speckle modulation of each dot, 0..1
    reverb_db: float = -np.inf
    particle_rate: float = 0.0
    particle_db: tuple[float, float] = (-30.0, -18.0)
    bubble_rate: float = 0.0
    bubble_db: tuple[float, float] = (-6.0, 6.0)
    comet_fraction: float = 0.0
    tank_unevenness_mm: float = 0.0
    tank_mottle_db: float = 0.0
    dot_dropout: float = 0.0  # chance that a dot fades by ``dropout_db``
    dropout_db: tuple[float, float] = (-20.0, -10.0)


_REALISTIC = NoiseModel(
    speckle_db=-52.0,
    tgc_jitter_db=1.5,
    dot_jitter_db=1.0,
    dot_texture=0.4,
    reverb_db=-36.0,
    particle_rate=4.0,
    particle_db=(-32.0, -20.0),
    tank_unevenness_mm=0.25,
    tank_mottle_db=5.0,
)
NOISE_LEVELS: dict[str, NoiseModel] = {
    "none": NoiseModel(),
    "realistic": _REALISTIC,
    "harsh": NoiseModel(
        speckle_db=-39.0,
        tgc_jitter_db=3.0,
        dot_jitter_db=3.0,
        dot_texture=0.6,
        reverb_db=-18.0,
        particle_rate=40.0,
        particle_db=(-28.0, -6.0),
        bubble_rate=3.0,
        bubble_db=(-6.0, 6.0),
        comet_fraction=0.5,
        tank_unevenness_mm=0.4,
        tank_mottle_db=8.0,
    ),
    "bench": replace(_REALISTIC, dot_jitter_db=2.5, dot_texture=0.5, dot_dropout=0.02),
}
BENCH_IMAGING = ImagingModel(
    dot_db=3.0,
    tail_db=-6.0,
    tail_length_mm=0.3,
    sidelobe_db=-26.0,
    elevation_fwhm_mm=2.5,
    elevation_focus_mm=20.0,
    elevation_divergence=0.08,
    wire_roughness=1.0,
    wire_diameter_mm=0.3,
    incidence_loss_db=6.0,
    incidence_widening=0.5,
    ringdown_db=-16.0,
    ringdown_mm=1.2,
)
"""The scanner of the ``bench`` level: dots below saturation, a longer echo tail and stronger side
lobes, a 1.2 mm elevational slice at 20 mm, angle-dependent echoes and a ring-down under each
wire (``core.twin.levels``)."""


def _tail(zz: np.ndarray, core: np.ndarray, im: ImagingModel) -> np.ndarray:
    """Echo tail: follows the Gaussian core above the arc, decays exponentially below it."""
    return np.where(zz < 0.0, core, np.exp(-np.maximum(zz, 0.0) / im.tail_length_mm))


def axial_profile(z: np.ndarray, sigma_z: float, im: ImagingModel) -> np.ndarray:
    """Axial amplitude (1 at z = 0) at offsets z (mm, + deeper): Gaussian top, exponential tail."""
    core = np.exp(-0.5 * (z / sigma_z) ** 2)
    t = 10 ** (im.tail_db / 20)
    return (core + t * _tail(z, core, im)) / (1.0 + t)


def _lateral_profile(x: np.ndarray, sigma_x: float, im: ImagingModel) -> np.ndarray:
    """Lateral amplitude (1 at x = 0) at offsets x (mm): main lobe plus a faint side-lobe skirt."""
    s = 10 ** (im.sidelobe_db / 20)
    r = (x / sigma_x) ** 2
    return (np.exp(-0.5 * r) + s * np.exp(-0.5 * r / im.sidelobe_width**2)) / (1.0 + s)


def dot_amplitude(x: np.ndarray, z: np.ndarray, sigma_x: float, sigma_z: float, im: ImagingModel) -> np.ndarray:
    """Wire-dot PSF (1 at the centre) on the grid z (rows) x x (columns) of offsets (mm): for x
    (..., C) and z (..., R), an array (..., R, C).

    The axial profile is centred on the smile arc ``z = -smile_per_mm * x^2``, whose ends bend
    toward the probe.
    """
    return dot_amplitude_at(np.asarray(x)[..., None, :], np.asarray(z)[..., :, None], sigma_x, sigma_z, im)


def dot_amplitude_at(x: np.ndarray, z: np.ndarray, sigma_x: float, sigma_z: float, im: ImagingModel) -> np.ndarray:
    """The wire-dot PSF of :func:`dot_amplitude` at lateral and axial offsets (mm) that broadcast
    together (a beam's own axes: a turned beam's offsets are turned into them first)."""
    zz = z + im.smile_per_mm * x**2
    core = np.exp(-0.5 * (zz / sigma_z) ** 2)
    tail_lat = np.exp(-0.5 * (x / (im.tail_width * sigma_x)) ** 2)
    t = 10 ** (im.tail_db / 20)
    return (_lateral_profile(x, sigma_x, im) * core + t * tail_lat * _tail(zz, core, im)) / (1 + t)


def _solve_increasing(f: Callable[[float], float], target: float, hi: float) -> float:
    """The p in (0, hi] with f(p) = target, for an increasing f, by bisection."""
    lo = 0.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < target else (lo, mid)
    return 0.5 * (lo + hi)


def _width_above(values: np.ndarray, grid: np.ndarray, level: float) -> float:
    """Extent of ``grid`` over which ``values`` >= level."""
    above = grid[values >= level]
    return float(above[-1] - above[0]) if above.size else 0.0


def axial_sigma_mm(im: ImagingModel) -> float:
    """Core Gaussian sigma (mm) that gives the displayed axial FWHM, tail included."""
    z = np.linspace(-3.0, 3.0, 3001)
    level = 10 ** ((im.half_level_db - im.dot_db) / 20)

    def width(sigma_z: float) -> float:
        return _width_above(axial_profile(z, sigma_z, im), z, level)

    return _solve_increasing(width, im.axial_fwhm_mm, 1.0)


def lateral_sigma_mm(fwhm_mm: float, sigma_z: float, im: ImagingModel) -> float:
    """Main-lobe sigma (mm) that gives a displayed lateral FWHM along the dot's centre row."""
    x = np.linspace(-2.0 * fwhm_mm, 2.0 * fwhm_mm, 2001)
    level = 10 ** ((im.half_level_db - im.dot_db) / 20)
    z0 = np.zeros(1)

    def width(sigma_x: float) -> float:
        return _width_above(dot_amplitude(x, z0, sigma_x, sigma_z, im)[0], x, level)

    return _solve_increasing(width, fwhm_mm, fwhm_mm)


@dataclass(frozen=True)
class Psf:
    """Dot PSF at one depth (mm): core sigmas, patch extent about the wire, and the beam's angle
    (rad, from the image's downward axis toward +x; a convex probe's beams fan out)."""

    sigma_x: float
    sigma_z: float
    half_x: float
    above_z: float
    below_z: float
    beam_rad: float = 0.0
