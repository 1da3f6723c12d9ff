"""UR3 kinematics and motion-time model (design §4).

Standard Denavit-Hartenberg parameters from Universal Robots' published tables (the UR3 the
twin simulates, and the e-Series UR3e); link i maps
frame i into frame i-1 as ``Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``. Frame 0 is the robot ``base``
and frame 6 the flange (``tool``), so the forward kinematics is ``tool_to_base``. Lengths are in
mm, joint angles in rad; the motion limits take degrees for angular speed and acceleration.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from probecal.core.geometry.transforms import (
    interpolate_pose,
    invert_transform,
    is_rigid,
    nearest_rotation,
    rotation_angle_deg,
    rotation_angles_deg,
)


@dataclass(frozen=True)
class DhTable:
    """A UR arm's standard DH table per joint (6,): lengths ``d`` and ``a`` (mm), twists
    ``alpha`` (rad)."""

    name: str
    d: np.ndarray
    a: np.ndarray
    alpha: np.ndarray


ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
UR3 = DhTable("UR3", np.array([151.9, 0.0, 0.0, 112.35, 85.35, 81.9]),
              np.array([0.0, -243.65, -213.25, 0.0, 0.0, 0.0]), ALPHA)
UR3E = DhTable("UR3e", np.array([151.85, 0.0, 0.0, 131.05, 85.35, 92.1]),
               np.array([0.0, -243.55, -213.2, 0.0, 0.0, 0.0]), ALPHA)
ARM_TABLES = {table.name: table for table in (UR3, UR3E)}
"""The arms whose tables probecal knows, by the name a session's manifest gives (``arm``)."""
ARM_MATCH_MM = 5.0
"""How near (mm) a table's forward kinematics must put the flange the controller reports for
:func:`identify_arm` to name it: well inside the 8.5 mm (at least) by which the UR3's and the
UR3e's tables place the flange apart at any joints."""

JOINT_LIMITS = np.tile([-2.0 * np.pi, 2.0 * np.pi], (6, 1))
"""(6, 2) lower and upper limit of each joint in rad (UR3: ±360° on every joint)."""

IK_TOLERANCE_MM = 1e-6
IK_TOLERANCE_RAD = 1e-6
_SINGULAR_EPS = 1e-12


class Unreachable(ValueError):
    """No joint solution reaches the requested pose (or the motion to it)."""


@dataclass(frozen=True)
class DhDeviation:
    """How a real arm's standard DH parameters differ from UR's table, per joint (6,): joint
    zero offsets ``theta`` and twists ``alpha`` in rad, lengths ``d`` and ``a`` in mm.

    The controller computes flange poses from the table; the arm moves with its own parameters,
    so the reported and the actual flange differ systematically across the workspace (absolute
    error, on top of repeatability).
    """

    theta: np.ndarray
    d: np.ndarray
    a: np.ndarray
    alpha: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, length_mm: float, angle_deg: float) -> DhDeviation:
        """Deviations drawn uniformly within ±``length_mm`` and ±``angle_deg``."""
        angles = np.radians(rng.uniform(-angle_deg, angle_deg, (2, 6)))
        lengths = rng.uniform(-length_mm, length_mm, (2, 6))
        return cls(theta=angles[0], d=lengths[0], a=lengths[1], alpha=angles[1])

    def plus(self, other: DhDeviation | None) -> DhDeviation:
        """The deviation of an arm off by ``other`` from one off by this (arrays broadcast)."""
        if other is None:
            return self
        return DhDeviation(theta=self.theta + other.theta, d=self.d + other.d, a=self.a + other.a,
                           alpha=self.alpha + other.alpha)


def _links(q: np.ndarray, deviation: DhDeviation | None = None, table: DhTable = UR3) -> np.ndarray:
    """Standard DH link transforms (..., 6, 4, 4), frame i into frame i-1, for joints (..., 6),
    with UR's ``table`` or, given a deviation, the real arm's parameters."""
    d, a, alpha = (table.d, table.a, table.alpha) if deviation is None else (
        table.d + deviation.d, table.a + deviation.a, table.alpha + deviation.alpha)
    if deviation is not None:
        q = q + deviation.theta
    ct, st = np.cos(q), np.sin(q)
    ca, sa = np.cos(alpha), np.sin(alpha)
    links = np.zeros(q.shape + (4, 4))
    links[..., 0, :] = np.stack([ct, -st * ca, st * sa, a * ct], axis=-1)
    links[..., 1, :] = np.stack([st, ct * ca, -ct * sa, a * st], axis=-1)
    links[..., 2, 1:] = np.stack(np.broadcast_arrays(sa, ca, d), axis=-1)
    links[..., 3, 3] = 1.0
    return links


