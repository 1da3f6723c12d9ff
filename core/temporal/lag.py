"""The lag between the images and the pose stream, from one motion seen by both.

The image signal is an echo's position in each frame (px, e.g. :mod:`core.temporal.echo`), stamped
with the frames' timestamps; the motion signal is the probe's position along its main direction
of motion (mm, :func:`principal_motion`), sampled by the pose stream on its own clock. The latency
``L`` is the shift that best lines the two up: the frame stamped ``t`` shows the probe where it
was at ``t - L``. Both signals are normalised (zero mean, unit spread) and their correlation is
found on a 1 ms grid of lags and refined between grid points; frames whose echo disagrees with
the motion at that lag (a missed floor, a reverberation) are dropped and the search is run again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypedDict

import numpy as np
from scipy.optimize import minimize_scalar

MAX_LAG_S = 0.5
"""Lags searched: within this of zero (s). Real scanners run 20-150 ms behind their trackers."""
GRID_S = 0.001
"""Spacing of the lag grid (s) before refinement."""
OUTLIER_SIGMAS = 4.0
"""A frame whose echo lies further than this many robust deviations from the aligned motion is dropped."""
MIN_FRAMES = 10
"""Fewer usable frames than this measure no lag."""
class TooFewFrames(ValueError):
    """Fewer usable frames than a lag needs: ``found`` of ``needed``."""

    def __init__(self, message: str, found: int, needed: int):
        super().__init__(message)
        self.found, self.needed = found, needed


MIN_MOTION_MM = 2.0
"""The motion must span at least this (mm, peak to peak) for its lag to be measured."""


class LatencyReport(TypedDict):
    """A latency estimate as JSON (``probecal temporal-calibrate --out``, a calibration's
    ``metrics.temporal``): the fields of :class:`LatencyEstimate` but its search curve."""

    image_latency_s: float
    std_error_s: float
    correlation: float
    residual: float
    peak_halfwidth_s: float
    frames_used: int
    frames_rejected: int
    motion_mm: float


class FittedLatencyReport(TypedDict):
    """:func:`core.calibration.latency.fitted_latency` as JSON (a calibration's ``metrics.temporal``)."""

    method: str
    image_latency_s: float
    std_error_s: float
    applied: bool
    frames_used: int
    residual_at_zero_mm: float
    residual_mm: float
    searched_s: float


@dataclass(frozen=True)
class LatencyEstimate:
    """A measured image latency and how well it is determined.

    ``image_latency_s``: a frame stamped ``t`` shows the probe where it was at ``t - L``;
    ``std_error_s``: its standard error from the misfit and the motion's speed, widened when the
    misfit drifts slowly rather than jumping from frame to frame;
    ``correlation``: Pearson correlation of the echo and the motion at that lag (its sign says
    which way the echo moves as the probe moves along the principal direction);
    ``residual``: the misfit of the normalised echo there, ``sqrt(1 - correlation**2)``;
    ``peak_halfwidth_s``: lags within this of the best one leave at most twice its unexplained
    variance (a sharp peak is narrow); ``lags_s`` and ``misfit`` are the whole search.
    """

    image_latency_s: float
    std_error_s: float
    correlation: float
    residual: float
    peak_halfwidth_s: float
    frames_used: int
    frames_rejected: int
    motion_mm: float
    lags_s: np.ndarray
    misfit: np.ndarray

    def to_json(self) -> LatencyReport:
        """The JSON of ``probecal temporal-calibrate --out`` (design §6), without the search curve."""
        return LatencyReport(
            image_latency_s=round(self.image_latency_s, 6),
            std_error_s=round(self.std_error_s, 6),
            correlation=round(self.correlation, 5),
            residual=round(self.residual, 5),
            peak_halfwidth_s=round(self.peak_halfwidth_s, 6),
            frames_used=self.frames_used,
            frames_rejected=self.frames_rejected,
            motion_mm=round(self.motion_mm, 3),
        )


@dataclass(frozen=True)
class _Fit:
    """One search: the frames used, the lag (s), the grid's misfit, the echo per motion mm and
    every frame's distance from the aligned motion (echo units)."""

    keep: np.ndarray
    lag: float
    misfit: np.ndarray
    slope: float
    off: np.ndarray


def principal_motion(positions_mm: np.ndarray, axis_from: np.ndarray | None = None) -> np.ndarray:
    """(M,) positions (mm) of (M, 3) points along the first principal axis of those selected by
    ``axis_from`` (a mask; all by default), about their mean. ValueError when it selects fewer
    than two."""
    chosen = positions_mm if axis_from is None else positions_mm[axis_from]
    if len(chosen) < 2:
        raise ValueError("the pose stream holds fewer than two poses while the frames were taken")
    mean = chosen.mean(axis=0)
    axis = np.linalg.svd(chosen - mean, full_matrices=False)[2][0]
    return (positions_mm - mean) @ axis


def _correlations(echo: np.ndarray, frame_times: np.ndarray, pose_times: np.ndarray, motion: np.ndarray,
                  lags: np.ndarray) -> np.ndarray:
    """Pearson correlation of ``echo`` with the motion at ``frame_times - lag`` for every lag."""
    shifted = np.interp(frame_times[None, :] - lags[:, None], pose_times, motion)
    shifted -= shifted.mean(axis=1, keepdims=True)
    e = echo - echo.mean()
    denominator = np.sqrt((shifted**2).sum(axis=1) * (e**2).sum())
    return (shifted @ e) / np.where(denominator > 0, denominator, np.inf)


def _best_lag(echo: np.ndarray, frame_times: np.ndarray, pose_times: np.ndarray, motion: np.ndarray,
              lags: np.ndarray) -> tuple[float, np.ndarray]:
    """The lag of the strongest correlation (s), refined between grid points, and the grid's misfit."""
    r = _correlations(echo, frame_times, pose_times, motion, lags)
    k = int(np.argmax(r**2))
    if k in (0, len(lags) - 1):
        raise ValueError(f"the echo best matches the motion at the edge of the lags searched "
                         f"({lags[k] * 1000:+.0f} ms): the latency may lie beyond it")

    def unexplained(lag: float) -> float:
        return float(1 - _correlations(echo, frame_times, pose_times, motion, np.array([lag]))[0] ** 2)

    step = lags[1] - lags[0]
    refined = minimize_scalar(unexplained, bounds=(lags[k] - step, lags[k] + step), method="bounded",
                              options={"xatol": 1e-7})
    return float(refined.x), np.sqrt(np.clip(1 - r**2, 0, None))


def estimate_latency(
    frame_times: np.ndarray,
    echo: np.ndarray,
    pose_times: np.ndarray,
    motion_mm: np.ndarray,
    max_lag_s: float = MAX_LAG_S,
) -> LatencyEstimate:
    """The image latency that lines the echo signal up with the motion signal.

    ``frame_times`` (N,) s and ``echo`` (N,) (any unit, NaN where a frame shows no echo) are the
    image side; ``pose_times`` (M,) s, increasing, and ``motion_mm`` (M,) the pose side, on the same
    clock. Frames are used where the pose stream covers every lag searched (``max_lag_s`` each
    way). Raises ValueError when the data cannot measure a lag.
    """
    frame_times, echo = np.asarray(frame_times, float), np.asarray(echo, float)
    pose_times, motion_mm = np.asarray(pose_times, float), np.asarray(motion_mm, float)
    if len(pose_times) < 2 or np.any(np.diff(pose_times) <= 0):
        raise ValueError("the pose stream needs at least two samples in increasing time order")
    covered = (frame_times - max_lag_s >= pose_times[0]) & (frame_times + max_lag_s <= pose_times[-1])
    usable = covered & np.isfinite(echo)
    if usable.sum() < MIN_FRAMES:
        raise TooFewFrames(f"{int(usable.sum())} frames show the echo while the pose stream covers them "
                           f"(of {len(echo)}); at least {MIN_FRAMES} are needed", int(usable.sum()), MIN_FRAMES)
    swing = float(np.ptp(np.interp(frame_times[usable], pose_times, motion_mm)))
    if swing < MIN_MOTION_MM:
        raise ValueError(f"the probe moved {swing:.2f} mm while the frames showed the echo, under the "
                         f"{MIN_MOTION_MM:g} mm a lag needs")
    lags = np.arange(-round(max_lag_s / GRID_S), round(max_lag_s / GRID_S) + 1) * GRID_S

    def fit(keep: np.ndarray) -> _Fit:
        if keep.sum() < MIN_FRAMES:
            raise TooFewFrames(f"{int(keep.sum())} frames agree with the motion (of {len(echo)}); "
                               f"at least {MIN_FRAMES} are needed", int(keep.sum()), MIN_FRAMES)
        if np.ptp(echo[keep]) == 0:
            raise ValueError("the echo does not move in the images")
        lag, misfit = _best_lag(echo[keep], frame_times[keep], pose_times, motion_mm, lags)
        aligned = np.interp(frame_times - lag, pose_times, motion_mm)
        slope, offset = np.polyfit(aligned[keep], echo[keep], 1)
        return _Fit(keep, lag, misfit, float(slope), np.abs(echo - (slope * aligned + offset)))

    result = fit(usable)
    for _ in range(5):
        sigma = 1.4826 * float(np.median(result.off[result.keep]))
        inliers = usable & (result.off <= OUTLIER_SIGMAS * max(sigma, 1e-9))
        if np.array_equal(inliers, result.keep):
            break
        result = fit(inliers)
    keep, lag, misfit = result.keep, result.lag, result.misfit
    t, e = frame_times[keep], echo[keep]
    r = float(_correlations(e, t, pose_times, motion_mm, np.array([lag]))[0])
    speed = np.interp(t - lag, pose_times, np.gradient(motion_mm, pose_times))
    signed = e - result.slope * np.interp(t - lag, pose_times, motion_mm)
    signed -= signed.mean()
    residual_rms = float(np.sqrt(np.sum(signed**2) / max(len(e) - 3, 1)))
    # Misfits that persist from frame to frame (a slow drift of the echo) carry less information
    # than independent ones: the standard error grows as for an AR(1) series of that correlation.
    rho = float(np.clip(np.corrcoef(signed[:-1], signed[1:])[0, 1], 0.0, 0.95)) if len(e) > 2 else 0.0
    sensitivity = float(np.sqrt(np.sum((result.slope * speed) ** 2)))
    best = int(np.argmin(misfit))
    wide = np.flatnonzero(misfit**2 > 2 * max(misfit[best] ** 2, 1e-12))
    left, right = wide[wide < best], wide[wide > best]
    halfwidth = min(best - (left[-1] if len(left) else 0), (right[0] if len(right) else len(lags) - 1) - best)
    return LatencyEstimate(
        image_latency_s=lag,
        std_error_s=float(residual_rms / sensitivity * np.sqrt((1 + rho) / (1 - rho))) if sensitivity > 0 else np.inf,
        correlation=r,
        residual=float(np.sqrt(max(1 - r**2, 0.0))),
        peak_halfwidth_s=float(halfwidth * GRID_S),
        frames_used=int(keep.sum()),
        frames_rejected=int(usable.sum() - keep.sum()),
        motion_mm=swing,
        lags_s=lags,
        misfit=misfit,
    )
