"""A session's image latency (:mod:`core.temporal`), measured on its own frames.

- A robot session that kept its pose stream and moved the probe up and down before its sweep
  (frames recorded with ``phase`` "temporal", :func:`core.acquisition.plan.temporal_waypoints`)
  measures its latency on those frames (:func:`session_latency`): over an N-wire phantom the echo
  is the mean row of the labelled wire dots (every dot moves with the probe), over a tank floor
  with no phantom the floor's depth (:mod:`core.temporal.echo`).
- A tracked recording (a PLUS sequence: the tracker's pose at every frame's time, kept as its pose
  stream) has no such motion; the calibration measures its latency itself
  (:func:`fitted_latency`): the frames paired at every lag, the lag that puts the markers
  nearest their wires.

Timestamps are the session's (s), rows are pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from probecal.core.acquisition.pairing import stream_buffer
from probecal.core.calibration.handeye import qr24, x_from_known_y
from probecal.core.calibration.jointfit import refine
from probecal.core.calibration.segment import FrameResult, segment_session
from probecal.core.errors import InputError, Remedy
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.session import Session
from probecal.core.robot.posestream import PoseBuffer
from probecal.core.temporal.echo import floor_echo_rows
from probecal.core.temporal.lag import (
    MAX_LAG_S,
    FittedLatencyReport,
    LatencyEstimate,
    TooFewFrames,
    estimate_latency,
    principal_motion,
)

TEMPORAL_PHASE = "temporal"
MIN_FIT_FRAMES = 6
"""Fewer frames than this that can be paired at every lag measure no latency."""
STREAM_MARGIN_S = 0.5
"""Pose samples kept (s) beyond the temporal frames' lag window, for the motion's principal axis."""


class TooFewEchoes(InputError):
    """A temporal session whose frames showed the echo ``found`` times, ``needed`` being the
    fewest that measure a latency: a longer motion may."""

    def __init__(self, path: str | Path | None, problem: str, found: int = 0, needed: int = 0):
        super().__init__(path, problem)
        self.found, self.needed = found, needed


def temporal_frames(session: Session) -> list[int]:
    """The frames recorded during the temporal calibration's motion; every frame of a session
    recorded for temporal calibration alone (kind "temporal")."""
    if session.manifest.kind == TEMPORAL_PHASE:
        return list(range(len(session)))
    return [i for i, r in enumerate(session.records) if r.extra.get("phase") == TEMPORAL_PHASE]


def marker_rows(results: list[FrameResult], count: int) -> np.ndarray:
    """(count,) mean row (px) of each frame's labelled markers, NaN where no pattern was found."""
    rows = np.full(count, np.nan)
    for r in results:
        if r.found and r.markers is not None:
            rows[r.index] = float(np.mean(r.markers[:, 1]))
    return rows


@dataclass(frozen=True)
class _SessionFrames:
    """Frames ``indices`` of ``session``, each read when asked for (``echo.Frames``): a motion's
    frames are never all held at once."""

    session: Session
    indices: list[int]

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int) -> np.ndarray:
        return self.session.image(self.indices[k])


def session_latency(session: Session, results: list[FrameResult] | None = None,
                    max_lag_s: float = MAX_LAG_S) -> LatencyEstimate:
    """The latency measured on the session's temporal frames against its pose stream; the wire
    dots' rows come from ``results`` (the session's segmentation) or a segmentation made here.
    InputError naming the session when it has no pose stream, no temporal frames or no
    measurable lag."""
    stream = session.pose_stream()
    if stream is None:
        raise InputError(session.path, "the session kept no pose stream (posestream.jsonl): record it with "
                                       "continuous motion to measure its latency", (Remedy.CONTINUOUS,))
    frames = temporal_frames(session)
    if not frames:
        raise InputError(session.path, "no frames of a temporal calibration motion (phase \"temporal\")")
    times = np.array([np.nan if session.records[i].timestamp is None else session.records[i].timestamp
                      for i in frames])
    if session.phantom is not None:
        if results is None:
            results = segment_session(session)
        echo = marker_rows(results, len(session))[frames]
    else:
        echo = floor_echo_rows(_SessionFrames(session, frames))
    stream_times, poses = stream
    first, last = np.nanmin(times), np.nanmax(times)
    reach = max_lag_s + STREAM_MARGIN_S
    window = (stream_times >= first - reach) & (stream_times <= last + reach)
    during = (stream_times[window] >= first) & (stream_times[window] <= last)
    try:
        motion = principal_motion(poses[window, :3, 3], axis_from=during)
        return estimate_latency(times, echo, stream_times[window], motion, max_lag_s)
    except TooFewFrames as exc:
        raise TooFewEchoes(session.path, f"no latency measured: {exc}", exc.found, exc.needed)
    except ValueError as exc:
        raise InputError(session.path, f"no latency measured: {exc}")


