"""The calibration pipeline: labelled markers and poses in, a validated ``image_to_tool`` out.

:func:`calibrate_session` runs it as named steps, each in its own module:

1. :func:`core.calibration.frames.paired`: the frames paired with their poses at the measured
   image latency; frames whose pattern was not found or whose pose is invalid are left out;
2. :func:`core.calibration.fits.fit_objectives`: every objective of
   :mod:`core.calibration.objectives` fitted and cross-validated in blocks;
3. :func:`core.calibration.fits.chosen`: one objective kept;
4. :func:`core.calibration.bound.validated`: its corner bound, its bound map over the image and
   validation;
5. :func:`fit_metrics` and :func:`report`, here.

``method="auto"`` keeps ``all-wire`` where the phantom pose is solved (the robot's way), and
where it is known (a tracked recording) ``middle-wire`` unless another objective's held-out
PRE3D beats it on the blocks beyond their scatter (:func:`core.calibration.crossval.choose`);
any other method forces that objective. The report adds a 95 % bound on how far the image
corners may be off and says in words when the pose set does not pin the calibration down
(:mod:`core.calibration.uncertainty`).

With a known ``phantom_to_base`` (PLUS's PhantomToReference) Y is held fixed unless asked. With Y
solved, PRE3D on the calibration frames (even cross-validated) measures consistency, not accuracy:
a biased mount and phantom pose can agree with each other; the corner bound is the accuracy figure.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from probecal.core.calibration.bound import Validation, validated
from probecal.core.calibration.fits import Chosen, Fits, chosen, fit_objectives
from probecal.core.calibration.frames import Paired, paired
from probecal.core.calibration.handeye import marker_offsets
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.kinematics import deviation_json, undetermined
from probecal.core.calibration.metrics import pre3d
from probecal.core.calibration.objectives import OBJECTIVES, WIRE_PRIOR, Mapper, Observations, Solution
from probecal.core.calibration.result import (
    BoundMap,
    Calibration,
    CalibrationMetrics,
    CornerError,
    CurvePoint,
    ObjectiveRow,
)
from probecal.core.calibration.segment import FrameResult, Segmenter, segment_session
from probecal.core.calibration.uncertainty import CornerBound, PointBounds, weak_determination
from probecal.core.calibration.validity import valid_for
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.session import Session

METHODS = ("auto", *OBJECTIVES)


@dataclass
class CalibrationReport:
    """The calibration (with its ``metrics``), which frames it used and which it rejected and why,
    the held-out error as poses are added, OpenCV's SHAH for comparison (Y solved), the reasons the
    poses leave it weakly determined, and the segmentation it came from (when it segmented)."""

    calibration: Calibration
    frames_total: int
    frames_used: list[int]
    frames_rejected: dict[int, str]
    curve: list[CurvePoint]
    shah: dict | None
    weakly_determined: list[str]
    segmentation: list[FrameResult] | None = None


def _objective_rows(fits: Fits) -> dict[str, ObjectiveRow]:
    """The metrics' side-by-side table of the compared objectives."""
    return {
        name: ObjectiveRow(
            cv_pre3d_mm=cv.get("pre3d_mm"),
            cv_pre3d_std_mm=cv.get("pre3d_std_mm"),
            cv_pre3d_per_block_mm=cv.get("pre3d_per_block_mm", []),
            cv_folds=cv.get("folds", 0),
            pixel_spacing_mm=list(fits.solutions[name].pixel_spacing_mm),
            frames_rejected=len(fits.solutions[name].rejected),
        )
        for name, cv in fits.cv.items()
    }


def _wire_shifts(phantom: Phantom, solution: Solution) -> dict[str, float | None] | None:
    """How far the fit located each wire off the definition (mm, the farther end point), by wire
    name; None when the objective held the wires."""
    if solution.wire_shifts_mm is None:
        return None
    farther = np.linalg.norm(solution.wire_shifts_mm, axis=2).max(axis=1)
    return {wire.name: _rounded(d) for wire, d in zip(phantom.wires, farther)}


