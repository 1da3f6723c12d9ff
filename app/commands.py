"""What each ``probecal`` command does (``app.cli`` parses the command line): calls ``core``, prints
what it did, and leaves failures to the caller as InputError or DeviceError. ``core`` is imported
inside each command, so that ``--help`` stays fast."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from probecal.app.progress import Progress, Status, clear_line
from probecal.core.errors import InputError
from probecal.core.io.files import fresh_folder, staged_folder

T = TypeVar("T")


def _latency_from(args: argparse.Namespace) -> None:
    """--latency-from FILE sets --latency to the image latency FILE records."""
    if args.latency_from is None:
        return
    from probecal.core.calibration.result import read_image_latency

    if args.latency not in (None, 0.0):
        raise InputError(args.latency_from, "give --latency or --latency-from, not both")
    args.latency = read_image_latency(args.latency_from)


def _check_latency_source(path: Path, rig, force: bool) -> None:
    """A calibration made for other images than the rig's gives no latency for them (--force: a
    warning)."""
    from probecal.core.calibration.result import read_valid_for
    from probecal.core.calibration.validity import differences

    made_for = read_valid_for(path)
    problems = differences(made_for, *rig.image_format()) if made_for is not None else []
    if problems and not force:
        raise InputError(path, f"made for other images than {rig.image_name}'s: {'; '.join(problems)}; "
                               "--force takes its latency anyway")
    if problems:
        _warn(f"warning: {path}: made for other images than {rig.image_name}'s ({'; '.join(problems)}); "
              "its latency taken anyway (--force)")


def serve(args: argparse.Namespace) -> int:
    from probecal.app.console.gate import read_token
    from probecal.app.console.server import serve
    from probecal.core.robot.safety import load_workspace

    _latency_from(args)
    workspace = load_workspace(args.workspace) if args.workspace else None
    tracked = None
    if args.tracker is not None:
        from probecal.app.tracked import TrackedSpec

        args.seed = 0
        tracked = TrackedSpec.from_args(args)
        args.image = "sim"  # the robot's twin stays, unconnected; the tracked probe brings its own images
    serve(host=args.host, port=args.port, robot=args.robot, image=args.image, sessions_dir=args.sessions,
          time_scale=args.time_scale, token=read_token(args.token_file), workspace=workspace, publish=args.publish,
          latency_s=args.latency, spacing_mm=args.spacing, start_depth_mm=args.start_depth_mm,
          probe=_rig_probe(args), unattended=args.unattended, tracked=tracked)
    return 0


def _twin_probe(args: argparse.Namespace):
    """The twin's probe (``--probe``) at the depth preset and image size the command line gives,
    refused in one line naming the probe when it is beyond any scanner's or its frames' imaging
    would pass the memory limit."""
    from probecal.core.geometry.probe import DEFAULT_PROBE, ConvexProbe, Probe
    from probecal.core.io.probefile import checked_probe, load_probe
    from probecal.core.twin.bmode import check_imaging

    source = args.probe or DEFAULT_PROBE
    probe = load_probe(source)
    options = " ".join([*(["--image-size", *map(str, args.image_size)] if args.image_size else []),
                        *(["--depth-mm", f"{args.depth_mm:g}"] if args.depth_mm else [])])
    shaped_by = f"{source} at {options}" if options else source
    shaped: Probe
    if isinstance(probe, ConvexProbe):
        if args.start_depth_mm:
            raise InputError(source, "a convex probe's fan starts at its face: it takes no --start-depth-mm")
        shaped = checked_probe(dataclasses.replace(probe, width_px=args.image_size[0] if args.image_size else
                                                   probe.width_px, depth_mm=args.depth_mm or probe.depth_mm),
                               shaped_by)
        if args.image_size and args.image_size[1] != shaped.height_px:
            raise InputError(source, f"a fan {shaped.width_px} px wide is {shaped.height_px} px high, not "
                                     f"{args.image_size[1]}: its height follows from its width")
    else:
        width, height = args.image_size or (probe.width_px, probe.height_px)
        shaped = checked_probe(dataclasses.replace(probe, width_px=width, height_px=height,
                                                   depth_mm=args.depth_mm or probe.depth_mm,
                                                   start_depth_mm=args.start_depth_mm),
                               shaped_by)
    check_imaging(shaped, shaped_by)
    return shaped


def _rig_probe(args: argparse.Namespace):
    """The twin's probe a rig images with: ``--probe`` (refused naming it when imaging its frames
    would pass the memory limit), else a resumed session's own, else the default (None)."""
    from probecal.core.io.probefile import load_probe
    from probecal.core.io.session import read_manifest
    from probecal.core.twin.bmode import check_imaging

    if args.probe is not None:
        probe = load_probe(args.probe)
        check_imaging(probe, args.probe)
        return probe
    out_dir = getattr(args, "out_dir", None)
    if getattr(args, "resume", False) and out_dir is not None:
        return read_manifest(out_dir).probe
    return None


