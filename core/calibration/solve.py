"""The calibration pipeline: labelled markers and poses in, a validated ``image_to_tool`` out.

:func:`calibrate_session` runs it as named steps: the frames paired with their poses at the
measured image latency (:func:`paired`; frames whose pattern was not found or whose pose is
invalid are left out), every objective of :mod:`core.calibration.objectives` fitted and
cross-validated in blocks (:func:`fit_objectives`), one kept (:func:`chosen`), its bound and
validation (:func:`validated`) and the report (:func:`fit_metrics`, :func:`report`).

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
import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from probecal.core.acquisition.pairing import paired_again
from probecal.core.calibration.crossval import (
    CV_BLOCKS,
    FoldFit,
    block_folds,
    choose,
    error_curve,
    fold_fit,
    summary,
)
from probecal.core.calibration.dots import echo_peak_rows
from probecal.core.calibration.handeye import marker_offsets, opencv_shah
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.kinematics import ArmKinematics, arm_joints, deviation_json
from probecal.core.calibration.latency import (
    FIT_MAX_LAG_S,
    FittedLatency,
    TooFewEchoes,
    fitted_latency,
    session_latency,
    temporal_frames,
)
from probecal.core.calibration.metrics import pre3d
from probecal.core.calibration.objectives import (
    LOOSE_WIRE_SIGMA_MM,
    OBJECTIVES,
    REGISTRATION,
    WIRE_PRIOR,
    Mapper,
    Observations,
    Solution,
    check_pose_set,
    fit,
)
from probecal.core.calibration.result import (
    Calibration,
    CalibrationMetrics,
    CornerError,
    CurvePoint,
    HeldOut,
    ObjectiveRow,
)
from probecal.core.calibration.segment import FrameResult, Segmenter, on_two_threads, segment_session
from probecal.core.calibration.uncertainty import (
    SPACING_OBJECTIVES,
    CornerBound,
    block_bootstrap,
    corner_bound,
    fold_spread_mm,
    image_corners_px,
    weak_determination,
)
from probecal.core.calibration.validity import valid_for
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing
from probecal.core.io.session import Session
from probecal.core.robot.ur3 import ARM_TABLES
from probecal.core.temporal.lag import LatencyEstimate

METHODS = ("auto", *OBJECTIVES)


def observations(session: Session, results: list[FrameResult]) -> tuple[Observations, dict[int, str]]:
    """Frames with a found pattern and a valid pose; the others with the reason they are out. A
    session recorded by an arm whose kinematics probecal knows (manifest ``arm``) gives the
    joints of every frame, and the all-wire fit then fits the arm's kinematic errors too."""
    if session.phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    keep, left_out = [], {}
    for r in results:
        record = session.records[r.index]
        if not r.found:
            left_out[r.index] = f"pattern not found: {r.reason}"
        elif not record.pose_valid:
            left_out[r.index] = "no valid pose"
        else:
            keep.append(r)
    markers = np.array([r.markers for r in keep], dtype=float).reshape(len(keep), session.phantom.n_wires, 2)
    poses = np.array([session.records[r.index].tool_to_base for r in keep]).reshape(len(keep), 4, 4)
    arm = session.manifest.arm
    table = None if arm is None else ARM_TABLES.get(arm)
    joints = None if table is None else arm_joints(poses, table)
    kinematics = None if table is None or joints is None else ArmKinematics.at(joints, table)
    return Observations(markers, poses, np.array([r.index for r in keep], dtype=int), kinematics=kinematics), left_out


def _usable(session: Session, results: list[FrameResult]) -> tuple[Observations, dict[int, str]]:
    """:func:`observations`, or InputError naming the session when no frame is usable."""
    obs, left_out = observations(session, results)
    if len(obs) == 0:
        reasons = sorted(set(left_out.values()))
        raise InputError(session.path, f"no usable frame among {len(session)} ({'; '.join(reasons[:3])})")
    return obs, left_out


