"""A robot's pose stream: flange poses stamped by the controller's own clock, kept where they
arrive, and looked up at any time in between.

A UR controller publishes its state at 500 Hz with its own ``timestamp``; the twin publishes
its motion at ``STREAM_HZ`` on its own clock. Stamping poses with the time a busy Python thread
happened to read them would put them tens of milliseconds off whenever the machine is loaded, so
poses keep the controller's stamp, mapped once to this machine's clock (``time.time()``, s) by
:class:`ClockSync`. Poses are ``tool_to_base`` 4x4 in mm.
"""

from __future__ import annotations

import bisect
import itertools
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.geometry.transforms import interpolate_pose, transform_error

STILL_MM = 0.02
STILL_DEG = 0.01
"""Poses closer than this are the robot standing still (encoder noise is a few micrometres)."""


@dataclass(frozen=True)
class PoseSamples:
    """A stretch of a pose stream, oldest first: ``timestamps`` (n,) s on this machine's clock,
    ``tool_to_base`` (n, 4, 4) mm."""

    timestamps: np.ndarray
    tool_to_base: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps)

    @classmethod
    def empty(cls) -> PoseSamples:
        return cls(np.empty(0), np.empty((0, 4, 4)))


class ClockSync:
    """Maps a device's clock to this machine's: ``host = device + offset``.

    Every observation pairs a device timestamp with the host time it was seen at, which is never
    earlier than the true mapping; the smallest ``host - device`` over the last ``window_s`` of
    host time is the estimate (off by the fastest delivery, well under a millisecond on a
    controller's network), and the window lets it follow a slow drift between the two clocks.
    """

    def __init__(self, window_s: float = 30.0):
        self.window_s = window_s
        self._candidates: deque[tuple[float, float]] = deque()  # (host time, offset), offsets increasing
        self._lock = threading.Lock()

    def observe(self, device_time: float, host_time: float) -> None:
        """A device timestamp (s) that was known by ``host_time`` (s, this machine's clock)."""
        offset = host_time - device_time
        with self._lock:
            candidates = self._candidates
            while candidates and candidates[-1][1] >= offset:
                candidates.pop()
            candidates.append((host_time, offset))
            while candidates[0][0] < host_time - self.window_s:
                candidates.popleft()

    @property
    def offset(self) -> float | None:
        """Host minus device time (s), None before the first observation."""
        with self._lock:
            return self._candidates[0][1] if self._candidates else None