def simulate_calibration(args: argparse.Namespace) -> int:
    from probecal.core.acquisition.simulate import simulate_calibration
    from probecal.core.io.phantomfile import default_phantom, load_phantom, phantom_path

    phantom = load_phantom(phantom_path(args.phantom)) if args.phantom else default_phantom()
    built = load_phantom(args.as_built) if args.as_built else None
    if built is not None and built.n_wires != phantom.n_wires:
        raise InputError(args.as_built, f"has {built.n_wires} wires, the phantom's definition {phantom.n_wires}")
    out = fresh_folder(args.out_dir)
    try:
        session = simulate_calibration(
            out, n_poses=args.poses, seed=args.seed, noise=args.noise, phantom=phantom,
            progress=Progress("simulating calibration sweep"), motion=args.motion, frame_rate_hz=args.frame_rate,
            image_latency_s=args.image_latency, built_phantom=built,
            probe=_twin_probe(args),
        )
    except ValueError as exc:  # the plan cannot keep the phantom's wires in the probe's view
        raise InputError(args.phantom or args.probe or out, str(exc))
    if args.motion == "continuous":
        temporal = sum(r.extra.get("phase") == "temporal" for r in session.records)
        print(f"{session.path}: {len(session)} frames at {args.frame_rate:g} frames/s ({temporal} of them while "
              f"the probe moved up and down to measure the latency), UR3 time {session.manifest.robot_time_s:.0f} s "
              f"for the whole procedure without stopping, pose stream kept, ground truth in truth.json")
    else:
        print(f"{session.path}: {len(session)} frames, estimated UR3 time "
              f"{(session.manifest.plan or {})['estimated_robot_time_s']:.0f} s, ground truth in truth.json")
    return 0


def temporal_calibrate(args: argparse.Namespace) -> int:
    from probecal.core.io.jsonio import write_json

    out = _output_file(Path(args.out), args.force)
    if (args.session is None) == (args.video is None) or (args.video is None) != (args.tracker is None):
        raise InputError(None, "give either a SESSION or both --video and --tracker")
    if args.session is not None:
        from probecal.core.calibration.latency import session_latency
        from probecal.core.io.session import load_recorded_session

        estimate = session_latency(load_recorded_session(args.session), max_lag_s=args.max_lag)
        source = {"session": str(Path(args.session).resolve())}
    else:
        from probecal.core.temporal.plusbuffers import plus_latency

        estimate = plus_latency(args.video, args.tracker, args.tool, args.reference, args.max_lag)
        source = {"video": str(Path(args.video).resolve()), "tracker": str(Path(args.tracker).resolve()),
                  "tool_pose": f"{args.tool}To{args.reference}"}
    result = {**estimate.to_json(), "plus_tracker_lag_s": round(-estimate.image_latency_s, 6), "source": source}
    write_json(out, result)
    print(f"image latency {estimate.image_latency_s * 1000:.1f} +- {estimate.std_error_s * 1000:.1f} ms: a frame "
          f"stamped t shows the probe where it was at t - {estimate.image_latency_s * 1000:.1f} ms "
          f"(PLUS's TrackerLagSec {-estimate.image_latency_s:.4f}): {out}")
    print(f"  {estimate.frames_used} frames used, {estimate.frames_rejected} rejected (echo off the motion); "
          f"echo-motion correlation {abs(estimate.correlation):.4f}, misfit {estimate.residual:.3f} of the echo's "
          f"spread; lags within {estimate.peak_halfwidth_s * 1000:.0f} ms of the best fit at most twice as badly; "
          f"the probe moved {estimate.motion_mm:.1f} mm")
    return 0


