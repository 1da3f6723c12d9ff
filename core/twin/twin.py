"""The digital twin: a UR3 carrying a linear probe over an N-wire phantom or a test object in a
water tank, with exact ground truth (SPEC §4).

Frames: ``base`` is the robot base (z up), ``tool`` the flange, ``image`` the pixel frame, and
``phantom``/``object`` the target's own frame. The true ``image_to_tool_rigid`` and the true
phantom placement differ from the nominal (design) ones by a few mm and degrees, drawn from the
seed, so a calibration has something real to find.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from probecal.core.twin.bmode import BModeRenderer
from probecal.core.twin.levels import Level, SetupErrors, level, water_sound_speed
from probecal.core.geometry.phantom import Phantom, default_phantom
from probecal.core.acquisition.plan import (
    Setup,
    SweepPlan,
    calibration_plan,
    image_across_wires,
    setup_from_centred_pose,
    volume_plan,
)
from probecal.core.geometry.probe import LinearProbe
from probecal.core.robot.simulated import SimulatedRobot
from probecal.core.io.session import Session, SessionWriter, load_session
from probecal.core.volume.surface import extract_surface
from probecal.core.twin.testobject import TEST_OBJECT_FILE, load_test_object
from probecal.core.geometry.transforms import invert_transform, make_transform, transform_points
from probecal.core.robot.ur3 import DhDeviation, Unreachable, flange_offset, forward_kinematics

Progress = Callable[[int, int], None]

# Design calibration of the probe mount: image x along tool x, depth (image y) along the tool z
# axis (out of the flange), the image's top-left pixel 100 mm beyond the flange.
MOUNT_OFFSET_MM = 100.0
# Nominal placement of targets in the base frame: turned half-way about the vertical so that the
# image x axis matches the flange x axis of the robot's home pose, centred below it at (0, -300).
TARGET_ROTATION_IN_BASE = np.diag([-1.0, -1.0, 1.0])
PHANTOM_ORIGIN_IN_BASE_MM = np.array([60.0, -250.0, -80.0])
# The tank floor sits this far below the lowest wire layer.
TANK_FLOOR_BELOW_WIRES_MM = 10.0


def nominal_image_to_tool(probe: LinearProbe) -> np.ndarray:
    """The mount's design ``image_to_tool_rigid`` (mm)."""
    axes = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return make_transform(axes, [-probe.width_mm / 2, 0.0, MOUNT_OFFSET_MM])