def tracked_latency(session: Session, obs: Observations, phantom: Phantom, spacing0_mm: tuple[float, float],
                    known_y: np.ndarray | None, mapper: Mapper = map) -> FittedLatency:
    """The image latency of a recording whose frames were taken while the probe moved, with the
    tracker's poses kept as its pose stream (an imported PLUS recording), measured by the
    calibration itself (:func:`core.calibration.latency.fitted_latency`). InputError naming the
    session when it cannot be measured."""
    stream = session.pose_stream()
    assert stream is not None  # called for sessions that kept one
    times = np.array([np.nan if session.records[i].timestamp is None else session.records[i].timestamp
                      for i in obs.indices])
    registered = obs.registered(phantom, spacing0_mm, "point-to-wire", mapper).registrations
    ok = np.isfinite(times) & np.all(np.isfinite(registered.reshape(len(obs), 16)), axis=1)
    try:
        return fitted_latency(phantom, obs.markers_px[ok], times[ok], registered[ok], stream, spacing0_mm, known_y)
    except ValueError as exc:
        raise InputError(session.path, f"no image latency measured: {exc}")


def paired_with_latency(session: Session, results: list[FrameResult],
                        latency_s: float | None) -> tuple[Session, list[FrameResult]]:
    """A continuous session's frames paired again from its pose stream with the image latency
    (s), without the frames of the temporal motion; any other session as it is."""
    if latency_s is None or not session.manifest.continuous:
        return session, results
    temporal = set(temporal_frames(session))
    return paired_again(session, latency_s), [r for r in results if r.index not in temporal]


def initial_spacing(session: Session, obs: Observations, phantom: Phantom) -> tuple[float, float]:
    """The scanner's nominal spacing if recorded, else PLUS's approximate spacing hint, else an
    estimate from the outer-dot distances against the outer-wire separations (sx = sy)."""
    if session.nominal_spacing_mm is not None:
        return session.nominal_spacing_mm
    ratios = []
    for k, layer in enumerate(phantom.layers):
        separation = np.linalg.norm(np.cross(layer.wires[0].direction, layer.wires[2].front - layer.wires[0].front))
        span = np.linalg.norm(obs.markers_px[:, 3 * k + 2] - obs.markers_px[:, 3 * k], axis=1)
        ratios.append(separation / span)
    value = float(np.nanmedian(np.concatenate(ratios)))
    return value, value


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
        return fit(phantom, registered, spacing0_mm, name, known_y, prior=prior)
    except InputError as exc:
        return exc


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


@dataclass(frozen=True)
class Paired:
    """A session's frames ready to fit: paired with the robot's or tracker's poses at the image
    latency the session measures (``latency``; None where it measures none), a fan image's
    markers set right for its beams' ``stretch``, the usable frames (``obs``) and those left out
    with the reason; the spacing every fit starts from (mm/px) and the phantom pose when known
    (``known_y``; None: solved)."""

    session: Session
    phantom: Phantom
    results: list[FrameResult]
    obs: Observations
    left_out: dict[int, str]
    spacing0_mm: tuple[float, float]
    known_y: np.ndarray | None
    latency: LatencyEstimate | FittedLatency | None = None
    fan: Fan | None = None
    stretch: float | None = None

    @property
    def applied_latency_s(self) -> float | None:
        """The latency the frames were paired with again (s), if any."""
        if self.latency is None or (isinstance(self.latency, FittedLatency) and not self.latency.applied):
            return None
        return self.latency.image_latency_s

    def usable_again(self, session: Session, results: list[FrameResult]) -> Paired:
        """These frames of ``session`` as :func:`observations` finds them, the spacing held as before."""
        obs, left_out = _usable(session, results)
        return replace(self, session=session, results=results, obs=replace(obs, spacing_held=self.obs.spacing_held),
                       left_out=left_out)


def pair_temporal(session: Session, results: list[FrameResult],
                  say: Callable[[str], None]) -> tuple[Session, list[FrameResult], LatencyEstimate | None]:
    """A continuous session with a temporal motion: its latency measured on that motion's frames,
    and the sweep's frames paired again with it (the motion's frames left out); a stream too slow
    for the motion leaves the latency to :func:`pair_tracked`. Any other session as it is."""
    temporal = set(temporal_frames(session))
    if not temporal or not session.manifest.continuous:
        return session, results, None
    say(f"measuring the image latency on the {len(temporal)} frames of the temporal motion")
    try:
        latency = session_latency(session, results)
    except TooFewEchoes as exc:  # a slow stream: the sweep's own frames fit it, as a tracked recording's do
        say(f"{exc.problem}; fitting it on the sweep's frames instead")
        return session, [r for r in results if r.index not in temporal], None
    session, results = paired_with_latency(session, results, latency.image_latency_s)
    return session, results, latency


