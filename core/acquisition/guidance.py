"""Guidance for a probe held by hand, or by a robot probecal does not command: which of the poses
that pin a calibration down are still missing.

A pose is measured as the robot's plan measures it (:func:`~probecal.core.acquisition.plan.perturbed`):
offsets of the image from the centre pose (the image across the wires), in the phantom's axes,
turning about a pivot at the image centre. Five of the six count: the tilts about the image's
three axes and its depth and position along the wires; sliding across the wires does not. Each
frame's pose comes from its own wire dots (:func:`~probecal.core.calibration.register.register_frame`,
refined with the image's depth scale free), so guidance needs neither the tracker, nor the
phantom's pose, nor a calibration.

The targets are spread over the plan's ranges by a Latin hypercube, as the robot's poses are,
keeping every wire in view. A target is reached when a kept frame lies within ``REACH`` of its
range on every measure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from probecal.core.acquisition.plan import PoseRanges, crossings_in_view, perturbed, pivot_mm
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import LinearProbe, Probe
from probecal.core.geometry.setup import Setup, image_across_wires
from probecal.core.geometry.transforms import invert_transform, make_transform

MEASURES = ("tilt about image x", "tilt about image y", "tilt about image z", "depth", "along the wires")
"""The measures, in the order :func:`measures` gives them (deg, deg, deg, mm, mm)."""
UNITS = ("deg", "deg", "deg", "mm", "mm")
OFFSET_AXES = (3, 5, 4, 2, 1)
"""Which of the plan's offsets (x, y, z mm; about x, y, z deg, phantom axes) each measure is:
the image's x is the phantom's x, its depth the phantom's -z, its normal the wires (phantom y)."""
REACH = 0.25
"""A frame reaches a target within this fraction of each measure's range (either way)."""
BINS = 8
"""The coverage display's bins per measure, over its range."""
TARGETS = 16
GUIDE_RANGES = PoseRanges(rotation_deg=(30.0, 30.0, 20.0))
"""The ranges the targets spread over: a hand tilts the probe further than the robot's plan
(+-22 deg), and the turns pin the calibration's position down when the phantom's pose is solved.
On the freehand twin the bound reaches 1 mm about half again as fast as at the plan's ranges
(``benchmarks/bench_freehand.py --rotation``)."""


def frames_probe(size_px: tuple[int, int], spacing_mm: tuple[float, float], start_depth_mm: float = 0.0) -> Probe:
    """A linear probe whose frames are ``size_px`` (width, height) at ``spacing_mm`` (sx, sy): the
    image a live scanner's frames show, its spacing taken as true."""
    width, height = size_px
    return LinearProbe(n_elements=width, pitch_mm=spacing_mm[0], depth_mm=spacing_mm[1] * height, width_px=width,
                       height_px=height, medium_sound_speed=LinearProbe.nominal_sound_speed,
                       start_depth_mm=start_depth_mm)


def guide_setup(phantom: Phantom, probe: Probe) -> Setup:
    """What guidance needs of a set-up: the phantom, the image and the centre pose (no robot, no
    calibration: both are left the identity)."""
    return Setup(phantom, probe, np.eye(4), np.eye(4), image_across_wires(phantom, probe))


def measures(offsets: np.ndarray) -> np.ndarray:
    """The five measures (..., 5) of plan offsets (..., 6)."""
    return np.asarray(offsets)[..., list(OFFSET_AXES)]


def offsets_of(setup: Setup, image_to_phantom: np.ndarray) -> np.ndarray:
    """The plan offsets (6,) that put the centre pose at ``image_to_phantom``: the inverse of
    :func:`perturbed` about the plan's pivot."""
    centre = setup.image_to_phantom
    about_pivot = image_to_phantom @ invert_transform(centre)
    pivot = centre[:3, :3] @ pivot_mm(setup) + centre[:3, 3]
    rotation = about_pivot[:3, :3]
    translation = about_pivot[:3, 3] - pivot + rotation @ pivot
    return np.concatenate([translation, Rotation.from_matrix(rotation).as_euler("xyz", degrees=True)])


def facing(setup: Setup, image_to_phantom: np.ndarray) -> Setup:
    """``setup`` with its centre pose turned half a turn about the vertical when the probe is held
    that way round (its image's x along the phantom's -x), so that offsets stay small."""
    if image_to_phantom[0, 0] >= 0:
        return setup
    centre = setup.phantom.center()
    half_turn = make_transform(np.diag([-1.0, -1.0, 1.0]), [2 * centre[0], 2 * centre[1], 0.0])
    return Setup(setup.phantom, setup.probe, setup.phantom_to_base, setup.image_to_tool_rigid,
                 half_turn @ setup.image_to_phantom)


