"""The self-check: one rigid object swept from two or more wrist angles
(``core.acquisition.plan.ProbeView``; a session's frames record their ``view`` and ``sweep``, or,
recorded elsewhere, are grouped by the wrist angle the robot held), each pass's surface
reconstructed in the base frame with the same calibration, and every pass of every view
registered point to plane (normals by open3d) to the same pass of an earlier view, and to a pass of its
own view swept with the beam turned.

With a right calibration and an arm that is where it reports, the views' surfaces coincide. A
calibration error moves them apart, each view by the error seen through its own wrist angle;
an arm error, by how its kinematics err at each view's joints. Passes are compared one by one
because a pass sees the object along one direction: an extruded object's top pins no slide along
its length, so each pass is compared only along the moves its surface pins, and passes swept
across each other see different components of the calibration.

Points are in the base frame (mm); a calibration change is a small rigid move of the image in
its own frame (mm along, deg about the image x, y, z axes), applied as
``image_to_tool_rigid @ change``. Needs no ground truth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TypedDict

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from probecal.core.calibration.result import Calibration, CalibrationSource, calibration_source
from probecal.core.errors import InputError
from probecal.core.geometry.transforms import invert_transform, make_transform, skew, transform_points
from probecal.core.io.files import fresh_folder, staged_folder
from probecal.core.io.jsonio import write_json
from probecal.core.io.session import Session
from probecal.core.volume.pointcloud import write_ply
from probecal.core.volume.reconstruct import (
    REPORT,
    as_calibrated,
    frame_surface,
    frames_set_right,
    surface_cloud,
    usable_poses,
)
from probecal.core.volume.surface import SurfaceParams

COMPONENTS = ("x mm", "y mm", "z mm", "about x deg", "about y deg", "about z deg")
"""A calibration change's components: along and about the image axes (x across, y down the beam,
z out of the plane)."""


@dataclass(frozen=True)
class CheckSettings:
    """``max_offset_mm``/``max_rotation_deg``: the views agree when every pass's centroid sits
    within this of where the pass it is compared with puts it, and turns less than this
    (``benchmarks/bench_selfcheck.py``). ``icp_distances_mm``: the ICP's correspondence distances,
    coarse to fine; ``normal_radius_mm``, the neighbourhood of a surface normal; ``min_pin``, the
    least information (of the largest direction's) a move needs for a surface to pin it;
    ``across_weight``, how much of a normal across its frame's plane counts for that
    (:func:`first_surface`); ``fit_points``, the points per pass the calibration change is fitted
    on; ``max_step_mm``, how far apart a pass's frames may lie (median, mm) for the check to hold
    its figures: farther, the surface between them is not seen and its normals, so what it pins,
    come out wrong (on the twin the views agree within 0.02 mm at 0.62 mm, not at 1.9), and the
    report cautions so; beyond ``refuse_step_mm`` the check is refused. ``beam_turn_deg`` and
    ``min_overlap``: which passes of a view are compared to show a shift along the beam
    (:func:`beam_pairs`). ``surface``: the echo's edge is placed where it rises most steeply, which
    moves least with the echo's strength (``core.volume.surface``), since passes whose beams meet a
    surface at different angles, so echoing it at different strengths, are compared."""

    max_offset_mm: float = 0.3
    max_rotation_deg: float = 0.3
    icp_distances_mm: tuple[float, ...] = (3.0, 1.0, 0.5)
    normal_radius_mm: float = 2.0
    min_pin: float = 0.01
    fit_points: int = 2000
    max_step_mm: float = 0.7
    refuse_step_mm: float = 3.0
    beam_turn_deg: float = 10.0
    min_overlap: float = 0.5
    across_weight: float = 0.5
    surface: SurfaceParams = SurfaceParams(edge="steepest")
    floor_up: tuple[float, float, float] | None = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class PassSurface:
    """One pass's surface points (base frame, mm) and, for each, the frame it came from, as that
    frame's rigid ``image_to_base`` (``tool_to_base @ image_to_tool_rigid``); ``step_mm``, how far
    apart its frames lie (median, mm)."""

    points_base: np.ndarray
    image_to_base: np.ndarray  # (n, 4, 4)
    step_mm: float = 0.0

    @cached_property
    def tree(self) -> cKDTree:
        """A tree of its points, built once for every comparison that pairs with them."""
        return cKDTree(self.points_base)


@dataclass(frozen=True)
class PassOffset:
    """How pass ``pass_index`` of view ``view`` sits against pass ``against_pass`` of view
    ``against_view`` (the same pass of an earlier view, :func:`nearest_view`, or an earlier pass of
    its own view swept with the beam turned, :func:`beam_pairs`). ``view_to_first`` is the rigid
    move (base frame, mm) that lays its surface on that one's, along what that surface pins
    (``loose``: (k, 6) unit twists (mm, rad) it does not); ``offset_mm`` where its centroid
    (``centroid_mm``) sits from where that move puts it (base frame, mm), ``rotation_deg`` the
    move's angle. Median surface distances (mm, to that surface)
    before and after the move, over the ``paired`` fraction of its points within the ICP's coarse
    distance of that surface."""

    view: int
    pass_index: int
    against_view: int
    against_pass: int
    points: int
    view_to_first: np.ndarray
    centroid_mm: np.ndarray
    offset_mm: np.ndarray
    rotation_deg: float
    median_before_mm: float
    median_after_mm: float
    paired: float
    loose: np.ndarray
    projector: np.ndarray  # (6, 6) FirstSurface.projector of the surface it is compared with
    pinned_about_mm: np.ndarray  # the centre of that projector's twists

    @property
    def offset_norm_mm(self) -> float:
        return float(np.linalg.norm(self.offset_mm))

    def pinned_offset_mm(self, move: np.ndarray) -> np.ndarray:
        """The offset (base frame, mm) the check would report were ``move`` (4x4, base mm) what
        lays this pass on the other: where its part along the moves that surface pins puts the
        centroid from itself."""
        pinned = _move(self.projector @ _twist(move, self.pinned_about_mm), self.pinned_about_mm)
        return self.centroid_mm - transform_points(pinned, self.centroid_mm[None])[0]


@dataclass(frozen=True)
class CalibrationChange:
    """The small calibration error that best explains the offsets (image frame: mm along, deg
    about x, y, z; applying its inverse would remove them), fitted on the components the views
    can see. ``sensitivity``: how far apart (mm RMS over a pass's surface, the pass that shows it
    most) one mm or one degree of each component moves the views; ``visible`` where that is at
    least the check's ``max_offset_mm``, so that an error of that size is flagged.
    ``unexplained_mm``: how much of the offsets (mm RMS over the surfaces) no calibration change
    explains, of ``offsets_mm``."""

    translation_mm: np.ndarray
    rotation_deg: np.ndarray
    sensitivity: np.ndarray  # (6,) mm per mm or per deg, in COMPONENTS order
    visible: tuple[bool, ...]
    unexplained_mm: float
    offsets_mm: float


@dataclass(frozen=True)
class SelfCheck:
    """Every pass of every view against another, what the offsets imply about the
    calibration, and whether to trust the volumes (``cause``: what most likely moved the views
    apart, or why they agree; ``cautions``: what makes the figures less sure)."""

    offsets: tuple[PassOffset, ...]
    change: CalibrationChange
    trusted: bool
    cause: str
    cautions: tuple[str, ...] = ()

    def worst(self, view: int) -> PassOffset:
        """The pass of ``view`` that sits farthest from the pass it is compared with."""
        return max((o for o in self.offsets if o.view == view), key=lambda o: o.offset_norm_mm)


VIEW_APART_DEG = 5.0
"""Where no frame states its view, frames whose flange turns less than this (deg) from a view's
first frame belong to that view: a robot holds the wrist angle of a straight pass exactly."""
MIN_VIEW_SHARE = 0.05
"""Of a session's frames, the fewest a wrist angle must hold to count as a view where no frame
states one (fewer: the robot turning between views)."""


def stated_views(session: Session) -> list[list[list[int]]]:
    """The frames of each view by the ``view`` every record states, pass by pass (by ``sweep``, in
    order; one pass where no record states one). InputError naming the session unless they state two
    views or more, each with as many passes."""
    stated = [r.extra.get("view") for r in session.records]
    views = [v for v in stated if isinstance(v, int)]
    if len(views) < len(stated):
        raise InputError(session.path, "some frames state no view")
    present = sorted(set(views))
    if len(present) < 2:
        raise InputError(session.path, f"its frames are all of view {present[0]}: a self-check needs two or more views")
    passes = session_passes(session)
    grouped = [[kept for kept in ([i for i in frames if views[i] == k] for frames in passes) if kept] for k in present]
    if len({len(view) for view in grouped}) > 1:
        raise InputError(session.path, f"its views have {', '.join(str(len(v)) for v in grouped)} passes: a "
                                       "self-check compares the same passes from every view")
    return grouped


def held_views(session: Session, apart_deg: float = VIEW_APART_DEG) -> list[list[list[int]]]:
    """The frames of a session that states no views, grouped by the wrist angle the robot held
    (the flange's orientation, within ``apart_deg`` of each group's first frame), in the order they
    were first held; each group is a view of one pass, and groups of fewer than ``MIN_VIEW_SHARE``
    of the frames are left out. InputError naming the session unless two views or more remain."""
    usable = [(i, pose) for i, pose in enumerate(usable_poses(session)) if pose is not None]
    if not usable:
        raise InputError(session.path, "no frame has a valid pose")
    posed = [i for i, _ in usable]
    orientations = Rotation.from_matrix(np.array([pose[:3, :3] for _, pose in usable]))
    left = np.ones(len(posed), bool)
    groups = []
    while left.any():
        first = int(np.argmax(left))
        held = left & ((orientations[first].inv() * orientations).magnitude() < np.radians(apart_deg))
        groups.append([posed[i] for i in np.flatnonzero(held)])
        left &= ~held
    views = [[group] for group in groups if len(group) >= MIN_VIEW_SHARE * len(session.records)]
    if len(views) < 2:
        raise InputError(session.path, "its frames state no view and the probe is held at one wrist angle "
                                       f"throughout (within {apart_deg:g} deg): a self-check needs one object "
                                       "swept from two or more wrist angles")
    return views


def frames_by_view(session: Session) -> list[list[list[int]]]:
    """The frames of each view, pass by pass: as the records state them (:func:`stated_views`), or,
    where none does, as the robot held the probe (:func:`held_views`)."""
    if any(isinstance(r.extra.get("view"), int) for r in session.records):
        return stated_views(session)
    return held_views(session)


@dataclass(frozen=True)
class ViewedSweep:
    """One view: its frames in ``session``, pass by pass, and the calibration applied to them."""

    session: Session
    calibration: Calibration
    passes: list[list[int]]


def session_passes(session: Session) -> list[list[int]]:
    """A session's frames pass by pass (by the ``sweep`` its records state, in order; one pass
    where none does)."""
    passes = [r.extra.get("sweep", 0) for r in session.records]
    return [[i for i, p in enumerate(passes) if p == pass_index] for pass_index in sorted(set(passes))]


def viewed_sweeps(sessions: list[tuple[Session, Calibration]]) -> list[ViewedSweep]:
    """The views of one session (:func:`frames_by_view`), or of several, each session a view and
    its passes those its records state; InputError naming the last session unless every view has as
    many passes."""
    if len(sessions) == 1:
        session, calibration = sessions[0]
        return [ViewedSweep(session, calibration, passes) for passes in frames_by_view(session)]
    _refuse_repeated([session for session, _ in sessions])
    views = [ViewedSweep(session, calibration, session_passes(session)) for session, calibration in sessions]
    if len({len(v.passes) for v in views}) > 1:
        raise InputError(sessions[-1][0].path, f"the sessions have {', '.join(str(len(v.passes)) for v in views)} "
                                               "passes: a self-check compares the same passes from every view")
    return views


def _refuse_repeated(sessions: list[Session]) -> None:
    """InputError naming a session given again, as itself or as a copy of its frames: one sweep
    compared with itself agrees by construction, and would say to trust any calibration."""
    seen: dict[tuple, Path] = {}
    for session in sessions:
        for key in (("folder", session.path.resolve()), ("frames", _frames_key(session))):
            if key in seen:
                raise InputError(session.path, f"is {'the same sweep as' if key[0] == 'frames' else 'given twice, as'} "
                                               f"{seen[key]}: a self-check compares different sweeps of one object")
            seen[key] = session.path


def _frames_key(session: Session) -> tuple:
    """What tells one sweep from another: when its frames were recorded, and where."""
    return (session.manifest.created, tuple(record.image for record in session.records),
            tuple(None if r.tool_to_base is None else r.tool_to_base.tobytes() for r in session.records))


def _pass_surface(session: Session, calibration: Calibration, poses: list[np.ndarray | None], frames: list[int],
                  label: str, settings: CheckSettings) -> PassSurface:
    """The surface of one pass (``label`` names it in errors) of a session set up for
    ``calibration`` (:func:`as_calibrated`), with ``poses`` its usable poses."""
    set_right = frames_set_right(calibration, (session.image_size[1], session.image_size[0]))
    posed = [(i, pose) for i, pose in ((i, poses[i]) for i in frames) if pose is not None]
    origins = np.array([pose[:3, 3] for _, pose in posed]).reshape(-1, 3)
    steps = np.linalg.norm(np.diff(origins, axis=0), axis=1)
    step = float(np.median(steps)) if len(steps) else 0.0
    if step > settings.refuse_step_mm:
        raise InputError(session.path, f"the frames of {label} lie {step:.2f} mm apart: a self-check needs them at "
                                       f"most {settings.max_step_mm:g} mm apart (more frames per pass, or a slower "
                                       "sweep)")
    clouds, frame_poses = [], []
    for i, tool_to_base in posed:
        image = session.image(i) if set_right is None else set_right(session.image(i))
        cloud = frame_surface(image, tool_to_base, calibration.image_to_tool, settings.surface)
        clouds.append(cloud)
        frame_poses.append(np.broadcast_to(tool_to_base @ calibration.image_to_tool_rigid, (len(cloud), 4, 4)))
    raw = np.concatenate(clouds) if clouds else np.empty((0, 3))
    points = surface_cloud(raw, settings.floor_up)
    if len(points) == 0:
        raise InputError(session.path, f"{label} shows no surface (nothing brighter than the threshold)")
    _, nearest = cKDTree(raw).query(points)
    return PassSurface(points, np.concatenate(frame_poses)[nearest], step)


def view_surfaces(views: list[ViewedSweep], settings: CheckSettings = CheckSettings()) -> list[list[PassSurface]]:
    """Every pass's surface, view by view, as ``probecal reconstruct`` makes it (frames paired
    with the calibration's latency and through its fitted arm, set right for a fan, merged, without
    the tank floor); InputError naming the session when a pass shows none."""
    calibrated: dict[Path, tuple[Session, list[np.ndarray | None]]] = {}  # a session's views share its pairing
    surfaces = []
    for k, view in enumerate(views):
        if view.session.path not in calibrated:
            session, _ = as_calibrated(view.session, view.calibration)
            calibrated[view.session.path] = session, usable_poses(session)
        session, poses = calibrated[view.session.path]
        surfaces.append([_pass_surface(session, view.calibration, poses, frames, f"pass {p} of view {k}", settings)
                         for p, frames in enumerate(view.passes)])
    return surfaces


def _twist(move: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(6,) a rigid move's twist about ``centre``: (v mm, w rad)."""
    w = Rotation.from_matrix(move[:3, :3]).as_rotvec()
    return np.concatenate([move[:3, :3] @ centre + move[:3, 3] - centre, w])