def set_right_fan(paired: Paired, say: Callable[[str], None], mapper: Mapper, prior: WirePrior) -> Paired:
    """A fan image's markers set right for the stretch of its beams (:func:`fan_stretch`, fitted
    on the markers at their echoes' peaks), holding the scanner's own spacing where the session
    gives one (PLUS's approximate hint is only a start); any other session's as they are."""
    session = paired.session
    fan = session.fan if session.nominal_spacing_mm is not None else None
    if fan is None:
        return paired
    say("fitting the stretch of the fan's beams (the medium's sound speed over the scanner's)")
    peaks, _ = _usable(session, [at_echo_peaks(r) for r in paired.results])
    stretch = fan_stretch(paired.phantom, replace(peaks, fan=fan), paired.spacing0_mm, paired.known_y, mapper, prior)
    results = [stretched(r, fan, stretch) for r in paired.results]
    obs, left_out = _usable(session, results)
    held = session.pixel_spacing_mm is not None
    return replace(paired, results=results, obs=replace(obs, spacing_held=held), left_out=left_out, fan=fan,
                   stretch=stretch)


def pair_tracked(paired: Paired, say: Callable[[str], None], mapper: Mapper) -> Paired:
    """A session that kept its pose stream and measured no latency yet: the latency that best fits
    its frames (:func:`tracked_latency`), and its frames paired again with it where it matters."""
    session, obs = paired.session, paired.obs
    if paired.latency is not None or not session.has_pose_stream:
        return paired
    say(f"measuring the image latency: the {len(obs)} frames fitted at every lag within "
        f"{FIT_MAX_LAG_S:g} s of their tracked poses")
    latency = tracked_latency(session, obs, paired.phantom, paired.spacing0_mm, paired.known_y, mapper)
    paired = replace(paired, latency=latency)
    if not latency.applied:
        return paired
    return paired.usable_again(paired_again(session, latency.image_latency_s), paired.results)


def paired(session: Session, results: list[FrameResult], solve_phantom_pose: bool, say: Callable[[str], None],
           mapper: Mapper, prior: WirePrior) -> Paired:
    """The first step of :func:`calibrate_session`: the frames paired at the measured latency
    (:func:`pair_temporal`, :func:`pair_tracked`), a fan's set right (:func:`set_right_fan`); the
    pose set refused at once if it cannot determine a calibration."""
    if len(session) == 0:
        raise InputError(session.path, "session has no frames")
    phantom = session.phantom
    if phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    session, results, latency = pair_temporal(session, results, say)
    obs, left_out = _usable(session, results)
    known_y = None if solve_phantom_pose else session.phantom_to_base
    frames = Paired(session, phantom, results, obs, left_out, initial_spacing(session, obs, phantom), known_y, latency)
    check_pose_set(obs.tool_to_base, known_y is None)  # before any slow work
    return pair_tracked(set_right_fan(frames, say, mapper, prior), say, mapper)


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
        image_latency_s=None if applied is None else round(applied, 6),
    )
    if frames.latency is not None:
        metrics["temporal"] = frames.latency.to_json()
    return metrics


@dataclass(frozen=True)
class Validation:
    """How far the chosen fit may be off: the 95 % corner bound, the held-out errors, the error as
    poses are added and, with the phantom pose solved, OpenCV's SHAH (X and Y) for comparison."""

    bound: CornerBound
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
    """The chosen fit's corner bound (block bootstrap and :func:`corner_refits`), its held-out
    errors, its error vs poses and OpenCV's SHAH."""
    phantom, solution, spacing0, known_y = frames.phantom, kept.solution, frames.spacing0_mm, frames.known_y
    say(f"bootstrapping the {kept.objective} fit")
    refits = block_bootstrap(phantom, kept.start_obs, spacing0, solution, known_y, progress=say, mapper=mapper,
                             prior=prior)
    echo, loose, references = corner_refits(frames, fits, kept, say, mapper, prior)
    corners = image_corners_px(frames.session.image_size)
    if frames.fan is not None and frames.stretch is not None:  # a fan's own corners, set right
        corners = frames.fan.stretched(frames.fan.corners_px(), frames.stretch)
    # With the phantom pose solved the objective is fixed, and another one's disagreement
    # counts only beyond that objective's own random error; where held-out figures chose
    # among them, the choice itself is uncertain and the bound covers every candidate.
    spreads = {name: fold_spread_mm(folds, fits.solutions[name], corners) for name, folds in fits.folds.items()}
    bound = corner_bound(solution, refits, references, corners, echo, spreads, loose, excess_only=known_y is None)
    held_out = summary(phantom, fits.folds[kept.objective], kept.start_obs, kept.final_obs)
    curve = error_curve(phantom, kept.used_obs, kept.used_final, spacing0, kept.objective, known_y, progress=say,
                        mapper=mapper, prior=prior)
    return Validation(bound, held_out, curve, _shah(kept, known_y))