FIT_MAX_LAG_S = 1.0
"""Lags searched by :func:`fitted_latency` (s, either sign): a tracked recording's poses may run
far behind its images (PLUS's fCal 1.2 test recordings: about 0.45 s)."""
FIT_GRID_S = 0.05
"""Its coarse grid (s); the best grid point is then refined on a finer one."""
FIT_FINE_S = 0.005
FIT_BLOCKS = 10
"""Blocks of consecutive frames for the standard error of the latency (clustered sandwich)."""
FIT_SIGNIFICANCE = 2.0
"""The latency is applied only when it lies this many standard errors from zero."""


@dataclass(frozen=True)
class FittedLatency:
    """The image latency that best fits a tracked recording's frames to its poses.

    ``image_latency_s``: a frame stamped ``t`` shows the probe where it was at ``t - L``;
    ``std_error_s``: its standard error over blocks of consecutive frames; ``applied``: whether
    it lies far enough from zero (``FIT_SIGNIFICANCE``) to pair the frames again with it;
    ``residual_at_zero_mm`` and ``residual_mm``: the markers' mean distance to their wires
    (median frame) with the frames as recorded and at the latency; ``lags_s`` and
    ``residual_per_lag_mm``: the coarse search."""

    image_latency_s: float
    std_error_s: float
    applied: bool
    frames_used: int
    residual_at_zero_mm: float
    residual_mm: float
    lags_s: np.ndarray
    residual_per_lag_mm: np.ndarray

    def to_json(self) -> FittedLatencyReport:
        return FittedLatencyReport(
            method="fit", image_latency_s=round(self.image_latency_s, 6), std_error_s=round(self.std_error_s, 6),
            applied=self.applied, frames_used=self.frames_used,
            residual_at_zero_mm=round(self.residual_at_zero_mm, 4), residual_mm=round(self.residual_mm, 4),
            searched_s=FIT_MAX_LAG_S)


def _frame_costs(phantom: Phantom, markers_px: np.ndarray, buffer: PoseBuffer, times: np.ndarray, lags: np.ndarray,
                 start: tuple[np.ndarray, np.ndarray, tuple[float, float]], solve_y: bool) -> np.ndarray:
    """(len(lags), F) each frame's mean marker-to-wire distance (mm) under an all-wire fit (wires
    held) from ``start`` (X, Y, spacing) with every frame paired at ``t - lag``; NaN where a frame
    cannot be paired."""
    costs = np.full((len(lags), len(times)), np.nan)
    for k, lag in enumerate(lags):
        poses = buffer.poses_at(times - lag)
        use = np.all(np.isfinite(poses.reshape(len(times), -1)), axis=1)
        if use.sum() < MIN_FIT_FRAMES:
            continue
        fit = refine(phantom, markers_px[use], poses[use], *start, solve_y=solve_y, objective="all-wire")
        costs[k, use] = np.nanmean(fit.residuals_mm, axis=1)
    return costs