def _move(twist: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The rigid move (4x4) of a twist about ``centre`` (:func:`_twist`'s inverse)."""
    rotation = Rotation.from_rotvec(twist[3:]).as_matrix()
    return make_transform(rotation, twist[:3] + centre - rotation @ centre)


@dataclass(frozen=True)
class FirstSurface:
    """A pass as others are registered to it: its points with normals, a
    tree of them, and the rigid moves its surface pins. A twist about ``centre_mm`` (v mm, w rad)
    counts its rotation as the move of points ``size_mm`` (their RMS distance from the centre)
    away; ``projector`` (6, 6) keeps its part along the directions point-to-plane ICP can measure
    there, those whose information is at least ``CheckSettings.min_pin`` of the largest's;
    ``pinned_twists`` (6, m) those directions as twists (each a move of 1 mm so counted), ``loose``
    (k, 6) the others, unit twists."""

    cloud: o3d.geometry.PointCloud
    tree: cKDTree
    centre_mm: np.ndarray
    size_mm: float
    projector: np.ndarray
    pinned_twists: np.ndarray
    loose: np.ndarray


def first_surface(surface: PassSurface, settings: CheckSettings) -> FirstSurface:
    """A pass that others are registered to, with its normals and what it pins: the eigen-directions of its
    point-to-plane information (twists scaled as :class:`FirstSurface` says), with the part of
    every normal across its frame's plane weighed by ``CheckSettings.across_weight``: a frame
    measures the surface in its plane, while across the frames the surface is known only as
    finely as they lie apart, and two views' frames need not lie in the same planes (where an
    object ends along the sweep, the views then see its end up to a frame's spacing apart)."""
    points = surface.points_base
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(settings.normal_radius_mm, 30))
    across = surface.image_to_base[:, :3, 2]
    normals = np.asarray(cloud.normals)
    weighed = normals - (1.0 - settings.across_weight) * np.einsum("ij,ij->i", normals, across)[:, None] * across
    centre = points.mean(axis=0)
    size = float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))
    rows = np.hstack([weighed, np.cross(points - centre, weighed) / size])  # per twist scaled to (v, w * size)
    information, directions = np.linalg.eigh(rows.T @ rows / len(rows))
    pinned = information >= settings.min_pin * information.max()
    scale = np.array([1.0, 1.0, 1.0, size, size, size])
    kept = directions[:, pinned]
    loose = directions[:, ~pinned].T / scale
    return FirstSurface(cloud, surface.tree, centre, size, np.diag(1 / scale) @ kept @ kept.T @ np.diag(scale),
                        np.diag(1 / scale) @ kept, loose / np.linalg.norm(loose, axis=1, keepdims=True))


