"""Sessions recorded on the digital twin: a calibration sweep over the phantom or straight volume
sweeps over the test object, each with its ground truth in ``truth.json`` (design §4)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from probecal.core.acquisition.pairing import stream_buffer
from probecal.core.acquisition.plan import (
    DEFAULT_PASSES,
    FREEHAND_RANGES,
    HAND_CYCLES,
    PASS_LENGTH_MM,
    VOLUME_SPEED_MM_S,
    Leg,
    PoseRanges,
    ProbeView,
    SweepPass,
    SweepPlan,
    calibration_plan,
    continuous_calibration_legs,
    continuous_volume_legs,
    hand_path,
    viewed_volume_plan,
)
from probecal.core.errors import InputError, Remedy
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Probe
from probecal.core.geometry.setup import Setup, image_across_wires
from probecal.core.io.files import staged_folder
from probecal.core.io.limits import checked_bytes
from probecal.core.io.manifest import CONTINUOUS, Manifest, matrix_of
from probecal.core.io.session import Session, SessionWriter, load_session
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.simulated import STREAM_HZ, SimulatedRobot
from probecal.core.robot.trajectory import CHECK_STEP_S, BlendedPath, blended_path
from probecal.core.robot.ur3 import Unreachable, closest_ik, forward_kinematics
from probecal.core.twin.bmode import check_imaging
from probecal.core.twin.levels import Level, level
from probecal.core.twin.scanner import VOLUME_STANDOFF_MM, TwinScanner, json_from_markers, twin_scanner
from probecal.core.twin.testobject import TEST_OBJECT_FILE
from probecal.core.twin.twin import Twin, pose_drift, pose_noise

Progress = Callable[[int, int], None]


def session_manifest(kind: str, twin: Twin, seed: int, noise: str | Level, plan: SweepPlan) -> Manifest:
    """The manifest of a session the twin's scanner images (with a convex probe's fan)."""
    return Manifest(
        kind=kind,
        source={"simulator": "probecal digital twin", "seed": seed, "noise": level(noise).name},
        arm="UR3",
        image_size=(twin.probe.width_px, twin.probe.height_px),
        pixel_spacing_mm=twin.probe.nominal_spacing_mm,
        start_depth_mm=twin.probe.start_depth_mm,
        plan=plan.summary(),
        fan=twin.probe.fan,
    )


MOTIONS = ("stop", "continuous")
FRAME_RATE_HZ = 25.0
"""The twin scanner's frame rate in a continuous sweep (Hz)."""
MAX_SIMULATED_FRAMES = 100_000
MAX_SIMULATED_S = 3600.0
"""A continuous sweep on the twin records at most this many frames, its pose stream at most this long."""
STREAM_TAIL_S = 1.0
"""The pose stream is kept this long (s) beyond the last frame's timestamp: the robot at rest."""


@contextmanager
def _staged_writer(out_dir: str | Path, manifest: Manifest, phantom: Phantom | None = None, probe: Probe | None = None,
                   files: dict[str, bytes] | None = None) -> Iterator[SessionWriter]:
    """A writer of the new session ``out_dir``, built under another name beside it, read back and
    renamed into place once whole: on any error, an interrupt too, nothing is left
    (:func:`staged_folder`)."""
    with staged_folder(out_dir) as folder:
        with SessionWriter(folder, manifest, phantom, probe, files=files) as writer:
            yield writer
        load_session(folder)


