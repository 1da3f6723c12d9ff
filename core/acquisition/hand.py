"""The freehand twin's hand: a person moving the probe over the phantom, toward the targets the
console shows, or at random.

The hand works in the plan's offsets about the centre pose (:func:`~probecal.core.acquisition.plan.perturbed`:
mm along the phantom's axes, deg about them). Told a target, it reacts, then reaches for it in a
minimum-jerk stroke at a person's pace, lands off by its aim, and holds there; still told the
same target once it has held for a while, it reaches again, aiming better. On top of every pose
it sways slowly and trembles at 8-12 Hz. Time is the hand's own (s), so a benchmark can run it
faster than real time and the console's twin at the wall clock.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

TREMOR_HZ = (8.0, 12.0)
"""Physiological tremor's band."""
SWAY_HZ = (0.1, 0.5)
"""A held arm's slow sway's band."""
AIM_TURN_DEG = 20.0
"""A reach that turns the probe this far lands off by ``HandParams.aim_deg``; a smaller turn, by
as much less (a movement's error grows with its size), so that a probe moved straight up and down
stays nearly upright."""
SAME_TARGET = 1.0
"""A target that moves less than this (mm or deg, on every axis) is still the same target."""


@dataclass(frozen=True)
class HandParams:
    """How a person moves a probe (offsets in mm and deg)."""

    speed_mm_s: float = 25.0  # mean speed of a reach (translation)
    turn_deg_s: float = 25.0  # mean turn rate of a reach
    shortest_reach_s: float = 0.6
    reaction_s: float = 0.4  # from a new target shown to the hand moving
    hold_s: float = 1.5  # held at a target before reaching for it again, still told to
    aim_mm: float = 1.0  # where a reach lands: sd about the target per axis
    aim_deg: float = 1.5  # for a turn of AIM_TURN_DEG; in proportion to the turn (Weber), at least a tenth
    tremor_mm: float = 0.05  # RMS per axis
    tremor_deg: float = 0.03
    sway_mm: float = 0.3
    sway_deg: float = 0.2


def sinusoids(freqs_hz: np.ndarray, phases: np.ndarray, amps: np.ndarray,
              rms: np.ndarray) -> Callable[[float], np.ndarray]:
    """A smooth signal of time, one value per axis: the sum of the sinusoids (count, axes) of
    ``freqs_hz``, ``phases`` and relative ``amps``, scaled to ``rms`` per axis."""
    scaled = amps * (np.asarray(rms) * np.sqrt(2) / np.linalg.norm(amps, axis=0))[None]

    def at(t: float) -> np.ndarray:
        return np.sum(scaled * np.sin(2 * np.pi * freqs_hz * t + phases), axis=0)

    return at


def _waves(rng: np.random.Generator, band: tuple[float, float], rms: np.ndarray,
           count: int = 3) -> Callable[[float], np.ndarray]:
    """A smooth random signal (6,) of time: ``count`` sinusoids per axis in ``band`` (Hz) with
    random phases, scaled to ``rms`` per axis."""
    freqs = rng.uniform(*band, size=(count, len(rms)))
    phases = rng.uniform(0, 2 * np.pi, size=(count, len(rms)))
    return sinusoids(freqs, phases, rng.normal(size=(count, len(rms))), rms)


def minimum_jerk(fraction: float) -> float:
    """How far along a minimum-jerk stroke (0-1) at ``fraction`` of its time."""
    s = min(max(fraction, 0.0), 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s * s)


@dataclass
class Hand:
    """A hand at ``start`` offsets (6,) at time 0. :meth:`at` advances it to a later time, told
    the target of that moment (None: hold where it is)."""

    start: np.ndarray
    params: HandParams = HandParams()
    seed: int = 0
    _from: np.ndarray = field(init=False)
    _to: np.ndarray = field(init=False)
    _began: float = field(init=False, default=0.0)
    _takes: float = field(init=False, default=0.0)
    _target: np.ndarray | None = field(init=False, default=None)
    _told: float = field(init=False, default=0.0)
    _tries: int = field(init=False, default=0)
    _t: float = field(init=False, default=0.0)

    def __post_init__(self) -> None:
        rng = np.random.default_rng([self.seed, 56])
        self._aim = np.random.default_rng([self.seed, 57])
        p = self.params
        self._tremor = _waves(rng, TREMOR_HZ, np.array([p.tremor_mm] * 3 + [p.tremor_deg] * 3))
        self._sway = _waves(rng, SWAY_HZ, np.array([p.sway_mm] * 3 + [p.sway_deg] * 3))
        self._from = self._to = np.asarray(self.start, dtype=float)

    def aimed(self, t: float) -> np.ndarray:
        """Where the hand means the probe to be at ``t`` (no sway or tremor)."""
        if self._takes <= 0:
            return self._to
        return self._from + minimum_jerk((t - self._began) / self._takes) * (self._to - self._from)

    def at(self, t: float, target: np.ndarray | None) -> np.ndarray:
        """The probe's offsets (6,) at ``t`` (s, not before the last call)."""
        self._t = t
        if target is not None:
            self._follow(t, np.asarray(target, dtype=float))
        return self.aimed(t) + self._sway(t) + self._tremor(t)

    def _follow(self, t: float, target: np.ndarray) -> None:
        if self._target is None or np.abs(target - self._target).max() > SAME_TARGET:
            self._told, self._tries = t, 0
        self._target = target  # a target nudged a little is the same: the next reach aims at where it is now
        settled = t >= self._began + self._takes
        ended = self._began + self._takes
        due = self._told + self.params.reaction_s if self._tries == 0 else ended + self.params.hold_s
        if settled and t >= due:
            self._reach(t, target)

    def _reach(self, t: float, target: np.ndarray) -> None:
        p = self.params
        start = self.aimed(t)
        turn = max(float(np.linalg.norm(target[3:] - start[3:])) / AIM_TURN_DEG, 0.1)
        scale = 0.5 ** self._tries  # each new try aims better
        aim = self._aim.normal(size=6) * np.array([p.aim_mm] * 3 + [p.aim_deg * turn] * 3) * scale
        self._from, self._to = start, target + aim
        move = self._to - self._from
        # a minimum-jerk stroke's mean speed: its length over its time
        self._takes = max(p.shortest_reach_s, float(np.linalg.norm(move[:3])) / p.speed_mm_s,
                          float(np.linalg.norm(move[3:])) / p.turn_deg_s)
        self._began = t
        self._tries += 1