def _arm_correction(obs: Observations, solution: Solution, image_size: tuple[int, int]) -> float | None:
    """How far (mm) the fitted arm puts the image centre from where the reported poses put it,
    at the frame where they differ most; None when the fit left the arm as its table says."""
    if solution.kinematic_units is None:
        return None
    centre = solution.calibration.image_to_tool @ [(image_size[0] - 1) / 2, (image_size[1] - 1) / 2, 0.0, 1.0]
    moved = (solution.poses(obs) - obs.tool_to_base) @ centre
    return _rounded(float(np.linalg.norm(moved[:, :3], axis=1).max()))


def _rounded(value: float | None, digits: int = 4) -> float | None:
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def _corner_metrics(bound: CornerBound) -> CornerError:
    return CornerError(
        bootstrap_95_mm=_rounded(bound.bootstrap_mm),
        jackknife_95_mm=_rounded(bound.jackknife_mm),
        objective_disagreement_mm={name: _rounded(d) for name, d in bound.disagreements_mm.items()},
        objective_excess_mm={name: _rounded(d) for name, d in bound.excess_mm.items()},
        fold_spread_mm={name: _rounded(d) for name, d in bound.spreads_mm.items()},
        echo_peak_disagreement_mm=_rounded(bound.echo_peak_mm),
        wire_prior_disagreement_mm=_rounded(bound.wire_prior_mm),
        resamples=bound.resamples,
        failed_resamples=bound.failed_resamples,
    )


def _bound_map(bounds: PointBounds) -> BoundMap:
    return BoundMap(points_px=np.round(bounds.points_px, 2).tolist(),
                    bound_mm=[[_rounded(b) for b in row] for row in bounds.bound_mm])


def fit_metrics(frames: Paired, fits: Fits, kept: Chosen, method: str) -> CalibrationMetrics:
    """The chosen fit's metrics on its own frames: FRE, marker-to-wire, PRE3D (consistency with the
    phantom pose solved), the objectives side by side, the frames left out and why."""
    phantom, solution, used_obs, used_final = frames.phantom, kept.solution, kept.used_obs, kept.used_final
    rejected = _rejected(frames, kept)
    used_poses = solution.poses(used_obs)
    pre_mean, pre_std = pre3d(phantom, used_obs.markers_px, used_poses, solution.calibration.image_to_tool,
                              solution.phantom_to_base)
    offsets = marker_offsets(phantom, np.nan_to_num(used_obs.markers_px), used_poses,
                             solution.image_to_tool_rigid, solution.phantom_to_base, solution.pixel_spacing_mm)
    wire_distances = np.linalg.norm(offsets, axis=2)[np.all(np.isfinite(used_obs.markers_px), axis=2)]
    assert used_final.fre_mm is not None  # registered() gives every frame its FRE
    applied = frames.applied_latency_s
    metrics = CalibrationMetrics(
        method=method, objective=kept.objective, objective_choice=kept.why,
        frames_total=len(frames.results), frames_used=len(solution.used), frames_rejected=len(rejected),
        frames_rejected_by_fit=len(solution.rejected),
        rejected_frames={int(i): reason for i, reason in sorted(rejected.items())},
        fre_mm=float(np.nanmean(used_final.fre_mm)),
        fre_per_frame_mm={int(i): _rounded(f) for i, f in zip(used_final.indices, used_final.fre_mm)},
        calibration_residual_mm=float(wire_distances.mean()),
        pre3d_mm=pre_mean, pre3d_std_mm=pre_std,
        cv_pre3d_mm=fits.cv[kept.objective]["pre3d_mm"] if fits.cv else None,
        corner_error_95_mm=None,
        phantom_pose="solved" if frames.known_y is None else "known",
        initial_pixel_spacing_mm=list(frames.spacing0_mm),
        objectives=_objective_rows(fits),
        wire_shifts_mm=_wire_shifts(phantom, solution),
        arm_correction_mm=_arm_correction(used_obs, solution, frames.session.image_size),
        arm_undetermined=None if solution.kinematic_determined is None else undetermined(solution.kinematic_determined),
        image_latency_s=None if applied is None else round(applied, 6),
    )
    if frames.latency is not None:
        metrics["temporal"] = frames.latency.to_json()
    return metrics