def simulate_volume(args: argparse.Namespace) -> int:
    from probecal.core.acquisition.plan import (
        DEFAULT_PASSES,
        PASS_LENGTH_MM,
        SELF_CHECK_PASS_MM,
        SELF_CHECK_PASSES,
        ProbeView,
    )
    from probecal.core.acquisition.simulate import simulate_volume

    out = fresh_folder(args.out_dir)
    views = None if args.views is None else tuple(ProbeView(turn, tilt) for turn, tilt in args.views)
    session = simulate_volume(out, seed=args.seed, noise=args.noise, n_frames=args.frames_per_pass,
                              progress=Progress("simulating volume sweeps"), motion=args.motion,
                              frame_rate_hz=args.frame_rate, image_latency_s=args.image_latency, speed_mm_s=args.speed,
                              probe=_twin_probe(args), views=views,
                              length_mm=PASS_LENGTH_MM if views is None else SELF_CHECK_PASS_MM,
                              passes=DEFAULT_PASSES if views is None else SELF_CHECK_PASSES,
                              planning=Progress("planning volume sweeps"))
    plan = session.manifest.plan or {}
    if args.motion == "continuous":
        print(f"{session.path}: {len(session)} frames in {plan['passes']} passes at {args.speed:g} mm/s and "
              f"{args.frame_rate:g} frames/s, UR3 time {session.manifest.robot_time_s:.0f} s, pose stream kept, "
              f"CAD mesh {session.manifest.cad_mesh}")
    else:
        print(f"{session.path}: {len(session)} frames in {plan['passes']} passes, estimated UR3 time "
              f"{plan['estimated_robot_time_s']:.0f} s, CAD mesh {session.manifest.cad_mesh}")
    return 0


def import_plus(args: argparse.Namespace) -> int:
    from probecal.core.io.plusimport import import_plus

    tool, reference = args.tool, args.reference
    if args.tool_pose is not None:
        if tool is not None or reference is not None:
            raise InputError(None, "--tool-pose names the tool and the reference: give it or "
                                   "--tool/--reference, not both")
        tool, reference = args.tool_pose
    session = import_plus(
        args.sequence, args.config, args.out_dir, tool=tool, reference=reference,
        spacing_mm=args.spacing, progress=Progress("importing frames"),
        start_depth_mm=args.start_depth_mm,
    )
    valid = sum(r.pose_valid for r in session.records)
    phantom = session.phantom.name if session.phantom else "none"
    known = "known" if session.phantom_to_base is not None else "unknown"
    print(f"{session.path}: {len(session)} frames ({valid} with a valid pose), phantom {phantom}, "
          f"phantom pose {known}; {_tool_pose_origin(session.manifest.source or {})}")
    return 0


def _tool_pose_origin(source: dict) -> str:
    """Where an imported recording's tool pose came from: the transform it holds, or the product
    of those composed into it (``core.geometry.transformrepo``)."""
    pose, path = source["tool_pose"], source["tool_pose_path"]
    return f"{pose} as the recording holds it" if path == pose else f"{pose} = {path}"


def _frame_import_settings(args: argparse.Namespace):
    """The phantom and the nominal spacing an import of a lab's frames is given."""
    from probecal.core.io.frameimport import NominalSpacing
    from probecal.core.io.phantomfile import default_phantom, load_phantom, phantom_path

    if args.spacing is not None and (args.depth_mm or args.width_mm):
        raise InputError(None, "give the spacing or the image's depth and width, not both")
    phantom = load_phantom(phantom_path(args.phantom)) if args.phantom else default_phantom()
    return phantom, NominalSpacing(args.spacing, args.depth_mm, args.width_mm)


def _import_summary(session) -> str:
    sx, sy = session.pixel_spacing_mm or (0.0, 0.0)
    width, height = session.image_size
    valid = sum(r.pose_valid for r in session.records)
    return (f"{session.path}: {len(session)} frames of {width}x{height} px ({valid} with a pose) at {sx:.4g} x "
            f"{sy:.4g} mm/px, phantom {session.phantom.name}")


