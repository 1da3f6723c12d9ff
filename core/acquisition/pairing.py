"""Pairing frames with robot poses by timestamp.

A frame stamped at ``t`` (s) shows the probe where it was at ``t - latency_s`` (the image path's
delay relative to the robot's clock, plus any offset of the source's clock). Its pose is read
from the robot's own pose stream (``Robot.poses_since``: stamped by the controller's clock and
kept where the data arrives), fetched in batches into a :class:`core.robot.posestream.PoseBuffer`,
and interpolated there: translation linear, rotation Slerp. Both times are returned so that a
session records both (``SessionWriter.append(timestamp=..., pose_timestamp=...)``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from probecal.core.errors import InputError
from probecal.core.io.session import Session
from probecal.core.robot.contract import PoseSource
from probecal.core.robot.posestream import PoseBuffer, PoseSamples

LOOKBACK_S = 2.0
"""How far before the first frame's time the first fetch of the pose stream reaches (s)."""
FETCH_S = 0.005
"""How often the pose stream is fetched again while a frame waits for it to catch up (s)."""
MAX_GAP_S = 0.05
"""Widest gap (s) of a robot's pose stream interpolated while it moves."""
GAP_PER_SAMPLE = 2.5
"""A kept stream sampled more slowly (a tracker's samples at the frames' times) is interpolated
across gaps of up to this many of its median sample intervals: a dropped sample, not a stall."""


@dataclass(frozen=True)
class PosePairing:
    """A frame's pose: ``tool_to_base`` (4x4 mm) at ``pose_timestamp`` (s), or None and ``reason``."""

    frame_timestamp: float
    pose_timestamp: float
    tool_to_base: np.ndarray | None
    reason: str = ""


@dataclass(frozen=True)
class Refusal:
    """A frame that could not be paired with a pose: its index in the stream, its timestamp (s)
    and why."""

    frame_index: int
    timestamp: float
    reason: str

    def __str__(self) -> str:
        return f"frame {self.frame_index}: {self.reason}"

    def to_json(self) -> dict:
        return {"source_index": self.frame_index,
                "timestamp": self.timestamp if np.isfinite(self.timestamp) else None, "reason": self.reason}


class FramePairer:
    """Pairs frames with the pose stream of ``robot`` (or of any other pose source: a tracker).

    ``latency_s`` is subtracted from frame timestamps; ``max_gap_s`` is the widest gap of the
    pose stream that is interpolated while the robot moves (any gap is, while it stands still).
    """

    def __init__(self, robot: PoseSource, latency_s: float = 0.0, max_gap_s: float = MAX_GAP_S):
        self.robot = robot
        self.latency_s = latency_s
        self.poses = PoseBuffer(max_gap_s=max_gap_s)

    def fetch(self, back_to: float) -> int:
        """Fetch the robot's poses newer than the buffer's newest (the first time: from
        ``back_to``, s); returns how many arrived."""
        newest = self.poses.newest
        return self.poses.extend(self.robot.poses_since(back_to if newest is None else newest))

    def pair(self, frame_timestamp: float, wait_s: float = 0.5) -> PosePairing:
        """The pose at ``frame_timestamp - latency_s``, waiting up to ``wait_s`` for the pose
        stream to reach that time; None with the reason when it cannot be known."""
        t = frame_timestamp - self.latency_s
        deadline = time.monotonic() + wait_s
        self.fetch(t - LOOKBACK_S)
        while (self.poses.newest or -np.inf) < t and time.monotonic() < deadline:
            time.sleep(FETCH_S)
            self.fetch(t - LOOKBACK_S)
        pose, reason = self.poses.pose_at(t)
        return PosePairing(frame_timestamp, t, pose, reason)


def stream_buffer(timestamps: np.ndarray, tool_to_base: np.ndarray, max_gap_s: float | None = None) -> PoseBuffer:
    """A pose buffer holding a whole kept pose stream ((M,) s, (M, 4, 4) mm); gaps of up to
    ``max_gap_s`` are interpolated while moving (by default ``MAX_GAP_S``, or ``GAP_PER_SAMPLE``
    sample intervals of a slower stream)."""
    if max_gap_s is None:
        interval = float(np.median(np.diff(timestamps))) if len(timestamps) > 1 else 0.0
        max_gap_s = max(MAX_GAP_S, GAP_PER_SAMPLE * interval)
    poses = PoseBuffer(capacity=max(len(timestamps), 1), max_gap_s=max_gap_s)
    poses.extend(PoseSamples(timestamps, tool_to_base))
    return poses


def paired_again(session: Session, latency_s: float) -> Session:
    """``session`` with every frame paired again, from the pose stream it kept, with the pose at
    its timestamp minus ``latency_s``; a frame the stream cannot place gets no pose. InputError
    when the session kept no pose stream."""
    stream = session.pose_stream()
    if stream is None:
        raise InputError(session.path, "the session kept no pose stream (posestream.jsonl): its frames cannot be "
                                       "paired again")
    times = np.array([np.nan if r.timestamp is None else r.timestamp - latency_s for r in session.records])
    poses = stream_buffer(*stream).poses_at(times)
    records = []
    for record, t, pose in zip(session.records, times, poses):
        if not np.isfinite(t):
            records.append(replace(record, tool_to_base=None))
            continue
        valid = bool(np.all(np.isfinite(pose)))
        records.append(replace(record, tool_to_base=pose if valid else None, pose_timestamp=float(t)))
    return replace(session, records=records)


def paired_at_latency(session: Session, latency_s: float | None) -> tuple[Session, float | None]:
    """``session`` paired again with a calibration's image latency (s) when it kept its pose
    stream (a continuous sweep, or a tracked recording's tracker samples) and the latency is
    known; else as recorded. Returns the session and the latency it was paired with (None: as
    recorded)."""
    if latency_s is None or not session.has_pose_stream:
        return session, None
    return paired_again(session, latency_s), latency_s
