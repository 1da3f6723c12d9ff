"""A session's image latency (:mod:`core.temporal`) from the frames of its temporal motion.

A robot session that kept its pose stream and moved the probe up and down before its sweep
(frames recorded with ``phase`` "temporal", :func:`core.acquisition.plan.temporal_waypoints`)
measures its latency on those frames: over an N-wire phantom the echo is the mean row of the
labelled wire dots (every dot moves with the probe), over a tank floor with no phantom the
floor's depth (:mod:`core.temporal.echo`). Timestamps are the session's (s), rows are pixels.
"""

from __future__ import annotations

import numpy as np

from probecal.core.calibration.segment import FrameResult, segment_session
from probecal.core.errors import InputError
from probecal.core.io.session import Session
from probecal.core.temporal.echo import floor_echo_rows
from probecal.core.temporal.lag import MAX_LAG_S, LatencyEstimate, estimate_latency, principal_motion

TEMPORAL_PHASE = "temporal"
STREAM_MARGIN_S = 0.5
"""Pose samples kept (s) beyond the temporal frames' lag window, for the motion's principal axis."""


def temporal_frames(session: Session) -> list[int]:
    """The frames recorded during the temporal calibration's motion; every frame of a session
    recorded for temporal calibration alone (kind "temporal")."""
    if session.manifest.get("kind") == TEMPORAL_PHASE:
        return list(range(len(session)))
    return [i for i, r in enumerate(session.records) if r.extra.get("phase") == TEMPORAL_PHASE]


def marker_rows(results: list[FrameResult], count: int) -> np.ndarray:
    """(count,) mean row (px) of each frame's labelled markers, NaN where no pattern was found."""
    rows = np.full(count, np.nan)
    for r in results:
        if r.found and r.markers is not None:
            rows[r.index] = float(np.mean(r.markers[:, 1]))
    return rows


def session_latency(session: Session, results: list[FrameResult] | None = None,
                    max_lag_s: float = MAX_LAG_S) -> LatencyEstimate:
    """The latency measured on the session's temporal frames against its pose stream; the wire
    dots' rows come from ``results`` (the session's segmentation) or a segmentation made here.
    InputError naming the session when it has no pose stream, no temporal frames or no
    measurable lag."""
    stream = session.pose_stream()
    if stream is None:
        raise InputError(session.path, "the session kept no pose stream (posestream.jsonl): record it with "
                                       "--motion continuous to measure its latency")
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
        echo = floor_echo_rows(np.stack([session.image(i) for i in frames]))
    stream_times, poses = stream
    first, last = np.nanmin(times), np.nanmax(times)
    reach = max_lag_s + STREAM_MARGIN_S
    window = (stream_times >= first - reach) & (stream_times <= last + reach)
    during = (stream_times[window] >= first) & (stream_times[window] <= last)
    try:
        motion = principal_motion(poses[window, :3, 3], axis_from=during)
        return estimate_latency(times, echo, stream_times[window], motion, max_lag_s)
    except ValueError as exc:
        raise InputError(session.path, f"no latency measured: {exc}")
