"""Temporal calibration of a PLUS recording made as two buffers: the video (frames and their
timestamps) and the tracker (poses and their timestamps), as PLUS fCal records them.

PLUS reports ``TrackerLagSec``, how far the tracker stream lags the video; probecal reports
``image_latency_s``, how far the video lags the tracker. The two are the same measurement with
opposite signs: ``image_latency_s = -TrackerLagSec``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from probecal.core.errors import InputError
from probecal.core.io.sequence import TrackedSequence, oriented_mf, read_sequence
from probecal.core.temporal.echo import floor_echo_rows
from probecal.core.temporal.lag import MAX_LAG_S, LatencyEstimate, estimate_latency, principal_motion

PLUS_TOOL = "Probe"
PLUS_REFERENCE = "Tracker"
"""PLUS fCal's moving signal by default: the ProbeToTracker transform."""


def _timestamps(seq: TrackedSequence, path: Path) -> np.ndarray:
    if seq.timestamps is None:
        raise InputError(path, "no Seq_FrameNNNN_Timestamp fields: a temporal calibration needs them")
    return seq.timestamps


@dataclass(frozen=True)
class PlusBuffers:
    """A PLUS video buffer and tracker buffer read for temporal calibration: ``frames`` (N, H, W)
    uint8 as PLUS holds them (MF), ``frame_times`` (N,) s, ``image_ok`` (N,); ``pose_times`` (M,)
    s, increasing, and ``positions_mm`` (M, 3) of the tool in the reference frame."""

    frames: np.ndarray
    frame_times: np.ndarray
    image_ok: np.ndarray
    pose_times: np.ndarray
    positions_mm: np.ndarray


def read_plus_buffers(video_file: str | Path, tracker_file: str | Path, tool: str = PLUS_TOOL,
                      reference: str = PLUS_REFERENCE) -> PlusBuffers:
    """The video's frames and timestamps and ``tool``'s positions in ``reference`` (composed from
    the stored transforms, as PLUS's transform repository does) where valid. InputError naming
    the file."""
    video_file, tracker_file = Path(video_file), Path(tracker_file)
    video = read_sequence(video_file)
    tracker = read_sequence(tracker_file, images=False)
    frame_times, pose_times = _timestamps(video, video_file), _timestamps(tracker, tracker_file)
    found = tracker.transform(tool, reference)
    if found is None:
        raise InputError(tracker_file, f"no {tool}To{reference} transform, stored or composed "
                                       f"(transforms: {', '.join(sorted(tracker.transforms)) or 'none'})")
    poses, valid = found
    order = np.argsort(pose_times[valid], kind="stable")
    times, positions = pose_times[valid][order], poses[valid][order][:, :3, 3]
    distinct = np.concatenate([[True], np.diff(times) > 0])
    if distinct.sum() < 2:
        raise InputError(tracker_file, f"fewer than two valid {tool}To{reference} poses")
    frames = oriented_mf(video.frames, video.fields.get("UltrasoundImageOrientation", "MF"))
    image_ok = video.image_ok if video.image_ok is not None else np.ones(len(video), bool)
    return PlusBuffers(frames, frame_times, image_ok, times[distinct], positions[distinct])


def plus_latency(
    video_file: str | Path,
    tracker_file: str | Path,
    tool: str = PLUS_TOOL,
    reference: str = PLUS_REFERENCE,
    max_lag_s: float = MAX_LAG_S,
    video_shift_s: float = 0.0,
) -> LatencyEstimate:
    """The image latency of a PLUS video buffer relative to its tracker buffer, from the probe
    moving up and down over a flat reflector (a water tank's floor): the echo is the floor's
    depth in every frame whose ImageStatus is OK, the motion ``tool``'s position in ``reference``
    along its main direction (see :func:`read_plus_buffers`). ``video_shift_s`` is added to every
    video timestamp first (to check that the latency follows it). InputError naming the file."""
    buffers = read_plus_buffers(video_file, tracker_file, tool, reference)
    echo = floor_echo_rows(buffers.frames)
    echo[~buffers.image_ok] = np.nan
    try:
        return estimate_latency(buffers.frame_times + video_shift_s, echo, buffers.pose_times,
                                principal_motion(buffers.positions_mm), max_lag_s)
    except ValueError as exc:
        raise InputError(video_file, f"no latency measured against {Path(tracker_file).name}: {exc}")