def flange_offset(deviation: DhDeviation, table: DhTable = UR3) -> np.ndarray:
    """``flange_to_tool`` (mm): the part of the real flange's error that is the same at every pose,
    seen from the flange the controller reports (link 6's own deviations). The real flange is
    ``E(q) @ tool_to_base @ flange_offset``, with E(q) (base frame) from joints 1-5. To the controller
    this constant is part of the probe mount: a hand-eye calibration finds it with the mount, and
    sweeps that use the calibration with reported poses put the image where it really is.
    Deviations of shape (..., 6) give (..., 4, 4)."""
    zero = np.zeros(6)
    return invert_transform(_links(zero, table=table)[5]) @ _links(zero, deviation, table)[..., 5, :, :]


def _joints(q: ArrayLike) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape[-1:] != (6,):
        raise ValueError(f"expected 6 joint angles, got shape {q.shape}")
    return q


def link_frames(q: ArrayLike, deviation: DhDeviation | None = None, table: DhTable = UR3) -> list[np.ndarray]:
    """The 7 frames ``link_i_to_base`` (mm) for joints q (rad): the base, then after each joint;
    with a ``deviation``, those of the real arm rather than UR's ``table``.

    q may be a batch (..., 6); each frame then has shape (..., 4, 4).
    """
    q = _joints(q)
    links = _links(q, deviation, table)
    frames = [np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4))]
    for i in range(6):
        frames.append(frames[-1] @ links[..., i, :, :])
    return frames


def forward_kinematics(q: ArrayLike, deviation: DhDeviation | None = None, table: DhTable = UR3) -> np.ndarray:
    """``tool_to_base`` (flange pose, mm) for joints q (rad) by ``table``; (..., 4, 4) for a batch
    (..., 6). With a ``deviation``, where the real arm puts the flange."""
    return link_frames(q, deviation, table)[-1]


def identify_arm(joints: ArrayLike, tool_to_base: ArrayLike) -> DhTable | None:
    """The known table whose forward kinematics puts the flange at joints ``joints`` (6,) rad where
    the controller reports it (``tool_to_base``, mm, of the same state) within ``ARM_MATCH_MM``;
    None for an arm probecal does not know."""
    position = np.asarray(tool_to_base, dtype=float)[:3, 3]
    for table in ARM_TABLES.values():
        if np.linalg.norm(forward_kinematics(joints, table=table)[:3, 3] - position) < ARM_MATCH_MM:
            return table
    return None


def _matching(a_to_b: np.ndarray, a_to_b_ref: np.ndarray) -> np.ndarray:
    """(k,) True where each of the poses ``a_to_b`` (k, 4, 4) agrees with ``a_to_b_ref`` within
    ``IK_TOLERANCE_MM`` and ``IK_TOLERANCE_RAD``."""
    dt = np.linalg.norm(a_to_b[:, :3, 3] - a_to_b_ref[:3, 3], axis=1)
    dr = np.radians(rotation_angles_deg(np.swapaxes(a_to_b[:, :3, :3], 1, 2) @ a_to_b_ref[:3, :3]))
    return (dt < IK_TOLERANCE_MM) & (dr < IK_TOLERANCE_RAD)


def _wrap(angles: np.ndarray) -> np.ndarray:
    """Angles wrapped into (-pi, pi]."""
    return -np.remainder(-np.asarray(angles) + np.pi, 2.0 * np.pi) + np.pi


def check_pose(tool_to_base: ArrayLike) -> np.ndarray:
    """The pose as a float 4x4, its rotation the rotation nearest the one given: a pose written
    to a few digits (a lab's table, a controller's report) is rigid only to that precision, and
    the joints that reach it are those of the rigid pose nearest it. Raises Unreachable unless it
    is a finite rigid transform to ``is_rigid``'s tolerance."""
    pose = np.array(tool_to_base, dtype=float)
    if not is_rigid(pose):
        raise Unreachable("target pose is not a finite rigid 4x4 transform")
    pose[:3, :3] = nearest_rotation(pose[:3, :3])
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    return pose


