"""Pairing frames with robot poses by timestamp.

The robot's pose stream (``tool_to_base``, 4x4 mm, at its own rate) fills a bounded, thread-safe
buffer. A frame stamped at ``t`` shows the probe where it was at ``t - latency_s`` (the image
path's delay relative to the robot clock, both in seconds on the same clock); its pose is
interpolated there: translation linear, rotation Slerp. Both times are returned so that a session
records both (``SessionWriter.append(timestamp=..., pose_timestamp=...)``).
"""

from __future__ import annotations

import bisect
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from core.robot import interpolate_pose


@dataclass(frozen=True)
class PosePairing:
    """A frame's pose: ``tool_to_base`` (4x4 mm) at ``pose_timestamp`` (s), or None and ``reason``."""

    frame_timestamp: float
    pose_timestamp: float
    tool_to_base: np.ndarray | None
    reason: str = ""


class PoseBuffer:
    """The last ``capacity`` robot poses, for looking up the pose at a frame's time.

    ``latency_s`` is the frame delay subtracted from frame timestamps; ``max_gap_s`` the widest
    gap between the two poses around that time that is still interpolated.
    """

    def __init__(self, capacity: int = 2000, latency_s: float = 0.0, max_gap_s: float = 0.05):
        self.latency_s = latency_s
        self.max_gap_s = max_gap_s
        self._times: deque[float] = deque(maxlen=capacity)
        self._poses: deque[np.ndarray] = deque(maxlen=capacity)
        self._cond = threading.Condition()

    def __len__(self) -> int:
        with self._cond:
            return len(self._times)

    def span(self) -> tuple[float, float] | None:
        """(oldest, newest) pose timestamps in s, None when empty."""
        with self._cond:
            return (self._times[0], self._times[-1]) if self._times else None

    def add(self, tool_to_base: np.ndarray, timestamp: float) -> bool:
        """Store a pose; False (not stored) when ``timestamp`` is not after the newest one.

        Raises ValueError for a pose that is not a finite 4x4.
        """
        pose = np.array(tool_to_base, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose at {timestamp} s is not a finite 4x4 matrix")
        with self._cond:
            if self._times and timestamp <= self._times[-1]:
                return False
            self._times.append(float(timestamp))
            self._poses.append(pose)
            self._cond.notify_all()
        return True

    def pose_at(self, frame_timestamp: float, wait_s: float = 0.0) -> PosePairing:
        """The pose at ``frame_timestamp - latency_s``, waiting up to ``wait_s`` for the robot's
        stream to reach that time. None with a reason when the time is outside the buffer or the
        poses around it are more than ``max_gap_s`` apart."""
        t = frame_timestamp - self.latency_s
        with self._cond:
            self._cond.wait_for(lambda: self._times and self._times[-1] >= t, wait_s)
            times, poses = self._times, self._poses

            def refuse(reason: str) -> PosePairing:
                return PosePairing(frame_timestamp, t, None, reason)

            if not times:
                return refuse("no robot poses yet")
            if t < times[0]:
                return refuse(f"{t:.3f} s is before the oldest buffered pose ({times[0]:.3f} s)")
            if t > times[-1]:
                return refuse(f"{t:.3f} s is after the newest pose ({times[-1]:.3f} s)")
            i = bisect.bisect_left(times, t)
            if times[i] == t:
                return PosePairing(frame_timestamp, t, poses[i].copy())
            t0, t1 = times[i - 1], times[i]
            if t1 - t0 > self.max_gap_s:
                return refuse(
                    f"the poses around {t:.3f} s are {t1 - t0:.3f} s apart (more than {self.max_gap_s:.3f} s)"
                )
            pose = interpolate_pose(poses[i - 1], poses[i], (t - t0) / (t1 - t0))
        return PosePairing(frame_timestamp, t, pose)
