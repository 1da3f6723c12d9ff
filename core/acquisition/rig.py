"""What the console and ``probecal sweep`` drive: a robot behind the workspace guard, where the
frames come from, and what the planner knows of the set-up; and the recording of a sweep.

The robot is the twin's UR3 in-process or a UR controller (or the simulated one, ``URSim``)
through ur_rtde. The images are the twin's scanner's, imaged at whatever pose the robot reports,
or a live stream (core.acquisition.imagesource). With the twin's scanner the planner knows where
the twin put the phantom and the test object and the session gets its truth.json; with a live
source the operator first jogs the probe so that the wire pattern (or the object) is centred
under it, and the plans are made around that pose.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from probecal.core.acquisition.imagesource import ImageSource
from probecal.core.acquisition.plan import (
    DEFAULT_PASSES,
    PASS_LENGTH_MM,
    SELF_CHECK_PASS_MM,
    SELF_CHECK_PASSES,
    SELF_CHECK_VIEWS,
    TEMPORAL_STROKES,
    VOLUME_SPEED_MM_S,
    Leg,
    PoseRanges,
    ProbeView,
    SweepPass,
    SweepPlan,
    calibration_plan,
    continuous_calibration_legs,
    continuous_volume_legs,
    legs_duration_s,
    temporal_legs,
    temporal_waypoints,
    viewed_volume_plan,
)
from probecal.core.acquisition.simulate import session_manifest
from probecal.core.acquisition.sweep import (
    ContinuousSweep,
    Grabber,
    Show,
    SourceGrabber,
    Sweep,
    SweepOutcome,
    TwinGrabber,
    resume_state,
    start_session,
)
from probecal.core.errors import InputError
from probecal.core.geometry.probe import Probe
from probecal.core.geometry.setup import Setup, nominal_image_to_tool, setup_from_centred_pose
from probecal.core.geometry.transforms import make_transform, transform_points
from probecal.core.io.jsonio import expect_list
from probecal.core.io.manifest import CONTINUOUS, Manifest, RigSpec
from probecal.core.io.session import TRUTH, SessionWriter, read_manifest, read_truth
from probecal.core.robot.armkinematics import record_of
from probecal.core.robot.contract import Robot
from probecal.core.robot.safety import GuardedRobot, Workspace, load_workspace
from probecal.core.robot.ur3 import UR3, MotionLimits, identify_arm
from probecal.core.twin.levels import DEFAULT_LEVEL
from probecal.core.twin.scanner import VOLUME_STANDOFF_MM, TwinScanner, twin_scanner
from probecal.core.twin.testobject import TEST_OBJECT_FILE
from probecal.core.twin.twin import TARGET_ROTATION_IN_BASE, Twin


@dataclass
class Rig:
    """A robot (guarded), a frame source and the set-up the planner works from."""

    robot: GuardedRobot
    robot_name: str
    scanner: TwinScanner
    source: ImageSource | None = None  # None: the twin's scanner
    seed: int = 0
    latency_s: float = 0.0  # image timestamps minus this are robot-pose times (s)
    specs: tuple[str, str] = ("sim", "sim")  # the robot and the images as the user named them
    spacing_mm: tuple[float, float] | None = None  # the scanner's nominal (sx, sy) mm/px, as given
    start_depth_mm: float | None = None  # a live scanner's first row below the probe's face (mm), as given

    @property
    def twin(self) -> Twin:
        return self.scanner.twin

    @property
    def simulated_images(self) -> bool:
        return self.source is None

    @property
    def image_name(self) -> str:
        return "the simulated scanner" if self.source is None else self.source.name

    def open(self) -> None:
        """Connect the robot and open the image stream. The twin's arm deviates from the
        kinematics the controller states it computes with (a factory-calibrated UR3's), when it
        states them."""
        if not self.robot.connected:
            self.robot.connect()
        kinematics = self.robot.kinematics()
        if kinematics is not None and kinematics.table.name == UR3.name:
            self.scanner.twin = replace(self.twin, controller=kinematics.deviation)
        if self.source is not None:
            self.source.open()

    def close(self) -> None:
        self.robot.stop()
        self.robot.disconnect()
        if self.source is not None:
            self.source.close()

    def grabber(self, kind: str) -> Grabber:
        if self.source is None:
            return TwinGrabber(self.scanner, "volume" if kind == "volume" else "calibration", self.seed)
        return SourceGrabber(self.source, self.latency_s)

    def image_format(self) -> tuple[tuple[int, int], tuple[float, float]]:
        """(width, height) px and the nominal (sx, sy) mm/px of the frames: as given, else the
        source's when it states one, else the twin probe's."""
        if self.source is None:
            probe = self.twin.probe
            return (probe.width_px, probe.height_px), self.spacing_mm or probe.nominal_spacing_mm
        frame = self.source.latest(2.0)
        spacing = self.spacing_mm or frame.pixel_spacing_mm or self.twin.probe.nominal_spacing_mm
        return (frame.image.shape[1], frame.image.shape[0]), spacing

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """A frame at the robot's current pose and that pose."""
        pose = self.robot.tool_to_base()
        if self.source is None:
            return self.scanner.calibration_frame(pose, np.random.default_rng())[0], pose
        return self.source.latest(2.0).image, pose

    def setup(self) -> Setup:
        """Where the planner believes the phantom is."""
        if self.source is None:
            return self.twin.nominal
        twin = self.twin
        return setup_from_centred_pose(twin.phantom, twin.probe, nominal_image_to_tool(twin.probe),
                                       self.robot.tool_to_base())

    def calibration_plan(self, n_poses: int, ranges: PoseRanges, limits: MotionLimits, draw: int = 0,
                         progress: Callable[[int, int], None] | None = None) -> SweepPlan:
        """``n_poses`` calibration poses within ``ranges``; ``draw`` picks other poses of the same
        seed (a sweep's added poses, not those it holds); ``progress`` as for
        :func:`core.acquisition.plan.calibration_plan`."""
        seed = self.seed if not draw else np.random.default_rng([self.seed, draw])
        try:
            plan = calibration_plan(self.setup(), n_poses, seed=seed, ranges=ranges, start_joints=self.robot.joints(),
                                    limits=limits, progress=progress)
        except ValueError as exc:
            raise InputError(None, f"no calibration plan: {exc}")
        return self._inside_workspace(SweepPlan.from_plans([plan]))

    def temporal_plan(self, strokes: int = TEMPORAL_STROKES) -> SweepPlan:
        """The temporal calibration's motion about the centre pose over the phantom, ``strokes``
        up or down: a continuous recording of kind "temporal" drives it (:class:`Recording`)."""
        setup = self.setup()
        centre = setup.tool_to_base(setup.image_to_phantom)
        poses = [centre, *temporal_waypoints(centre, setup.image_to_tool_rigid, strokes=strokes)]
        return self._inside_workspace(SweepPlan(poses, [0] * len(poses), 0.0))

    def volume_plan(self, frames_per_pass: int, limits: MotionLimits,
                    progress: Callable[[int, int], None] | None = None,
                    views: tuple[ProbeView, ...] | None = None, passes: tuple[SweepPass, ...] = DEFAULT_PASSES,
                    length_mm: float = PASS_LENGTH_MM) -> SweepPlan:
        """``passes`` of ``frames_per_pass`` frames, ``length_mm`` long, over the object (its top
        under the probe, on a live rig), swept again from each of ``views`` in turn when given (the
        plan then states each pose's view); ``progress`` as for
        :func:`core.acquisition.plan.volume_plan`, over every view's poses."""
        if self.source is None:
            region_to_base = self.scanner.region_to_base()
        else:  # the object's top centre lies under the probe face, at the scanning stand-off
            mount = nominal_image_to_tool(self.twin.probe)
            face = transform_points(self.robot.tool_to_base() @ mount,
                                    np.array([[self.twin.probe.width_mm / 2, 0, 0]]))[0]
            region_to_base = make_transform(TARGET_ROTATION_IN_BASE, face - [0.0, 0.0, VOLUME_STANDOFF_MM])
        try:
            plan = viewed_volume_plan(region_to_base, self.twin.nominal.image_to_tool_rigid, self.twin.probe,
                                      VOLUME_STANDOFF_MM, views, passes, length_mm, frames_per_pass,
                                      self.robot.joints(), limits, progress)
        except ValueError as exc:
            raise InputError(None, f"no volume plan: {exc}")
        return self._inside_workspace(plan)

    def self_check_plan(self, frames_per_pass: int, limits: MotionLimits,
                        progress: Callable[[int, int], None] | None = None) -> SweepPlan:
        """A self-check's sweep (``core.volume.selfcheck``): :data:`SELF_CHECK_PASSES`, each
        :data:`SELF_CHECK_PASS_MM` long with ``frames_per_pass`` frames, from every one of
        :data:`SELF_CHECK_VIEWS`."""
        return self.volume_plan(frames_per_pass, limits, progress, SELF_CHECK_VIEWS, SELF_CHECK_PASSES,
                                SELF_CHECK_PASS_MM)

    def _inside_workspace(self, plan: SweepPlan) -> SweepPlan:
        workspace = self.robot.workspace
        outside = sum(not workspace.contains(p) for p in plan.poses)
        if outside:
            raise InputError(None, f"{outside} of the plan's {len(plan.poses)} poses leave the workspace box; "
                                   "narrow the ranges or move the probe")
        return plan

    def manifest(self, kind: str, plan: SweepPlan) -> Manifest:
        """The session manifest of an acquisition on this rig; its ``arm`` is the table the
        robot's joints and flange pose follow (:func:`core.robot.ur3.identify_arm`), its
        ``arm_kinematics`` what the controller computes them with, where it states that."""
        if self.source is None:
            manifest = session_manifest(kind, self.twin, self.seed, self.scanner.level, plan)
            manifest = replace(manifest, source={**(manifest.source or {}), "robot": self.robot_name},
                               pixel_spacing_mm=self.image_format()[1])
        else:
            size, spacing = self.image_format()
            manifest = Manifest(kind=kind, source={"robot": self.robot_name, "image": self.source.name},
                                image_size=size, pixel_spacing_mm=spacing, start_depth_mm=self.start_depth_mm,
                                plan=plan.summary())
        arm = identify_arm(self.robot.joints(), self.robot.tool_to_base())
        kinematics = self.robot.kinematics()
        return replace(manifest,
                       arm=None if arm is None else arm.name,  # the table its joints and poses follow
                       arm_kinematics=None if kinematics is None else record_of(kinematics),
                       rig=RigSpec(robot=self.specs[0], image=self.specs[1], seed=self.seed,
                                   latency_s=self.latency_s, spacing_mm=self.spacing_mm,
                                   start_depth_mm=self.start_depth_mm),
                       workspace=self.robot.workspace.to_dict(),
                       cad_mesh=TEST_OBJECT_FILE.name if kind == "volume" else None)

    def truth(self, kind: str) -> dict | None:
        """truth.json (without the per-frame part) when the twin made the images."""
        if self.source is not None:
            return None
        return self.scanner.volume_truth() if kind == "volume" else self.twin.truth()


def assemble_rig(arm: Robot, robot_name: str, source: ImageSource | None, seed: int = 0,
                 workspace: Workspace | None = None, latency_s: float = 0.0,
                 spacing_mm: tuple[float, float] | None = None, start_depth_mm: float | None = None,
                 probe: Probe | None = None, specs: tuple[str, str] = ("sim", "sim")) -> Rig:
    """A rig of ``arm`` (called ``robot_name`` in messages) behind ``workspace`` (default the
    shipped one) and ``source`` (None: the twin's scanner, imaging with ``probe``, its default when
    None); ``specs`` name the robot and the images as the user did, recorded to resume a sweep."""
    return Rig(GuardedRobot(arm, workspace or load_workspace()), robot_name,
               twin_scanner(seed, DEFAULT_LEVEL, probe=probe), source, seed, latency_s, specs=specs,
               spacing_mm=spacing_mm, start_depth_mm=start_depth_mm)


class Recording:
    """One sweep of a rig into a session folder: a new session from ``plan``, or, with no plan,
    the unfinished sweep in ``path`` resumed where it ended. ``motion`` "stop" takes one frame at
    every settled pose; "continuous" drives the plan without stopping (for a calibration, after
    the temporal calibration's up-and-down motion) and records every frame of the stream
    (``core.acquisition.sweep.ContinuousSweep``; not resumable), a volume's passes at
    ``speed_mm_s``. ``sweep`` can be stopped from another thread while :meth:`run` records."""

    def __init__(self, rig: Rig, kind: str, path: Path, plan: SweepPlan | None, limits: MotionLimits,
                 show: Show | None = None, motion: str = "stop", speed_mm_s: float = VOLUME_SPEED_MM_S):
        self.rig, self.kind, self.path, self.speed_mm_s = rig, kind, Path(path), speed_mm_s
        self.earlier_truth_frames: list[dict] = []  # of the frames recorded before a resume
        self.robot_time_s = plan.duration_s if plan is not None else 0.0  # the estimated UR3 time
        if plan is None:
            if read_manifest(self.path).continuous:
                raise InputError(self.path, "a continuous sweep cannot be resumed: record a new one")
            plan, self.done = resume_state(self.path)
            self.writer = SessionWriter(self.path, Manifest(), resume=True)
            truth = read_truth(self.path)  # the writer has read the records already
            if truth is not None:
                self.earlier_truth_frames = expect_list(truth.get("frames", []), self.path / TRUTH, "frames")
        else:
            self.done = set()
            phantom = rig.twin.phantom if kind != "volume" else None
            files = {TEST_OBJECT_FILE.name: TEST_OBJECT_FILE.read_bytes()} if kind == "volume" else None
            manifest = rig.manifest(kind, plan)
            if motion == "continuous":
                legs = self._legs(plan, limits)
                self.robot_time_s = legs_duration_s(rig.robot.tool_to_base(), legs)
                estimate = {"estimated_robot_time_s": round(self.robot_time_s, 1)}
                manifest = replace(manifest, motion=CONTINUOUS, plan={**(manifest.plan or {}), **estimate})
            self.writer = start_session(self.path, manifest, plan, files, phantom=phantom, probe=rig.twin.probe)
        self.sweep: Sweep | ContinuousSweep
        if motion == "continuous":
            self.sweep = ContinuousSweep(rig.robot, rig.grabber(kind), legs, rig.latency_s, show)
        else:
            self.sweep = Sweep(rig.robot, rig.grabber(kind), plan, limits, show)

    def _legs(self, plan: SweepPlan, limits: MotionLimits) -> list[Leg]:
        """Volume: its passes; temporal: the motion its plan holds; calibration: the temporal
        motion, then the plan."""
        if self.kind == "volume":
            return continuous_volume_legs(plan, limits, self.speed_mm_s)
        if self.kind == "temporal":
            return temporal_legs(plan.poses, limits)
        setup = self.rig.setup()
        return continuous_calibration_legs(setup.tool_to_base(setup.image_to_phantom), setup.image_to_tool_rigid,
                                           plan, limits)

    @property
    def frames(self) -> int:
        """Frames in the session, from earlier runs and this one."""
        return len(self.writer)

    def run(self) -> SweepOutcome:
        """Record; the session, its truth (for the twin's images) and every frame stay on disk
        however the sweep ends."""
        with self.writer:
            try:
                return self.sweep.run(self.writer, self.done)
            finally:
                self._write_truth()

    def _write_truth(self) -> None:
        truth = self.rig.truth(self.kind)
        if truth is None:
            return
        if self.kind != "volume":
            truth["frames"] = self.earlier_truth_frames + self.sweep.truth_frames
        self.writer.write_truth(truth)