PINNED_ITERATIONS = 30
PINNED_STEP_MM = 1e-4
"""The registration's Gauss-Newton steps at most per correspondence distance, and the step (mm, or
rad times the surface's size) under which it has converged."""


def _pinned_steps(points: np.ndarray, first: FirstSurface, move: np.ndarray, distance_mm: float) -> np.ndarray:
    """``move`` refined by point-to-plane Gauss-Newton steps, the points paired with the other
    pass's within ``distance_mm``, along the moves its surface pins only (a plain point-to-plane
    ICP slides off along the loose ones, where nothing holds it), each step at most
    ``distance_mm`` long (scaled as :class:`FirstSurface` counts it)."""
    normals = np.asarray(first.cloud.normals)
    for _ in range(PINNED_ITERATIONS):
        moved = transform_points(move, points)
        gap, nearest = first.tree.query(moved, distance_upper_bound=distance_mm)
        paired = np.isfinite(gap)
        if paired.sum() < first.pinned_twists.shape[1]:
            break
        n, x = normals[nearest[paired]], moved[paired]
        residual = np.einsum("ij,ij->i", x - first.tree.data[nearest[paired]], n)
        rows = np.hstack([n, np.cross(x - first.centre_mm, n)]) @ first.pinned_twists
        step = np.linalg.lstsq(rows, -residual, rcond=None)[0]
        step *= min(1.0, distance_mm / max(float(np.linalg.norm(step)), 1e-12))
        move = _move(first.pinned_twists @ step, first.centre_mm) @ move
        if np.linalg.norm(step) < PINNED_STEP_MM:
            break
    return move