def _small_transform(rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    return make_transform(
        Rotation.from_euler("xyz", rng.uniform(-deg, deg, 3), degrees=True), rng.uniform(-mm, mm, 3)
    )


@dataclass(frozen=True)
class Twin:
    """Ground truth of one simulated set-up.

    ``phantom`` is the definition the software knows; ``built_phantom`` the wires as built (None:
    exactly the definition). ``dh_deviation`` makes the arm put its flange elsewhere than it
    reports (None: where it reports). ``image_to_flange_rigid`` is the mount on the real flange;
    the true calibration ``image_to_tool_rigid`` adds the constant part of the arm's error
    (``flange_to_tool``), as the controller's tool frame sees it. Image timestamps run
    ``image_latency_s`` late, with ``timestamp_jitter_s`` of jitter (s). ``water_temperature_c``
    set the probe's medium speed.
    """

    phantom: Phantom
    probe: LinearProbe
    phantom_to_base: np.ndarray
    image_to_flange_rigid: np.ndarray
    nominal: Setup
    built_phantom: Phantom | None = None
    dh_deviation: DhDeviation | None = None
    image_latency_s: float = 0.0
    timestamp_jitter_s: float = 0.0
    water_temperature_c: float | None = None

    @property
    def pixel_spacing_mm(self) -> tuple[float, float]:
        return self.probe.true_spacing_mm

    @property
    def wires(self) -> Phantom:
        """The phantom as built: what the images show."""
        return self.built_phantom or self.phantom

    @property
    def flange_to_tool(self) -> np.ndarray:
        """The constant part of the arm's flange error (``core.robot.ur3.flange_offset``); identity for
        an arm that moves as its table says. ``image_to_tool_rigid`` includes it: it is the true
        calibration in the tool frame the controller reports."""
        return np.eye(4) if self.dh_deviation is None else flange_offset(self.dh_deviation)

    @property
    def image_to_tool_rigid(self) -> np.ndarray:
        """The true calibration (mm): the mount seen from the tool frame the controller reports."""
        return self.flange_to_tool @ self.image_to_flange_rigid

    def actual_tool_to_base(self, reported_tool_to_base: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Where the tool frame is (mm) when the controller reports ``reported_tool_to_base`` at
        ``joints`` (rad): the real arm's kinematics applied to the reported pose, less the
        constant part of that error, which ``image_to_tool_rigid`` carries."""
        if self.dh_deviation is None:
            return reported_tool_to_base
        correction = invert_transform(forward_kinematics(joints)) @ forward_kinematics(joints, self.dh_deviation)
        return reported_tool_to_base @ correction @ invert_transform(self.flange_to_tool)

    @property
    def image_to_tool(self) -> np.ndarray:
        """PLUS-style ``image_to_tool`` including the pixel spacing (SPEC §2)."""
        return self.image_to_tool_rigid @ self.probe.scale_matrix()

    def image_to_phantom(self, tool_to_base: np.ndarray) -> np.ndarray:
        return invert_transform(self.phantom_to_base) @ tool_to_base @ self.image_to_tool_rigid

    def markers_px(self, tool_to_base: np.ndarray) -> np.ndarray:
        """(W, 2) true pixel positions of every wire crossing, phantom wire order; NaN where a
        wire does not cross the plane or crosses it out of view."""
        sx, sy = self.pixel_spacing_mm
        out = np.full((self.phantom.n_wires, 2), np.nan)
        for c in self.wires.crossings(self.image_to_phantom(tool_to_base)):
            u, v = c.point_image[0] / sx, c.point_image[1] / sy
            if 0 <= u <= self.probe.width_px - 1 and 0 <= v <= self.probe.height_px - 1:
                out[c.index] = (u, v)
        return out

    def wire_directions(self, tool_to_base: np.ndarray) -> np.ndarray:
        """(W, 3) unit direction of every wire as built, in the image frame, for a flange pose."""
        lines = self.wires.lines()
        d = lines[:, 1] - lines[:, 0]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d @ self.image_to_phantom(tool_to_base)[:3, :3]

    def truth(self) -> dict:
        """The SPEC §2 keys with their true values, and the set-up's errors."""
        dh = self.dh_deviation
        return {
            "image_to_tool": self.image_to_tool,
            "image_to_tool_rigid": self.image_to_tool_rigid,
            "pixel_spacing_mm": list(self.pixel_spacing_mm),
            "phantom_to_base": self.phantom_to_base,
            "setup": {
                "image_to_flange_rigid": self.image_to_flange_rigid,
                "water_temperature_c": self.water_temperature_c,
                "sound_speed_m_s": self.probe.medium_sound_speed,
                "image_latency_s": self.image_latency_s,
                "timestamp_jitter_s": self.timestamp_jitter_s,
                "dh_deviation": None if dh is None else {
                    "theta_deg": np.degrees(dh.theta).tolist(), "d_mm": dh.d.tolist(), "a_mm": dh.a.tolist(),
                    "alpha_deg": np.degrees(dh.alpha).tolist()},
                "wires_as_built": None if self.built_phantom is None else self.built_phantom.lines().tolist(),
            },
        }


def _built(phantom: Phantom, rng: np.random.Generator, tolerance_mm: float) -> Phantom | None:
    """The phantom with every wire end point off by up to ``tolerance_mm`` per axis; None at 0."""
    if tolerance_mm <= 0.0:
        return None
    return phantom.moved(rng.uniform(-tolerance_mm, tolerance_mm, (phantom.n_wires, 2, 3)))


def make_twin(seed: int = 0, phantom: Phantom | None = None, probe: LinearProbe | None = None,
              setup: SetupErrors = SetupErrors()) -> Twin:
    """A set-up whose true mount and phantom placement are drawn from ``seed``: the mount is off
    its design by up to 2 mm and 3 degrees per axis, the phantom by up to 2 mm and 2 degrees;
    then the ``setup`` errors (``core.twin.levels``), from their own stream so that the mount and
    placement of a seed are the same at every level.

    The planner knows only the mount's design and, as in the seed (3.3), where the operator
    jogged the probe so that the wire pattern is centred in the live image: from that flange
    pose it infers where the phantom must be.
    """
    phantom = phantom or default_phantom()
    probe = probe or LinearProbe()
    rng = np.random.default_rng(seed)
    phantom_to_base = make_transform(TARGET_ROTATION_IN_BASE, PHANTOM_ORIGIN_IN_BASE_MM) @ _small_transform(rng, 2.0, 2.0)
    mount = nominal_image_to_tool(probe) @ _small_transform(rng, 2.0, 3.0)
    centred_flange = phantom_to_base @ image_across_wires(phantom, probe) @ invert_transform(mount)
    bench = np.random.default_rng([seed, 15])
    temperature = None
    if setup.water_temperature_c is not None:
        temperature = float(bench.uniform(*setup.water_temperature_c))
        probe = replace(probe, medium_sound_speed=round(water_sound_speed(temperature), 2))
    dh = DhDeviation.draw(bench, setup.dh_length_mm, setup.dh_angle_deg) if setup.dh_length_mm or setup.dh_angle_deg else None
    return Twin(
        phantom=phantom,
        probe=probe,
        phantom_to_base=phantom_to_base,
        image_to_flange_rigid=mount,
        nominal=setup_from_centred_pose(phantom, probe, nominal_image_to_tool(probe), centred_flange),
        built_phantom=_built(phantom, bench, setup.phantom_tolerance_mm),
        dh_deviation=dh,
        image_latency_s=float(bench.uniform(*setup.image_latency_s)),
        timestamp_jitter_s=setup.timestamp_jitter_s,
        water_temperature_c=temperature,
    )


def _tank_bottom_rows(twin: Twin, image_to_target: np.ndarray, floor_z_mm: float) -> np.ndarray:
    """Per-column row where the plane z = floor_z (target frame) meets the image, NaN if none."""
    sx, sy = twin.pixel_spacing_mm
    u = np.arange(twin.probe.width_px, dtype=float)
    top = transform_points(image_to_target, np.column_stack([u * sx, np.zeros_like(u), np.zeros_like(u)]))
    down = image_to_target[:3, 1]  # unit depth direction in the target frame
    with np.errstate(divide="ignore", invalid="ignore"):
        depth_mm = (floor_z_mm - top[:, 2]) / down[2]
    rows = depth_mm / sy
    rows[(rows < 0) | (rows > twin.probe.height_px - 1) | ~np.isfinite(rows)] = np.nan
    return rows


def session_manifest(kind: str, twin: Twin, seed: int, noise: str | Level, plan: SweepPlan) -> dict:
    """The manifest of a session the twin's scanner images."""
    return {
        "kind": kind,
        "source": {"simulator": "probecal digital twin", "seed": seed, "noise": level(noise).name},
        "image_size": [twin.probe.width_px, twin.probe.height_px],
        "pixel_spacing_mm": list(twin.probe.nominal_spacing_mm),
        "phantom_to_base": None,
        "plan": plan.summary(),
    }


# Volume scene: the test object sits on the tank floor in front of the robot, the probe face
# 12 mm above its highest point.
OBJECT_ORIGIN_IN_BASE_MM = np.array([30.0, -280.0, -80.0])
VOLUME_STANDOFF_MM = 12.0


class TwinScanner:
    """The twin's scanner: the B-mode frame a flange pose sees of the phantom (calibration) or
    of the test object (volume). The object's true placement is drawn from ``seed`` like the
    phantom's; ``nominal_object_to_base`` is where it was meant to go."""

    def __init__(self, twin: Twin, noise: str | Level = "realistic", seed: int = 0):
        self.level = level(noise)
        self.twin, self.noise = twin, self.level.name
        self.renderer = BModeRenderer(twin.probe, self.level.noise, seed, self.level.imaging)
        self.nominal_object_to_base = make_transform(TARGET_ROTATION_IN_BASE, OBJECT_ORIGIN_IN_BASE_MM)
        self.object_to_base = self.nominal_object_to_base @ _small_transform(np.random.default_rng(seed + 1), 2.0, 2.0)
        self._floor_z = twin.phantom.lines()[..., 2].min() - TANK_FLOOR_BELOW_WIRES_MM

    @cached_property
    def mesh(self) -> trimesh.Trimesh:
        """The test object's CAD mesh (object frame, mm)."""
        return load_test_object()

    @cached_property
    def _onset_px(self) -> float:
        return echo_onset_offset_px(self.twin.probe)

    def region_to_base(self) -> np.ndarray:
        """The volume scan's region of interest: the top centre of the object where it was meant
        to sit (z up, mm)."""
        lo, hi = self.mesh.bounds
        return self.nominal_object_to_base @ make_transform(np.eye(3), [*(lo + hi)[:2] / 2, hi[2]])

    def calibration_frame(self, tool_to_base: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The frame over the phantom at a flange pose, and the true marker pixels (W, 2; NaN
        where a wire is out of view)."""
        twin = self.twin
        markers = twin.markers_px(tool_to_base)
        seen = np.all(np.isfinite(markers), axis=1)
        image = self.renderer.render(
            markers[seen],
            tank_bottom_row=_tank_bottom_rows(twin, twin.image_to_phantom(tool_to_base), self._floor_z),
            rng=rng,
            directions=twin.wire_directions(tool_to_base)[seen],
        )
        return image, markers

    def image_delay_s(self, rng: np.random.Generator) -> float:
        """How late (s) the scanner stamps a frame: the twin's latency plus its jitter."""
        jitter = self.twin.timestamp_jitter_s
        return self.twin.image_latency_s + (float(rng.normal(0.0, jitter)) if jitter else 0.0)

    def volume_frame(self, tool_to_base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The frame over the test object at a flange pose."""
        image_to_object = invert_transform(self.object_to_base) @ tool_to_base @ self.twin.image_to_tool_rigid
        return self.renderer.render(
            np.empty((0, 2)),
            surface_rows=_surface_rows(self.twin, self.mesh, image_to_object) + self._onset_px,
            tank_bottom_row=_tank_bottom_rows(self.twin, image_to_object, 0.0),
            rng=rng,
        )

    def volume_truth(self) -> dict:
        return {**self.twin.truth(), "object_to_base": self.object_to_base, "cad_mesh": TEST_OBJECT_FILE.name}


def twin_scanner(seed: int = 0, noise: str | Level = "realistic", phantom: Phantom | None = None) -> TwinScanner:
    """The twin of ``seed`` with the set-up errors of level ``noise``, and its scanner."""
    lvl = level(noise)
    return TwinScanner(make_twin(seed, phantom, setup=lvl.setup), lvl, seed)


def markers_to_json(markers: np.ndarray) -> list:
    """truth.json's per-frame ``markers_px``: [u, v] per wire, null where out of view."""
    return [None if np.isnan(m[0]) else m.tolist() for m in markers]


def simulate_calibration(
    out_dir: str | Path,
    n_poses: int = 60,
    seed: int = 0,
    noise: str | Level = "realistic",
    phantom: Phantom | None = None,
    progress: Progress | None = None,
) -> Session:
    """Run the calibration acquisition on the twin and record it as a session with truth.json.

    The session records the flange pose the robot reports; the image shows the phantom from
    where the flange actually is (``Twin.actual_tool_to_base``), and is stamped by the scanner's
    late clock. At ``harsh`` noise some frames are dropped by the "scanner" (not recorded) and
    some poses are shifted so that a wire leaves the field of view.
    """
    scanner = twin_scanner(seed, noise, phantom)
    twin, lvl = scanner.twin, scanner.level
    plan = calibration_plan(twin.nominal, n_poses, seed=seed)
    rng = np.random.default_rng(seed + 1)
    robot = SimulatedRobot(seed=seed, time_scale=0.0)
    robot.connect()
    truth_frames = []
    dropped = 0
    harsh = lvl.name == "harsh"
    manifest = session_manifest("calibration", twin, seed, lvl, SweepPlan.from_plans([plan]))
    with SessionWriter(out_dir, manifest, twin.phantom, twin.probe) as writer:
        for k, target in enumerate(plan.poses):
            if progress:
                progress(k + 1, len(plan.poses))
            if harsh and rng.random() < 0.05:
                target = target.copy()  # slide sideways so that an outer wire leaves the view
                target[:3, 3] += target[:3, 0] * rng.choice([-1.0, 1.0]) * 8.0
            try:
                robot.move_linear(target)
            except Unreachable:
                continue
            reported = robot.tool_to_base()
            actual = twin.actual_tool_to_base(reported, robot.joints())
            if harsh and rng.random() < 0.03:
                dropped += 1
                continue
            image, markers = scanner.calibration_frame(actual, rng)
            t = robot.elapsed_motion_s
            index = writer.append(image, reported, timestamp=t + scanner.image_delay_s(rng), pose_timestamp=t)
            truth_frames.append({"index": index, "markers_px": markers_to_json(markers),
                                 "tool_to_base": actual.tolist()})
        writer.write_truth({**twin.truth(), "frames": truth_frames})
        writer.update_manifest(dropped_frames=dropped, robot_time_s=round(robot.elapsed_motion_s, 1))
    return load_session(out_dir)


def echo_onset_offset_px(probe: LinearProbe) -> float:
    """How far (px) a specular echo's centre lies below the edge where it rises through the
    display's half gray level. The twin puts that leading edge on the interface, because a real
    echo begins where the sound meets the surface and rings on below it."""
    rows = np.full(probe.width_px, probe.height_px / 2.0)
    image = BModeRenderer(probe, "none", 0).render(np.empty((0, 2)), surface_rows=rows)
    _, leading = extract_surface(image)
    return float(rows[0] - np.median(leading))


def _surface_rows(twin: Twin, mesh: trimesh.Trimesh, image_to_object: np.ndarray) -> np.ndarray:
    """Per-column row of the first surface the beam meets in the image plane, NaN where none."""
    sx, sy = twin.pixel_spacing_mm
    origin, normal = image_to_object[:3, 3], image_to_object[:3, 2]
    segments = trimesh.intersections.mesh_plane(mesh, normal, origin)
    rows = np.full(twin.probe.width_px, np.nan)
    if len(segments) == 0:
        return rows
    seg = transform_points(invert_transform(image_to_object), segments)[..., :2]  # image mm
    x0, x1, y0, y1 = seg[:, 0, 0], seg[:, 1, 0], seg[:, 0, 1], seg[:, 1, 1]
    x = np.arange(twin.probe.width_px)[:, None] * sx
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (x - x0) / (x1 - x0)
    hit = (t >= 0) & (t <= 1) & np.isfinite(t)
    depth = np.where(hit, y0 + t * (y1 - y0), np.inf).min(axis=1)
    valid = np.isfinite(depth) & (depth >= 0)
    rows[valid] = depth[valid] / sy
    rows[rows > twin.probe.height_px - 1] = np.nan
    return rows


def simulate_volume(out_dir: str | Path, seed: int = 0, noise: str | Level = "realistic", n_frames: int = 120,
                    progress: Progress | None = None) -> Session:
    """Sweep the test object in straight passes and record a session with truth.json and the
    object's CAD mesh (``test_object.stl``) beside it; poses and stamps as in
    :func:`simulate_calibration`."""
    scanner = twin_scanner(seed, noise)
    twin, lvl = scanner.twin, scanner.level
    rng = np.random.default_rng(seed + 1)
    passes = volume_plan(scanner.region_to_base(), twin.nominal.image_to_tool_rigid, twin.probe, VOLUME_STANDOFF_MM,
                         n_frames=n_frames)
    total = sum(len(p.poses) for p in passes)
    manifest = session_manifest("volume", twin, seed, lvl, SweepPlan.from_plans(passes))
    manifest["cad_mesh"] = TEST_OBJECT_FILE.name
    robot = SimulatedRobot(seed=seed, time_scale=0.0)
    robot.connect()
    done = 0
    with SessionWriter(out_dir, manifest, probe=twin.probe) as writer:
        (Path(out_dir) / TEST_OBJECT_FILE.name).write_bytes(TEST_OBJECT_FILE.read_bytes())
        for pass_index, plan in enumerate(passes):
            for target in plan.poses:
                done += 1
                robot.move_linear(target)
                reported = robot.tool_to_base()
                image = scanner.volume_frame(twin.actual_tool_to_base(reported, robot.joints()), rng)
                t = robot.elapsed_motion_s
                writer.append(image, reported, timestamp=t + scanner.image_delay_s(rng), pose_timestamp=t,
                              sweep=pass_index)
                if progress:
                    progress(done, total)
        writer.write_truth(scanner.volume_truth())
        writer.update_manifest(robot_time_s=round(robot.elapsed_motion_s, 1))
    return load_session(out_dir)