def _arm_joints(tool_to_link1: np.ndarray, q1: float, q5: float, q6: float,
                table: DhTable) -> tuple[list[np.ndarray], float]:
    """Both elbow solutions (q2, q3, q4) for given q1, q5, q6, and how far (mm) the wrist lies
    out of the elbow's reach (0 within it: then the solutions; out of it, none).

    ``tool_to_link1`` is the target flange pose in frame 1 (after joint 1).
    """
    wrist = _links(np.array([0.0, 0.0, 0.0, 0.0, q5, q6]), table=table)
    t14 = tool_to_link1 @ invert_transform(wrist[4] @ wrist[5])
    p13 = (t14 @ np.array([0.0, -table.d[3], 0.0, 1.0]))[:2]
    a2, a3 = table.a[1], table.a[2]
    c3 = (p13 @ p13 - a2 ** 2 - a3 ** 2) / (2.0 * a2 * a3)
    if abs(c3) > 1.0 + 1e-12:
        span = float(np.linalg.norm(p13))
        return [], max(span - (abs(a2) + abs(a3)), abs(abs(a2) - abs(a3)) - span)
    phi = np.arctan2(t14[1, 0], t14[0, 0])
    out = []
    for q3 in (np.arccos(np.clip(c3, -1.0, 1.0)), -np.arccos(np.clip(c3, -1.0, 1.0))):
        q2 = np.arctan2(p13[1], p13[0]) - np.arctan2(a3 * np.sin(q3), a2 + a3 * np.cos(q3))
        out.append(np.array([q1, q2, q3, phi - q2 - q3, q5, q6]))
    return out, 0.0


def inverse_kinematics(tool_to_base: np.ndarray, q6_free: float = 0.0, table: DhTable = UR3) -> np.ndarray:
    """All analytic joint solutions (k, 6) in rad, k <= 8, for a flange pose ``tool_to_base`` (mm)
    of the arm of ``table``.

    Each solution is one configuration (shoulder, wrist, elbow) with every joint wrapped into
    (-pi, pi], which lies inside ``JOINT_LIMITS``; the 2π-shifted equivalents are not listed
    (``closest_ik`` considers them). At a wrist singularity (sin q5 = 0) q6 is free and set to
    ``q6_free``. Every solution reproduces the pose within ``IK_TOLERANCE_MM`` and
    ``IK_TOLERANCE_RAD``. Raises Unreachable when there is none.
    """
    pose = check_pose(tool_to_base)
    shoulder = table.d[3]
    p05 = pose @ np.array([0.0, 0.0, -table.d[5], 1.0])
    radius = np.hypot(p05[0], p05[1])
    if radius < shoulder:
        raise Unreachable(f"wrist centre is {radius:.1f} mm from the base axis, {shoulder - radius:.1f} mm inside the "
                          f"{shoulder} mm shoulder offset")
    psi = np.arctan2(p05[1], p05[0])
    phi = np.arccos(shoulder / radius)
    candidates, out_mm = [], np.inf
    for q1 in (psi + phi + np.pi / 2, psi - phi + np.pi / 2):
        # Joint 2's axis seen from the tool is (cos q6 sin q5, -sin q6 sin q5, cos q5).
        axis2 = pose[:3, :3].T @ np.array([np.sin(q1), -np.cos(q1), 0.0])
        tool_to_link1 = invert_transform(_links(np.array([q1, 0.0, 0.0, 0.0, 0.0, 0.0]), table=table)[0]) @ pose
        sin5 = np.hypot(axis2[0], axis2[1])
        wrists = ([(np.arctan2(0.0, axis2[2]), q6_free)] if sin5 < _SINGULAR_EPS else
                  [(sign * np.arctan2(sin5, axis2[2]), np.arctan2(-sign * axis2[1], sign * axis2[0]))
                   for sign in (1.0, -1.0)])
        for q5, q6 in wrists:
            found, out = _arm_joints(tool_to_link1, q1, q5, q6, table)
            candidates.extend(found)
            out_mm = min(out_mm, out)
    wrapped = _wrap(np.array(candidates).reshape(-1, 6))
    solutions = wrapped[_matching(forward_kinematics(wrapped, table=table), pose)] if len(wrapped) else wrapped
    if not len(solutions):
        p = pose[:3, 3]
        how_far = f"its wrist {out_mm:.1f} mm out of the elbow's reach" if np.isfinite(out_mm) and out_mm > 0 else \
            "no joints reproduce it"
        raise Unreachable(f"pose at ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm is out of the {table.name}'s reach: "
                          f"{how_far}")
    return solutions