def report(frames: Paired, kept: Chosen, metrics: CalibrationMetrics,
           validation: Validation | None) -> CalibrationReport:
    """The calibration with its metrics, the validation's where it ran, and what it is valid for."""
    curve, shah, bound = [], None, None
    if validation is not None:
        curve, shah, bound = validation.curve, validation.shah, validation.bound
        metrics["corner_error_95_mm"] = _rounded(bound.bound_mm)
        metrics["corner_error"] = _corner_metrics(bound)
        metrics["bound_map"] = _bound_map(validation.bound_map)
        metrics["cross_validation"] = validation.cross_validation
    weak = weak_determination(kept.used_obs.tool_to_base, frames.known_y is None, bound)
    metrics["weakly_determined"] = weak
    metrics["error_vs_poses"] = curve
    units, session = kept.solution.kinematic_units, frames.session
    arm = None if units is None or session.manifest.arm is None else deviation_json(session.manifest.arm, units)
    calibration = replace(kept.solution.calibration, metrics=metrics, valid_for=valid_for(session),
                          image_latency_s=frames.applied_latency_s, arm=arm, fan=frames.fan, stretch=frames.stretch)
    return CalibrationReport(calibration, len(frames.results), [int(i) for i in kept.solution.used],
                             _rejected(frames, kept), curve, shah, weak)


def _rejected(frames: Paired, kept: Chosen) -> dict[int, str]:
    """Every frame left out, by session index: unusable, or rejected by the kept fit, with why."""
    return {**frames.left_out, **kept.solution.rejected}


def calibrate_session(
    session: Session,
    results: list[FrameResult],
    method: str = "auto",
    solve_phantom_pose: bool = False,
    with_validation: bool = True,
    progress: Callable[[str], None] | None = None,
    mapper: Mapper = map,
    prior: WirePrior = WIRE_PRIOR,
) -> CalibrationReport:
    """Calibrate a segmented session; raises InputError with a clear message on unusable input.
    The steps are listed in the module's docstring.

    ``with_validation`` adds the corner bound (block bootstrap, its refits run by ``mapper``), the
    held-out identity error, the error-vs-poses curve and OpenCV's SHAH; without it a forced method
    fits its objective alone. ``prior`` is the ``all-wire`` fit's prior on the phantom as built.

    A fan image's session (a convex or phased probe's, ``session.fan``) is calibrated in two
    steps: the ``all-wire`` fit finds the stretch of the beams' depths (the sound speeds' ratio,
    which no affine map of the pixels follows; :func:`core.calibration.frames.fan_stretch`), then
    every objective fits the markers set right by it, holding the scanner's stated spacing
    (fitting it from PLUS's approximate hint); the calibration keeps the fan and the stretch.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}")
    say = progress or (lambda _msg: None)
    compare = method == "auto" or with_validation
    with _naming(session):
        frames = paired(session, results, solve_phantom_pose, say, mapper, prior)
        fits = fit_objectives(frames.phantom, frames.obs, frames.spacing0_mm,
                              OBJECTIVES if compare else (method,), frames.known_y, compare, say, mapper, prior)
    kept = chosen(frames, fits, method, mapper)
    metrics = fit_metrics(frames, fits, kept, method)
    validation = validated(frames, fits, kept, say, mapper, prior) if with_validation else None
    return report(frames, kept, metrics, validation)


@contextlib.contextmanager
def _naming(session: Session) -> Iterator[None]:
    """An InputError raised within names ``session``'s folder (a fit's names none)."""
    try:
        yield
    except InputError as exc:
        if exc.path == session.path:
            raise
        raise InputError(session.path, exc.problem, exc.remedies)


def segment_and_calibrate(
    session: Session,
    segmenter: Segmenter | None = None,
    method: str = "auto",
    solve_phantom_pose: bool = False,
    frame_progress: Callable[[int, int], None] | None = None,
    progress: Callable[[str], None] | None = None,
    mapper: Mapper = map,
) -> CalibrationReport:
    """``probecal calibrate`` and the console's Calibrate: segment every frame (with ``segmenter``,
    by default the session's own, tuned on it), then :func:`calibrate_session`; the report keeps
    the segmentation."""
    results = segment_session(session, frame_progress, segmenter)
    report = calibrate_session(session, results, method, solve_phantom_pose, progress=progress, mapper=mapper)
    return replace(report, segmentation=results)