def simulate_calibration(
    out_dir: str | Path,
    n_poses: int = 60,
    seed: int = 0,
    noise: str | Level = "realistic",
    phantom: Phantom | None = None,
    progress: Progress | None = None,
    motion: str = "stop",
    frame_rate_hz: float = FRAME_RATE_HZ,
    image_latency_s: float | None = None,
    built_phantom: Phantom | None = None,
    ranges: PoseRanges | None = None,
    probe: Probe | None = None,
) -> Session:
    """Run the calibration acquisition on the twin and record it as a session with truth.json.

    ``motion="stop"``: the robot stops at every pose and one frame is taken there. The session
    records the flange pose the robot reports; the image shows the phantom from where the flange
    actually is (``Twin.actual_tool_to_base``), and is stamped by the scanner's late clock. At
    ``harsh`` noise some frames are dropped by the "scanner" (not recorded) and some poses are
    shifted so that a wire leaves the field of view.

    ``motion="continuous"``: see :func:`_continuous_calibration`. ``image_latency_s`` replaces
    the twin's own (drawn from the seed at ``bench``); ``built_phantom``, the phantom the images
    show (the definition's wires placed as built; the session records the definition); ``ranges``,
    how far the plan's poses spread about the nominal one (default: :class:`PoseRanges`'s);
    ``probe``, another probe than the default (its image size: a scanner that resamples finer or
    coarser).
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {', '.join(MOTIONS)}")
    scanner = twin_scanner(seed, noise, phantom, image_latency_s, built_phantom, probe)
    twin, lvl = scanner.twin, scanner.level
    _check_frames(twin.probe, n_poses)
    plan = calibration_plan(twin.nominal, n_poses, seed=seed, ranges=ranges or PoseRanges())
    rng = np.random.default_rng(seed + 1)
    manifest = session_manifest("calibration", twin, seed, lvl, SweepPlan.from_plans([plan]))
    if motion == "continuous":
        return _continuous_calibration(out_dir, scanner, SweepPlan.from_plans([plan]), manifest, rng, frame_rate_hz,
                                       progress)
    robot = SimulatedRobot(seed=seed, time_scale=0.0)
    robot.connect()
    truth_frames = []
    dropped = 0
    harsh = lvl.name == "harsh"
    with _staged_writer(out_dir, manifest, twin.phantom, twin.probe) as writer:
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
            truth_frames.append({"index": index, "markers_px": json_from_markers(markers),
                                 "tool_to_base": actual.tolist()})
        writer.write_truth({**twin.truth(), "frames": truth_frames})
        writer.update_manifest(dropped_frames=dropped, robot_time_s=round(robot.elapsed_motion_s, 1))
    return load_session(out_dir)


def simulate_freehand(
    out_dir: str | Path,
    n_poses: int = 120,
    seed: int = 0,
    noise: str | Level = "bench",
    phantom: Phantom | None = None,
    built_phantom: Phantom | None = None,
    ranges: PoseRanges = FREEHAND_RANGES,
    cycles: float = HAND_CYCLES,
    path: int = 0,
    progress: Progress | None = None,
) -> Session:
    """A tracked freehand calibration recording on the twin, as PLUS's fCal records one: a hand
    moves the probe along a smooth path (:func:`~probecal.core.acquisition.plan.hand_path`, on the
    phantom where it is), an optical tracker reports every pose in its ``base`` (reference) frame
    with the level's ``tracker_noise`` and its slow ``tracker_drift``, and the phantom pose is known
    as registered (manifest ``phantom_to_base``, off the truth by the level's
    ``phantom_registration``, the same on every path of a seed). No arm; one frame per pose, stamped with it.

    The level's set-up errors that belong to a robot (its kinematics, the image latency) do not
    act; the phantom as built, the water and the scanner do, so the same seed's wires are built
    off the same way as in :func:`simulate_calibration`; ``path`` picks another of the hand's
    paths over the same bench (a validation recording)."""
    scanner = twin_scanner(seed, noise, phantom, 0.0, built_phantom)
    twin, lvl = scanner.twin, scanner.level
    _check_frames(twin.probe, n_poses)
    seen = Setup(twin.phantom, twin.probe, twin.phantom_to_base, twin.image_to_tool_rigid,
                 image_across_wires(twin.phantom, twin.probe))
    poses = hand_path(seen, n_poses, seed, ranges, cycles, path)
    sd = np.asarray(lvl.setup.phantom_registration, dtype=float)
    registered = twin.phantom_to_base @ pose_noise(np.random.default_rng([seed, 30]), sd[:3], sd[3:])
    manifest = replace(session_manifest("calibration", twin, seed, lvl,
                                        SweepPlan(poses, [0] * len(poses), len(poses) / FRAME_RATE_HZ)),
                       arm=None, phantom_to_base=matrix_of(registered))
    rng = np.random.default_rng([seed, 1, path])
    tracker = np.random.default_rng([seed, 18, path])
    mm, deg = lvl.setup.tracker_noise
    drift = pose_drift(np.random.default_rng([seed, 20, path]), len(poses), *lvl.setup.tracker_drift)
    truth_frames = []
    with _staged_writer(out_dir, manifest, twin.phantom, twin.probe) as writer:
        for k, actual in enumerate(poses):
            if progress:
                progress(k + 1, len(poses))
            image, markers = scanner.calibration_frame(actual, rng)
            t = k / FRAME_RATE_HZ
            index = writer.append(image, actual @ drift[k] @ pose_noise(tracker, mm, deg), timestamp=t,
                                  pose_timestamp=t)
            truth_frames.append({"index": index, "markers_px": json_from_markers(markers),
                                 "tool_to_base": actual.tolist()})
        writer.write_truth({**twin.truth(), "frames": truth_frames})
    return load_session(out_dir)

@dataclass(frozen=True)
class _Driven:
    """A leg as the robot drives it: its path from where the leg before it ended."""

    path: BlendedPath
    record: dict | None


FRAME_BYTES = 16 << 10
"""What recording one simulated frame holds until its session is written: its planned pose, its
record and its truth (the true pose and marker pixels); measured 13 kB a calibration frame, 6 kB
a volume frame."""


def _check_frames(probe: Probe, frames: float) -> None:
    """InputError when recording ``frames`` frames of ``probe`` would pass the memory limit:
    :data:`FRAME_BYTES` each beside what imaging them takes (:func:`check_imaging`), counted
    before the plan is made."""
    checked_bytes(None, f"simulating {frames:.0f} frames of {probe.width_px} x {probe.height_px} px",
                  [math.ceil(frames) * FRAME_BYTES + check_imaging(probe)])


def _check_recording(frames: float, duration_s: float) -> None:
    """Refuse a continuous sweep of more than :data:`MAX_SIMULATED_FRAMES` frames or whose pose
    stream (the robot's time and the image latency) passes :data:`MAX_SIMULATED_S`, before its
    times are laid out in memory."""
    if not (frames <= MAX_SIMULATED_FRAMES and duration_s <= MAX_SIMULATED_S):
        raise InputError(None, f"the simulated sweep would record {frames:.3g} frames over {duration_s:.3g} s (robot "
                               f"time and image latency); at most {MAX_SIMULATED_FRAMES} frames and "
                               f"{MAX_SIMULATED_S:g} s: check the pass speed, the frame rate and the image latency",
                         (Remedy.SWEEP_TIMING,))


def _record_legs(writer: SessionWriter, scanner: TwinScanner, plan_legs: list[Leg], frame_rate_hz: float,
                 rng: np.random.Generator, frame: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]],
                 progress: Progress | None) -> tuple[list[dict], float]:
    """Drive the legs one after the other from the home pose, each a blended path
    (``core.robot.trajectory``, as ``Robot.move_path`` drives it), while the scanner images at
    ``frame_rate_hz``; keep the pose stream (``STREAM_HZ``) and record the frames of the recorded
    legs, each stamped by the scanner's late clock and paired with the stream's pose at its
    timestamp, as a rig that does not know the latency pairs it. ``frame`` images the true flange
    pose (and gives the true markers, if any). Returns the truth's per-frame entries and the UR3
    time of all legs (s)."""
    twin = scanner.twin
    legs: list[_Driven] = []
    at = forward_kinematics(HOME_JOINTS)
    for plan_leg in plan_legs:
        legs.append(_Driven(blended_path([at, *plan_leg.poses], plan_leg.limits), plan_leg.record))
        at = plan_leg.poses[-1]
    starts = np.concatenate([[0.0], np.cumsum([leg.path.duration_s for leg in legs])])
    frames = sum(leg.path.duration_s for leg in legs if leg.record is not None) * frame_rate_hz
    _check_recording(frames, float(starts[-1]) + twin.image_latency_s)
    _check_frames(twin.probe, frames)
    acquired = [(np.arange(t0, t0 + leg.path.duration_s, 1.0 / frame_rate_hz), k)
                for k, (leg, t0) in enumerate(zip(legs, starts)) if leg.record is not None]
    last_stamp = max((times[-1] for times, _ in acquired if len(times)), default=0.0) + twin.image_latency_s
    stream_times = np.arange(0.0, max(starts[-1], last_stamp) + STREAM_TAIL_S, 1.0 / STREAM_HZ)
    stream_poses = np.empty((len(stream_times), 4, 4))
    leg_of = np.clip(np.searchsorted(starts, stream_times, side="right") - 1, 0, len(legs) - 1)
    for k, leg in enumerate(legs):
        stream_poses[leg_of == k] = leg.path.poses_at(stream_times[leg_of == k] - starts[k])
    writer.append_poses(stream_times, stream_poses)
    poses = stream_buffer(stream_times, stream_poses)
    joints, q = [], HOME_JOINTS
    for leg in legs:  # every leg's joints checked before anything moves
        joints.append(leg.path.joints_along(q))
        q = joints[-1][-1]
    truth, total, done = [], sum(len(times) for times, _ in acquired), 0
    for times, k in acquired:
        path, steps = legs[k].path, joints[k]
        for t in times:
            reported = path.poses_at(np.array([t - starts[k]]))[0]
            step = min(int((t - starts[k]) / CHECK_STEP_S), len(steps) - 1)
            actual = twin.actual_tool_to_base(reported, closest_ik(reported, steps[step]))
            image, markers = frame(actual)
            stamp = float(t + scanner.image_delay_s(rng))
            index = writer.append(image, poses.pose_at(stamp)[0], timestamp=stamp, pose_timestamp=stamp,
                                  **(legs[k].record or {}))
            if markers is not None:
                truth.append({"index": index, "markers_px": json_from_markers(markers),
                              "tool_to_base": actual.tolist(), "acquired_s": float(t)})
            done += 1
            if progress:
                progress(done, total)
    return truth, float(starts[-1])


def _continuous_calibration(out_dir: str | Path, scanner: TwinScanner, plan: SweepPlan, manifest: Manifest,
                            rng: np.random.Generator, frame_rate_hz: float, progress: Progress | None) -> Session:
    """The robot moves from home to the centre pose, up and down there (the temporal calibration's
    motion, :func:`core.acquisition.plan.temporal_waypoints`), then through the plan's poses
    without stopping (:mod:`core.robot.trajectory`), while the scanner images at ``frame_rate_hz``;
    the frames of the last two legs are recorded with ``phase`` "temporal" and "calibration"
    (see :func:`_record_legs`); ``probecal calibrate`` measures the latency and pairs the frames
    again."""
    twin = scanner.twin
    centre = twin.nominal.tool_to_base(twin.nominal.image_to_phantom)
    legs = continuous_calibration_legs(centre, twin.nominal.image_to_tool_rigid, plan)
    with _staged_writer(out_dir, replace(manifest, motion=CONTINUOUS, frame_rate_hz=frame_rate_hz),
                        twin.phantom, twin.probe) as writer:
        truth, robot_s = _record_legs(writer, scanner, legs, frame_rate_hz, rng,
                                      lambda pose: scanner.calibration_frame(pose, rng), progress)
        writer.write_truth({**twin.truth(), "frames": truth})
        writer.update_manifest(robot_time_s=round(robot_s, 1))
    return load_session(out_dir)


def _test_object() -> dict[str, bytes]:
    """The test object's CAD mesh, a volume session's file."""
    return {TEST_OBJECT_FILE.name: TEST_OBJECT_FILE.read_bytes()}


def simulate_volume(out_dir: str | Path, seed: int = 0, noise: str | Level = "realistic", n_frames: int = 120,
                    progress: Progress | None = None, motion: str = "stop", frame_rate_hz: float = FRAME_RATE_HZ,
                    image_latency_s: float | None = None, speed_mm_s: float = VOLUME_SPEED_MM_S,
                    probe: Probe | None = None, views: tuple[ProbeView, ...] | None = None,
                    length_mm: float = PASS_LENGTH_MM, passes: tuple[SweepPass, ...] = DEFAULT_PASSES,
                    planning: Progress | None = None) -> Session:
    """Sweep the test object in straight passes and record a session with truth.json and the
    object's CAD mesh (``test_object.stl``) beside it.

    ``motion="stop"``: ``n_frames`` poses per pass, one frame at each, poses and stamps as in
    :func:`simulate_calibration`. ``motion="continuous"``: every pass at ``speed_mm_s`` while the
    scanner images at ``frame_rate_hz``, every frame of the passes recorded (with ``sweep``, its
    pass) and the pose stream kept, paired as :func:`_record_legs` says; a reconstruction with a
    calibration that knows the latency pairs them again. ``image_latency_s`` replaces the
    twin's own; ``probe``, the default probe (another depth preset or image size); ``passes`` and
    ``length_mm``, the passes and their length.

    ``views``: the passes are swept again from each of these wrist angles in turn (a self-check's
    sweep, ``core.volume.selfcheck``); every frame records ``view``, its index in ``views``, and
    ``sweep`` counts the passes of all views. A stop-motion sweep's truth then also keeps every
    frame's true flange pose (``frames``: ``index``, ``tool_to_base``), where the arm's error
    put it. ``planning(poses checked, poses in all)`` is told as the plan's poses are checked."""
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {', '.join(MOTIONS)}")
    scanner = twin_scanner(seed, noise, image_latency_s=image_latency_s, probe=probe)
    twin, lvl = scanner.twin, scanner.level
    _check_frames(twin.probe, len(views or (None,)) * len(passes) * n_frames)
    rng = np.random.default_rng(seed + 1)
    plan = viewed_volume_plan(scanner.region_to_base(), twin.nominal.image_to_tool_rigid, twin.probe,
                              VOLUME_STANDOFF_MM, views, passes, length_mm, n_frames, progress=planning)
    manifest = replace(session_manifest("volume", twin, seed, lvl, plan), cad_mesh=TEST_OBJECT_FILE.name)
    if motion == "continuous":
        legs = continuous_volume_legs(plan, speed_mm_s=speed_mm_s)
        manifest = replace(manifest, motion=CONTINUOUS, frame_rate_hz=frame_rate_hz, speed_mm_s=speed_mm_s)
        with _staged_writer(out_dir, manifest, probe=twin.probe, files=_test_object()) as writer:
            _, robot_s = _record_legs(writer, scanner, legs, frame_rate_hz, rng,
                                      lambda pose: (scanner.volume_frame(pose, rng), None), progress)
            writer.write_truth(scanner.volume_truth())
            writer.update_manifest(robot_time_s=round(robot_s, 1))
        return load_session(out_dir)
    robot = SimulatedRobot(seed=seed, time_scale=0.0)
    robot.connect()
    truth_frames = []
    with _staged_writer(out_dir, manifest, probe=twin.probe, files=_test_object()) as writer:
        for k, (target, pass_index) in enumerate(zip(plan.poses, plan.passes)):
            robot.move_linear(target)
            reported = robot.tool_to_base()
            actual = twin.actual_tool_to_base(reported, robot.joints())
            image = scanner.volume_frame(actual, rng)
            t = robot.elapsed_motion_s
            viewed = {} if plan.views is None else {"view": plan.views[k]}
            index = writer.append(image, reported, timestamp=t + scanner.image_delay_s(rng), pose_timestamp=t,
                                  sweep=pass_index, **viewed)
            truth_frames.append({"index": index, "tool_to_base": actual.tolist()})
            if progress:
                progress(k + 1, len(plan.poses))
        writer.write_truth({**scanner.volume_truth(), **({} if views is None else {"frames": truth_frames})})
        writer.update_manifest(robot_time_s=round(robot.elapsed_motion_s, 1))
    return load_session(out_dir)