def import_rosbag(args: argparse.Namespace) -> int:
    from probecal.core.acquisition.rosbagimport import import_rosbag

    phantom, spacing = _frame_import_settings(args)
    session, source = import_rosbag(args.bag, args.out_dir, phantom, spacing, args.image_topic,
                                    pose_topic=args.pose_topic, tf=None if args.tf is None else tuple(args.tf),
                                    latency_s=args.latency, mirror=args.mirror, progress=Progress("importing frames"),
                                    start_depth_mm=args.start_depth_mm)
    print(f"{_import_summary(session)}; poses from {source}, paired {1e3 * args.latency:g} ms earlier, pose stream "
          f"kept")
    return 0


def import_frames(args: argparse.Namespace) -> int:
    from probecal.core.io.frameimport import import_frames

    phantom, spacing = _frame_import_settings(args)
    session, table = import_frames(args.images_dir, args.poses, args.out_dir, phantom, spacing, units=args.units,
                                   direction=args.pose, mirror=args.mirror, progress=Progress("importing frames"),
                                   start_depth_mm=args.start_depth_mm)
    paired = "by the table's file names" if table.files is not None else "in natural order of the file names"
    times = ", times kept" if table.times_s is not None else ""
    region = session.manifest.scanner_region
    if region is not None:
        sx, sy = region["pixel_spacing_mm"]
        depth = region["start_depth_mm"]
        times += (f"; the DICOM files' region calibration: image region {region['region_px']} px (frames cut to it) "
                  f"at {sx:.4g} x {sy:.4g} mm/px, first row "
                  + ("at an unstated depth" if depth is None else f"{depth:g} mm below the probe's face"))
    units = " (--units to set them)" if table.units_guessed else ""
    print(f"{_import_summary(session)}; {table.summary()}{units}; paired {paired}{times}")
    return 0


def export_plus(args: argparse.Namespace) -> int:
    from probecal.core.io.plusimport import export_plus
    from probecal.core.io.sequence import sequence_file_name
    from probecal.core.io.session import load_recorded_session

    _output_file(sequence_file_name(args.out), args.force)
    session = load_recorded_session(args.session)
    export_plus(session, args.out, progress=Progress("exporting frames"))
    print(f"{args.out}: {len(session)} frames with ProbeToReference transforms")
    return 0


def _fill_rig_arguments(args: argparse.Namespace) -> None:
    """What the command line leaves out comes from the rig of the session in OUT_DIR (being
    resumed), else from the usual defaults."""
    from probecal.core.io.manifest import RigSpec
    from probecal.core.io.session import read_manifest

    rig = (read_manifest(args.out_dir).rig if args.out_dir.is_dir() else None) or RigSpec()
    for name, given, default in (("robot", rig.robot, "sim"), ("image", rig.image, "sim"), ("seed", rig.seed, 0),
                                 ("latency", rig.latency_s, 0.0), ("spacing", rig.spacing_mm, None),
                                 ("start_depth_mm", rig.start_depth_mm, None)):
        if getattr(args, name) is None:
            setattr(args, name, default if given is None else given)


