"""Held-out errors of a calibration objective on the calibration recording itself.

Neighbouring frames of a recording are near copies (the probe barely moved, the tracking and
segmentation errors hardly changed), so frames are held out in blocks of consecutive frames, never
at random: a random fold leaves each held-out frame's twin in the training set and flatters the
objective that fits noise best.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.metrics import identity_error, pre3d_errors, trimmed_mean_std
from probecal.core.calibration.objectives import MIN_FRAMES, WIRE_PRIOR, Mapper, Observations, Solution, fit
from probecal.core.calibration.result import CurvePoint, HeldOut
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing

CV_BLOCKS = 6
SOLVED_POSE_OBJECTIVE = "all-wire"
"""Kept where the phantom pose is solved (the robot's way): it uses every marker (see :func:`choose`)."""
KNOWN_POSE_DEFAULT = "middle-wire"
"""Kept where the phantom pose is known (a tracked recording) unless another objective is clearly
better held out: on the twin's tracked freehand benches its image corners lie nearer the truth
than all-wire's on 15 of 20 (1.17 against 1.81 mm on average with the bench's registration error,
0.86 against 1.11 without it), and it validates better on both of PLUS's fCal benches."""
SIGNIFICANT_GAIN = 2.0  # standard errors of the per-block gain


def block_folds(n: int, k: int = CV_BLOCKS) -> list[np.ndarray]:
    """``k`` blocks of consecutive positions 0..n-1 (recording order), sizes differing by at most one."""
    return [block for block in np.array_split(np.arange(n), min(k, n)) if block.size]


@dataclass
class FoldFit:
    """One fold: the held-out positions (into the observations) and the fit on the others (None
    when the other frames could not determine a calibration)."""

    held: np.ndarray
    solution: Solution | None


def cross_validate(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, objective: str,
                   known_y: np.ndarray | None,
                   k: int = CV_BLOCKS, prior: WirePrior = WIRE_PRIOR) -> list[FoldFit]:
    """Fit ``objective`` on all blocks but one, for each of ``k`` blocks (see :func:`fit`)."""
    return [fold_fit(phantom, obs, spacing0_mm, objective, known_y, held, prior) for held in block_folds(len(obs), k)]


def fold_fit(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, objective: str, known_y: np.ndarray | None,
             held: np.ndarray,
             prior: WirePrior = WIRE_PRIOR) -> FoldFit:
    """``objective`` fitted on every frame of ``obs`` but the ``held`` ones (positions): one fold."""
    keep = np.setdiff1d(np.arange(len(obs)), held)
    return FoldFit(held, _fit_or_none(phantom, obs, spacing0_mm, objective, known_y, prior, keep))


def _fit_or_none(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, objective: str,
                 known_y: np.ndarray | None, prior: WirePrior,
                 keep: np.ndarray) -> Solution | None:
    """``objective`` fitted on the frames ``keep`` (positions) of ``obs``; None where their pose
    set cannot determine it."""
    try:
        return fit(phantom, obs.subset(keep), spacing0_mm, objective, known_y, prior=prior)
    except InputError:
        return None


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _held_out_errors(phantom: Phantom, solution: Solution, held: np.ndarray, obs: Observations) -> np.ndarray:
    """The held-out frames' PRE3D errors (mm, flat) under the fold's calibration, phantom pose and
    arm (where it fitted the arm's kinematics), against the phantom's definition whatever the
    objective fitted (see :func:`choose`)."""
    held_obs = obs.subset(held)
    return pre3d_errors(phantom, held_obs.markers_px, solution.poses(held_obs), solution.calibration.image_to_tool,
                        solution.phantom_to_base).ravel()


def summary(phantom: Phantom, folds: list[FoldFit], obs: Observations,
            held_obs: Observations | None = None) -> HeldOut:
    """PRE3D over all held-out frames pooled and per block (mean of the lowest 95 %, as PLUS; None
    where a fold could not be fitted) and, given the frames registered at the calibrated spacing
    (``held_obs``), the thesis's eq. 4.1 identity error."""
    errors = {i: _held_out_errors(phantom, f.solution, f.held, obs) for i, f in enumerate(folds)
              if f.solution is not None}
    pre_mean, pre_std = trimmed_mean_std(np.concatenate(list(errors.values())) if errors else [])
    out = HeldOut(
        folds=len(errors), blocks=len(folds), pre3d_mm=_finite(pre_mean), pre3d_std_mm=_finite(pre_std),
        pre3d_per_block_mm=[_finite(trimmed_mean_std(errors[i])[0]) if i in errors else None
                            for i in range(len(folds))],
    )
    if held_obs is not None:
        registrations = held_obs.registrations
        identity = [
            identity_error(f.solution.image_to_tool_rigid, f.solution.phantom_to_base, pose, registrations[i])
            for f in folds if f.solution is not None
            for i, pose in zip(f.held, f.solution.poses(held_obs.subset(f.held)))
            if np.all(np.isfinite(registrations[i]))
        ]
        out["identity_translation_mm"] = float(np.mean([e.translation_mm for e in identity])) if identity else None
        out["identity_rotation_deg"] = float(np.mean([e.rotation_deg for e in identity])) if identity else None
    return out


def block_gain(reference: HeldOut, other: HeldOut) -> tuple[float, float] | None:
    """Mean and standard error (mm) over the blocks of how much lower ``other``'s held-out PRE3D
    is than ``reference``'s (two :func:`summary` results); None with fewer than 3 common blocks."""
    pairs = [(a, b) for a, b in zip(reference["pre3d_per_block_mm"], other["pre3d_per_block_mm"])
             if a is not None and b is not None]
    if len(pairs) < 3:
        return None
    gains = np.array([a - b for a, b in pairs])
    return float(gains.mean()), float(gains.std(ddof=1) / np.sqrt(len(gains)))


def choose(cv: dict[str, HeldOut], phantom_pose_solved: bool = False) -> tuple[str, str]:
    """The objective to keep, and why in words.

    Every objective's held-out blocks are scored alike: PRE3D against the phantom's definition,
    with the fold's phantom pose (``_held_out_errors``), a yardstick none of them moves (all-wire
    used to be scored against the wires it located itself, which flattered it). Where the
    phantom pose is known (a tracked recording with PLUS's PhantomToReference), that is the
    frame a calibration is used and judged in, and the choice is the lowest held-out PRE3D
    among ``KNOWN_POSE_DEFAULT`` and those that beat it on the blocks by more than
    ``SIGNIFICANT_GAIN`` standard errors (a lower pooled figure that the blocks do not agree on
    is noise).

    Where the phantom pose is solved (the robot's way), a held-out PRE3D measures how well the
    fitted mount and phantom pose agree with each other, not how right they are: middle-wire,
    which fits PRE3D itself, wins it on every twin seed while its image corners lie twice as far
    from the truth as all-wire's (``benchmarks/bench_objectives.py``). ``SOLVED_POSE_OBJECTIVE``
    is kept then: all-wire uses every marker against its own wire (the least-squares fit under
    isotropic segmentation noise) and locates the wires; the others are reported beside it."""
    if phantom_pose_solved:
        return SOLVED_POSE_OBJECTIVE, (f"{SOLVED_POSE_OBJECTIVE} kept: with the phantom pose solved, held-out PRE3D "
                                       "measures how well the mount and the phantom pose agree, not accuracy")
    default = KNOWN_POSE_DEFAULT
    reference = cv[default]["pre3d_mm"]
    if reference is None:
        return default, f"{default} kept: no block could be held out from it (the rest did not determine a calibration)"
    contenders, notes = {default: reference}, []  # contenders' held-out PRE3D by name
    for name, row in cv.items():
        pre3d_mm = row["pre3d_mm"]
        if name == default or pre3d_mm is None:
            continue
        gain = block_gain(cv[default], row)
        if gain is not None and gain[0] > SIGNIFICANT_GAIN * gain[1]:
            contenders[name] = pre3d_mm
        elif pre3d_mm < reference:
            spread = "" if gain is None else f" ({gain[0]:.3f} +- {gain[1]:.3f} mm per block)"
            notes.append(f"{name} has a lower held-out PRE3D, but within the block-to-block scatter{spread}")
    chosen = min(contenders, key=contenders.__getitem__)
    if chosen != default:
        why = f"lowest held-out PRE3D, below that of {default} on the blocks beyond their scatter"
    else:
        why = "lowest held-out PRE3D" if not notes else f"{default} kept: " + "; ".join(notes)
    return chosen, why


def error_curve(phantom: Phantom, obs: Observations, held_obs: Observations, spacing0_mm: Spacing, objective: str,
                known_y: np.ndarray | None,
                seed: int = 0, progress: Callable[[str], None] | None = None, mapper: Mapper = map,
                prior: WirePrior = WIRE_PRIOR) -> list[CurvePoint]:
    """Thesis Fig. 4.5: errors on the last block of the recording as the number of calibration poses,
    drawn at random from the other blocks, grows. ``obs`` is registered at ``spacing0_mm``;
    ``held_obs`` (the same frames) at the calibrated spacing; ``mapper`` runs the fits."""
    *_, held = block_folds(len(obs))
    train = np.random.default_rng(seed).permutation(np.setdiff1d(np.arange(len(obs)), held))
    # The fits are asked for largest first, so that two workers finish together.
    steps = sorted({n for n in (MIN_FRAMES, 10, 15, 20, 30, 45, 60, 90, 120, 180, len(train))
                    if MIN_FRAMES <= n <= len(train)}, reverse=True)
    fits = mapper(functools.partial(_fit_or_none, phantom, obs, spacing0_mm, objective, known_y, prior),
                  [train[:n] for n in steps])
    curve = []
    for n, solution in reversed(list(zip(steps, fits))):
        if progress:
            progress(f"error vs poses: {n} poses")
        if solution is None:
            continue
        row = summary(phantom, [FoldFit(held, solution)], obs, held_obs)
        curve.append(CurvePoint(poses=n, identity_translation_mm=row.get("identity_translation_mm"),
                                identity_rotation_deg=row.get("identity_rotation_deg"), pre3d_mm=row.get("pre3d_mm")))
    return curve