def register_pass(points: np.ndarray, first: FirstSurface, settings: CheckSettings) -> np.ndarray:
    """``view_to_first`` (4x4, base frame mm): a pass's points registered onto another pass's
    surface from where they were reconstructed, point to plane along the moves that surface pins
    (:func:`_pinned_steps`), the correspondences coarse to fine."""
    move = np.eye(4)
    for distance in settings.icp_distances_mm:
        move = _pinned_steps(points, first, move, distance)
    return move


def surface_distances(points: np.ndarray, first: FirstSurface, max_mm: float) -> np.ndarray:
    """Distances (mm) of points to another pass's surface, each along the normal of its nearest
    point there; only the points within ``max_mm`` of one."""
    gap, nearest = first.tree.query(points, distance_upper_bound=max_mm)
    paired = np.isfinite(gap)
    normals = np.asarray(first.cloud.normals)[nearest[paired]]
    return np.abs(np.einsum("ij,ij->i", points[paired] - first.tree.data[nearest[paired]], normals))


def pass_offset(view: int, pass_index: int, surface: PassSurface, against: tuple[int, int], first: FirstSurface,
                settings: CheckSettings) -> PassOffset:
    """How a pass's surface sits against pass ``against`` (view, pass), ``first``
    (:class:`PassOffset`)."""
    points = surface.points_base
    move = register_pass(points, first, settings)
    centroid = points.mean(axis=0)
    reach = settings.icp_distances_mm[0]
    before = surface_distances(points, first, reach)
    after = surface_distances(transform_points(move, points), first, reach)
    return PassOffset(
        view=view, pass_index=pass_index, against_view=against[0], against_pass=against[1], points=len(points),
        view_to_first=move, centroid_mm=centroid,
        offset_mm=centroid - transform_points(move, centroid[None])[0],
        rotation_deg=float(np.degrees(Rotation.from_matrix(move[:3, :3]).magnitude())),
        median_before_mm=float(np.median(before)) if len(before) else float("nan"),
        median_after_mm=float(np.median(after)) if len(after) else float("nan"),
        paired=len(before) / len(points),
        loose=first.loose,
        projector=first.projector,
        pinned_about_mm=first.centre_mm,
    )


