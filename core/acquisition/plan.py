"""Acquisition plans: calibration poses over an N-wire phantom and straight volume sweeps.

Poses are flange poses ``tool_to_base`` (4x4, mm). A plan is built from the *nominal* set-up
(where the phantom is meant to sit, the probe mount's design calibration); the visibility margin
absorbs the difference from the true set-up.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from probecal.core.errors import InputError
from probecal.core.geometry.probe import Probe
from probecal.core.geometry.setup import Setup
from probecal.core.geometry.transforms import invert_transform, make_transform
from probecal.core.io.jsonio import (
    expect_integer,
    expect_list,
    expect_matrix,
    expect_number,
    optional,
    read_json,
    required,
)
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.trajectory import blended_path
from probecal.core.robot.ur3 import MotionLimits, Unreachable, closest_ik, forward_kinematics, linear_move_duration
from probecal.core.twin.twin import smooth_offsets

FRAME_CAPTURE_S = 0.1  # time to grab and store one frame after the robot settles


@dataclass(frozen=True)
class PoseRanges:
    """Perturbation ranges about the nominal pose, phantom axes: the thesis's Table 3.2 (±10 mm,
    ±15° about each axis, ±3 mm in depth, ``THESIS_RANGES``), but ±22° about the two horizontal
    axes, which tilt the image: on twin ``bench`` seeds 0-19 the image corners come 0.19 mm from
    the truth instead of 0.21, for a second more of UR3 time (``benchmarks/bench_plan.py``)."""

    translation_mm: tuple[float, float, float] = (10.0, 10.0, 3.0)
    rotation_deg: tuple[float, float, float] = (22.0, 22.0, 15.0)
    margin_mm: float = 1.5  # how far inside the image every wire's crossing must be (planned set-up)


THESIS_RANGES = PoseRanges(rotation_deg=(15.0, 15.0, 15.0))


@dataclass(frozen=True)
class Plan:
    """An ordered list of flange poses with the estimated robot time (s)."""

    poses: list[np.ndarray]
    duration_s: float


@dataclass(frozen=True)
class SweepPlan:
    """The poses of a whole acquisition in order, each with its pass (volume scans have several),
    and the estimated robot time (s); a self-check's also with each pose's ``views`` (an index into
    the wrist angles its passes are swept from, :class:`ProbeView`; None: one view, as planned).
    Stored in a session as ``plan.json`` so that an interrupted sweep can be resumed."""

    poses: list[np.ndarray]
    passes: list[int]
    duration_s: float
    views: list[int] | None = None

    @staticmethod
    def from_plans(plans: list[Plan], views: list[int] | None = None) -> SweepPlan:
        """The plans one after the other, each a pass; ``views``, the view of each plan."""
        poses = [pose for plan in plans for pose in plan.poses]
        passes = [k for k, plan in enumerate(plans) for _ in plan.poses]
        viewed = None if views is None else [views[k] for k in passes]
        return SweepPlan(poses, passes, sum(plan.duration_s for plan in plans), viewed)

    @property
    def n_passes(self) -> int:
        return len(set(self.passes))

    def view_of_pass(self, pass_index: int) -> int | None:
        """The view a pass is swept from (None: the plan states no views)."""
        return None if self.views is None else self.views[self.passes.index(pass_index)]

    def summary(self) -> dict:
        """The manifest's ``plan``: (passes,) (views,) poses and the estimated robot time."""
        summary = {"poses": len(self.poses), "estimated_robot_time_s": round(self.duration_s, 1)}
        if self.views is not None:
            summary = {"views": len(set(self.views)), **summary}
        return {"passes": self.n_passes, **summary} if self.n_passes > 1 else summary

    def to_dict(self) -> dict:
        views = {} if self.views is None else {"views": self.views}
        return {"poses": [p.tolist() for p in self.poses], "passes": self.passes, **views,
                "duration_s": self.duration_s}

    @staticmethod
    def load(path: Path) -> SweepPlan:
        """A plan from its JSON file; InputError naming the file and the field if it is not one:
        ``poses`` rigid 4x4 flange poses, ``passes`` one whole number (from 0) per pose, ``views``
        (optional) one whole number (from 0) per pose, ``duration_s`` a non-negative number."""
        data = read_json(path)
        poses = required(data, "poses", expect_list, path)
        passes = required(data, "passes", expect_list, path, length=len(poses))
        views = optional(data, "views", expect_list, path, length=len(poses))
        duration = required(data, "duration_s", expect_number, path)
        if duration < 0:
            raise InputError(path, f"duration_s must not be negative, got {duration:g}")
        return SweepPlan(
            [expect_matrix(p, path, f"poses[{i}]", rigid=True) for i, p in enumerate(poses)],
            [expect_integer(k, path, f"passes[{i}]", minimum=0) for i, k in enumerate(passes)],
            duration,
            None if views is None else [expect_integer(k, path, f"views[{i}]", minimum=0) for i, k in enumerate(views)],
        )


