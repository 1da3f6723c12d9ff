"""The fourth step of a calibration: how far the kept fit may be off.

:func:`validated` gives the 95 % bound on the image corners (mm, image plane in the tool frame)
from a block bootstrap and from refits that would move the corners if the model were wrong
(:func:`corner_refits`: at the echoes' peaks, under the loose wire prior, the other objectives),
the same bound at a grid of points over the image from the same fits (the bound map), the
held-out errors, the error as poses are added and OpenCV's SHAH for comparison.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from probecal.core.calibration.crossval import error_curve, summary
from probecal.core.calibration.dots import echo_peak_rows
from probecal.core.calibration.fits import Chosen, Fits
from probecal.core.calibration.frames import Paired
from probecal.core.calibration.handeye import opencv_shah
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.objectives import LOOSE_WIRE_SIGMA_MM, REGISTRATION, Mapper, Observations, Solution, fit
from probecal.core.calibration.result import CurvePoint, HeldOut
from probecal.core.calibration.segment import FrameResult, on_two_threads
from probecal.core.calibration.uncertainty import (
    SPACING_OBJECTIVES,
    CornerBound,
    PointBounds,
    block_bootstrap,
    bound_grid_px,
    corner_bound,
    fold_spread_mm,
    fold_spreads_mm,
    image_corners_px,
    point_bounds_mm,
)
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing
from probecal.core.io.session import Session


@dataclass(frozen=True)
class Refit:
    """One of the refits the corner bound compares with the chosen fit: :func:`fit`'s arguments,
    started from ``start``."""

    phantom: Phantom
    obs: Observations
    objective: str
    known_y: np.ndarray | None
    start: Solution
    prior: WirePrior


def _refitted(spacing0_mm: Spacing, task: Refit) -> Solution | None:
    """``task`` fitted; None where its frames cannot determine it."""
    try:
        return fit(task.phantom, task.obs, spacing0_mm, task.objective, task.known_y, start=task.start,
                   prior=task.prior)
    except InputError:
        return None


def located_references(phantom: Phantom, fits: Fits, solution: Solution, prior: WirePrior) -> dict[str, Refit]:
    """The other objectives' fits that ``solution`` (the phantom pose solved) is compared with for
    its bound: each fitted again against the wires where ``solution`` located them (from its fit on
    the definition). A wire built off its definition pulls ``middle-wire``, which holds the wires, by
    far more than ``all-wire``, which locates them; against the definition the two would stay
    apart by that pull, a bias of the other fit and not of the chosen one. What still sets them
    apart on the same wires (a centroid bias, a wrong model) is what the comparison is there to see."""
    wires = solution.wires(phantom)
    return {name: Refit(wires, fits.registered[REGISTRATION[name]], name, None, other, prior)
            for name, other in fits.solutions.items() if name != solution.objective and name in SPACING_OBJECTIVES}


def echo_peak_refit(session: Session, results: list[FrameResult], phantom: Phantom, obs: Observations,
                    spacing0_mm: tuple[float, float],
                    solution: Solution, known_y: np.ndarray | None, prior: WirePrior) -> Refit:
    """``solution``'s objective to be refitted with every marker's row moved to its echo's peak
    (:func:`core.calibration.dots.echo_peak_rows`; the centroid's row where no peak is found). The
    peaks are the segmentation's where ``results`` kept them, else read from the frames again."""
    markers = obs.markers_px.copy()
    kept = {r.index: r.peak_rows for r in results if r.peak_rows is not None}

    def peaks(k: int) -> np.ndarray:
        index = int(obs.indices[k])
        if index in kept:
            return kept[index]
        return echo_peak_rows(session.image(index), markers[k], spacing0_mm)

    for k, rows in enumerate(on_two_threads(peaks, range(len(obs.indices)))):
        markers[k, :, 1] = np.where(np.isfinite(rows), rows, markers[k, :, 1])
    # Only rows move, so the frames that register stay the same; the joint fits start from
    # ``solution`` and need the registrations only for that, the thesis's method fits them.
    moved = replace(obs, markers_px=markers)
    if solution.objective == "thesis":
        moved = moved.registered(phantom, spacing0_mm, REGISTRATION[solution.objective])
    return Refit(phantom, moved, solution.objective, known_y, solution, prior)


@dataclass(frozen=True)
class Validation:
    """How far the chosen fit may be off: the 95 % corner bound and the bound map over the image,
    the held-out errors, the error as poses are added and, with the phantom pose solved, OpenCV's
    SHAH (X and Y) for comparison."""

    bound: CornerBound
    bound_map: PointBounds
    cross_validation: HeldOut
    curve: list[CurvePoint]
    shah: dict | None


def corner_refits(frames: Paired, fits: Fits, kept: Chosen, say: Callable[[str], None], mapper: Mapper,
                  prior: WirePrior) -> tuple[Solution | None, Solution | None, dict[str, Solution]]:
    """The refits the corner bound compares the chosen fit with: at the markers' echo peaks,
    under the loose wire prior, and the other objectives (on the wires it located, when it
    located them)."""
    phantom, solution, spacing0 = frames.phantom, kept.solution, frames.spacing0_mm
    say(f"refitting the {kept.objective} objective to the markers at their echoes' peaks")
    tasks = {"echo peaks": echo_peak_refit(frames.session, frames.results, phantom, kept.start_obs, spacing0,
                                           solution, frames.known_y, prior)}
    located = frames.known_y is None and solution.wire_shifts_mm is not None
    if located:
        say(f"refitting the {kept.objective} objective under the loose wire prior, and the others on its wires")
        loose = replace(prior, end_sigma_mm=LOOSE_WIRE_SIGMA_MM)
        tasks["loose"] = Refit(phantom, kept.start_obs, kept.objective, None, solution, loose)
        tasks.update(located_references(phantom, fits, solution, prior))
    refitted = dict(zip(tasks, mapper(functools.partial(_refitted, spacing0), tasks.values())))
    echo, loose_fit = refitted.pop("echo peaks"), refitted.pop("loose", None)
    references = {name: s for name, s in refitted.items() if s is not None} if located else fits.solutions
    return echo, loose_fit, references


def validated(frames: Paired, fits: Fits, kept: Chosen, say: Callable[[str], None], mapper: Mapper,
              prior: WirePrior) -> Validation:
    """The chosen fit's corner bound (block bootstrap and :func:`corner_refits`), the same bound
    at a grid of points over the image (:func:`core.calibration.uncertainty.bound_grid_px`, the
    wires' depths among its rows), its held-out errors, its error vs poses and OpenCV's SHAH."""
    phantom, solution, spacing0, known_y = frames.phantom, kept.solution, frames.spacing0_mm, frames.known_y
    say(f"bootstrapping the {kept.objective} fit")
    refits = block_bootstrap(phantom, kept.start_obs, spacing0, solution, known_y, progress=say, mapper=mapper,
                             prior=prior)
    echo, loose, references = corner_refits(frames, fits, kept, say, mapper, prior)
    fan, stretch = (frames.fan, frames.stretch) if frames.stretch is not None else (None, 1.0)

    def set_right(pixels: np.ndarray) -> np.ndarray:  # pixels as a fan image's fits take them
        return pixels if fan is None else fan.stretched(pixels, stretch)

    corners = set_right(image_corners_px(frames.session.image_size) if fan is None else fan.corners_px())
    # With the phantom pose solved the objective is fixed, and another one's disagreement
    # counts only beyond that objective's own random error; where held-out figures chose
    # among them, the choice itself is uncertain and the bound covers every candidate.
    spreads = {name: fold_spread_mm(folds, fits.solutions[name], corners) for name, folds in fits.folds.items()}
    bound = corner_bound(solution, refits, references, corners, echo, spreads, loose, excess_only=known_y is None)
    grid = bound_grid_px(frames.session.image_size, fan, wire_depths_px(frames.results, phantom, fan))
    points = set_right(grid)
    point_spreads = {name: fold_spreads_mm(folds, fits.solutions[name], points) for name, folds in fits.folds.items()}
    bound_map = PointBounds(grid, point_bounds_mm(solution, refits, references, points, echo, point_spreads, loose,
                                                  excess_only=known_y is None))
    held_out = summary(phantom, fits.folds[kept.objective], kept.start_obs, kept.final_obs)
    curve = error_curve(phantom, kept.used_obs, kept.used_final, spacing0, kept.objective, known_y, progress=say,
                        mapper=mapper, prior=prior)
    return Validation(bound, bound_map, held_out, curve, _shah(kept, known_y))


def wire_depths_px(results: list[FrameResult], phantom: Phantom, fan: Fan | None) -> np.ndarray:
    """Each layer's median depth over the frames whose pattern was found (px down the image as
    it shows them; on a fan image, px from the fan's origin), where the wires pin the calibration
    down; a layer never seen has none."""
    found = [r.markers for r in results if r.found and r.markers is not None]
    if not found:
        return np.empty(0)
    markers = np.array(found, dtype=float).reshape(len(found), len(phantom.layers), -1, 2)
    depths = markers[..., 1] if fan is None else np.hypot(markers[..., 0] - fan.origin_px[0],
                                                         markers[..., 1] - fan.origin_px[1])
    layers = [depths[:, k][np.isfinite(depths[:, k])] for k in range(len(phantom.layers))]
    return np.array([np.median(d) for d in layers if d.size])


def _shah(kept: Chosen, known_y: np.ndarray | None) -> dict | None:
    """OpenCV's SHAH on the used frames registered at the calibrated spacing (the phantom pose solved)."""
    if known_y is not None:
        return None
    n = kept.used_final.registrations
    ok = np.all(np.isfinite(n.reshape(len(n), -1)), axis=1)
    x_shah, y_shah = opencv_shah(kept.used_obs.tool_to_base[ok], n[ok])
    return {"image_to_tool_rigid": x_shah, "phantom_to_base": y_shah}