def _start(phantom: Phantom, markers_px: np.ndarray, registrations: np.ndarray, buffer: PoseBuffer, times: np.ndarray,
           spacing0_mm: tuple[float, float],
           known_y: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """X, Y and spacing of the all-wire fit (wires held) with the frames as recorded: where every
    lag's fit starts."""
    poses = buffer.poses_at(times)
    use = np.all(np.isfinite(poses.reshape(len(times), -1)), axis=1)
    if use.sum() < MIN_FIT_FRAMES:
        raise ValueError(f"only {int(use.sum())} frames can be paired with the pose stream "
                         f"(at least {MIN_FIT_FRAMES} needed)")
    m, n = poses[use], registrations[use]
    x, y = qr24(m, n) if known_y is None else (x_from_known_y(m, n, known_y), known_y)
    fit = refine(phantom, markers_px[use], m, x, y, spacing0_mm, solve_y=known_y is None, objective="all-wire")
    return fit.image_to_tool_rigid, fit.phantom_to_base, fit.pixel_spacing_mm


def _total(costs: np.ndarray, common: np.ndarray, cap: float) -> np.ndarray:
    """Σ over the common frames of each frame's cost, capped at ``cap`` (a frame that fits no lag
    weighs no more than a bad one): (L,) for (L, F) costs."""
    return np.minimum(costs[:, common], cap).sum(axis=1)


def fitted_latency(phantom: Phantom, markers_px: np.ndarray, times: np.ndarray, registrations: np.ndarray,
                   stream: tuple[np.ndarray, np.ndarray], spacing0_mm: tuple[float, float],
                   known_y: np.ndarray | None) -> FittedLatency:
    """The latency of a tracked recording measured by the calibration itself: every frame paired
    at ``t - L`` from the recording's pose ``stream`` (s, (M, 4, 4) mm), the all-wire objective
    (wires held) fitted at every ``L`` on a grid within ``FIT_MAX_LAG_S`` and then finer around
    the best, which minimises the markers' distances to their wires.

    ``markers_px`` (F, W, 2), ``times`` (F,) s and ``registrations`` (F, 4, 4) are the frames'
    (``image_to_phantom`` at ``spacing0_mm``); ``known_y`` the phantom pose, None to solve it.
    The standard error is the sandwich over ``FIT_BLOCKS`` blocks of consecutive frames (a frame's
    error lasts for several frames). ValueError when too few frames can be paired."""
    buffer = stream_buffer(*stream)
    start = _start(phantom, markers_px, registrations, buffer, times, spacing0_mm, known_y)
    coarse = np.arange(-FIT_MAX_LAG_S, FIT_MAX_LAG_S + FIT_GRID_S / 2, FIT_GRID_S)
    costs = _frame_costs(phantom, markers_px, buffer, times, coarse, start, known_y is None)
    common = np.all(np.isfinite(costs), axis=0)
    if common.sum() < MIN_FIT_FRAMES:
        raise ValueError(f"only {int(common.sum())} frames can be paired at every lag within "
                         f"{FIT_MAX_LAG_S:g} s (at least {MIN_FIT_FRAMES} needed)")
    zero = int(np.argmin(np.abs(coarse)))
    cap = 3.0 * float(np.median(costs[zero, common]))
    best = coarse[int(np.argmin(_total(costs, common, cap)))]
    fine = np.arange(best - FIT_GRID_S, best + FIT_GRID_S + FIT_FINE_S / 2, FIT_FINE_S)
    fine_costs = _frame_costs(phantom, markers_px, buffer, times, fine, start, known_y is None)
    common &= np.all(np.isfinite(fine_costs), axis=0)
    k = int(np.clip(np.argmin(_total(fine_costs, common, cap)), 1, len(fine) - 2))
    # The parabola through the best grid point and its neighbours places the minimum between
    # them; the clustered sandwich gives its standard error: each block's slope of its summed
    # cost there, against the curvature of the whole.
    capped = np.minimum(fine_costs[k - 1 : k + 2][:, common], cap)
    below, at, above = capped.sum(axis=1)
    curvature = (below - 2 * at + above) / FIT_FINE_S**2
    latency = float(fine[k])
    if curvature > 0:
        latency += float(np.clip((below - above) / (2 * FIT_FINE_S * curvature), -FIT_FINE_S, FIT_FINE_S))
    blocks = np.array_split(np.arange(int(common.sum())), FIT_BLOCKS)
    slopes = np.array([(capped[2, b].sum() - capped[0, b].sum()) / (2 * FIT_FINE_S) for b in blocks if b.size])
    std_error = float(np.sqrt((slopes**2).sum()) / curvature) if curvature > 0 else float("inf")
    return FittedLatency(
        image_latency_s=latency, std_error_s=std_error,
        applied=bool(abs(latency) > FIT_SIGNIFICANCE * std_error), frames_used=int(common.sum()),
        residual_at_zero_mm=float(np.median(costs[zero, common])),
        residual_mm=float(np.median(fine_costs[k, common])),
        lags_s=coarse, residual_per_lag_mm=np.median(costs[:, common], axis=1))