def crossings_in_view(
    setup: Setup, image_to_phantom: np.ndarray, margin_mm: float = 1.5, min_separation_mm: float = 2.0
) -> bool:
    """True when every wire crosses the image inside the field of view (a fan image's fan), with
    well separated dots."""
    sx, sy = setup.probe.true_spacing_mm
    width, depth = setup.probe.width_px * sx, setup.probe.height_px * sy
    points = setup.phantom.crossing_points(image_to_phantom)
    if not np.all(np.isfinite(points)):
        return False
    inside = (
        (points[:, 0] > margin_mm)
        & (points[:, 0] < width - margin_mm)
        & (points[:, 1] > margin_mm)
        & (points[:, 1] < depth - margin_mm)
    )
    fan = setup.probe.fan
    if fan is not None:  # and inside the fan, as far from its lines and arcs
        inside &= fan.contains(setup.probe.pixels_from_mm(points), margin_mm / setup.probe.nominal_spacing_mm[0])
    if not inside.all():
        return False
    gaps = np.linalg.norm(points[:, None] - points[None], axis=2) + np.eye(len(points)) * 1e9
    return bool(gaps.min() >= min_separation_mm)


def perturbed(image_to_phantom: np.ndarray, pivot_image: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Rotate (deg, xyz phantom axes) about a pivot given in image mm, then translate (mm)."""
    pivot = image_to_phantom[:3, :3] @ pivot_image + image_to_phantom[:3, 3]
    rotation = Rotation.from_euler("xyz", offsets[3:], degrees=True).as_matrix()
    about_pivot = make_transform(rotation, pivot + offsets[:3] - rotation @ pivot)
    return about_pivot @ image_to_phantom


def order_poses(poses: list[np.ndarray], start: np.ndarray) -> list[np.ndarray]:
    """Greedy nearest-neighbour order (position plus 1 mm per degree) to shorten the path."""
    stacked = np.array(poses).reshape(-1, 4, 4)
    remaining = list(range(len(poses)))
    order, current = [], start
    while remaining:
        left = stacked[remaining]
        turn_deg = np.degrees(Rotation.from_matrix(left[:, :3, :3] @ current[:3, :3].T).magnitude())
        cost = np.linalg.norm(left[:, :3, 3] - current[:3, 3], axis=1) + turn_deg
        current = poses[remaining.pop(int(np.argmin(cost)))]
        order.append(current)
    return order


def pose_durations_s(poses: list[np.ndarray], start: np.ndarray, limits: MotionLimits | None = None) -> np.ndarray:
    """(N,) robot time (s) to reach each of ``poses`` from the one before (the first from
    ``start``) with a linear move, settle and capture its frame."""
    limits = limits or MotionLimits()
    steps = np.zeros(len(poses))
    for k, pose in enumerate(poses):
        steps[k] = linear_move_duration(start if k == 0 else poses[k - 1], pose, limits) + FRAME_CAPTURE_S
    return steps


def plan_duration(poses: list[np.ndarray], start: np.ndarray, limits: MotionLimits | None = None) -> float:
    """Robot time (s) to visit ``poses`` from ``start`` with linear moves, settling and capture."""
    return float(pose_durations_s(poses, start, limits).sum())


def pivot_mm(setup: Setup) -> np.ndarray:
    """Where the plans turn the probe about: the image centre, 25 mm deep (image mm)."""
    return np.array([setup.probe.width_px * setup.probe.true_spacing_mm[0] / 2, 25.0, 0.0])


HOPELESS_ROUNDS = 10
"""Rounds of candidates a calibration plan draws before it may give up (see :func:`calibration_plan`)."""


def calibration_plan(
    setup: Setup,
    n_poses: int,
    seed: int | np.random.Generator = 0,
    ranges: PoseRanges = PoseRanges(),
    start_joints: np.ndarray = HOME_JOINTS,
    limits: MotionLimits | None = None,
    max_candidates: int = 200,
    progress: Callable[[int, int], None] | None = None,
) -> Plan:
    """``n_poses`` diverse, reachable flange poses that keep every wire in view.

    Candidates come from a Latin hypercube over the ranges (so they spread evenly over all six
    axes), about a pivot at the image centre; invisible or unreachable ones are skipped, up to
    ``max_candidates`` rounds of them. After :data:`HOPELESS_ROUNDS` rounds the plan is given up
    when the poses found so far, kept up, would not find half of ``n_poses`` in all of them (a
    phantom whose wires the ranges seldom keep in view). ``progress(poses found, n_poses)`` is
    told of each pose found (and may raise to end the work).
    """
    if n_poses < 1:
        raise ValueError("a plan needs at least one pose")
    pivot = pivot_mm(setup)
    bounds = np.array([*ranges.translation_mm, *ranges.rotation_deg])
    sampler = qmc.LatinHypercube(d=6, seed=seed)
    accepted: list[np.ndarray] = []
    joints = np.asarray(start_joints, dtype=float)
    for rounds in range(max_candidates):
        if rounds >= HOPELESS_ROUNDS and 2 * len(accepted) * max_candidates < n_poses * rounds:
            break
        for unit in sampler.random(max(n_poses, 16)):
            candidate = perturbed(setup.image_to_phantom, pivot, (2 * unit - 1) * bounds)
            if not crossings_in_view(setup, candidate, margin_mm=ranges.margin_mm):
                continue
            pose = setup.tool_to_base(candidate)
            try:
                closest_ik(pose, joints)
            except Unreachable:
                continue
            accepted.append(pose)
            if progress is not None:
                progress(len(accepted), n_poses)
            if len(accepted) == n_poses:
                break
        if len(accepted) == n_poses:
            break
    if len(accepted) < n_poses:
        raise ValueError(
            f"only {len(accepted)} of {n_poses} poses keep every wire in view and are reachable"
        )
    start = forward_kinematics(joints)
    poses = order_poses(accepted, start)
    return Plan(poses, plan_duration(poses, start, limits))


FREEHAND_RANGES = PoseRanges(translation_mm=(2.0, 4.0, 1.0), rotation_deg=(0.7, 0.6, 1.4))
"""How a hand wanders the probe over the phantom on top of its sweep and its pivot, where the
robot's plan turns it +-15 to +-22 deg about every axis (the turns: the median over PLUS's
recordings of how far each axis's turn strays from its slope with the sweep, as a uniform
spread's RMS)."""
HAND_PIVOT_DEG_PER_MM = ((0.12, 0.28), (0.04, 0.11), (0.06, 0.23))
"""A hand pivots at the wrist or elbow as it slides the probe along the wires, so it turns the
probe about each phantom axis (x across the wires, y along them, z up) by a slope (deg per mm of
sweep) drawn within these, either way: the range of the slopes over PLUS's five recordings
(``benchmarks/bench_realism.py``'s *turn with the sweep*)."""
HAND_CYCLES = 0.5
"""The hand's slowest wander: this many periods over a recording (its halves cover different
poses, as those of PLUS's recordings do: each half rotates about half as much as the whole)."""
HAND_SWEEP_MM = 21.0
"""The hand sweeps the probe this far along the wires (phantom y, mm) over a recording, from one
end to the other. Together with ``FREEHAND_RANGES`` and ``HAND_PIVOT_DEG_PER_MM`` it moves the
probe as PLUS's recordings do (``benchmarks/bench_realism.py``'s hand rows: the image centre
4.9-8.8 mm about its mean along the wires, the two halves' means apart along them, the image
turning about 1 deg RMS per axis, that turn following the sweep)."""


def hand_path(setup: Setup, n_poses: int, seed: int = 0, ranges: PoseRanges = FREEHAND_RANGES,
              cycles: float = HAND_CYCLES, path: int = 0, sweep_mm: float = HAND_SWEEP_MM) -> list[np.ndarray]:
    """``n_poses`` tool poses (mm, base frame) along a hand's smooth path over the phantom.

    Each of the six axes (phantom axes, about a pivot at the image centre, as in
    :func:`calibration_plan`) wanders smoothly (:func:`~probecal.core.twin.twin.smooth_offsets`
    with ``cycles``), scaled to the RMS of a uniform spread over ``ranges``; along the wires the
    probe also sweeps ``sweep_mm`` from one end to the other (half a cosine, either way), turning
    with the sweep about each axis as the hand pivots (``HAND_PIVOT_DEG_PER_MM``; the wander keeps
    none of its own turn with the sweep, so the pivot's slope is the path's). Where
    the path loses a wire from view the frames are skipped; the poses are spread evenly over the
    rest. ``path`` draws another of the seed's paths (a second recording of the same bench)."""
    if n_poses < 1:
        raise ValueError("a path needs at least one pose")
    rng = np.random.default_rng([seed, 17, path])
    spread = [bound / np.sqrt(3.0) for bound in (*ranges.translation_mm, *ranges.rotation_deg)]
    offsets = smooth_offsets(rng, 4 * n_poses, spread, cycles)
    sweep = rng.choice([-0.5, 0.5]) * sweep_mm * np.cos(np.linspace(0.0, np.pi, len(offsets)))
    offsets[:, 1] += sweep
    low, high = np.array(HAND_PIVOT_DEG_PER_MM).T
    centred = sweep - sweep.mean()
    wander = offsets[:, 3:] - np.outer(centred, centred @ offsets[:, 3:] / (centred @ centred))  # none with the sweep
    offsets[:, 3:] = wander + np.outer(sweep, rng.uniform(low, high) * rng.choice([-1.0, 1.0], 3))
    pivot = pivot_mm(setup)
    seen = [c for c in (perturbed(setup.image_to_phantom, pivot, o) for o in offsets) if crossings_in_view(setup, c)]
    if len(seen) < n_poses:
        raise ValueError(f"only {len(seen)} of {n_poses} poses along the hand's path keep every wire in view")
    return [setup.tool_to_base(seen[k]) for k in np.linspace(0, len(seen) - 1, n_poses).round().astype(int)]

TEMPORAL_AMPLITUDE_MM = 5.0
TEMPORAL_STROKES = 10
"""The temporal calibration's motion: this many strokes, each ``2 * TEMPORAL_AMPLITUDE_MM`` long, up
and down along the image's depth axis about the centre pose, then back to it."""
TEMPORAL_LIMITS = MotionLimits(linear_speed_mm_s=20.0, linear_accel_mm_s2=250.0)
"""Its speed: slow enough for a dozen frames a stroke at 25 frames/s (about 5 s in all)."""
VOLUME_SPEED_MM_S = 20.0
"""The probe's speed along a continuous volume pass (mm/s)."""


def temporal_waypoints(centre_tool_to_base: np.ndarray, image_to_tool_rigid: np.ndarray,
                       amplitude_mm: float = TEMPORAL_AMPLITUDE_MM,
                       strokes: int = TEMPORAL_STROKES) -> list[np.ndarray]:
    """Flange poses that move the probe up and down along the image's depth axis (``image y``)
    about ``centre_tool_to_base``, ending there: every echo in the image moves with the probe, so
    the images and the pose stream see one motion (core.temporal)."""
    depth = (centre_tool_to_base @ image_to_tool_rigid)[:3, 1]
    poses = []
    for k in range(strokes):
        pose = centre_tool_to_base.copy()
        pose[:3, 3] += depth * amplitude_mm * (1.0 if k % 2 == 0 else -1.0)
        poses.append(pose)
    return [*poses, centre_tool_to_base.copy()]


@dataclass(frozen=True)
class Leg:
    """One stretch of a continuous acquisition: flange poses the robot passes through without
    stopping (``Robot.move_path``) within ``limits``, and the fields of the frames recorded on
    the way (None: a transit, its frames are shown but not recorded)."""

    poses: list[np.ndarray]
    limits: MotionLimits
    record: dict | None


def leg_durations_s(start_tool_to_base: np.ndarray, legs: list[Leg]) -> np.ndarray:
    """(L,) robot time (s) of each of ``legs`` driven one after the other from ``start_tool_to_base``."""
    steps, at = np.zeros(len(legs)), start_tool_to_base
    for k, leg in enumerate(legs):
        steps[k] = blended_path([at, *leg.poses], leg.limits).duration_s
        at = leg.poses[-1]
    return steps


def legs_duration_s(start_tool_to_base: np.ndarray, legs: list[Leg]) -> float:
    """Robot time (s) to drive ``legs`` one after the other from ``start_tool_to_base``."""
    return float(leg_durations_s(start_tool_to_base, legs).sum())


def continuous_calibration_legs(centre_tool_to_base: np.ndarray, image_to_tool_rigid: np.ndarray,
                                plan: SweepPlan, limits: MotionLimits | None = None) -> list[Leg]:
    """To the centre pose, up and down there (:func:`temporal_waypoints`, frames with ``phase``
    "temporal"), then through the plan's poses (``phase`` "calibration")."""
    limits = limits or MotionLimits()
    temporal = temporal_legs([centre_tool_to_base, *temporal_waypoints(centre_tool_to_base, image_to_tool_rigid)],
                             limits)
    return [*temporal, Leg(list(plan.poses), replace(limits, settle_s=0.0), {"phase": "calibration"})]


def temporal_legs(poses: list[np.ndarray], limits: MotionLimits) -> list[Leg]:
    """To the first of ``poses`` within ``limits``, then through the others at the temporal
    calibration's speed, its frames recorded with ``phase`` "temporal"."""
    return [Leg([poses[0]], limits, None),
            Leg(list(poses[1:]), replace(TEMPORAL_LIMITS, settle_s=0.0), {"phase": "temporal"})]


def continuous_volume_legs(plan: SweepPlan, limits: MotionLimits | None = None,
                           speed_mm_s: float = VOLUME_SPEED_MM_S) -> list[Leg]:
    """Each pass of a volume plan driven from its first pose to its last at ``speed_mm_s`` (frames
    with ``sweep``, the pass, and ``view``, its view, when the plan states views), with a transit
    to its start before it."""
    limits = limits or MotionLimits()
    along = replace(limits, linear_speed_mm_s=min(speed_mm_s, limits.linear_speed_mm_s), settle_s=0.0)
    legs = []
    for k in range(plan.n_passes):
        poses = [pose for pose, p in zip(plan.poses, plan.passes) if p == k]
        view = plan.view_of_pass(k)
        record = {"sweep": k} if view is None else {"sweep": k, "view": view}
        legs += [Leg([poses[0]], limits, None), Leg([poses[-1]], along, record)]
    return legs


def sweep_plan(
    start_tool_to_base: np.ndarray,
    direction_base: np.ndarray,
    length_mm: float,
    n_frames: int,
    limits: MotionLimits | None = None,
) -> Plan:
    """A straight pass: ``n_frames`` evenly spaced flange poses over ``length_mm`` along a
    base-frame direction, at a fixed orientation (thesis 3.7: 120 frames over 40 mm)."""
    direction = np.asarray(direction_base, float) / np.linalg.norm(direction_base)
    poses = []
    for s in np.linspace(0.0, length_mm, n_frames):
        pose = start_tool_to_base.copy()
        pose[:3, 3] += s * direction
        poses.append(pose)
    return Plan(poses, plan_duration(poses, start_tool_to_base, limits))


@dataclass(frozen=True)
class SweepPass:
    """One straight pass of a volume scan. ``yaw_deg`` turns the image plane about the vertical
    (0: image x along the region's x, sweeping along its y); ``tilt_deg`` tilts the beam about the
    sweep direction, so that walls facing sideways echo too; ``offset_mm`` shifts the pass sideways
    (along the image x) to cover a region wider than the probe."""

    yaw_deg: float = 0.0
    tilt_deg: float = 0.0
    offset_mm: float = 0.0


# Thesis 3.7: 120 frames over 40 mm, repeated from several angles. Two side-by-side passes cover
# 60 mm across, one crosses them, and two tilted ones look at the risers from either side.
DEFAULT_PASSES = (
    SweepPass(0.0, 0.0, -11.0),
    SweepPass(0.0, 0.0, 11.0),
    SweepPass(90.0, 0.0, 0.0),
    SweepPass(0.0, 20.0, 0.0),
    SweepPass(0.0, -20.0, 0.0),
)


@dataclass(frozen=True)
class ProbeView:
    """A wrist angle a volume scan's passes are swept from, as a move of the image in its own
    frame (deg): turned ``turn_deg`` about the beam down its centre column (joint 6 turns; at 180
    the image is mirrored across the object), then tilted ``tilt_deg`` in its plane about the
    region's top under that column (the beam leans across the image). The same passes from two
    views show the same surfaces through different calibrations' errors (``core.volume.selfcheck``)."""

    turn_deg: float = 0.0
    tilt_deg: float = 0.0

    def image_move(self, width_mm: float, depth_mm: float) -> np.ndarray:
        """``image_to_viewed_image`` (4x4, mm): the move about the point ``width_mm / 2`` across
        and ``depth_mm`` down the image."""
        pivot = make_transform(np.eye(3), [width_mm / 2, depth_mm, 0.0])
        turn = Rotation.from_euler("yz", [self.turn_deg, self.tilt_deg], degrees=True)
        return pivot @ make_transform(turn, np.zeros(3)) @ invert_transform(pivot)


AS_PLANNED = ProbeView()
SELF_CHECK_VIEWS = (AS_PLANNED, ProbeView(turn_deg=180.0))
"""The views a self-check sweeps by default: as planned, and turned half a turn about the beam,
which mirrors the calibration's every error but one along the beam (``benchmarks/bench_selfcheck.py``)."""
SELF_CHECK_PASS_MM = 56.0
"""A self-check's passes (mm): 8 mm beyond either end of the 40 mm test object, so that every view
sees all of it, wherever the seed puts it (+-2 mm) and however far a view's turn moves the true
image (twice the mount's offset from the beam it turns about, a few mm)."""
SELF_CHECK_PASSES = DEFAULT_PASSES[2:]
"""A self-check's passes: the scan's crossing pass and its two tilted ones. From two wrist angles
they flag a calibration shifted 1 mm along any image axis or turned 1 deg about one
(``benchmarks/bench_selfcheck.py``): the tilted passes, their beams 40 deg apart, show a shift
along the beam, which no turn about the beam does; the crossing pass with either shows the turns
about x and y and the shift along z, which side-by-side passes alone miss."""
SELF_CHECK_SPEED_MM_S = 5.0
"""A self-check's passes driven without stopping (mm/s): its frames lie within the check's 0.7 mm
(``core.volume.selfcheck.CheckSettings.max_step_mm``) for any stream of 8 frames/s or more. The
twin's scanner, imaging in real time on a busy machine, kept 12 to 16 of its 25 frames/s: at 10 mm/s
its frames lay 0.72 mm apart."""


PROGRESS_EVERY = 50
"""Poses a volume plan checks between two reports of its progress."""
PASS_LENGTH_MM = 40.0
"""A volume pass's length (mm): the test object's depth along the sweep (thesis 3.7)."""


def volume_plan(
    region_to_base: np.ndarray,
    image_to_tool_rigid: np.ndarray,
    probe: Probe,
    standoff_mm: float,
    passes: tuple[SweepPass, ...] = DEFAULT_PASSES,
    length_mm: float = PASS_LENGTH_MM,
    n_frames: int = 120,
    start_joints: np.ndarray = HOME_JOINTS,
    limits: MotionLimits | None = None,
    progress: Callable[[int, int], None] | None = None,
    view: ProbeView = AS_PLANNED,
) -> list[Plan]:
    """Straight passes over a region of interest whose frame sits at the top centre of the
    object (z up, mm): the probe face passes ``standoff_mm`` above it, each pass ``length_mm``
    long with ``n_frames`` frames, the probe held at ``view``'s wrist angle. Every pose is
    checked for reachability (ValueError if a pass cannot be driven); each plan's duration
    includes the transit to its start.
    ``progress(poses checked, poses in all)`` is told after every ``PROGRESS_EVERY`` poses and each
    pass (and may raise to end the work)."""
    limits = limits or MotionLimits()
    down_plane = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    joints = np.asarray(start_joints, dtype=float)
    previous = forward_kinematics(joints)
    plans = []
    for k, sweep in enumerate(passes):
        axes = Rotation.from_euler("z", sweep.yaw_deg, degrees=True).as_matrix() @ down_plane
        axes = Rotation.from_rotvec(np.radians(sweep.tilt_deg) * axes[:, 2]).as_matrix() @ axes
        axes_in_base = region_to_base[:3, :3] @ axes
        direction = axes_in_base[:, 2]  # sweep along the image normal
        pivot = region_to_base[:3, 3]
        face_centre = pivot - axes_in_base[:, 1] * standoff_mm + axes_in_base[:, 0] * sweep.offset_mm
        top_centre = face_centre - axes_in_base[:, 1] * probe.face_below_first_row_mm  # a convex face bulges below
        origin = top_centre - axes_in_base[:, 0] * probe.width_mm / 2 - direction * length_mm / 2
        image_to_base = make_transform(axes_in_base, origin)
        if view != AS_PLANNED:  # as planned, the poses stay bit for bit those of a scan without views
            image_to_base = image_to_base @ view.image_move(probe.width_mm, standoff_mm + probe.face_below_first_row_mm)
        start = image_to_base @ invert_transform(image_to_tool_rigid)
        plan = sweep_plan(start, direction, length_mm, n_frames, limits)
        for i, pose in enumerate(plan.poses):
            try:
                joints = closest_ik(pose, joints)
            except Unreachable as exc:
                raise ValueError(f"volume pass {k + 1} is out of the robot's reach ({exc})")
            if progress is not None and ((i + 1) % PROGRESS_EVERY == 0 or i + 1 == len(plan.poses)):
                progress(k * len(plan.poses) + i + 1, len(passes) * len(plan.poses))
        transit = linear_move_duration(previous, start, limits)
        plans.append(Plan(plan.poses, plan.duration_s + transit))
        previous = plan.poses[-1]
    return plans


def viewed_volume_plan(
    region_to_base: np.ndarray,
    image_to_tool_rigid: np.ndarray,
    probe: Probe,
    standoff_mm: float,
    views: tuple[ProbeView, ...] | None = None,
    passes: tuple[SweepPass, ...] = DEFAULT_PASSES,
    length_mm: float = PASS_LENGTH_MM,
    n_frames: int = 120,
    start_joints: np.ndarray = HOME_JOINTS,
    limits: MotionLimits | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SweepPlan:
    """:func:`volume_plan`'s passes swept again from each of ``views`` in turn, each view starting
    where the one before ends; the plan states each pose's view (None: the passes once, as
    planned, and no views). ``progress`` as for :func:`volume_plan`, over every view's poses."""
    plans: list[Plan] = []
    view_of_pass: list[int] = []
    joints = np.asarray(start_joints, dtype=float)
    swept = views or (AS_PLANNED,)
    for k, view in enumerate(swept):
        told = None if progress is None else _viewed_progress(progress, k, len(swept))
        planned = volume_plan(region_to_base, image_to_tool_rigid, probe, standoff_mm, passes, length_mm, n_frames,
                              joints, limits, told, view)
        plans += planned
        view_of_pass += [k] * len(planned)
        joints = closest_ik(planned[-1].poses[-1], joints)
    return SweepPlan.from_plans(plans, None if views is None else view_of_pass)


def _viewed_progress(progress: Callable[[int, int], None], view: int, views: int) -> Callable[[int, int], None]:
    """A view's ``progress(poses checked, poses in all)`` told over all ``views``."""

    def told(done: int, total: int) -> None:
        progress(view * total + done, views * total)

    return told
