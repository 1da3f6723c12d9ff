"""What a robot controller reports of its arm, checked as any input is (design §7): its joints,
its TCP pose and its timestamp, as ur_rtde reads them from a UR's RTDE stream.

A controller is a peer on the network like any other: a value that is not a finite number, that
no arm could have, or that contradicts the rest of what the controller says is refused before
any arithmetic is done on it, so that a session never records what its reader would refuse and
no computation on it warns or fails far from here. The checks are kept loose enough that a real
arm's own small discrepancies never trip them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from probecal.core.geometry.transforms import RIGID_TOLERANCE, is_rigid, transform_error
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.robot.rtde import pose_from_ur
from probecal.core.robot.ur3 import ArmModel

MAX_JOINT_RAD = 100.0
"""The largest joint angle (rad, in size) a controller may report: a UR's joints turn ±360°, an
endless wrist a few turns more; past this it is no angle an arm reached."""
MAX_REACH_MM = 10_000.0
"""How far from its base (mm) a controller may put its TCP: beyond the reach of any arm UR makes
(1.75 m at most)."""
MAX_ROTATION_RAD = 2.0 * np.pi
"""The longest rotation vector (rad) a controller may send: a UR's is at most half a turn."""
AGREE_MM = 20.0
AGREE_DEG = 2.0
"""How far the TCP of an arm at rest may lie from where its joints put the flange by its
kinematics: ten times what a UR's factory calibration moves its flange from its table's."""
CLOCK_LEAP_S = 5.0
"""How much further (s) a controller's clock may advance between two states than this computer's
did: a clock running fast by more has leapt."""


class StateError(ValueError):
    """A controller's report that is no arm's state; the message says what and quotes it."""


class PoseSample(NamedTuple):
    """One state of a controller: flange pose (4x4, mm), joints (6,) rad, its timestamp (s)."""

    tool_to_base: np.ndarray
    joints: np.ndarray
    timestamp_s: float


def _quoted(values: ArrayLike) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in np.ravel(np.asarray(values, dtype=float))[:6]) + "]"


def _numbers(value: ArrayLike, count: int, name: str) -> np.ndarray:
    """``value`` as (count,) floats if it is ``count`` finite numbers; StateError otherwise."""
    try:
        numbers = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise StateError(f"the controller sent {name} that is not numbers") from None
    if numbers.size != count or not np.all(np.isfinite(numbers)):
        raise StateError(f"the controller sent {name} {_quoted(numbers)}: not {count} finite numbers")
    return numbers


def _length(vector: np.ndarray) -> float:
    """The length of a finite vector, without squaring a huge component (which overflows)."""
    largest = float(np.abs(vector).max())
    return 0.0 if largest == 0.0 else largest * float(np.linalg.norm(vector / largest))


def checked_tcp(tcp_ur: ArrayLike, name: str = "a TCP pose (actual_TCP_pose)") -> np.ndarray:
    """A TCP pose in UR's [x, y, z, rx, ry, rz] (m, rad) as a 4x4 in mm, checked before it is
    converted: finite, within :data:`MAX_REACH_MM` and :data:`MAX_ROTATION_RAD`, and a rigid pose
    as a session's reader takes it. StateError naming the value (as ``name``) otherwise."""
    tcp = _numbers(tcp_ur, 6, name)
    reach_m = _length(tcp[:3])
    if reach_m * 1000.0 > MAX_REACH_MM:
        raise StateError(f"the controller sent {name} {reach_m:.6g} m from its base, beyond any arm's reach "
                         f"({MAX_REACH_MM / 1000.0:g} m)")
    turn_rad = _length(tcp[3:])
    if turn_rad > MAX_ROTATION_RAD:
        raise StateError(f"the controller sent {name} whose rotation vector of {turn_rad:.6g} rad is no rotation a "
                         f"controller states (at most {MAX_ROTATION_RAD:.6g})")
    pose = pose_from_ur(tcp)
    if not is_rigid(pose, tol=RIGID_TOLERANCE):
        raise StateError(f"the controller sent {name} {_quoted(tcp)}: not a rotation and a translation")
    return pose


def checked_sample(tcp_ur: ArrayLike, joints: ArrayLike, timestamp_s: float) -> PoseSample:
    """A controller's state as one pose sample: its TCP pose ``tcp_ur`` (:func:`checked_tcp`),
    its joints (rad: 6 finite numbers within :data:`MAX_JOINT_RAD`) and its timestamp (s: finite,
    within ``MAX_MAGNITUDE``), each checked before it is converted. StateError naming the value
    otherwise."""
    if not (np.isfinite(timestamp_s) and abs(timestamp_s) <= MAX_MAGNITUDE):
        raise StateError(f"the controller sent the timestamp {timestamp_s!r}, not a finite number of seconds "
                         f"(at most {MAX_MAGNITUDE:g})")
    q = _numbers(joints, 6, "joints (actual_q)")
    if np.abs(q).max() > MAX_JOINT_RAD:
        raise StateError(f"the controller sent joints (actual_q) beyond any arm's ({MAX_JOINT_RAD:g} rad): "
                         f"{_quoted(q)} rad")
    return PoseSample(checked_tcp(tcp_ur), q, float(timestamp_s))


def disagreement(sample: PoseSample, arm: ArmModel) -> str | None:
    """Why the TCP of an arm at rest is not where its joints put the flange by the kinematics
    ``arm`` (within :data:`AGREE_MM` and :data:`AGREE_DEG`); None when it is."""
    dt, dr = transform_error(arm.forward(sample.joints), sample.tool_to_base)
    if dt <= AGREE_MM and dr <= AGREE_DEG:
        return None
    return (f"the controller's TCP pose lies {dt:.1f} mm and {dr:.2f} deg from where its joints put the flange "
            f"(at most {AGREE_MM:g} mm and {AGREE_DEG:g} deg): its TCP is not the flange, or its joints are wrong")


class StreamClock:
    """The timestamps of a controller's stream, in the order they arrive: each new one must be
    later than the last, and must not run ahead of this computer's clock by more than
    :data:`CLOCK_LEAP_S` between two states."""

    def __init__(self) -> None:
        self._last: tuple[float, float] | None = None  # (controller time, host time), s

    def check(self, timestamp_s: float, host_s: float) -> None:
        """Take a new state's (finite) ``timestamp_s`` seen at ``host_s`` (s, this computer's
        clock); StateError when it runs backwards or leaps ahead."""
        if self._last is not None:
            last, last_host = self._last
            if timestamp_s < last:
                raise StateError(f"the controller's timestamp ran backwards, from {last:.6g} s to {timestamp_s:.6g} s")
            if timestamp_s - last > host_s - last_host + CLOCK_LEAP_S:
                raise StateError(f"the controller's clock leapt {timestamp_s - last:.6g} s ahead in "
                                 f"{host_s - last_host:.3g} s of this computer's")
        self._last = (timestamp_s, host_s)
