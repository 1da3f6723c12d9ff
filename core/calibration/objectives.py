"""Calibration objectives: one fit of X = ``image_to_tool_rigid``, Y = ``phantom_to_base`` and the
pixel spacing (sx, sy) per objective, with the frames each fit rejects.

- ``all-wire``: every marker's distance to its wire, robust joint fit of X, Y (unless known) and
  (sx, sy), started from QR24 on point-to-wire registrations; then the wires are located too,
  each end point free to sit across its wire under a prior of ``WIRE_SIGMA_MM`` (chosen on the
  real recordings and the twin together: ``benchmarks/bench_wire_sigma.py``);
- ``middle-wire``: PLUS's objective: each N's middle dot must map onto the middle-wire point that
  the N's dot ratio gives in the phantom frame; same robust joint fit and start;
- ``thesis``: the thesis's method: per-frame registration by N-wire ratios and ICP, QR24 with SVD
  orthonormalisation (or, with Y known, the mean of ``M_i^-1 Y N_i``), the scanner's nominal
  spacing (the thesis never estimates it).

With a known ``phantom_to_base`` (PLUS's PhantomToReference) Y is held fixed. Every objective
then rejects the frames whose worst residual (a marker's distance to its wire; for
``middle-wire`` a middle dot's distance to its middle-wire point) stands out, and fits again.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.calibration.handeye import marker_offsets, qr24, x_from_known_y
from probecal.core.calibration.jointfit import Refined, WirePrior, refine
from probecal.core.calibration.kinematics import ArmKinematics
from probecal.core.calibration.register import register_frame
from probecal.core.calibration.result import Calibration
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing

OBJECTIVES = ("all-wire", "middle-wire", "thesis")
# The per-frame registration that starts each fit (QR24 or, with Y known, the mean of M_i^-1 Y N_i).
REGISTRATION = {"all-wire": "point-to-wire", "middle-wire": "point-to-wire", "thesis": "thesis"}
REGISTER_CHUNKS = 8  # runs of consecutive frames registered apart (by a mapper's workers)
Mapper = Callable[..., Iterable[Any]]
"""Runs a function over an iterable and yields the results in order: ``map``, or a process pool's
``map`` (the command line's, to keep both cores busy)."""
MIN_FRAMES = 6
MIN_ROTATION_DEG = 0.5  # RMS rotation about each of two axes below which Y and X cannot be told apart
WIRE_SIGMA_MM = 0.05  # how far (1 sd per axis) a built phantom's wire end points may sit off the definition
# The all-wire fit's prior on the phantom as built: its wires' ends alone. The prior's other terms
# (a layer moved as a whole, looser diagonals, turned diagonals) stay off: each helps some twins
# and costs the bench's coverage or the held-out blocks (``benchmarks/bench_calibration_bound.py
# --layer-sigma``, ``--diagonal-factor``, ``benchmarks/bench_diagonal_turn.py``).
WIRE_PRIOR = WirePrior(WIRE_SIGMA_MM)
LOOSE_WIRE_SIGMA_MM = 0.5  # the same for a phantom built a millimetre off: the other end of the bound's bracket
REJECT_FLOOR_MM = 1.0
REJECT_FACTOR = 5.0
RESIDUAL_NOUN = {
    "all-wire": "a marker lies {:.2f} mm from its wire",
    "middle-wire": "a middle dot lies {:.2f} mm from its middle-wire point",
    "thesis": "a marker lies {:.2f} mm from its wire",
}


@dataclass
class Observations:
    """Frames usable for calibration, in recording order: markers (F, W, 2) px with NaN where
    missing, flange poses (F, 4, 4), the frames' indices in the session and, once registered,
    each frame's ``image_to_phantom`` (F, 4, 4; NaN where it failed) and FRE (F,); for an arm
    whose kinematics probecal knows, its joints at every frame (the all-wire fit then fits the
    arm's kinematic errors too: :mod:`core.calibration.kinematics`).

    ``fan``: the markers are a fan image's as it shows them, and the joint fits solve the stretch
    of its beams' depths with its spacing held (:func:`core.calibration.jointfit.refine`);
    ``spacing_held``: the joint fits hold the spacing they start from (a fan image's markers set
    right for a stretch found before)."""

    markers_px: np.ndarray
    tool_to_base: np.ndarray
    indices: np.ndarray
    image_to_phantom: np.ndarray | None = None
    fre_mm: np.ndarray | None = None
    kinematics: ArmKinematics | None = None
    fan: Fan | None = None
    spacing_held: bool = False

    def subset(self, keep: np.ndarray) -> Observations:
        return replace(
            self, markers_px=self.markers_px[keep], tool_to_base=self.tool_to_base[keep], indices=self.indices[keep],
            image_to_phantom=None if self.image_to_phantom is None else self.image_to_phantom[keep],
            fre_mm=None if self.fre_mm is None else self.fre_mm[keep],
            kinematics=None if self.kinematics is None else self.kinematics.subset(keep),
        )

    @property
    def registrations(self) -> np.ndarray:
        """``image_to_phantom`` (F, 4, 4); ValueError for frames not registered (see :meth:`registered`)."""
        if self.image_to_phantom is None:
            raise ValueError("the frames are not registered")
        return self.image_to_phantom

    def registered(self, phantom: Phantom, spacing_mm: Spacing, method: str, mapper: Mapper = map) -> Observations:
        """A copy with every frame registered at ``spacing_mm`` by ``method``'s registration;
        ``mapper`` runs :data:`REGISTER_CHUNKS` runs of consecutive frames."""
        chunks = np.array_split(self.markers_px, min(REGISTER_CHUNKS, max(len(self), 1)))
        done = mapper(functools.partial(_registrations, phantom, spacing_mm, method), chunks)
        n, fre = (np.concatenate(parts) for parts in zip(*done))
        return replace(self, image_to_phantom=n, fre_mm=fre)

    def __len__(self) -> int:
        return len(self.indices)


def _registrations(phantom: Phantom, spacing_mm: Spacing, method: str, markers_px: np.ndarray) -> tuple[np.ndarray,
                   np.ndarray]:
    """``image_to_phantom`` (F, 4, 4) and FRE (F,) mm of frames ``markers_px`` (F, W, 2) by
    :func:`core.calibration.register.register_frame`; NaN for a frame it cannot register."""
    n = np.full((len(markers_px), 4, 4), np.nan)
    fre = np.full(len(markers_px), np.nan)
    for i, markers in enumerate(markers_px):
        reg = register_frame(phantom, markers, spacing_mm, method)
        if reg is not None:
            n[i], fre[i] = reg.image_to_phantom, reg.fre_mm
    return n, fre


@dataclass
class Solution:
    """One objective's fit: X (rigid, mm), Y (mm), spacing (mm/px), the session indices of the
    frames it used and those it rejected with the reason, where it located the wires ((W, 2, 3)
    end-point shifts off the definition, mm; None if it held them), the arm's kinematic
    deviations it found (:mod:`core.calibration.kinematics` units; None if it fitted none) with
    how far the markers determine each (0 to 1), and, for a fan image's markers as shown, the
    stretch of its beams it found (else None)."""

    objective: str
    image_to_tool_rigid: np.ndarray
    phantom_to_base: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    used: np.ndarray
    rejected: dict[int, str] = field(default_factory=dict)
    wire_shifts_mm: np.ndarray | None = None
    kinematic_units: np.ndarray | None = None
    stretch: float | None = None
    kinematic_determined: np.ndarray | None = None

    def poses(self, obs: Observations) -> np.ndarray:
        """(F, 4, 4) the flange poses of ``obs`` as this fit has them: where its arm model puts
        the flange, when it fitted the arm's kinematics; else as reported."""
        if self.kinematic_units is None or obs.kinematics is None:
            return obs.tool_to_base
        return obs.kinematics.poses(self.kinematic_units)

    def wires(self, phantom: Phantom) -> Phantom:
        """The phantom as this fit located its wires (the definition if it held them)."""
        return phantom if self.wire_shifts_mm is None else phantom.moved(self.wire_shifts_mm)

    @property
    def calibration(self) -> Calibration:
        return Calibration(self.image_to_tool_rigid, self.pixel_spacing_mm, self.phantom_to_base)


def rotation_spread_deg(tool_to_base: np.ndarray) -> np.ndarray:
    """RMS spread (deg) of the poses' rotations about their three principal axes, largest first."""
    rotvecs = Rotation.from_matrix(tool_to_base[0, :3, :3].T @ tool_to_base[:, :3, :3]).as_rotvec(degrees=True)
    return np.linalg.svd(rotvecs - rotvecs.mean(axis=0), compute_uv=False) / np.sqrt(len(rotvecs))


def check_pose_set(tool_to_base: np.ndarray, solve_y: bool) -> None:
    """Refuse pose sets that cannot determine the calibration at all (a merely weak pose set is
    reported, see :mod:`core.calibration.uncertainty`)."""
    if len(tool_to_base) < MIN_FRAMES:
        raise InputError(None, f"too few usable poses: {len(tool_to_base)} (at least {MIN_FRAMES} needed)")
    if not solve_y:
        return
    spread = rotation_spread_deg(tool_to_base)
    if spread[0] < MIN_ROTATION_DEG:
        raise InputError(None, f"degenerate pose set: the poses hardly rotate (spread {spread[0]:.2f} deg); "
                               "rotate the probe about at least two axes")
    if spread[1] < MIN_ROTATION_DEG:
        raise InputError(
            None,
            f"degenerate pose set: the rotations turn about a single axis (spread {spread[0]:.1f} deg "
            f"about one, {spread[1]:.2f} deg about the others); rotate about at least two axes",
        )


def _start(obs: Observations, spacing0_mm: Spacing, objective: str, known_y: np.ndarray | None,
           start: Solution | None) -> tuple[np.ndarray, np.ndarray, Spacing]:
    """X, Y and the spacing a fit starts from: ``start``'s (not for the thesis's method, which
    never refines), else QR24's (Y solved) or the mean of ``M_i^-1 Y N_i`` (Y known)."""
    if start is not None and objective != "thesis":
        return start.image_to_tool_rigid, start.phantom_to_base, start.pixel_spacing_mm
    if known_y is None:
        x, y = qr24(obs.tool_to_base, obs.registrations)
        return x, y, spacing0_mm
    return x_from_known_y(obs.tool_to_base, obs.registrations, known_y), known_y, spacing0_mm


def _fit_once(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, objective: str, known_y: np.ndarray | None,
              start: Solution | None, prior: WirePrior, determine_arm: bool = False) -> Refined:
    """One fit without rejection: its residuals are the markers' distances to their wires for the
    thesis's method. A layer moves as a whole only with the phantom pose solved. ``determine_arm``
    as :func:`core.calibration.jointfit.refine` takes it."""
    x, y, spacing = _start(obs, spacing0_mm, objective, known_y, start)
    if objective == "thesis":
        offsets = marker_offsets(phantom, np.nan_to_num(obs.markers_px), obs.tool_to_base, x, y, spacing)
        distances = np.where(np.all(np.isfinite(obs.markers_px), axis=2), np.linalg.norm(offsets, axis=2), np.nan)
        return Refined(x, y, (float(spacing[0]), float(spacing[1])), distances)
    solve_y = known_y is None
    kinematics = obs.kinematics if objective == "all-wire" else None
    return refine(phantom, obs.markers_px, obs.tool_to_base, x, y, spacing, solve_y=solve_y, objective=objective,
                  prior=prior if solve_y else replace(prior, layer_sigma=None), kinematics=kinematics,
                  previous=start, solve_spacing=not obs.spacing_held, fan=obs.fan, determine_arm=determine_arm)


def outlier_frames(distances: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Frames whose worst residual exceeds ``REJECT_FACTOR`` times the median frame's worst (and
    at least ``REJECT_FLOOR_MM``): (F,) mask, (F,) worst residual (mm), the limit (mm)."""
    worst = np.nanmax(np.where(np.isfinite(distances), distances, -np.inf), axis=1)
    limit = max(REJECT_FLOOR_MM, REJECT_FACTOR * float(np.median(worst)))
    return worst > limit, worst, limit


def fit(
    phantom: Phantom,
    obs: Observations,
    spacing0_mm: Spacing,
    objective: str,
    known_phantom_to_base: np.ndarray | None = None,
    start: Solution | None = None,
    prior: WirePrior = WIRE_PRIOR,
    determine_arm: bool = False,
) -> Solution:
    """Fit ``objective`` to observations registered (for the start) at ``spacing0_mm`` by
    ``REGISTRATION[objective]``; ``start`` (a previous fit) replaces the start of the joint fits;
    ``prior`` is the ``all-wire`` fit's prior on the phantom as built; ``determine_arm``: say how
    far the markers determine each of the arm's deviations (the fit that is reported, not its
    resamples). Raises InputError for a degenerate pose set."""
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}")
    ok = np.all(np.isfinite(obs.registrations.reshape(len(obs), 16)), axis=1)
    rejected = {int(obs.indices[i]): "too few complete N patterns to register" for i in np.flatnonzero(~ok)}
    obs = obs.subset(ok)
    check_pose_set(obs.tool_to_base, known_phantom_to_base is None)
    once = _fit_once(phantom, obs, spacing0_mm, objective, known_phantom_to_base, start, prior, determine_arm)
    bad, worst, limit = outlier_frames(once.residuals_mm)
    if bad.any() and (~bad).sum() >= MIN_FRAMES:
        for i in np.flatnonzero(bad):
            rejected[int(obs.indices[i])] = (f"disagrees with the {objective} fit: "
                                             f"{RESIDUAL_NOUN[objective].format(worst[i])} (limit {limit:.2f} mm)")
        obs = obs.subset(~bad)
        previous = Solution(objective, once.image_to_tool_rigid, once.phantom_to_base, once.pixel_spacing_mm,
                            obs.indices, wire_shifts_mm=once.wire_shifts_mm, kinematic_units=once.kinematic_units,
                            stretch=once.stretch)
        once = _fit_once(phantom, obs, spacing0_mm, objective, known_phantom_to_base, previous, prior, determine_arm)
    return Solution(objective, once.image_to_tool_rigid, once.phantom_to_base, once.pixel_spacing_mm, obs.indices,
                    rejected, once.wire_shifts_mm, once.kinematic_units, once.stretch, once.kinematic_determined)
