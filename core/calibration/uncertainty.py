"""How far can the calibration be trusted? A bound on the image corners, and whether the pose set
pins the calibration down.

The figure is the largest distance (mm, tool frame) by which any of the image's four corners moves
between the fitted ``image_to_tool`` (spacing included) and an alternative one. Two alternatives
are looked at:

- **block-bootstrap refits**: the frames cut into blocks by where their patterns sit along the
  wires, blocks drawn with replacement, the objective fitted again (from the fitted calibration).
  The spread of the refits measures the random part of the error: noise, and frames that pull.
  A rough wire's echo is the same wherever the same stretch of it crosses the slice, so frames
  that see the same stretch share their errors (consecutive real frames' offsets from their wires
  correlate 0.7-0.9, ``benchmarks/bench_realism.py``), and the blocks keep them together.
- **the other objectives**: a refit cannot see a bias that every resample shares (a centroid
  bias, a wrong model), but two objectives weigh the same markers differently and a bias shows as
  a disagreement between them. The chosen fit is compared with every objective that estimates the
  spacing (``thesis`` never does: its disagreement measures the nominal spacing's error, so it is a
  reference for nothing, but it is compared with the others when it is the one chosen).
- **the echo peaks**: a wire echo rings on below the wire, so every dot centroid sits deeper
  than its wire, and deeper the larger the echo is; both objectives share that, and on the twin
  it puts the spacing about 0.2 % off (0.1 mm at the corners) at every noise level and pose
  count. The chosen objective is refitted with each marker's row moved to its echo's peak
  (:func:`core.calibration.dots.echo_peak_rows`), which sits on the wire on the twin; where in its echo a
  real wire lies cannot be told from the images, so the two definitions bracket it.
- **the wires' freedom** (the phantom pose solved): the all-wire fit locates the wires under a
  tight prior (``WIRE_SIGMA_MM``, a phantom built within a few tenths of a millimetre); a phantom
  built further off pulls a fit that holds its wires that tightly, and how far it is off cannot
  be told before the fit. The fit is done again under a loose prior (``LOOSE_WIRE_SIGMA_MM``) and
  the two bracket it: on the twin with wires ±0.3 mm off the two lie 0.05-0.16 mm apart, with
  ±0.6 mm 0.1-0.4 mm, where the tight fit's own error grows from 0.1-0.35 to 0.3-0.65 mm.

- **the block jackknife**: the fits of the chosen objective's block cross-validation, each with
  one block of consecutive frames left out (:func:`fold_spread_mm`). Blocks along the wires keep
  a wire's echo errors together; blocks in time keep together what changes along a recording
  (a tracker's drift, a hand's or an arm's error that moves with the pose). Twice its standard
  error is a second 95 % figure for the random part, and the larger of the two is used: on the
  twin's freehand benches it covers 9 of 10 where the bootstrap alone covered 7.

``corner_error_95_mm`` is that random part (the bootstrap's 95th percentile, or twice the
jackknife if larger) plus the systematic part: the largest
of the other objectives' disagreements, the echo peaks' and the wires' freedom's, three sources
that have nothing to do with each other, added in quadrature (as independent systematic
errors are). The sum with the bootstrap follows the triangle inequality: the chosen fit's error is
at most its distance to another fit plus that fit's own error, taken to be of the size of the
chosen fit's random error. Taking only the largest of the three left the truth uncovered on 1 of
10 twin seeds with the wires ±0.3 mm off and on 5 of 10 with ±0.6 mm; in quadrature, 0 and 2
(``benchmarks/bench_calibration_bound.py --wire-tolerance``). The
bootstrap alone is not enough: ``thesis``'s nominal spacing puts its corners some 10 mm off while
its refits scatter by only 3-4 mm, and without the echo peaks the echo bias left 8 of 20 twin
runs uncovered.

How much of another objective's disagreement counts depends on how the objective was chosen.
Where held-out figures chose it (a known phantom pose), the choice itself is uncertain: two halves
of PLUS's freehand recordings choose differently and lie 4-5 mm apart, so the whole disagreement
counts. Where the phantom pose is solved, all-wire is always kept, and middle-wire, fitted to one
derived point per N, is by far the noisier of the two (its calibrations from two halves of a twin
sweep lie 0.7-1.6 mm apart, all-wire's 0.1-0.4 mm); another objective's disagreement then counts
only beyond ``EXCESS_SIGMAS`` times that objective's own random error (from the fits of its block
cross-validation, :func:`fold_spread_mm`): what its noise cannot explain is a bias of the chosen
fit. The other objectives are then fitted against the wires where the chosen fit located them
(:func:`core.calibration.bound.located_references`): held at the definition, middle-wire keeps the
pull of every wire built off it, which all-wire has located, so the two stay apart by a bias of
middle-wire's own (on the twin with wires ±0.6 mm off: 0.9-2.0 mm apart on the definition,
0.4-1.4 on the located wires). A forced ``thesis`` fit is still measured by the full distance to
all-wire's.
``benchmarks/bench_calibration_bound.py`` measures the coverage on twin ``bench`` seeds, the
robot's way, and the agreement of two halves of every real recording with their bounds.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from probecal.core.calibration.crossval import FoldFit
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.objectives import (
    WIRE_PRIOR,
    Mapper,
    Observations,
    Solution,
    fit,
    rotation_spread_deg,
)
from probecal.core.calibration.result import Calibration
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing, image_mm_from_pixels
from probecal.core.geometry.transforms import invert_transform, transform_points

BOOTSTRAP_REPLICATES = 40
BOOTSTRAP_BLOCKS = 8  # each a few mm of wire: frames that see the same stretch share their errors
BOUND_QUANTILE = 95.0
SPACING_OBJECTIVES = ("all-wire", "middle-wire")
EXCESS_SIGMAS = 2.0  # another objective's disagreement counts beyond this many of both fits' random errors
JACKKNIFE_SIGMAS = 2.0  # the chosen fit's block jackknife, as a 95 % figure beside the bootstrap's
WEAK_ROTATION_DEG = 5.0  # RMS rotation about the second axis below which a solved phantom pose is weakly determined
WEAK_BOOTSTRAP_MM = 2.0  # refits scattering the corners beyond this: the pose set does not pin the calibration down
WEAK_FAILED_FRACTION = 0.1  # more bootstrap resamples than this that cannot be solved at all


def image_corners_px(image_size: tuple[int, int]) -> np.ndarray:
    """(4, 2) pixel centres of the corners of a (width, height) image."""
    w, h = image_size
    return np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])


MAP_STEPS = 8  # the bound map's grid: every 1/8 of the image's width (a fan's angle) and depth (its radius)


def bound_grid_px(image_size: tuple[int, int], fan: Fan | None, depths_px: np.ndarray) -> np.ndarray:
    """(rows, columns, 2) the points (u, v px, as the image shows them) the bound map is taken at,
    row by row down the image: every 1/``MAP_STEPS`` of its width and depth, the corners included,
    and a row at each of ``depths_px`` (the wires' rows, where the calibration is pinned down).
    On a fan image, inside the fan only: every 1/``MAP_STEPS`` of its angle (columns) and radius
    (rows, arcs), its corners included, ``depths_px`` then being radii from its origin."""
    if fan is None:
        w, h = image_size
        top, bottom = 0.0, h - 1.0
    else:
        top, bottom = fan.radius_start_px, fan.radius_stop_px
    depths = np.asarray(depths_px, dtype=float)
    rows = np.unique(np.concatenate([np.linspace(top, bottom, MAP_STEPS + 1), np.clip(depths, top, bottom)]))
    if fan is None:
        columns = np.linspace(0.0, w - 1.0, MAP_STEPS + 1)
        return np.stack(np.broadcast_arrays(columns[None, :], rows[:, None]), axis=-1)
    angles = np.radians(np.linspace(*fan.angles_deg, MAP_STEPS + 1))
    return np.stack([fan.origin_px[0] + rows[:, None] * np.sin(angles)[None, :],
                     fan.origin_px[1] + rows[:, None] * np.cos(angles)[None, :]], axis=-1)


def corner_distances_mm(a: Calibration, b: Calibration, corners_px: np.ndarray) -> np.ndarray:
    """Distance (mm, tool frame) between where ``a`` and ``b`` put each image corner."""
    points = np.column_stack([corners_px, np.zeros(len(corners_px))])
    return np.linalg.norm(transform_points(a.image_to_tool, points) - transform_points(b.image_to_tool, points), axis=1)


def corner_distance_mm(a: Calibration, b: Calibration, corners_px: np.ndarray) -> float:
    """Largest distance (mm, tool frame) between where ``a`` and ``b`` put the image corners."""
    return float(corner_distances_mm(a, b, corners_px).max())



def _refit(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, solution: Solution, known_y: np.ndarray | None,
           prior: WirePrior,
           picked: np.ndarray) -> Solution | None:
    try:
        return fit(phantom, obs.subset(picked), spacing0_mm, solution.objective, known_y, start=solution, prior=prior)
    except InputError:
        return None


def along_wires_order(phantom: Phantom, obs: Observations, solution: Solution) -> np.ndarray:
    """The frames of ``obs`` in the order of where their patterns sit along the wires (the mean
    of their markers in the phantom frame, along the first wire, as ``solution`` maps them). A
    wire's echo depends on the stretch of wire that crosses the slice, so frames that see the
    same stretch share their errors however far apart they were recorded, and a bootstrap block
    must hold them together."""
    image_to_phantom = (invert_transform(solution.phantom_to_base) @ solution.poses(obs)
                        @ solution.image_to_tool_rigid)
    centres = np.nanmean(image_mm_from_pixels(obs.markers_px, solution.pixel_spacing_mm), axis=1)
    along = np.einsum("fij,fj->fi", image_to_phantom[:, :3, :3], centres) + image_to_phantom[:, :3, 3]
    return np.argsort(along @ phantom.layers[0].wires[0].direction, kind="stable")


def block_bootstrap(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, solution: Solution,
                    known_y: np.ndarray | None,
                    replicates: int = BOOTSTRAP_REPLICATES, blocks: int = BOOTSTRAP_BLOCKS, seed: int = 0,
                    progress: Callable[[str], None] | None = None, mapper: Mapper = map,
                    prior: WirePrior = WIRE_PRIOR) -> list[Solution | None]:
    """Refits of ``solution``'s objective on block resamples of ``obs``, its frames in blocks of
    where their patterns sit along the wires (:func:`along_wires_order`); None for a resample
    that cannot determine a calibration. ``mapper`` runs the refits."""
    chunks = np.array_split(along_wires_order(phantom, obs, solution), min(blocks, len(obs)))
    rng = np.random.default_rng(seed)
    picks = [np.concatenate([chunks[i] for i in rng.integers(0, len(chunks), len(chunks))]) for _ in range(replicates)]
    refits: list[Solution | None] = []
    refit = functools.partial(_refit, phantom, obs, spacing0_mm, solution, known_y, prior)
    for r, refitted in enumerate(mapper(refit, picks)):
        if progress and r % 10 == 0:
            progress(f"bootstrap {r + 1}-{min(r + 10, replicates)} of {replicates}")
        refits.append(refitted)
    return refits


@dataclass
class CornerBound:
    """The 95 % bound on the image corners (mm) and what it is made of."""

    bound_mm: float
    bootstrap_mm: float
    disagreement_mm: float
    failed_resamples: int
    resamples: int
    disagreements_mm: dict[str, float] = field(default_factory=dict)
    echo_peak_mm: float | None = None
    wire_prior_mm: float | None = None
    excess_mm: dict[str, float] = field(default_factory=dict)
    spreads_mm: dict[str, float | None] = field(default_factory=dict)
    jackknife_mm: float | None = None


@dataclass(frozen=True)
class PointBounds:
    """The 95 % bound (mm, tool frame) at each of a grid of image points, each on its own
    (:func:`point_bounds_mm`): ``points_px`` (rows, columns, 2) u, v as the image shows them,
    ``bound_mm`` (rows, columns)."""

    points_px: np.ndarray
    bound_mm: np.ndarray


@dataclass(frozen=True)
class Measure:
    """How far apart two calibrations put image points (mm, tool frame): at each of ``points_px``
    (pixels as ``image_to_tool`` takes them, any leading shape), or with ``farthest`` the farthest
    of them alone (shape (1,)), as the corner bound measures the four corners."""

    points_px: np.ndarray
    farthest: bool = False

    def apart_mm(self, a: Calibration, b: Calibration) -> np.ndarray:
        """The distances between where ``a`` and ``b`` put the points."""
        points = np.asarray(self.points_px, dtype=float)
        distances = corner_distances_mm(a, b, points.reshape(-1, 2))
        return distances.max(keepdims=True) if self.farthest else distances.reshape(points.shape[:-1])


def _jackknife_mm(folds: list[FoldFit], solution: Solution, measure: Measure) -> np.ndarray | None:
    """The block jackknife's standard deviation of what ``measure`` measures (see :func:`fold_spread_mm`)."""
    moves = [measure.apart_mm(f.solution.calibration, solution.calibration) for f in folds if f.solution is not None]
    if len(moves) < 3:
        return None
    return np.sqrt((len(moves) - 1) / len(moves) * np.sum(np.square(moves), axis=0))


def fold_spread_mm(folds: list[FoldFit], solution: Solution, corners_px: np.ndarray) -> float | None:
    """The random error (mm, one standard deviation) of ``solution``'s image corners, from its
    block cross-validation: the jackknife over the fits that each left one block of consecutive
    frames out (their farthest corner from the fit on all frames); None with fewer than 3."""
    spread = _jackknife_mm(folds, solution, Measure(corners_px, farthest=True))
    return None if spread is None else float(spread[0])


def fold_spreads_mm(folds: list[FoldFit], solution: Solution, points_px: np.ndarray) -> np.ndarray | None:
    """:func:`fold_spread_mm` at each of ``points_px`` on its own (mm, the points' leading shape)."""
    return _jackknife_mm(folds, solution, Measure(points_px))


@dataclass(frozen=True)
class _Parts:
    """:func:`corner_bound`'s figures as arrays, one value per point :class:`Measure` measures."""

    bound: np.ndarray
    bootstrap: np.ndarray
    jackknife: np.ndarray | None
    disagreement: np.ndarray
    disagreements: dict[str, np.ndarray]
    excess: dict[str, np.ndarray]
    echo: np.ndarray | None
    wires: np.ndarray | None
    failed: int


def _combined(solution: Solution, refits: list[Solution | None], others: dict[str, Solution], measure: Measure,
              echo_peaks: Solution | None, spreads: dict[str, np.ndarray | None], loose_wires: Solution | None,
              excess_only: bool) -> _Parts:
    """The combination rule of :func:`corner_bound`, point by point of ``measure``."""
    fitted = solution.calibration
    shape = measure.apart_mm(fitted, fitted).shape
    moves = [measure.apart_mm(r.calibration, fitted) for r in refits if r is not None]
    bootstrap = np.percentile(moves, BOUND_QUANTILE, axis=0) if moves else np.full(shape, np.inf)
    own = spreads.get(solution.objective)
    jackknife = None if own is None else JACKKNIFE_SIGMAS * own
    references = [name for name in SPACING_OBJECTIVES if name != solution.objective and name in others]
    disagreements = {name: measure.apart_mm(others[name].calibration, fitted) for name in references}
    excess = dict(disagreements)
    for name in references:
        theirs = spreads.get(name)
        if excess_only and theirs is not None:
            excess[name] = np.maximum(0.0, disagreements[name] - EXCESS_SIGMAS * theirs)
    echo, wires = (None if other is None else measure.apart_mm(other.calibration, fitted)
                   for other in (echo_peaks, loose_wires))
    largest = np.max(list(excess.values()), axis=0) if excess else np.zeros(shape)
    zero = np.zeros(shape)
    disagreement = np.hypot.reduce([largest, zero if echo is None else echo, zero if wires is None else wires],
                                   axis=0)
    bound = np.maximum(bootstrap, zero if jackknife is None else jackknife) + disagreement
    return _Parts(bound, bootstrap, jackknife, disagreement, disagreements, excess, echo, wires,
                  len(refits) - len(moves))


def corner_bound(solution: Solution, refits: list[Solution | None], others: dict[str, Solution],
                 corners_px: np.ndarray, echo_peaks: Solution | None = None,
                 spreads: dict[str, float | None] | None = None, loose_wires: Solution | None = None,
                 excess_only: bool = True) -> CornerBound:
    """Combine the bootstrap refits, the other objectives' fits, the fit to the markers moved
    to their echoes' peaks and the fit under the loose wire prior (see the module docstring).
    ``spreads`` holds each objective's random error (:func:`fold_spread_mm`). The chosen fit's
    random part is the larger of the bootstrap's and ``JACKKNIFE_SIGMAS`` times its own spread;
    with ``excess_only``, another objective's disagreement counts only beyond ``EXCESS_SIGMAS``
    times that objective's own random error."""
    spreads = dict(spreads or {})
    parts = _combined(solution, refits, others, Measure(corners_px, farthest=True), echo_peaks,
                      {name: None if s is None else np.array([s]) for name, s in spreads.items()}, loose_wires,
                      excess_only)

    def one(value: np.ndarray | None) -> float | None:
        return None if value is None else float(value[0])

    return CornerBound(float(parts.bound[0]), float(parts.bootstrap[0]), float(parts.disagreement[0]), parts.failed,
                       len(refits), {name: float(d[0]) for name, d in parts.disagreements.items()}, one(parts.echo),
                       one(parts.wires), {name: float(d[0]) for name, d in parts.excess.items()}, spreads,
                       one(parts.jackknife))


def point_bounds_mm(solution: Solution, refits: list[Solution | None], others: dict[str, Solution],
                    points_px: np.ndarray, echo_peaks: Solution | None = None,
                    spreads: dict[str, np.ndarray | None] | None = None, loose_wires: Solution | None = None,
                    excess_only: bool = True) -> np.ndarray:
    """:func:`corner_bound` at each of ``points_px`` (pixels as ``image_to_tool`` takes them) on
    its own, from the same fits: the 95 % bound (mm, tool frame) of how far the calibration puts
    that point off, in the points' leading shape. ``spreads`` holds each objective's random error
    at each point (:func:`fold_spreads_mm`). At a corner it is at most the corner bound, which
    bounds the farthest of the four at once."""
    return _combined(solution, refits, others, Measure(points_px), echo_peaks, dict(spreads or {}), loose_wires,
                     excess_only).bound


def weak_determination(tool_to_base: np.ndarray, solve_y: bool, bound: CornerBound | None) -> list[str]:
    """Plain-language reasons why the pose set does not pin the calibration down (empty if it does):
    little rotation with the phantom pose solved, resamples that cannot be solved, or refits that
    scatter the image corners widely."""
    reasons = []
    if solve_y:
        spread = rotation_spread_deg(tool_to_base)
        if spread[1] < WEAK_ROTATION_DEG:
            reasons.append(
                f"the poses rotate little about a second axis ({spread[0]:.1f} and {spread[1]:.1f} deg RMS; "
                f"want {WEAK_ROTATION_DEG:.0f} deg or more about two axes): the phantom pose and the mount are "
                "hard to tell apart")
    if bound is not None and bound.failed_resamples > WEAK_FAILED_FRACTION * bound.resamples:
        reasons.append(f"{bound.failed_resamples} of {bound.resamples} bootstrap resamples could not be "
                       "solved at all")
    if bound is not None and bound.bootstrap_mm > WEAK_BOOTSTRAP_MM:
        reasons.append(f"refits on resampled frames move the image corners by up to {bound.bootstrap_mm:.1f} mm")
    return reasons