def _rigid_field(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(3n, 6): a rigid motion's small twist (v mm, w rad; about ``centre``) to its displacement of
    each of the (n, 3) points, ``v + w x (p - centre)``."""
    rows = np.concatenate([np.tile(np.eye(3), (len(points), 1, 1)), -skew(points - centre)], axis=2)
    return rows.reshape(-1, 6)


def _calibration_field(surface: PassSurface, sample: np.ndarray) -> np.ndarray:
    """(3n, 6): how the sampled points of a pass move (base frame, mm) per mm along and per deg
    about each image axis of a change of the calibration (:data:`COMPONENTS`)."""
    frames = surface.image_to_base[sample]
    rotation = frames[:, :3, :3]
    in_image = np.einsum("nji,nj->ni", rotation, surface.points_base[sample] - frames[:, :3, 3])
    turn = -rotation @ skew(in_image) * np.radians(1.0)
    return np.concatenate([rotation, turn], axis=2).reshape(-1, 6)


def _rms(field: np.ndarray) -> float:
    """RMS length (mm) of a (3n,) displacement field."""
    return float(np.sqrt(np.mean(np.sum(field.reshape(-1, 3) ** 2, axis=1))))


@dataclass(frozen=True)
class _Pair:
    """A pass against another: each twist (about the first's centre, scaled as
    :class:`FirstSurface` says) per unit of each calibration component, as far as the first's surface
    pins it (6, 6); the twist measured; and what turns a twist into the pass's points' moves."""

    per_unit: np.ndarray
    measured: np.ndarray
    field: np.ndarray  # (3n, 6) the scaled twist to the moves of the pass's sampled points


def _pair(surface: PassSurface, first_pass: PassSurface, first: FirstSurface, offset: PassOffset,
          settings: CheckSettings) -> _Pair:
    """How a calibration change would move a pass against another (linearised: each
    pass's surface moves rigidly by the least-squares twist of how the change moves its points)."""
    rng = np.random.default_rng(0)
    centre, scale = first.centre_mm, np.array([1.0, 1.0, 1.0, first.size_mm, first.size_mm, first.size_mm])

    def effect(s: PassSurface) -> tuple[np.ndarray, np.ndarray]:
        sample = rng.choice(len(s.points_base), min(settings.fit_points, len(s.points_base)), replace=False)
        rigid = _rigid_field(s.points_base[sample], centre)
        return np.linalg.lstsq(rigid, _calibration_field(s, sample), rcond=None)[0], rigid

    own, rigid = effect(surface)
    theirs, _ = effect(first_pass)
    per_unit = np.diag(scale) @ first.projector @ (own - theirs)
    measured = scale * (first.projector @ _twist(invert_transform(offset.view_to_first), centre))
    return _Pair(per_unit, measured, rigid / scale)


def calibration_change(pairs: list[_Pair], settings: CheckSettings) -> CalibrationChange:
    """The calibration change whose effect through every pass's known poses best explains the
    offsets of every pass against the one it is compared with."""
    sensitivity = np.array([max(_rms(p.field @ p.per_unit[:, j]) for p in pairs) for j in range(6)])
    visible = sensitivity >= settings.max_offset_mm
    change = np.zeros(6)
    if visible.any():  # combinations of components that move the views less than a flag's worth are left out
        system = np.concatenate([p.per_unit[:, visible] for p in pairs])
        largest = np.linalg.svd(system, compute_uv=False)[0]
        change[visible] = np.linalg.lstsq(system, np.concatenate([p.measured for p in pairs]),
                                          rcond=settings.max_offset_mm / largest)[0]
    left = [_rms(p.field @ (p.measured - p.per_unit @ change)) for p in pairs]
    offsets = [_rms(p.field @ p.measured) for p in pairs]
    return CalibrationChange(change[:3], change[3:], sensitivity, tuple(bool(v) for v in visible),
                             float(np.sqrt(np.mean(np.square(left)))), float(np.sqrt(np.mean(np.square(offsets)))))


def _cause(offsets: tuple[PassOffset, ...], change: CalibrationChange, trusted: bool) -> str:
    """What the offsets say, in a sentence."""
    worst = max(offsets, key=lambda o: o.offset_norm_mm)
    turned = max(o.rotation_deg for o in offsets)
    if trusted:
        unseen = [name for name, seen in zip(COMPONENTS, change.visible) if not seen]
        return (f"the views agree within {worst.offset_norm_mm:.2f} mm and {turned:.2f} deg" +
                (f" (a calibration error of {', '.join(unseen)}, which every view shares, stays unseen)"
                 if unseen else ""))
    apart = f"the views are up to {worst.offset_norm_mm:.2f} mm and {turned:.2f} deg apart"
    components = [f"{v:+.2f} {name}" for v, name, seen in zip([*change.translation_mm, *change.rotation_deg],
                                                              COMPONENTS, change.visible) if seen and abs(v) >= 0.05]
    if components and change.unexplained_mm <= 0.5 * change.offsets_mm:
        return (f"{apart}; a calibration error of {', '.join(components)} (image frame) explains it: recalibrate, "
                f"or check the scanner's preset (pixel spacing); an arm error at these poses can look the same (a "
                f"calibration that fits the arm's errors tells them apart)")
    return (f"{apart} and no calibration change explains {change.unexplained_mm:.2f} mm of it: most likely the "
            f"arm's kinematic error at these poses, or the object moved between the views")


def _beam(surface: PassSurface) -> np.ndarray:
    """A pass's beam direction (base frame, unit; the mean of its frames' image y axes)."""
    beam = surface.image_to_base[:, :3, 1].mean(axis=0)
    return beam / np.linalg.norm(beam)


def _overlap(one: PassSurface, other: PassSurface, settings: CheckSettings) -> float:
    """The share of ``one``'s points within the ICP's coarse distance of ``other``'s."""
    gaps, _ = other.tree.query(one.points_base, distance_upper_bound=settings.icp_distances_mm[0])
    return float(np.mean(np.isfinite(gaps)))


def nearest_view(surfaces: list[list[PassSurface]], k: int, p: int, settings: CheckSettings) -> int:
    """The earlier view whose pass ``p`` the same pass of view ``k`` overlaps most: the first view
    where every view swept the same passes, the nearest wrist angle's pass where the views are the
    wrist angles a recording held (:func:`held_views`), each its own pass."""
    return int(np.argmax([_overlap(surfaces[k][p], surfaces[j][p], settings) for j in range(k)]))


def beam_pairs(surfaces: list[list[PassSurface]], settings: CheckSettings) -> list[tuple[tuple[int, int], int]]:
    """Within each view, each pass (view, pass) against the earlier pass of the view (returned
    beside it) swept with the beam turned at least ``CheckSettings.beam_turn_deg`` from its own
    whose surface shows a shift of the calibration along the beam best: such a shift, which no
    turn about the beam shows, moves the two passes apart by twice the sine of half the turn per
    mm, over the share of the pass's points within the ICP's coarse distance of the other's
    surface (at least ``CheckSettings.min_overlap``)."""
    pairs = []
    for k, view in enumerate(surfaces):
        beams = [_beam(s) for s in view]
        for b in range(1, len(view)):
            best, shown = None, 0.0
            for a in range(b):
                turn = np.arccos(np.clip(beams[a] @ beams[b], -1.0, 1.0))
                overlap = _overlap(view[b], view[a], settings)
                if np.degrees(turn) >= settings.beam_turn_deg and overlap >= settings.min_overlap and \
                        overlap * 2 * np.sin(turn / 2) > shown:
                    best, shown = a, overlap * 2 * np.sin(turn / 2)
            if best is not None:
                pairs.append(((k, b), best))
    return pairs


def check_surfaces(surfaces: list[list[PassSurface]], settings: CheckSettings = CheckSettings()) -> SelfCheck:
    """Every pass of every view registered to the same pass of the earlier view it overlaps most
    (:func:`nearest_view`), and to the pass of its own view that shows a shift along the beam
    (:func:`beam_pairs`), and what the offsets imply."""
    if len(surfaces) < 2:
        raise ValueError("a self-check needs two or more views")
    compared = [((k, p), (nearest_view(surfaces, k, p, settings), p))
                for k in range(1, len(surfaces)) for p in range(len(surfaces[k]))]
    compared += [(one, (one[0], other)) for one, other in beam_pairs(surfaces, settings)]
    firsts = {against: first_surface(surfaces[against[0]][against[1]], settings) for _, against in compared}
    offsets, pairs = [], []
    for (k, p), against in compared:
        surface, first = surfaces[k][p], firsts[against]
        offsets.append(pass_offset(k, p, surface, against, first, settings))
        pairs.append(_pair(surface, surfaces[against[0]][against[1]], first, offsets[-1], settings))
    change = calibration_change(pairs, settings)
    trusted = all(o.offset_norm_mm <= settings.max_offset_mm and o.rotation_deg <= settings.max_rotation_deg
                  for o in offsets)
    return SelfCheck(tuple(offsets), change, trusted, _cause(tuple(offsets), change, trusted),
                     _cautions(surfaces, settings))


def _cautions(surfaces: list[list[PassSurface]], settings: CheckSettings) -> tuple[str, ...]:
    """A caution for every pass whose frames lie farther apart than the check holds its figures for."""
    return tuple(f"the frames of pass {p} of view {k} lie {s.step_mm:.2f} mm apart, more than the "
                 f"{settings.max_step_mm:g} mm the check's figures hold for: the offsets may be off by as much "
                 "(more frames per pass, or a slower sweep)"
                 for k, view in enumerate(surfaces) for p, s in enumerate(view) if s.step_mm > settings.max_step_mm)


def self_check(session: Session, calibration: Calibration, settings: CheckSettings = CheckSettings()) -> SelfCheck:
    """The self-check of one session's views (:func:`frames_by_view`) with ``calibration``."""
    return check_surfaces(view_surfaces(viewed_sweeps([(session, calibration)]), settings), settings)


VIEW_COLORS = ((230, 120, 30), (40, 130, 230), (60, 180, 80), (200, 60, 170))
"""Each view's colour in its PLY (orange, blue, green, purple, then again)."""


def view_file(view: int) -> str:
    """The name of a view's point cloud in a self-check's folder."""
    return f"view_{view}.ply"


class PassJSON(TypedDict):
    """One pass of a view against another (:class:`PassOffset`; mm, deg, base frame)."""

    view: int
    pass_index: int
    against_view: int
    against_pass: int
    points: int
    offset_mm: list[float]
    offset_norm_mm: float
    rotation_deg: float
    median_before_mm: float
    median_after_mm: float
    paired: float
    view_to_first: np.ndarray
    loose_twists: list[list[float]]  # (v mm, w rad) unit twists its surface does not pin


class ChangeJSON(TypedDict):
    """:class:`CalibrationChange` (image frame)."""

    translation_mm: list[float]
    rotation_deg: list[float]
    components: list[str]
    sensitivity_mm: list[float]
    visible: list[bool]
    unexplained_mm: float
    offsets_mm: float


class SelfCheckReport(TypedDict):
    """``report.json`` of ``probecal selfcheck``: the verdict, every pass's offset, the calibration
    change they imply, and each view's point cloud (base frame, mm)."""

    sessions: list[str]
    calibration: CalibrationSource
    trusted: bool
    cause: str
    cautions: list[str]
    max_offset_mm: float
    max_rotation_deg: float
    passes: list[PassJSON]
    calibration_change: ChangeJSON
    views: list[str]
    seconds: float


def _pass_json(offset: PassOffset) -> PassJSON:
    return PassJSON(view=offset.view, pass_index=offset.pass_index, against_view=offset.against_view,
                    against_pass=offset.against_pass, points=offset.points,
                    offset_mm=offset.offset_mm.tolist(), offset_norm_mm=offset.offset_norm_mm,
                    rotation_deg=offset.rotation_deg, median_before_mm=offset.median_before_mm,
                    median_after_mm=offset.median_after_mm, paired=offset.paired, view_to_first=offset.view_to_first,
                    loose_twists=offset.loose.tolist())


def write_self_check(views: list[ViewedSweep], out_dir: str | Path, settings: CheckSettings = CheckSettings(),
                     source: CalibrationSource | None = None) -> tuple[SelfCheck, SelfCheckReport]:
    """Check the views (:func:`viewed_sweeps`; ``source`` names their calibration, by default the
    first view's) and write ``report.json`` and every view's points (``view_K.ply``, one
    colour per view, base frame mm: 3D Slicer opens them) into the new folder ``out_dir``, built
    beside it and renamed into place once whole."""
    out_dir = fresh_folder(out_dir)
    started = time.perf_counter()
    surfaces = view_surfaces(views, settings)
    check = check_surfaces(surfaces, settings)
    change = check.change
    report = SelfCheckReport(
        sessions=list(dict.fromkeys(str(v.session.path) for v in views)),
        calibration=source or calibration_source(views[0].calibration), trusted=check.trusted,
        cause=check.cause, cautions=list(check.cautions), max_offset_mm=settings.max_offset_mm,
        max_rotation_deg=settings.max_rotation_deg,
        passes=[_pass_json(o) for o in check.offsets],
        calibration_change=ChangeJSON(translation_mm=change.translation_mm.tolist(),
                                      rotation_deg=change.rotation_deg.tolist(), components=list(COMPONENTS),
                                      sensitivity_mm=change.sensitivity.tolist(), visible=list(change.visible),
                                      unexplained_mm=change.unexplained_mm, offsets_mm=change.offsets_mm),
        views=[view_file(k) for k in range(len(surfaces))], seconds=0.0)
    with staged_folder(out_dir) as staging:
        for k, view in enumerate(surfaces):
            points = np.concatenate([s.points_base for s in view])
            write_ply(staging / view_file(k), points,
                      np.tile(np.array(VIEW_COLORS[k % len(VIEW_COLORS)], np.uint8), (len(points), 1)))
        report["seconds"] = round(time.perf_counter() - started, 2)
        write_json(staging / REPORT, report)
    return check, report