class PoseBuffer:
    """The last ``capacity`` poses of a stream, thread-safe, for looking up the pose at any time.

    A pose between two samples is interpolated (translation linear, rotation Slerp). Samples more
    than ``max_gap_s`` apart are interpolated only when the robot stood still across the gap
    (poses within ``STILL_MM`` / ``STILL_DEG``): a still robot is where it was, however long
    nobody looked, but a moving one may have been anywhere.
    """

    def __init__(self, capacity: int = 20_000, max_gap_s: float = 0.05):
        self.max_gap_s = max_gap_s
        self._times: deque[float] = deque(maxlen=capacity)
        self._poses: deque[np.ndarray] = deque(maxlen=capacity)
        self._lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._times)

    @property
    def newest(self) -> float | None:
        """Timestamp (s) of the newest pose, None when empty."""
        with self._lock:
            return self._times[-1] if self._times else None

    def span(self) -> tuple[float, float] | None:
        """(oldest, newest) pose timestamps in s, None when empty."""
        with self._lock:
            return (self._times[0], self._times[-1]) if self._times else None

    def add(self, tool_to_base: np.ndarray, timestamp: float) -> bool:
        """Store a pose; False (not stored) when ``timestamp`` is not after the newest one.

        Raises ValueError for a pose that is not a finite 4x4.
        """
        pose = np.array(tool_to_base, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose at {timestamp} s is not a finite 4x4 matrix")
        with self._lock:
            if self._times and timestamp <= self._times[-1]:
                return False
            self._times.append(float(timestamp))
            self._poses.append(pose)
        return True

    def extend(self, samples: PoseSamples) -> int:
        """Store the samples newer than the newest pose; returns how many were stored."""
        return sum(self.add(pose, t) for t, pose in zip(samples.timestamps, samples.tool_to_base))

    def since(self, after: float, offset: float = 0.0) -> PoseSamples:
        """The poses stamped after ``after`` (s), oldest first, with ``offset`` (s) added to their
        timestamps (``after`` is on that shifted clock too)."""
        with self._lock:
            start = bisect.bisect_right(self._times, after - offset)
            times = list(itertools.islice(self._times, start, None))
            poses = list(itertools.islice(self._poses, start, None))
        if not times:
            return PoseSamples.empty()
        return PoseSamples(np.array(times) + offset, np.array(poses))

    def poses_at(self, t: np.ndarray) -> np.ndarray:
        """(n, 4, 4) poses at the times ``t`` (n,) s, as :meth:`pose_at` gives them, NaN where
        it gives None: for looking up a whole kept stream at once."""
        t = np.asarray(t, dtype=float)
        with self._lock:
            times, poses = np.array(self._times), np.array(self._poses).reshape(-1, 4, 4)
        out = np.full(t.shape + (4, 4), np.nan)
        if not len(times):
            return out
        inside = np.flatnonzero((t >= times[0]) & (t <= times[-1]))
        i = np.clip(np.searchsorted(times, t[inside]), 1, max(len(times) - 1, 1))
        exact = times[np.minimum(i, len(times) - 1)] == t[inside]
        exact |= times[i - 1] == t[inside]
        on = np.where(times[i - 1] == t[inside], i - 1, i)
        out[inside[exact]] = poses[on[exact]]
        inside, i = inside[~exact], i[~exact]
        t0, t1, before, after = times[i - 1], times[i], poses[i - 1], poses[i]
        start = Rotation.from_matrix(before[:, :3, :3])
        turn = (start.inv() * Rotation.from_matrix(after[:, :3, :3])).as_rotvec()
        moved_mm = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
        moved = (moved_mm > STILL_MM) | (np.degrees(np.linalg.norm(turn, axis=1)) > STILL_DEG)
        ok = ~((t1 - t0 > self.max_gap_s) & moved)
        fraction = ((t[inside] - t0) / (t1 - t0))[ok]
        pose = np.zeros((int(ok.sum()), 4, 4))
        pose[:, :3, :3] = (start[ok] * Rotation.from_rotvec(fraction[:, None] * turn[ok])).as_matrix()
        pose[:, :3, 3] = (1 - fraction[:, None]) * before[ok, :3, 3] + fraction[:, None] * after[ok, :3, 3]
        pose[:, 3, 3] = 1.0
        out[inside[ok]] = pose
        return out

    def pose_at(self, t: float) -> tuple[np.ndarray | None, str]:
        """The pose at ``t`` (s), or None and why it cannot be known."""
        with self._lock:
            times, poses = self._times, self._poses
            if not times:
                return None, "no robot poses yet"
            if t < times[0]:
                return None, f"{t:.3f} s is before the oldest buffered pose ({times[0]:.3f} s)"
            if t > times[-1]:
                return None, f"{t:.3f} s is after the newest pose ({times[-1]:.3f} s)"
            i = bisect.bisect_left(times, t)
            if times[i] == t:
                return poses[i].copy(), ""
            t0, t1, before, after = times[i - 1], times[i], poses[i - 1], poses[i]
        if t1 - t0 > self.max_gap_s:
            moved_mm, moved_deg = transform_error(before, after)
            if moved_mm > STILL_MM or moved_deg > STILL_DEG:
                return None, (f"the robot moved {moved_mm:.2f} mm in a {t1 - t0:.3f} s gap of its pose stream "
                              f"around {t:.3f} s (gaps over {self.max_gap_s:.3f} s are trusted only when still)")
        return interpolate_pose(before, after, (t - t0) / (t1 - t0)), ""