def sweep(args: argparse.Namespace) -> int:
    from probecal.app.rigspec import make_rig
    from probecal.core.acquisition.plan import PoseRanges
    from probecal.core.acquisition.rig import Recording
    from probecal.core.robot.safety import load_workspace
    from probecal.core.robot.ur3 import MotionLimits

    if args.tracker is not None:
        return _tracked_sweep(args)
    if args.motion == "guided":
        raise InputError(None, "--motion guided guides a person holding a tracked probe: give --tracker")
    args.motion = args.motion or "stop"
    _latency_from(args)
    workspace = load_workspace(args.workspace) if args.workspace else None
    if args.resume:
        if not args.out_dir.is_dir():
            raise InputError(args.out_dir, "no session to resume")
    else:
        fresh_folder(args.out_dir)
    _fill_rig_arguments(args)
    rig = make_rig(args.robot, args.image, args.seed, args.time_scale, workspace, args.latency,
                   args.spacing, args.start_depth_mm, _rig_probe(args))
    limits = MotionLimits().scaled(args.speed)
    progress = Progress(f"{args.what} sweep")
    try:
        rig.open()
        if args.latency_from is not None:
            _check_latency_source(args.latency_from, rig, args.force)
        plan = None
        if not args.resume:
            plan = (rig.calibration_plan(args.poses, PoseRanges(), limits) if args.what == "calibration"
                    else rig.volume_plan(args.frames_per_pass, limits))
        recording = Recording(rig, args.what, args.out_dir, plan, limits,
                              lambda f: progress(f.done, f.total) if f.index is not None else None, args.motion)
        outcome = recording.run()
    finally:
        rig.close()
    recorded = recording.frames
    if not outcome.complete:
        clear_line()
        why = "stopped" if outcome.stopped else outcome.error
        then = ("a continuous sweep is not resumed: record a new one" if args.motion == "continuous" else
                f"'probecal sweep {args.what} {args.out_dir} --resume' records the {outcome.remaining} poses left")
        print(f"probecal: sweep ended early ({why}): {recorded} frames kept in {args.out_dir}{outcome.notes()}; {then}",
              file=sys.stderr)
        return 1
    text = f"{args.out_dir}: {recorded} frames recorded ({outcome.recorded} in this run{outcome.notes()})"
    if args.motion == "continuous":
        text += f"; UR3 time {recording.robot_time_s:.0f} s for the whole procedure, without stopping"
    print(text)
    return 0


def _tracked_sweep(args: argparse.Namespace) -> int:
    """``sweep --tracker``: a probe probecal does not move (app.tracked)."""
    from probecal.app.tracked import tracked_sweep

    if args.robot is not None or args.resume:
        raise InputError(None, "--tracker records a probe no robot moves: --robot and --resume are a robot's")
    args.motion = args.motion or ("guided" if args.what == "calibration" else "continuous")
    if args.motion == "stop":
        raise InputError(None, "--motion stop stops a robot at its poses: a tracked probe records guided or continuous")
    return tracked_sweep(args)


def _segmenter(session, args: argparse.Namespace, log: bool = True):
    """The segmenter ``args`` ask for, tuned on the session (its progress logged unless not
    ``log``); with --verbose says which, with what parameters."""
    from probecal.core.calibration.segment import session_segmenter

    segmenter = session_segmenter(session, args.segmenter, use_hints=not args.ignore_hints,
                                  progress=Progress("tuning the segmenter", log=log))
    if args.verbose:
        print(segmenter.describe())
    return segmenter


def _segment(session, args: argparse.Namespace):
    """Segment every frame with the segmenter ``args`` ask for."""
    from probecal.core.calibration.segment import segment_session

    segmenter = _segmenter(session, args)
    return segment_session(session, Progress("segmenting frames"), segmenter)


def _output_file(out: Path, force: bool) -> Path:
    """The one rule for output files: an existing one is refused unless --force (then replaced
    whole, atomically); a folder is never taken for a file."""
    if out.is_dir():
        raise InputError(out, "is a folder; give a file name")
    if out.exists() and not force:
        raise InputError(out, "exists; --force overwrites it")
    return out


def _replacing(out: Path, force: bool) -> bool:
    """The one rule for output folders: an existing one that is not empty is refused unless
    --force (then replaced whole, see :func:`_into_folder`); a file or a link is never taken for a
    folder (:func:`fresh_folder`). True when ``out`` is to be replaced."""
    replacing = fresh_folder(out, replace=True).is_dir() and any(out.iterdir())
    if replacing and not force:
        raise InputError(out, "exists; --force replaces it")
    return replacing


def _into_folder(out: Path, replacing: bool, build: Callable[[Path], T]) -> T:
    """``build(folder)`` into a new folder beside ``out`` that takes its place (replacing the old
    one when ``replacing``) only once whole (:func:`staged_folder`)."""
    with staged_folder(out, replace=replacing) as folder:
        return build(folder)


def _default_output(session_path: Path, out: Path | None, name: str, force: bool) -> Path:
    return _output_file(out if out is not None else session_path / name, force)


