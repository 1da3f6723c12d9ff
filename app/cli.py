"""The ``probecal`` command line (SPEC §6). Thin: parses arguments, calls ``core``, reports.

Bad input exits with code 2 and one line naming the file and the problem.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

from probecal.app.progress import Progress, Status, clear_line
from probecal.core.errors import DeviceError, InputError
from probecal.core.io.files import fresh_folder

# The twin's levels (core.twin.levels.LEVELS, not imported here so that --help stays fast).
NOISE_LEVELS = ("none", "realistic", "harsh", "bench")
DEFAULT_LEVEL = "bench"
NOISE_HELP = ("the twin's difficulty (default bench: slice thickness, robot kinematic errors, phantom "
              "tolerances, latency; realistic: a perfect set-up)")


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line (exit code 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def _nonnegative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not a positive number")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} is not a positive number")
    return value


def _nonnegative_float(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{text} is negative")
    return value


def _output_path(text: str) -> Path:
    """An output file or folder whose folder exists and is writable, checked before any work."""
    path = Path(text)
    folder = path.absolute().parent
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: the folder {folder} is not writable")
    return path


def cmd_serve(args: argparse.Namespace) -> int:
    from probecal.app.console.gate import read_token
    from probecal.app.console.server import serve
    from probecal.core.robot.safety import load_workspace

    workspace = load_workspace(args.workspace) if args.workspace else None
    serve(host=args.host, port=args.port, robot=args.robot, image=args.image, sessions_dir=args.sessions,
          time_scale=args.time_scale, token=read_token(args.token_file), workspace=workspace, publish=args.publish,
          latency_s=args.latency)
    return 0


def cmd_simulate_calibration(args: argparse.Namespace) -> int:
    from probecal.core.acquisition.simulate import simulate_calibration
    from probecal.core.io.phantomfile import load_phantom

    phantom = load_phantom(args.phantom) if args.phantom else None
    out = fresh_folder(args.out_dir)
    try:
        session = simulate_calibration(
            out, n_poses=args.poses, seed=args.seed, noise=args.noise, phantom=phantom,
            progress=Progress("simulating calibration sweep"),
        )
    except ValueError as exc:  # the plan cannot keep this phantom's wires in view
        raise InputError(args.phantom or out, str(exc))
    plan = session.manifest["plan"]
    print(
        f"{session.path}: {len(session)} frames, estimated UR3 time "
        f"{plan['estimated_robot_time_s']:.0f} s, ground truth in truth.json"
    )
    return 0


def cmd_simulate_volume(args: argparse.Namespace) -> int:
    from probecal.core.acquisition.simulate import simulate_volume

    out = fresh_folder(args.out_dir)
    session = simulate_volume(out, seed=args.seed, noise=args.noise, n_frames=args.frames_per_pass,
                              progress=Progress("simulating volume sweeps"))
    plan = session.manifest["plan"]
    print(
        f"{session.path}: {len(session)} frames in {plan['passes']} passes, estimated UR3 time "
        f"{plan['estimated_robot_time_s']:.0f} s, CAD mesh {session.manifest['cad_mesh']}"
    )
    return 0


def _tool_pose(text: str) -> tuple[str, str]:
    """(tool, reference) from a PLUS transform name such as ProbeToTemplate."""
    from probecal.core.geometry.transformrepo import frame_splits

    pairs = frame_splits(text)
    if len(pairs) != 1:
        readings = " or ".join(f"{a}->{b}" for a, b in pairs) or "none"
        raise argparse.ArgumentTypeError(f"{text!r} is not one <From>To<To> name (readings: {readings}); "
                                         "give --tool and --reference instead")
    return pairs[0]


def cmd_import_plus(args: argparse.Namespace) -> int:
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
    )
    valid = sum(r.pose_valid for r in session.records)
    phantom = session.phantom.name if session.phantom else "none"
    known = "known" if session.phantom_to_base is not None else "unknown"
    source = session.manifest["source"]
    print(f"{session.path}: {len(session)} frames ({valid} with a valid pose), phantom {phantom}, "
          f"phantom pose {known}; {source['tool_pose']} = {source['tool_pose_path']}")
    return 0


def cmd_export_plus(args: argparse.Namespace) -> int:
    from probecal.core.io.plusimport import export_plus
    from probecal.core.io.session import load_session

    if args.out.exists():
        raise InputError(args.out, "output file exists")
    session = load_session(args.session)
    export_plus(session, args.out, progress=Progress("exporting frames"))
    print(f"{args.out}: {len(session)} frames with ProbeToReference transforms")
    return 0


def _fill_rig_arguments(args: argparse.Namespace) -> None:
    """What the command line leaves out comes from the rig of the session in OUT_DIR (being
    resumed), else from the usual defaults."""
    from probecal.core.io.session import read_manifest

    rig = (read_manifest(args.out_dir).get("rig") or {}) if args.out_dir.is_dir() else {}
    for name, default in (("robot", "sim"), ("image", "sim"), ("seed", 0), ("latency", 0.0)):
        if getattr(args, name) is None:
            setattr(args, name, rig.get(name if name != "latency" else "latency_s", default))


def cmd_sweep(args: argparse.Namespace) -> int:
    from probecal.core.acquisition.plan import PoseRanges
    from probecal.core.acquisition.rig import Recording, make_rig
    from probecal.core.robot.safety import load_workspace
    from probecal.core.robot.ur3 import MotionLimits

    workspace = load_workspace(args.workspace) if args.workspace else None
    if args.resume:
        if not args.out_dir.is_dir():
            raise InputError(args.out_dir, "no session to resume")
    else:
        fresh_folder(args.out_dir)
    _fill_rig_arguments(args)
    rig = make_rig(args.robot, args.image, args.seed, args.time_scale, workspace, args.latency)
    limits = MotionLimits().scaled(args.speed)
    progress = Progress(f"{args.what} sweep")
    try:
        rig.open()
        plan = None
        if not args.resume:
            plan = (rig.calibration_plan(args.poses, PoseRanges(), limits) if args.what == "calibration"
                    else rig.volume_plan(args.frames_per_pass, limits))
        recording = Recording(rig, args.what, args.out_dir, plan, limits,
                              lambda f: f.index is not None and progress(f.done, f.total))
        outcome = recording.run()
    finally:
        rig.close()
    recorded = recording.frames
    if not outcome.complete:
        clear_line()
        why = "stopped" if outcome.stopped else outcome.error
        print(f"probecal: sweep ended early ({why}): {recorded} frames kept in {args.out_dir}{outcome.notes()}; "
              f"'probecal sweep {args.what} {args.out_dir} --resume' records the {outcome.remaining} poses left",
              file=sys.stderr)
        return 1
    print(f"{args.out_dir}: {recorded} frames recorded ({outcome.recorded} in this run{outcome.notes()})")
    return 0


def _add_segmenter_arguments(p: argparse.ArgumentParser) -> None:
    from probecal.core.calibration.segment import SEGMENTERS

    p.add_argument("--segmenter", choices=SEGMENTERS, default=SEGMENTERS[0],
                   help="dot finder and labeller: probecal's own (default), the thesis's, or PLUS's")
    p.add_argument("--ignore-hints", action="store_true",
                   help="use none of an imported recording's PLUS segmentation settings but its approximate "
                        "pixel spacing (the way a robot session runs)")


def _segmenter(session, args: argparse.Namespace):
    """The segmenter ``args`` ask for, tuned on the session; says which, with what parameters."""
    from probecal.core.calibration.segment import session_segmenter

    segmenter = session_segmenter(session, args.segmenter, use_hints=not args.ignore_hints)
    print(segmenter.describe())
    return segmenter


def _segment(session, args: argparse.Namespace):
    """Segment every frame with the segmenter ``args`` ask for."""
    from probecal.core.calibration.segment import segment_session

    return segment_session(session, Progress("segmenting frames"), _segmenter(session, args))


def _default_output(session_path: Path, out: Path | None, name: str) -> Path:
    out = out if out is not None else session_path / name
    if out.exists() and out.is_dir():
        raise InputError(out, "is a folder; give a file name")
    return out


def cmd_segment(args: argparse.Namespace) -> int:
    from probecal.core.calibration.segment import write_segmentation
    from probecal.core.io.session import load_session

    session = load_session(args.session)
    out = _default_output(args.session, args.out, "segmentation.json")
    results = _segment(session, args)
    write_segmentation(out, results, session)
    found = sum(r.found for r in results)
    print(f"{out}: pattern found in {found} of {len(results)} frames")
    return 0


def _format_curve(curve: list[dict]) -> list[str]:
    lines = ["  error vs poses (held-out frames): poses  eq.4.1 mm  eq.4.1 deg  PRE3D mm"]
    for row in curve:
        t, r, p = row["identity_translation_mm"], row["identity_rotation_deg"], row["pre3d_mm"]
        lines.append(f"  {row['poses']:>37d}  {t:9.3f}  {r:10.3f}  {p:8.3f}")
    return lines


def _format_objectives(m: dict) -> list[str]:
    """The objectives side by side: PRE3D on held-out blocks of consecutive frames, spacing, rejections."""
    lines = ["  objective     CV PRE3D mm  spacing mm/px       rejected frames"]
    for name, row in m["objectives"].items():
        cv = "n/a" if row["cv_pre3d_mm"] is None else f"{row['cv_pre3d_mm']:.3f}"
        sx, sy = row["pixel_spacing_mm"]
        chosen = "  <- chosen" if name == m["objective"] else ""
        lines.append(f"  {name:<12}  {cv:>11}  {sx:.5f} x {sy:.5f}  {row['frames_rejected']:>15}{chosen}")
    return lines


def cmd_calibrate(args: argparse.Namespace) -> int:
    from probecal.core.calibration.solve import segment_and_calibrate
    from probecal.core.geometry.transforms import transform_error
    from probecal.core.io.session import load_session

    session = load_session(args.session)
    out = _default_output(args.session, args.out, "calibration.json")
    report = segment_and_calibrate(session, _segmenter(session, args), args.method, args.solve_phantom_pose,
                                   Progress("segmenting frames"), Status("calibrate"))
    calibration = report.calibration
    xml_path = calibration.write(out)
    m = calibration.metrics
    sx, sy = calibration.pixel_spacing_mm
    chosen = "chosen by cross-validation" if args.method == "auto" else "forced"
    lines = [
        f"calibration ({m['objective']} objective, {chosen}): {out} (PLUS element in {xml_path})",
        f"  frames: {m['frames_used']} used, {m['frames_rejected']} rejected of {m['frames_total']} "
        f"({m['frames_rejected_by_fit']} of them by the fit: markers that disagree with the rest)",
        f"  FRE {m['fre_mm']:.3f} mm (per-frame registration), marker-to-wire {m['calibration_residual_mm']:.3f} mm",
        f"  PRE3D {m['pre3d_mm']:.3f} +- {m['pre3d_std_mm']:.3f} mm (calibration frames, phantom pose {m['phantom_pose']})",
        f"  pixel spacing {sx:.5f} x {sy:.5f} mm/px",
    ]
    if m["wire_shifts_mm"]:
        name, far = max(m["wire_shifts_mm"].items(), key=lambda item: item[1])
        lines.append(f"  wires located by the fit: up to {far:.3f} mm off the definition ({name}); PRE3D above "
                     f"scores against the definition, {m['objective']}'s CV PRE3D below against the located wires")
    if m["objectives"]:
        lines += _format_objectives(m) + [f"  choice: {m['objective_choice']}"]
    if m["corner_error_95_mm"] is not None:
        parts = m["corner_error"]
        disagree = ", ".join(f"{name} {d:.2f} mm" for name, d in parts["objective_disagreement_mm"].items())
        echo = parts["echo_peak_disagreement_mm"]
        lines.append(f"  image corners +-{m['corner_error_95_mm']:.2f} mm (95 %, tool frame): refits on resampled "
                     f"blocks +-{parts['bootstrap_95_mm']:.2f} mm" + (f", other objectives {disagree}" if disagree else "")
                     + (f", markers at their echoes' peaks {echo:.2f} mm" if echo is not None else ""))
    if m["phantom_pose"] == "solved":
        lines.append("  with the phantom pose solved, PRE3D measures consistency, not accuracy; "
                     "the image-corner bound is the accuracy figure")
    for reason in report.weakly_determined:
        lines.append(f"  WEAKLY DETERMINED: {reason}")
    cv = m.get("cross_validation")
    if cv and cv.get("identity_translation_mm") is not None:
        lines.append(
            f"  cross-validation ({cv['folds']} blocks): eq.4.1 {cv['identity_translation_mm']:.3f} mm / "
            f"{cv['identity_rotation_deg']:.3f} deg, PRE3D {cv['pre3d_mm']:.3f} mm"
        )
    if report.curve:
        lines += _format_curve(report.curve)
    if report.shah is not None:
        dt, dr = transform_error(report.shah["image_to_tool_rigid"], calibration.image_to_tool_rigid)
        lines.append(f"  OpenCV SHAH differs by {dt:.3f} mm / {dr:.3f} deg")
    for index, reason in sorted(report.frames_rejected.items())[:10]:
        lines.append(f"  rejected frame {index}: {reason}")
    if len(report.frames_rejected) > 10:
        lines.append(f"  ... and {len(report.frames_rejected) - 10} more rejected frames")
    print("\n".join(lines))
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    from probecal.core.calibration.result import load_calibration
    from probecal.core.calibration.validate import validate_session
    from probecal.core.io.jsonio import write_json
    from probecal.core.io.session import load_session

    calibration = load_calibration(args.calibration)
    session = load_session(args.session)
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


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from probecal.core.calibration.result import load_calibration
    from probecal.core.io.session import load_session
    from probecal.core.volume.cad import session_cad_target
    from probecal.core.volume.reconstruct import reconstruct_session

    calibration = load_calibration(args.calibration)
    settings = _volume_settings(args.volume_config or args.calibration)
    if args.voxel is not None:
        try:
            settings = dataclasses.replace(settings, spacing_mm=(args.voxel,) * 3, origin_mm=None, extent=None)
        except ValueError as exc:
            raise InputError(None, f"--voxel {args.voxel}: {exc}")
    session = load_session(args.session)
    fresh_folder(args.out)
    cad = session_cad_target(session, args.cad, args.register) if args.cad is not None else None
    # The base frame of a robot session has z up; a tracker's reference frame may point anywhere.
    keep_floor = args.keep_floor or session.manifest.get("kind") == "imported"
    report = reconstruct_session(
        session, calibration, args.out, settings, cad,
        floor_up=None if keep_floor else (0.0, 0.0, 1.0),
        progress=Progress("reconstructing"),
    ).report
    line = f"{args.out}: {report['surface_points']} surface points, volume {report['volume']['shape_zyx'][::-1]} voxels"
    if "surface_mean_mm" in report:
        line += (f"; surface error to CAD: mean {report['surface_mean_mm']:.3f} mm, 95th percentile "
                 f"{report['surface_p95_mm']:.3f} mm (CAD to points {report['cad_to_points_mean_mm']:.3f} / "
                 f"{report['cad_to_points_p95_mm']:.3f} mm)")
    print(line)
    return 0


def _rig_arguments(p: argparse.ArgumentParser, resumable: bool = False) -> None:
    """--robot, --image and their settings; for a resumable command they default to None (the
    session's own, or the usual defaults)."""
    p.add_argument("--robot", default=None if resumable else "sim",
                   help="robot: sim (the twin's UR3, default) or ur:HOST (ur_rtde)")
    p.add_argument("--image", default=None if resumable else "sim",
                   help="images: sim (default), igtl:HOST:PORT, video:DEVICE_OR_FILE or replay:SESSION")
    p.add_argument("--workspace", type=Path, metavar="FILE",
                   help="workspace box and speed limits (default static/configs/workspace.json)")
    p.add_argument("--latency", type=float, default=None if resumable else 0.0, metavar="S",
                   help="image timestamps lag the robot's by S seconds (pairing offset, default 0)")
    p.add_argument("--time-scale", type=_nonnegative_float, default=0.25,
                   help="simulated robot: wall seconds per robot second (default 0.25; 0: instant)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="probecal", description="Robot-guided ultrasound probe calibration and volume scanning.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("serve", help="start the browser console")
    _rig_arguments(p)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1; any other needs a token, made up when not given)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.add_argument("--token-file", type=Path, metavar="FILE",
                   help="a file whose first line is the token browsers must present (at least 16 characters; "
                        "or set PROBECAL_TOKEN)")
    p.add_argument("--sessions", type=Path, default=Path("sessions"), help="where sessions are recorded")
    p.add_argument("--publish", type=int, metavar="PORT",
                   help="send the calibration and live tracked frames to 3D Slicer over OpenIGTLink on PORT")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("simulate", help="record a session on the digital twin")
    sim = p.add_subparsers(dest="what", required=True, parser_class=_Parser)
    q = sim.add_parser("calibration", help="a calibration sweep over the N-wire phantom")
    q.add_argument("out_dir", type=_output_path, metavar="OUT_DIR")
    q.add_argument("--poses", type=_positive_int, default=60, help="number of poses (default 60)")
    q.add_argument("--seed", type=_nonnegative_int, default=0, help="random seed (default 0)")
    q.add_argument("--noise", choices=NOISE_LEVELS, default=DEFAULT_LEVEL, help=NOISE_HELP)
    q.add_argument("--phantom", type=Path, help="phantom definition (.json or PLUS device-set .xml)")
    q.set_defaults(func=cmd_simulate_calibration)
    q = sim.add_parser("volume", help="straight sweeps over the 3D-printed test object")
    q.add_argument("out_dir", type=_output_path, metavar="OUT_DIR")
    q.add_argument("--seed", type=_nonnegative_int, default=0, help="random seed (default 0)")
    q.add_argument("--noise", choices=NOISE_LEVELS, default=DEFAULT_LEVEL, help=NOISE_HELP)
    q.add_argument("--frames-per-pass", type=_positive_int, default=120, help="frames per pass (default 120)")
    q.set_defaults(func=cmd_simulate_volume)

    p = sub.add_parser("sweep", help="record a sweep on a robot (simulated or real) into a session")
    p.add_argument("what", choices=["calibration", "volume"])
    p.add_argument("out_dir", type=_output_path, metavar="OUT_DIR")
    _rig_arguments(p, resumable=True)
    p.add_argument("--poses", type=_positive_int, default=60, help="calibration poses (default 60)")
    p.add_argument("--frames-per-pass", type=_positive_int, default=120, help="volume frames per pass (default 120)")
    p.add_argument("--speed", type=_positive_float, default=1.0, help="fraction of the UR default speed (default 1)")
    p.add_argument("--seed", type=_nonnegative_int, help="plan and twin seed (default 0)")
    p.add_argument("--resume", action="store_true",
                   help="continue the unfinished sweep in OUT_DIR (with its robot, images and seed unless given)")
    p.set_defaults(func=cmd_sweep)

    # Listed here for --help; main() hands its arguments to core.robot.ursim's own parser.
    sub.add_parser("ursim", help="a UR controller simulator that ur_rtde can drive (probecal ursim --help)")

    p = sub.add_parser("import-plus", help="turn a PLUS .igs.mha recording into a session")
    p.add_argument("sequence", type=Path, metavar="SEQUENCE.igs.mha")
    p.add_argument("--config", type=Path, metavar="DEVICESET.xml",
                   help="PLUS device-set file (phantom, PhantomTo<reference>, other constant transforms)")
    p.add_argument("out_dir", type=_output_path, metavar="OUT_DIR")
    p.add_argument("--tool-pose", type=_tool_pose, metavar="NAME",
                   help="the tool pose as PLUS names it, e.g. ProbeToTemplate: composed and inverted from the "
                        "transforms the files hold (default ProbeToReference, else the recording's "
                        "DefaultFrameTransformName)")
    p.add_argument("--tool", help="tracked tool frame (default Probe)")
    p.add_argument("--reference", help="reference frame (default Reference)")
    p.add_argument("--spacing", type=_positive_float, metavar="MM",
                   help="the scanner's nominal pixel spacing (mm/px), for a recording whose device set "
                        "has no PLUS segmentation hints; calibration refines it")
    p.set_defaults(func=cmd_import_plus)

    p = sub.add_parser("segment", help="find and label the wire dots in every frame")
    p.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(p)
    p.add_argument("--out", type=_output_path, metavar="FILE", help="output JSON (default SESSION/segmentation.json)")
    p.set_defaults(func=cmd_segment)

    p = sub.add_parser("calibrate", help="solve image_to_tool from a calibration session")
    p.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(p)
    p.add_argument("--out", type=_output_path, metavar="FILE", help="output JSON (default SESSION/calibration.json)")
    p.add_argument("--method", choices=["auto", "all-wire", "middle-wire", "seed"], default="auto",
                   help="objective: auto (default) keeps the lowest block cross-validated PRE3D; all-wire (every "
                        "marker to its wire), middle-wire (PLUS's) or seed (the thesis's) force one")
    p.add_argument("--solve-phantom-pose", action="store_true",
                   help="solve phantom_to_base even when the session records it")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("validate", help="score a calibration on another session")
    p.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(p)
    p.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                   help="calibration JSON, truth.json, or PLUS device-set XML with Image->Probe")
    p.add_argument("--out", type=_output_path, metavar="FILE", help="write the metrics as JSON")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("reconstruct", help="surface point cloud and volume from a sweep session")
    p.add_argument("session", type=Path, metavar="SESSION")
    p.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                   help="calibration JSON, truth.json, or PLUS device-set XML with Image->Probe")
    p.add_argument("--out", type=_output_path, required=True, metavar="DIR")
    p.add_argument("--cad", type=Path, metavar="MESH.stl", help="compare the surface with this CAD model")
    p.add_argument("--register", action="store_true", help="register the CAD model to the points (ICP) first")
    p.add_argument("--volume-config", type=Path, metavar="DEVICESET.xml",
                   help="PLUS <VolumeReconstruction> settings (default: those in --calibration, else 0.5 mm NN mean)")
    p.add_argument("--voxel", type=_positive_float, metavar="MM", help="output voxel size in mm (default 0.5)")
    p.add_argument("--keep-floor", action="store_true", help="keep the tank floor in the point cloud")
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("export-plus", help="write a session as a PLUS .igs.mha sequence")
    p.add_argument("session", type=Path, metavar="SESSION")
    p.add_argument("out", type=_output_path, metavar="OUT.igs.mha")
    p.set_defaults(func=cmd_export_plus)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["ursim"]:
        from probecal.core.robot.ursim import main as ursim_main

        return ursim_main(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (InputError, DeviceError) as exc:  # each names its file, robot or stream
        clear_line()
        print(f"probecal: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("probecal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
