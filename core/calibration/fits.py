"""The second and third steps of a calibration: every objective fitted, and one kept.

:func:`fit_objectives` fits each objective of :mod:`core.calibration.objectives` to every frame
and cross-validates it in blocks of consecutive frames; :func:`chosen` keeps the one the method
asks for, or with ``auto`` the one :func:`core.calibration.crossval.choose` picks.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from probecal.core.calibration.crossval import CV_BLOCKS, FoldFit, block_folds, choose, fold_fit, summary
from probecal.core.calibration.frames import Paired
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.objectives import REGISTRATION, WIRE_PRIOR, Mapper, Observations, Solution, fit
from probecal.core.calibration.result import HeldOut
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing


@dataclass
class Fits:
    """Every objective's fit on all frames and, when compared, its block cross-validation; the
    observations registered (at the initial spacing) by each registration method."""

    registered: dict[str, Observations]
    solutions: dict[str, Solution]
    folds: dict[str, list[FoldFit]]
    cv: dict[str, HeldOut]


def fit_objectives(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, objectives: tuple[str, ...],
                   known_y: np.ndarray | None,
                   compare: bool, say: Callable[[str], None], mapper: Mapper = map,
                   prior: WirePrior = WIRE_PRIOR) -> Fits:
    """Fit each of ``objectives`` and, if ``compare``, cross-validate it in blocks; ``mapper``
    runs the fits (each objective's, then each fold's), which are independent of each other."""
    fits = Fits({}, {}, {}, {})
    folds = block_folds(len(obs), CV_BLOCKS) if compare else []
    pending: dict[str, Iterator[Any]] = {}  # each task's Solution, FoldFit or InputError
    for registration in sorted({REGISTRATION[name] for name in objectives}):
        say(f"registering {len(obs)} frames ({registration} registration)")
        # The first registration runs on the mapper; a later one (the thesis's ICP, which loads
        # open3d) runs here while the mapper fits the objectives of those before it.
        registered = obs.registered(phantom, spacing0_mm, registration, map if pending else mapper)
        fits.registered[registration] = registered
        tasks = [(name, held) for name in objectives if REGISTRATION[name] == registration for held in [None, *folds]]
        pending[registration] = iter(mapper(functools.partial(_objective_fit, phantom, registered, spacing0_mm,
                                                              known_y, prior), tasks))
    for name in objectives:
        done = pending[REGISTRATION[name]]
        say(f"fitting the {name} objective to {len(obs)} frames")
        solution = next(done)
        if isinstance(solution, InputError):
            raise solution
        fits.solutions[name] = solution
        if compare:
            say(f"cross-validating the {name} objective ({CV_BLOCKS} blocks of consecutive frames)")
            fits.folds[name] = [next(done) for _ in folds]
            fits.cv[name] = summary(phantom, fits.folds[name], fits.registered[REGISTRATION[name]])
    return fits


def _objective_fit(phantom: Phantom, registered: Observations, spacing0_mm: Spacing, known_y: np.ndarray | None,
                   prior: WirePrior,
                   task: tuple[str, np.ndarray | None]) -> Solution | FoldFit | InputError:
    """One task of :func:`fit_objectives`: an objective fitted to every frame of ``registered``
    (the InputError it raises is returned, to be raised where the task was asked for), or one
    of its folds."""
    name, held = task
    if held is not None:
        return fold_fit(phantom, registered, spacing0_mm, name, known_y, held, prior)
    try:
        return fit(phantom, registered, spacing0_mm, name, known_y, prior=prior, determine_arm=True)
    except InputError as exc:
        return exc


@dataclass(frozen=True)
class Chosen:
    """The objective kept and why, its fit, and its frames: registered at the initial spacing
    (``start_obs``, all the fit was given), the ones it used (``used_obs``), and both registered
    again at the calibrated spacing (``final_obs``, ``used_final``: the FRE to report, and the
    held-out frames)."""

    objective: str
    why: str
    solution: Solution
    start_obs: Observations
    used_obs: Observations
    final_obs: Observations
    used_final: Observations


def chosen(frames: Paired, fits: Fits, method: str, mapper: Mapper) -> Chosen:
    """The objective ``method`` asks for, or with ``auto`` the one cross-validation chooses
    (:func:`core.calibration.crossval.choose`)."""
    objective, why = choose(fits.cv, frames.known_y is None) if method == "auto" else (method, "forced")
    solution = fits.solutions[objective]
    start_obs = fits.registered[REGISTRATION[objective]]
    final_obs = start_obs.registered(frames.phantom, solution.pixel_spacing_mm, REGISTRATION[objective],
                                     mapper)
    return Chosen(objective, why, solution, start_obs, start_obs.subset(np.isin(start_obs.indices, solution.used)),
                  final_obs, final_obs.subset(np.isin(final_obs.indices, solution.used)))