def segment(args: argparse.Namespace) -> int:
    from probecal.core.calibration.segment import write_segmentation
    from probecal.core.io.session import load_recorded_session

    session = load_recorded_session(args.session)
    out = _default_output(args.session, args.out, "segmentation.json", args.force)
    results = _segment(session, args)
    write_segmentation(out, results, session)
    found = sum(r.found for r in results)
    print(f"{out}: pattern found in {found} of {len(results)} frames")
    return 0


def calibrate(args: argparse.Namespace) -> int:
    from probecal.app.jobs import run_calibration
    from probecal.app.report import calibration_lines, calibration_verdict
    from probecal.core.calibration.kinematics import with_arm
    from probecal.core.geometry.transforms import transform_error
    from probecal.core.io.session import load_recorded_session

    session = with_arm(load_recorded_session(args.session), args.arm)
    out = _default_output(args.session, args.out, "calibration.json", args.force)
    _output_file(out.with_suffix(".xml"), args.force)
    report = run_calibration(session, _segmenter(session, args, log=args.verbose), args.method, args.solve_phantom_pose,
                             Progress("segmenting frames", log=args.verbose), Status("calibrate", log=args.verbose))
    clear_line()
    verdict = calibration_verdict(report.calibration, args.tolerance)
    calibration = dataclasses.replace(report.calibration,
                                      metrics={**report.calibration.metrics, "verdict": verdict.to_json()})
    xml_path = calibration.write(out)
    shah = None
    if report.shah is not None:
        shah = transform_error(report.shah["image_to_tool_rigid"], calibration.image_to_tool_rigid)
    lines = [verdict.text, f"  saved: {out}, and {xml_path.name} beside it for PLUS and 3D Slicer",
             *calibration_lines(calibration, shah, args.verbose)]
    if not args.verbose:
        lines.append("  (--verbose: the objectives compared, the bound's parts, the error vs poses, every frame "
                     "left out)")
    print("\n".join(lines))
    return 0


def _warn(text: str) -> None:
    if text:
        print(text, file=sys.stderr)


def validate(args: argparse.Namespace) -> int:
    from probecal.core.calibration.presets import applied
    from probecal.core.calibration.result import load_calibration
    from probecal.core.calibration.validate import validate_session
    from probecal.core.io.jsonio import write_json
    from probecal.core.io.session import load_recorded_session

    calibration = load_calibration(args.calibration)
    session = load_recorded_session(args.session)
    if args.out is not None:
        _output_file(args.out, args.force)
    calibration, note = applied(calibration, args.calibration, session, args.force)
    _warn(note)
    metrics = validate_session(session, calibration, _segment(session, args))
    if args.out is not None:
        write_json(args.out, {"calibration": str(args.calibration), "session": str(args.session), "metrics": metrics})
    print(
        f"{args.session}: PRE3D {metrics['pre3d_mm']:.3f} +- {metrics['pre3d_std_mm']:.3f} mm over "
        f"{metrics['frames_used']} frames, marker-to-wire {metrics['marker_to_wire_mean_mm']:.3f} mm"
    )
    return 0


def _volume_settings(config: Path | None):
    from probecal.core.io.deviceset import read_device_set
    from probecal.core.volume.grid import settings_from_device_set
    from probecal.core.volume.reconstruct import DEFAULT_VOLUME

    if config is None or config.suffix.lower() != ".xml":
        return DEFAULT_VOLUME
    return settings_from_device_set(read_device_set(config)) or DEFAULT_VOLUME