def _shah(kept: Chosen, known_y: np.ndarray | None) -> dict | None:
    """OpenCV's SHAH on the used frames registered at the calibrated spacing (the phantom pose solved)."""
    if known_y is not None:
        return None
    n = kept.used_final.registrations
    ok = np.all(np.isfinite(n.reshape(len(n), -1)), axis=1)
    x_shah, y_shah = opencv_shah(kept.used_obs.tool_to_base[ok], n[ok])
    return {"image_to_tool_rigid": x_shah, "phantom_to_base": y_shah}


def report(frames: Paired, kept: Chosen, metrics: CalibrationMetrics,
           validation: Validation | None) -> CalibrationReport:
    """The calibration with its metrics, the validation's where it ran, and what it is valid for."""
    curve, shah, bound = [], None, None
    if validation is not None:
        curve, shah, bound = validation.curve, validation.shah, validation.bound
        metrics["corner_error_95_mm"] = _rounded(bound.bound_mm)
        metrics["corner_error"] = _corner_metrics(bound)
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
    The steps: pair the frames at the measured latency (:func:`paired`), fit every objective
    (:func:`fit_objectives`), choose one (:func:`chosen`), bound and validate it
    (:func:`validated`), report (:func:`fit_metrics`, :func:`report`).

    ``with_validation`` adds the corner bound (block bootstrap, its refits run by ``mapper``), the
    held-out identity error, the error-vs-poses curve and OpenCV's SHAH; without it a forced method
    fits its objective alone. ``prior`` is the ``all-wire`` fit's prior on the phantom as built.

    A fan image's session (a convex or phased probe's, ``session.fan``) is calibrated in two
    steps: the ``all-wire`` fit finds the stretch of the beams' depths (:func:`fan_stretch`, the
    sound speeds' ratio, which no affine map of the pixels follows), then every objective fits the
    markers set right by it (:func:`stretched`), holding the scanner's stated spacing (fitting it
    from PLUS's approximate hint); the calibration keeps the fan and the stretch.
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


def fan_stretch(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, known_y: np.ndarray | None,
                mapper: Mapper = map, prior: WirePrior = WIRE_PRIOR) -> float:
    """The stretch of a fan image's beams (the medium's sound speed over the scanner's) that the
    ``all-wire`` fit finds for markers as the image shows them (``obs.fan`` set; calibrate gives
    them at their echoes' peaks, :func:`at_echo_peaks`), the spacing held at the scanner's."""
    registered = obs.registered(phantom, spacing0_mm, REGISTRATION["all-wire"], mapper)
    stretch = fit(phantom, registered, spacing0_mm, "all-wire", known_y, prior=prior).stretch
    assert stretch is not None  # a fan's fit solves it
    return stretch


def at_echo_peaks(result: FrameResult) -> FrameResult:
    """A frame's segmentation with each marker's row at its echo's peak where the segmentation
    found one (``peak_rows``): a wire's echo peaks on it, while the tail below pulls a centroid
    deeper the deeper it lies, which reads as a stretch of the beams (on the twin's ``bench``:
    +4.4 per mille from the centroids, +1.1 from the peaks, over seeds 0-4)."""
    if result.markers is None or result.peak_rows is None:
        return result
    rows = np.where(np.isfinite(result.peak_rows), result.peak_rows, result.markers[:, 1])
    return replace(result, markers=np.column_stack([result.markers[:, 0], rows]))


def stretched(result: FrameResult, fan: Fan, stretch: float) -> FrameResult:
    """A frame's segmentation with its markers (and their echoes' peak rows) where a fan image
    shows them once every beam is stretched by ``stretch`` (:meth:`Fan.stretched`)."""
    if result.markers is None:
        return result
    rows = None
    if result.peak_rows is not None:
        rows = fan.stretched(np.column_stack([result.markers[:, 0], result.peak_rows]), stretch)[:, 1]
    return replace(result, markers=fan.stretched(result.markers, stretch), peak_rows=rows)


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