def guide_targets(setup: Setup, n: int = TARGETS, ranges: PoseRanges = GUIDE_RANGES,
                  seed: int | np.random.Generator = 0,
                  max_draws: int = 200) -> np.ndarray:
    """``n`` target offsets (n, 6) spread by a Latin hypercube over the five measures' ranges
    (none across the wires), each keeping every wire in view; ValueError when too few do."""
    bounds = np.array([*ranges.translation_mm, *ranges.rotation_deg])
    bounds[0] = 0.0
    sampler = qmc.LatinHypercube(d=6, seed=seed)
    pivot = pivot_mm(setup)
    found: list[np.ndarray] = []
    for _ in range(max_draws):
        for unit in sampler.random(max(n, 16)):
            offsets = (2 * unit - 1) * bounds
            if crossings_in_view(setup, perturbed(setup.image_to_phantom, pivot, offsets), ranges.margin_mm):
                found.append(offsets)
                if len(found) == n:
                    return np.array(found)
    raise ValueError(f"only {len(found)} of {n} targets keep every wire in view")


def reach_of(ranges: PoseRanges) -> np.ndarray:
    """How near (5,) a frame must come to a target on each measure to reach it."""
    bounds = np.array([*ranges.translation_mm, *ranges.rotation_deg])
    return REACH * 2 * measures(bounds)


def apart(a: np.ndarray, b: np.ndarray, ranges: PoseRanges) -> np.ndarray:
    """How far apart plan offsets ``a`` and ``b`` (..., 6) are: the largest of their measures'
    differences in units of the reach (1: just within it)."""
    return (np.abs(measures(a) - measures(b)) / reach_of(ranges)).max(axis=-1)


@dataclass
class Coverage:
    """Which targets the kept frames have reached, and how the frames spread over each measure."""

    targets: np.ndarray  # (K, 6) plan offsets
    ranges: PoseRanges = GUIDE_RANGES
    reached: np.ndarray = field(init=False)  # (K,) bool
    counts: np.ndarray = field(init=False)  # (5, BINS) frames per bin of each measure

    rounds: np.ndarray = field(init=False)  # (K,) the round each target was set in, from 0

    def __post_init__(self) -> None:
        self.reached = np.zeros(len(self.targets), dtype=bool)
        self.given_up = np.zeros(len(self.targets), dtype=bool)
        self.counts = np.zeros((len(MEASURES), BINS), dtype=int)
        self.rounds = np.zeros(len(self.targets), dtype=int)

    @property
    def round(self) -> int:
        """The newest round of targets."""
        return int(self.rounds.max()) if len(self.rounds) else 0

    def extend(self, targets: np.ndarray) -> None:
        """Set another round of targets, once every target is reached and more frames are wanted."""
        self.rounds = np.concatenate([self.rounds, np.full(len(targets), self.round + 1)])
        self.targets = np.concatenate([self.targets, targets])
        self.reached = np.concatenate([self.reached, np.zeros(len(targets), dtype=bool)])
        self.given_up = np.concatenate([self.given_up, np.zeros(len(targets), dtype=bool)])

    @property
    def fraction(self) -> float:
        """Of the newest round's targets, how many are reached (0-1)."""
        current = self.rounds == self.round
        return float(self.reached[current].mean()) if current.any() else 1.0

    def distances(self, offsets: np.ndarray) -> np.ndarray:
        """Each target's distance (K,) from a frame at ``offsets``: the largest of its measures'
        differences in units of their reach (1: just reached)."""
        return apart(self.targets, offsets, self.ranges)

    def add(self, offsets: np.ndarray) -> list[int]:
        """Count a kept frame at ``offsets``; the targets it reaches for the first time."""
        span = measures(np.array([*self.ranges.translation_mm, *self.ranges.rotation_deg]))
        unit = (measures(offsets) + span) / (2 * span)
        bins = np.clip((unit * BINS).astype(int), 0, BINS - 1)
        self.counts[np.arange(len(MEASURES)), bins] += 1
        new = np.flatnonzero((self.distances(offsets) <= 1.0) & ~self.reached)
        self.reached[new] = True
        return [int(k) for k in new]

    def give_up(self, k: int) -> None:
        """Offer target ``k`` no more (the probe did not reach it in time)."""
        self.given_up[k] = True

    def next_target(self, offsets: np.ndarray | None) -> int | None:
        """The target nearest a frame at ``offsets`` (the first when None) of those neither
        reached nor given up; None when there is none."""
        left = np.flatnonzero(~self.reached & ~self.given_up)
        if not len(left):
            return None
        if offsets is None:
            return int(left[0])
        return int(left[np.argmin(self.distances(offsets)[left])])
