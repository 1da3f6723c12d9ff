"""The twin's levels of difficulty (design §4, issue 15): each is an image noise model, a scanner
(point spread and elevational beam) and the set-up errors of a bench, drawn per seed.

``none``, ``realistic`` and ``harsh`` image a perfect set-up: a thin slice, a robot whose reported
pose is where the flange is, a phantom built exactly to its definition. ``bench`` adds what makes
real calibrations err:

- an elevational slice 2.5 mm thick at its 20 mm focus, thickening away from it, so oblique wires
  smear their dots in-plane, and rough 0.3 mm wires whose echoes add with random phases; echoes
  that weaken and lengthen as the wire tilts toward the beam; a short ring-down under every
  wire; dots that vary in brightness and sometimes fade;
- water at 18-24 °C, whose sound speed sets the true axial spacing;
- UR3 kinematic parameters off UR's table (±0.3 mm, ±0.03°), so reported and actual flange
  poses differ systematically across the workspace (absolute error), on top of repeatability;
- wire end points off their definition by up to ±0.3 mm per axis (manufacturing tolerance): the
  real recordings' dots keep 0.10-0.18 mm per wire off their wires, ±0.2 mm gave the twin
  0.08-0.12, ±0.3 mm gives 0.11-0.18 (``benchmarks/bench_realism.py``);
  the probe mount is off its design at every level (``core.twin.twin.make_twin``);
- image timestamps late by 20-150 ms, with 2 ms of jitter;
- on a tracked freehand recording, an optical tracker's noise on every pose: 0.15 mm and 0.1°
  (standard deviation per axis, about what an NDI Polaris gives a probe's marker body).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from probecal.core.twin.imaging import BENCH_IMAGING, NOISE_LEVELS, ImagingModel, NoiseModel


@dataclass(frozen=True)
class SetupErrors:
    """Bench errors drawn per seed; every one is off at its default.

    ``water_temperature_c``: (low, high) °C, or None for the probe's own medium speed.
    ``dh_length_mm``, ``dh_angle_deg``: UR3 DH parameter deviations, uniform within ±.
    ``phantom_tolerance_mm``: each wire end point coordinate off, uniform within ±.
    ``diagonal_tolerance_mm``: each end of each layer's diagonal wire off across the wire within
    its layer's plane, uniform within ±; ``diagonal_shift_mm``: each diagonal off across itself
    as a whole (both ends alike), uniform within ±; ``diagonal_turn_mm``: each diagonal turned
    about its middle within its layer, its ends across it the opposite ways, uniform within ±.
    ``layer_tolerance``: each layer moved as a whole, uniform within ± (x, y, z mm along the
    phantom's axes, then deg about them; the wires run along y).
    ``image_latency_s``: (low, high) s of the constant image delay; ``timestamp_jitter_s``: its
    per-frame standard deviation (s).
    ``tracker_noise``: (mm, deg) standard deviation per axis of a tracker's error on every pose it
    reports (a tracked freehand recording, ``simulate_freehand``; the robot reports its own).
    ``tracker_drift``: (mm, deg) RMS per axis of its slow error, wandering smoothly along a
    recording (``core.twin.twin.pose_drift``): where the tracker puts the probe against where the
    wires do. At ``bench`` half the median wander of PLUS's reference markers along their
    recordings: the size at which the freehand twin's validation PRE3D meets the real ones
    (``benchmarks/bench_realism.py``).
    ``phantom_registration``: standard deviation of the error in the phantom pose a tracked
    recording is given as registered (PLUS's PhantomToReference from a stylus), per axis of the
    phantom (x, y, z mm, then deg about them), drawn once per bench: every recording of it shares
    it. At ``bench`` 1.2 deg about the vertical alone: the RMS over PLUS's five recordings of the
    turn about the vertical that brings their markers closest to their wires (0.7-1.6 deg,
    ``benchmarks/bench_objectives.py``; docs/evidence/twin.md).
    """

    water_temperature_c: tuple[float, float] | None = None
    dh_length_mm: float = 0.0
    dh_angle_deg: float = 0.0
    phantom_tolerance_mm: float = 0.0
    diagonal_tolerance_mm: float = 0.0
    diagonal_shift_mm: float = 0.0
    diagonal_turn_mm: float = 0.0
    layer_tolerance: tuple[float, ...] = (0.0,) * 6
    image_latency_s: tuple[float, float] = (0.0, 0.0)
    timestamp_jitter_s: float = 0.0
    tracker_noise: tuple[float, float] = (0.0, 0.0)
    tracker_drift: tuple[float, float] = (0.0, 0.0)
    phantom_registration: tuple[float, ...] = (0.0,) * 6


BENCH_SETUP = SetupErrors(
    water_temperature_c=(18.0, 24.0),
    dh_length_mm=0.3,
    dh_angle_deg=0.03,
    phantom_tolerance_mm=0.3,
    image_latency_s=(0.02, 0.15),
    timestamp_jitter_s=0.002,
    tracker_noise=(0.15, 0.1),
    tracker_drift=(0.22, 0.075),
    phantom_registration=(0.0, 0.0, 0.0, 0.0, 0.0, 1.2),
)


@dataclass(frozen=True)
class Level:
    """One level of difficulty: its name, image noise, scanner and set-up errors."""

    name: str
    noise: NoiseModel
    imaging: ImagingModel = field(default_factory=ImagingModel)
    setup: SetupErrors = field(default_factory=SetupErrors)


LEVELS: dict[str, Level] = {
    "none": Level("none", NOISE_LEVELS["none"]),
    "realistic": Level("realistic", NOISE_LEVELS["realistic"]),
    "harsh": Level("harsh", NOISE_LEVELS["harsh"]),
    "bench": Level("bench", NOISE_LEVELS["bench"], BENCH_IMAGING, BENCH_SETUP),
}
DEFAULT_LEVEL = "bench"


def level(spec: str | Level) -> Level:
    """The level named ``spec`` (ValueError for an unknown name), or ``spec`` itself."""
    if isinstance(spec, Level):
        return spec
    if spec not in LEVELS:
        raise ValueError(f"noise must be one of {', '.join(LEVELS)}")
    return LEVELS[spec]


def water_sound_speed(temperature_c: float) -> float:
    """Speed of sound in pure water (m/s) at a temperature (°C), Marczak (1997), 0-95 °C."""
    t = float(temperature_c)
    return float(np.polyval([2.787860e-9, -1.398845e-6, 3.287156e-4, -5.799136e-2, 5.038813, 1.402385e3], t))