def _nearest_equivalent(solutions: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Each joint of each solution shifted by a multiple of 2π, within limits, nearest q_ref."""
    shifted = solutions[..., None] + 2.0 * np.pi * np.array([-1.0, 0.0, 1.0])
    inside = (shifted >= JOINT_LIMITS[:, :1]) & (shifted <= JOINT_LIMITS[:, 1:])
    gap = np.where(inside, np.abs(shifted - q_ref[:, None]), np.inf)
    return np.take_along_axis(shifted, gap.argmin(axis=-1)[..., None], axis=-1)[..., 0]


def closest_ik(tool_to_base: np.ndarray, q_ref: ArrayLike, table: DhTable = UR3) -> np.ndarray:
    """The joint solution (6,) in rad for ``tool_to_base`` nearest ``q_ref`` in joint space.

    Joints may take any 2π-equivalent value inside ``JOINT_LIMITS``; the nearest is chosen per
    joint, then the configuration with the smallest Euclidean joint distance. At a wrist
    singularity q6 keeps its reference value. Raises Unreachable when there is no solution.
    """
    q_ref = _joints(q_ref)
    candidates = _nearest_equivalent(inverse_kinematics(tool_to_base, q6_free=q_ref[5], table=table), q_ref)
    return candidates[np.linalg.norm(candidates - q_ref, axis=1).argmin()]


REFINE_MM = 1e-9
REFINE_RAD = 1e-12
"""How closely (mm, rad) :meth:`ArmModel.closest_ik` meets the pose on a calibrated arm, where
its parameters' size lets floating point get that close (else within ``IK_TOLERANCE_MM``)."""
REFINE_STEPS = 8
_JACOBIAN_STEP_RAD = 1e-7


def _pose_residual(target: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(..., 6) how far each of ``poses`` (..., 4, 4) is from ``target``, in the base frame:
    translation (mm) and the rotation that turns it onto the target as its axis times the sine
    of its angle (zero only when the orientations agree; the rotation vector to first order,
    which is all Newton's method needs this close to the solution)."""
    r = target[:3, :3] @ np.swapaxes(poses[..., :3, :3], -1, -2)
    sine_axis = 0.5 * np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                                r[..., 1, 0] - r[..., 0, 1]], axis=-1)
    return np.concatenate([target[:3, 3] - poses[..., :3, 3], sine_axis], axis=-1)


def _within(residual: np.ndarray, mm: float, rad: float) -> bool:
    return bool(np.linalg.norm(residual[:3]) < mm and np.linalg.norm(residual[3:]) < rad)


@dataclass(frozen=True)
class ArmModel:
    """The kinematics a UR controller computes the flange pose with: UR's ``table`` and, for a
    factory-calibrated arm, its ``deviation`` from that table (None: the table as published).

    Poses are ``tool_to_base`` (4x4, mm), joints rad."""

    table: DhTable = UR3
    deviation: DhDeviation | None = None

    def forward(self, q: ArrayLike) -> np.ndarray:
        """``tool_to_base`` (mm) at joints q (rad); (..., 4, 4) for a batch (..., 6)."""
        return forward_kinematics(q, self.deviation, self.table)

    def closest_ik(self, tool_to_base: np.ndarray, q_ref: ArrayLike) -> np.ndarray:
        """The joints (6,) rad nearest ``q_ref`` that put the flange at ``tool_to_base``: the
        table's analytic solution (:func:`closest_ik`), then, on a calibrated arm, Newton steps on
        its forward kinematics until the pose is met within ``REFINE_MM`` and ``REFINE_RAD``.
        Raises Unreachable when there is no solution."""
        q = closest_ik(tool_to_base, q_ref, self.table)
        if self.deviation is None:
            return q
        target = check_pose(tool_to_base)
        for _ in range(REFINE_STEPS):
            residual = _pose_residual(target, self.forward(q))
            if _within(residual, REFINE_MM, REFINE_RAD):
                return q
            nudged = self.forward(q + _JACOBIAN_STEP_RAD * np.eye(6))
            jacobian = (residual[:, None] - _pose_residual(target, nudged).T) / _JACOBIAN_STEP_RAD
            q = q + np.linalg.lstsq(jacobian, residual, rcond=None)[0]
        if _within(_pose_residual(target, self.forward(q)), IK_TOLERANCE_MM, IK_TOLERANCE_RAD):
            return q
        raise Unreachable("the calibrated kinematics do not converge on the pose (a singularity)")

    def dh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The controller's absolute DH parameters (6,) each: joint offsets theta (rad), lengths
        a and d (mm) and twists alpha (rad), as KinematicsInfo states them (in metres there)."""
        dev = self.deviation or DhDeviation(*np.zeros((4, 6)))
        return dev.theta, self.table.a + dev.a, self.table.d + dev.d, self.table.alpha + dev.alpha

    @classmethod
    def from_dh(cls, theta: ArrayLike, a: ArrayLike, d: ArrayLike, alpha: ArrayLike,
                joints: ArrayLike) -> ArmModel | None:
        """The model of a controller's absolute DH parameters (6,) each (rad, mm): the table
        :func:`identify_arm` names at ``joints`` (rad) for the flange those parameters put there,
        and the deviation from it; None for an arm probecal does not know."""
        theta, a, d, alpha = (np.asarray(v, dtype=float) for v in (theta, a, d, alpha))
        absolute = DhDeviation(theta=theta, d=d, a=a, alpha=alpha)
        zero = DhTable("absolute", np.zeros(6), np.zeros(6), np.zeros(6))
        table = identify_arm(joints, forward_kinematics(joints, absolute, zero))
        if table is None:
            return None
        return cls(table, DhDeviation(theta=theta, d=d - table.d, a=a - table.a, alpha=alpha - table.alpha))


NOMINAL_UR3 = ArmModel()
"""The UR3 as UR's table has it: what the twin's controller computes with."""


def trapezoid_duration(distance: float, v_max: float, a_max: float) -> float:
    """Time (s) to travel ``distance`` from rest to rest with speed and acceleration limits.

    The profile is triangular when the distance is too short to reach ``v_max``. Units are any
    consistent length (or angle) unit per second.
    """
    _check_profile(distance, v_max, a_max)
    if distance <= v_max**2 / a_max:
        return 2.0 * float(np.sqrt(distance / a_max))
    return distance / v_max + v_max / a_max


def trapezoid_position(t: float, distance: float, v_max: float, a_max: float) -> float:
    """Distance travelled at time t (s) along the profile of ``trapezoid_duration``."""
    duration = trapezoid_duration(distance, v_max, a_max)
    v_peak = min(v_max, float(np.sqrt(distance * a_max)))
    t_acc = v_peak / a_max
    if t <= 0.0:
        return 0.0
    if t >= duration:
        return float(distance)
    if t < t_acc:
        return 0.5 * a_max * t**2
    if t <= duration - t_acc:
        return 0.5 * a_max * t_acc**2 + v_peak * (t - t_acc)
    return distance - 0.5 * a_max * (duration - t) ** 2


def _check_profile(distance: float, v_max: float, a_max: float) -> None:
    if not (np.isfinite(distance) and distance >= 0.0):
        raise ValueError(f"distance must be finite and >= 0, got {distance}")
    if not (np.isfinite(v_max) and v_max > 0.0 and np.isfinite(a_max) and a_max > 0.0):
        raise ValueError(f"speed and acceleration must be finite and > 0, got {v_max}, {a_max}")


@dataclass(frozen=True)
class MotionLimits:
    """moveL limits in tool space (mm, deg, s), UR-like defaults, and the settle time per move."""

    linear_speed_mm_s: float = 100.0
    linear_accel_mm_s2: float = 500.0
    angular_speed_deg_s: float = 60.0
    angular_accel_deg_s2: float = 300.0
    settle_s: float = 0.1

    def __post_init__(self) -> None:
        _check_profile(0.0, self.linear_speed_mm_s, self.linear_accel_mm_s2)
        _check_profile(0.0, self.angular_speed_deg_s, self.angular_accel_deg_s2)
        if not (np.isfinite(self.settle_s) and self.settle_s >= 0.0):
            raise ValueError(f"settle time must be finite and >= 0, got {self.settle_s}")

    def scaled(self, fraction: float) -> MotionLimits:
        """These limits with every speed and acceleration times ``fraction`` (the console's and
        ``probecal sweep --speed``'s fraction of the UR defaults)."""
        return replace(self, linear_speed_mm_s=self.linear_speed_mm_s * fraction,
                       linear_accel_mm_s2=self.linear_accel_mm_s2 * fraction,
                       angular_speed_deg_s=self.angular_speed_deg_s * fraction,
                       angular_accel_deg_s2=self.angular_accel_deg_s2 * fraction)


def _dominant_profile(
    start_tool_to_base: np.ndarray, end_tool_to_base: np.ndarray, limits: MotionLimits
) -> tuple[float, float, float]:
    """(distance, speed, accel) of whichever of translation (mm) and rotation (deg) takes longer."""
    translation = (
        float(np.linalg.norm(end_tool_to_base[:3, 3] - start_tool_to_base[:3, 3])),
        limits.linear_speed_mm_s,
        limits.linear_accel_mm_s2,
    )
    rotation = (
        rotation_angle_deg(start_tool_to_base[:3, :3].T @ end_tool_to_base[:3, :3]),
        limits.angular_speed_deg_s,
        limits.angular_accel_deg_s2,
    )
    return max(translation, rotation, key=lambda profile: trapezoid_duration(*profile))


def linear_move_motion_time(
    start_tool_to_base: np.ndarray, end_tool_to_base: np.ndarray, limits: MotionLimits
) -> float:
    """Motion time (s) of a moveL: the longer of the translational and rotational trapezoids."""
    return trapezoid_duration(*_dominant_profile(start_tool_to_base, end_tool_to_base, limits))


def linear_move_duration(
    start_tool_to_base: np.ndarray, end_tool_to_base: np.ndarray, limits: MotionLimits
) -> float:
    """Time (s) a moveL takes on the robot: motion time plus the settle time."""
    return linear_move_motion_time(start_tool_to_base, end_tool_to_base, limits) + limits.settle_s


def linear_move_progress(
    t: float, start_tool_to_base: np.ndarray, end_tool_to_base: np.ndarray, limits: MotionLimits
) -> float:
    """Fraction (0..1) of a moveL path covered t seconds after its start (synchronised axes)."""
    distance, v_max, a_max = _dominant_profile(start_tool_to_base, end_tool_to_base, limits)
    if distance == 0.0:
        return 1.0
    return trapezoid_position(t, distance, v_max, a_max) / distance


PATH_SAMPLES = 20
MAX_JOINT_JUMP_DEG = 30.0


def linear_path_joints(
    start_joints: np.ndarray,
    target_tool_to_base: np.ndarray,
    samples: int = PATH_SAMPLES,
    max_jump_deg: float = MAX_JOINT_JUMP_DEG,
    arm: ArmModel = NOMINAL_UR3,
) -> np.ndarray:
    """Joints (samples + 1, 6) in rad along the straight line from the flange at ``start_joints``
    to the target, by the kinematics of ``arm``.

    Each sample is the IK solution closest to the previous one. Raises Unreachable when a sample
    has no solution or a joint would jump more than ``max_jump_deg`` (a configuration change).
    """
    start_joints = np.asarray(start_joints, dtype=float)
    target = check_pose(target_tool_to_base)
    fractions = np.arange(1, samples + 1) / samples
    poses = interpolate_pose(arm.forward(start_joints), target, fractions)
    path = [start_joints]
    for fraction, pose in zip(fractions, poses):
        try:
            q = arm.closest_ik(pose, path[-1])
        except Unreachable as exc:
            raise Unreachable(f"the straight path fails at {fraction:.0%}: {exc}") from exc
        jump = np.degrees(np.abs(q - path[-1]))
        if jump.max() > max_jump_deg:
            raise Unreachable(
                f"joint {jump.argmax() + 1} would jump {jump.max():.0f} deg at {fraction:.0%} "
                "of the straight path (configuration change)"
            )
        path.append(q)
    return np.array(path)