def reconstruct(args: argparse.Namespace) -> int:
    from probecal.app.report import cad_to_points_text, reconstruction_verdict
    from probecal.core.calibration.presets import applied
    from probecal.core.calibration.result import calibration_source, load_calibration
    from probecal.core.io.manifest import PLUS_IMPORT
    from probecal.core.io.session import load_recorded_session
    from probecal.core.volume.cad import session_cad_target
    from probecal.core.volume.reconstruct import reconstruct_session

    given = load_calibration(args.calibration)
    settings = _volume_settings(args.volume_config or args.calibration)
    if args.voxel is not None:
        try:
            settings = dataclasses.replace(settings, spacing_mm=(args.voxel,) * 3, origin_mm=None, extent=None)
        except ValueError as exc:
            raise InputError(None, f"--voxel {args.voxel}: {exc}")
    session = load_recorded_session(args.session)
    replacing = _replacing(args.out, args.force)
    calibration, note = applied(given, args.calibration, session, args.force)
    source = calibration_source(given, args.calibration, derived=calibration is not given)
    _warn(note)
    cad = (session_cad_target(session, args.cad, args.register, calibration.phantom_to_base)
           if args.cad is not None else None)
    # The base frame of a robot session has z up; a tracker's reference frame may point anywhere.
    keep_floor = args.keep_floor or session.manifest.kind == PLUS_IMPORT
    report = _into_folder(args.out, replacing, lambda folder: reconstruct_session(
        session, calibration, folder, settings, cad,
        floor_up=None if keep_floor else (0.0, 0.0, 1.0),
        progress=Progress("reconstructing"), source=source, stage=Status("reconstruct"),
        judge=lambda made: reconstruction_verdict(made, args.tolerance).to_json(),
    )).report
    clear_line()
    print(report["verdict"]["text"])
    shape = report["volume"]["shape_zyx"][::-1]
    line = f"  {args.out}: {report['surface_points']} surface points, volume {shape} voxels"
    if "surface_mean_mm" in report:
        line += (f"; surface error to CAD: mean {report['surface_mean_mm']:.3f} mm, 95th percentile "
                 f"{report['surface_p95_mm']:.3f} mm (CAD to points {cad_to_points_text(report)})")
    if report["image_latency_s"] is not None:
        line += (f"; frames paired again from the pose stream with the image latency "
                 f"{report['image_latency_s'] * 1000:.1f} ms")
    print(line)
    return 0


def selfcheck(args: argparse.Namespace) -> int:
    from probecal.app.report import self_check_verdict
    from probecal.core.calibration.presets import applied
    from probecal.core.calibration.result import calibration_source, load_calibration
    from probecal.core.io.session import load_recorded_session
    from probecal.core.volume.selfcheck import COMPONENTS, VIEW_COLORS, viewed_sweeps, write_self_check

    given = load_calibration(args.calibration)
    sessions = [load_recorded_session(path) for path in args.sessions]
    out = args.out if args.out is not None else Path(args.sessions[0]) / "selfcheck"
    replacing = _replacing(out, args.force)
    calibrated = []
    for session in sessions:
        calibration, note = applied(given, args.calibration, session, args.force)
        _warn(note)
        calibrated.append((session, calibration))
    views = viewed_sweeps(calibrated)
    source = calibration_source(given, args.calibration, derived=any(c is not given for _, c in calibrated))
    Status("selfcheck")("reconstructing and registering the views")
    check, report = _into_folder(out, replacing, lambda folder: write_self_check(views, folder, source=source))
    clear_line()
    print(self_check_verdict(report).headline)
    for caution in check.cautions:
        _warn(f"caution: {caution}")
    for o in check.offsets:
        print(f"  view {o.view} pass {o.pass_index} against view {o.against_view} pass {o.against_pass}: "
              f"{o.offset_norm_mm:.3f} mm {[round(v, 3) for v in o.offset_mm.tolist()]} and {o.rotation_deg:.2f} deg "
              f"off (base frame); median surface distance {o.median_before_mm:.3f} -> {o.median_after_mm:.3f} mm "
              "once laid on it")
    change = check.change
    values = [*change.translation_mm, *change.rotation_deg]
    seen = [f"{name} {v:+.2f}" for name, v, visible in zip(COMPONENTS, values, change.visible) if visible]
    unseen = [name for name, visible in zip(COMPONENTS, change.visible) if not visible]
    print(f"  calibration error that explains it (image frame): {', '.join(seen) or 'none the views can see'}"
          f"{'; not seen by these views: ' + ', '.join(unseen) if unseen else ''}")
    colours = ", ".join(f"{name} {VIEW_COLORS[k % len(VIEW_COLORS)]}" for k, name in enumerate(report["views"]))
    print(f"  {out}: report.json; points in the base frame (RGB): {colours}")
    return 0
