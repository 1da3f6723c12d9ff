"""The ``probecal`` command line (design §6). Thin: parses arguments, runs the command
(``app.commands``), and turns bad input into one line.

Bad input exits with code 2 and one line naming the file and the problem.
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
from collections.abc import Callable
from pathlib import Path

from probecal.app import bounds, commands, phantoms
from probecal.app.bounds import Bound
from probecal.app.oneline import OneLineParser
from probecal.app.progress import clear_line
from probecal.core.errors import DeviceError, InputError, Remedy
from probecal.core.geometry.probe import BUILTIN_PROBES, DEFAULT_PROBE
from probecal.core.io.files import no_space
from probecal.core.io.posetable import is_number

# The twin's levels (core.twin.levels.LEVELS, not imported here so that --help stays fast).
NOISE_LEVELS = ("none", "realistic", "harsh", "bench")
DEFAULT_LEVEL = "bench"
# The arms whose kinematic tables probecal knows (core.calibration.kinematics.ARMS), likewise.
ARMS = ("UR3", "UR3e")
# The calibration tolerance a verdict is judged against (app.report.DEFAULT_TOLERANCE_MM), likewise.
DEFAULT_TOLERANCE_MM = 1.0
NOISE_HELP = ("the twin's difficulty (default bench: slice thickness, robot kinematic errors, phantom "
              "tolerances, latency; realistic: a perfect set-up)")


def _within(low: float, high: float, unit: str = "", whole: bool = False) -> Callable[[str], float]:
    """An option's number from ``low`` to ``high`` ``unit`` (:class:`app.bounds.Bound`)."""
    return Bound(low, high, unit, whole).argument


PORT, SEED, POSES, FRAMES = bounds.PORT.argument, bounds.SEED.argument, bounds.POSES.argument, bounds.FRAMES.argument
IMAGE_PX, LENGTH_MM, DEPTH_MM = bounds.IMAGE_PX.argument, bounds.LENGTH_MM.argument, bounds.DEPTH_MM.argument
SECONDS, PIXEL_SIZE = bounds.SECONDS.argument, bounds.PIXEL_SIZE.argument


def _spacing_argument(p: argparse.ArgumentParser, more: str) -> None:
    """--spacing: the scanner's nominal pixel spacing, one number or lateral then axial (words
    joined by :func:`_spacing_joined`)."""
    p.add_argument("--spacing", type=_spacing, metavar="SX [SY]",
                   help=f"the scanner's nominal pixel spacing (mm/px): one number, or lateral then axial{more}")


def wrist_angles(text: str) -> tuple[tuple[float, float], ...]:
    """``--views``'s wrist angles, comma-joined, each a turn about the beam and optionally ``/`` a
    tilt in the image plane (deg), as (turn, tilt) pairs; as many as :data:`app.bounds.VIEWS`
    allows, counted before any is read."""
    angle = _within(-360, 360, " deg")
    parts = text.split(",")
    if len(parts) < bounds.VIEWS.low:
        raise argparse.ArgumentTypeError("two or more views, comma-joined (e.g. 0,180)")
    if len(parts) > bounds.VIEWS.high:
        raise argparse.ArgumentTypeError(f"{len(parts)} views: at most {bounds.VIEWS.high:g}, each sweeping every pass")
    views = []
    for part in parts:
        turn, _, tilt = part.partition("/")
        views.append((angle(turn), angle(tilt) if tilt else 0.0))
    return tuple(views)


def _spacing(text: str) -> tuple[float, float]:
    """``--spacing``'s one number (square pixels) or two, comma-joined (lateral, axial), as (sx, sy) mm/px."""
    numbers = [PIXEL_SIZE(part) for part in text.split(",")]
    if len(numbers) > 2:
        raise argparse.ArgumentTypeError(f"one or two numbers (lateral, axial mm/px), not {len(numbers)}")
    return numbers[0], numbers[-1]


_spacing.__name__ = "number"  # argparse's word for text that is none


def _spacing_joined(argv: list[str]) -> list[str]:
    """``argv`` with ``--spacing SX [SY]`` as one word, ``--spacing=SX,SY``: argparse's "one or
    more" would take a folder that follows for a number too (``--spacing 0.1 OUT_DIR``), so only
    the numbers that follow the option are its."""
    joined: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] == "--spacing":
            numbers = list(itertools.takewhile(is_number, argv[i + 1:]))
            joined.append("--spacing=" + ",".join(numbers) if numbers else "--spacing")
            i += 1 + len(numbers)
        else:
            joined.append(argv[i])
            i += 1
    return joined


def _start_depth_argument(p: argparse.ArgumentParser, default: float | None = None, more: str = "") -> None:
    """--start-depth-mm: how far below the probe's face the image's first row lies."""
    p.add_argument("--start-depth-mm", type=DEPTH_MM, default=default, metavar="MM",
                   help="how far below the probe's face the image's first row lies (the depth preset's start, mm): "
                        f"a calibration made at another preset of the probe is then derived for this one{more}")


def _frame_import_arguments(p: argparse.ArgumentParser) -> None:
    """The phantom, nominal spacing and orientation of an import of a lab's frames."""
    p.add_argument("--phantom", type=Path,
                   help="phantom definition (.json or PLUS device-set .xml) or a built-in phantom's name "
                        "(default the thesis's 4-layer phantom)")
    _spacing_argument(p, "")
    p.add_argument("--depth-mm", type=LENGTH_MM, metavar="MM", help="the image's depth (its height, mm)")
    p.add_argument("--width-mm", type=LENGTH_MM, metavar="MM", help="the image's width (mm)")
    _start_depth_argument(p)
    p.add_argument("--mirror", action="store_true",
                   help="flip every frame left to right (a scanner that shows the phantom the other way round)")


def _output_folder(text: str) -> Path:
    """An output folder: its nearest existing parent must be a writable folder (missing parents
    are made), checked before any work."""
    path = Path(text)
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {parent} is not a folder")
    if not os.access(parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: the folder {parent} is not writable")
    return path


def _output_path(text: str) -> Path:
    """An output file or folder whose folder exists and is writable, checked before any work."""
    path = Path(text)
    folder = path.absolute().parent
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: the folder {folder} is not writable")
    return path


def _tool_pose(text: str) -> tuple[str, str]:
    """(tool, reference) from a PLUS transform name such as ProbeToTemplate."""
    from probecal.core.geometry.transformrepo import frame_splits

    pairs = frame_splits(text)
    if len(pairs) != 1:
        readings = " or ".join(f"{a}->{b}" for a, b in pairs) or "none"
        raise argparse.ArgumentTypeError(f"{text!r} is not one <From>To<To> name (readings: {readings}); "
                                         "give --tool and --reference instead")
    return pairs[0]


def _method(text: str) -> str:
    """A method's name; the thesis's methods keep their old name, seed, as an alias of thesis."""
    return "thesis" if text == "seed" else text


def _add_segmenter_arguments(p: argparse.ArgumentParser) -> None:
    from probecal.core.calibration.segment import SEGMENTERS

    p.add_argument("--segmenter", type=_method, choices=SEGMENTERS, default=SEGMENTERS[0],
                   help="dot finder and labeller: probecal's own (default), the thesis's (thesis, or seed), or "
                        "PLUS's")
    p.add_argument("--ignore-hints", action="store_true",
                   help="use none of an imported recording's PLUS segmentation settings but its approximate "
                        "pixel spacing (the way a robot session runs)")
    p.add_argument("--verbose", action="store_true",
                   help="also print the segmenter tuned on the session, every step and the whole report")


def _rig_arguments(p: argparse.ArgumentParser, resumable: bool = False) -> None:
    """--robot, --image and their settings; for a resumable command they default to None (the
    session's own, or the usual defaults)."""
    p.add_argument("--robot", default=None if resumable else "sim",
                   help="robot: sim (the twin's UR3, default) or ur:HOST (ur_rtde)")
    p.add_argument("--image", default=None if resumable else "sim",
                   help="images: sim (default), igtl:HOST:PORT, video:DEVICE_OR_FILE or replay:SESSION")
    p.add_argument("--workspace", type=Path, metavar="FILE",
                   help="workspace box and speed limits (default static/configs/workspace.json)")
    p.add_argument("--latency", type=SECONDS, default=None if resumable else 0.0, metavar="S",
                   help="image timestamps lag the robot's by S seconds (pairing offset, default 0)")
    p.add_argument("--latency-from", type=Path, metavar="FILE",
                   help="the image latency a calibration JSON or probecal temporal-calibrate's JSON records")
    p.add_argument("--time-scale", type=_within(0, 100), default=0.25,
                   help="simulated robot: wall seconds per robot second (default 0.25; 0: instant)")
    _spacing_argument(p, "; default the image source's, else the twin probe's 0.1")
    _start_depth_argument(p, more=" (a live scanner's; the twin's images start at its probe's face)")
    _probe_option(p, " (the simulated scanner's; a resumed sweep keeps its own)" if resumable
                  else " (the simulated scanner's)")


def _probe_option(p: argparse.ArgumentParser, more: str = "") -> None:
    """--probe: the twin's probe, built in or from a file."""
    p.add_argument("--probe", metavar="NAME_OR_FILE",
                   help=f"the probe: {' or '.join(BUILTIN_PROBES)} (default {DEFAULT_PROBE}), or a probe file (.json: "
                        f"type linear or convex and its fields){more}")


def _probe_arguments(p: argparse.ArgumentParser) -> None:
    """The twin's probe, its depth preset and image size."""
    _probe_option(p)
    p.add_argument("--image-size", type=IMAGE_PX, nargs=2, metavar=("W", "H"),
                   help="the frames' size in pixels over the probe's width and its depth (default 384 500 for "
                        "linear-38: 0.1 mm/px; a convex probe's height follows from its width); a scanner that "
                        "resamples finer or coarser")
    p.add_argument("--depth-mm", type=bounds.PROBE_DEPTH_MM.argument, metavar="MM",
                   help="the depth preset's range (default 50 for linear-38, 70 below the face for convex-50)")
    _start_depth_argument(p, 0.0, " (default 0; a convex probe's fan starts at its face)")


def _motion_arguments(p: argparse.ArgumentParser, continuous: str) -> None:
    """--motion, --frame-rate and --image-latency of the twin's sweeps."""
    p.add_argument("--motion", choices=["stop", "continuous"], default="stop",
                   help=f"stop: one frame at every pose (default); continuous: {continuous}, while the scanner "
                        "streams at --frame-rate and the pose stream is kept")
    p.add_argument("--frame-rate", type=_within(0.1, 1000, " Hz"), default=25.0, metavar="HZ",
                   help="continuous: the scanner's frame rate (default 25)")
    p.add_argument("--image-latency", type=_within(0, 10, " s"), metavar="S",
                   help="the twin's true image latency in s (default: drawn from the seed at bench, 0 otherwise)")


def _tracker_arguments(p: argparse.ArgumentParser, tolerance: bool = True) -> None:
    """--tracker and what a tracked probe's recording needs besides its streams."""
    from probecal.core.acquisition.tracker import TrackerDevices

    p.add_argument("--tracker", metavar="SOURCE",
                   help="a tracked probe instead of a robot: igtl:HOST:PORT (a PLUS server, 3D Slicer or a robot's "
                        "own bridge; its images too unless --image says otherwise) or sim (the freehand twin: a "
                        "hand following the guidance, streamed by a PLUS-server stand-in on loopback)")
    p.add_argument("--tracker-devices", type=_devices, default=TrackerDevices(), metavar="PROBE[,REFERENCE]",
                   help="the TRANSFORM devices: the probe and the reference in the tracker's frame, composed as PLUS "
                        "does (default ProbeToTracker,ReferenceToTracker), or one device already in the reference's "
                        "frame (e.g. ProbeToReference)")
    p.add_argument("--device-set", type=Path, metavar="DEVICESET.xml",
                   help="a tracked probe's PLUS device set: the phantom, its registered pose PhantomToReference and "
                        "the segmentation settings (without it the phantom's pose is solved)")
    p.add_argument("--phantom", metavar="NAME_OR_FILE",
                   help="a tracked probe's phantom when no --device-set gives it (a built-in name or a file)")
    if tolerance:  # the console's is its Tolerance field
        p.add_argument("--tolerance", type=LENGTH_MM, default=DEFAULT_TOLERANCE_MM, metavar="MM",
                       help=f"guided: enough once the image corners' 95 %% bound is within MM (default "
                            f"{DEFAULT_TOLERANCE_MM:g})")


def _devices(text: str):
    from probecal.core.acquisition.tracker import parse_devices

    try:
        return parse_devices(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="probecal",
                           description="Robot-guided ultrasound probe calibration and volume scanning.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    p = sub.add_parser("serve", help="start the browser console")
    _rig_arguments(p)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1; any other needs a token, made up when not given)")
    p.add_argument("--port", type=PORT, default=8080, help="port (default 8080)")
    p.add_argument("--token-file", type=Path, metavar="FILE",
                   help="a file whose first line is the token browsers must present (at least 16 characters; "
                        "or set PROBECAL_TOKEN)")
    p.add_argument("--sessions", type=Path, default=Path("sessions"), help="where sessions are recorded")
    p.add_argument("--publish", type=PORT, metavar="PORT",
                   help="send the calibration and live tracked frames to 3D Slicer over OpenIGTLink on PORT")
    p.add_argument("--unattended", action="store_true",
                   help="let a sweep run on when no console page is open (by default it stops at its next pose, "
                        "to be resumed)")
    _tracker_arguments(p, tolerance=False)
    p.set_defaults(func=commands.serve)

    p = sub.add_parser("simulate", help="record a session on the digital twin")
    sim = p.add_subparsers(dest="what", required=True, parser_class=OneLineParser)
    q = sim.add_parser("calibration", help="a calibration sweep over the N-wire phantom")
    q.add_argument("out_dir", type=_output_folder, metavar="OUT_DIR")
    q.add_argument("--poses", type=POSES, default=60, help="number of poses (default 60)")
    q.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
    q.add_argument("--noise", choices=NOISE_LEVELS, default=DEFAULT_LEVEL, help=NOISE_HELP)
    q.add_argument("--phantom", type=Path,
                   help="phantom definition (.json or PLUS device-set .xml) or a built-in phantom's name")
    q.add_argument("--as-built", type=Path, metavar="FILE",
                   help="the phantom as built: the same wires placed where they really are (a definition file), "
                        "imaged instead of the level's manufacturing tolerance")
    _probe_arguments(q)
    _motion_arguments(q, "the robot moves the probe up and down (to measure the latency), then through the "
                         "poses without stopping")
    q.set_defaults(func=commands.simulate_calibration)
    q = sim.add_parser("volume", help="straight sweeps over the 3D-printed test object")
    q.add_argument("out_dir", type=_output_folder, metavar="OUT_DIR")
    q.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
    q.add_argument("--noise", choices=NOISE_LEVELS, default=DEFAULT_LEVEL, help=NOISE_HELP)
    q.add_argument("--frames-per-pass", type=FRAMES, default=120,
                   help="stop: frames per pass (default 120)")
    _probe_arguments(q)
    _motion_arguments(q, "every pass at --speed")
    q.add_argument("--speed", type=_within(0.1, 1000, " mm/s"), default=20.0, metavar="MM_S",
                   help="continuous: the probe's speed along a pass (default 20 mm/s)")
    q.add_argument("--views", type=wrist_angles, metavar="TURN[/TILT],...",
                   help="sweep the passes again from each of these wrist angles (deg: turned about the beam, tilted "
                        "in the image plane), each frame recording its view, for probecal selfcheck; the passes are "
                        "then 56 mm long, so that both ends of the object are seen (e.g. 0,180; 2 to 8 views)")
    q.set_defaults(func=commands.simulate_volume)

    p = sub.add_parser("sweep", help="record a sweep on a robot (simulated or real) into a session")
    p.add_argument("what", choices=["calibration", "volume"])
    p.add_argument("out_dir", type=_output_folder, metavar="OUT_DIR")
    _rig_arguments(p, resumable=True)
    p.add_argument("--poses", type=POSES, default=60, help="calibration poses (default 60)")
    p.add_argument("--frames-per-pass", type=FRAMES, default=120, help="volume frames per pass (default 120)")
    p.add_argument("--speed", type=bounds.SPEED.argument, default=1.0,
                   help="fraction of the UR default speed (default 1)")
    p.add_argument("--seed", type=SEED, help="plan and twin seed (default 0)")
    p.add_argument("--resume", action="store_true",
                   help="continue the unfinished sweep in OUT_DIR (with its robot, images and seed unless given)")
    p.add_argument("--force", action="store_true",
                   help="take --latency-from a calibration made for other images than this rig's")
    p.add_argument("--motion", choices=["stop", "continuous", "guided"],
                   help="stop: one frame at every settled pose (a robot's default, resumable); continuous: the robot "
                        "moves without stopping (a calibration starts with an up-and-down motion that measures the "
                        "image latency) while every frame of the stream is recorded and the pose stream is kept; "
                        "guided (a tracked probe's default for a calibration): frames held still, until the corner "
                        "bound is within --tolerance")
    _tracker_arguments(p)
    p.add_argument("--frames", type=FRAMES, help="a tracked probe's continuous recording: stop after this many frames")
    p.set_defaults(func=commands.sweep)

    # Listed here for --help; main() hands its arguments to app.ursim's own parser.
    sub.add_parser("ursim", help="a UR controller simulator that ur_rtde can drive (probecal ursim --help)")

    p = sub.add_parser("import-plus", help="turn a PLUS .igs.mha recording into a session")
    p.add_argument("sequence", type=Path, metavar="SEQUENCE.igs.mha")
    p.add_argument("--config", type=Path, metavar="DEVICESET.xml",
                   help="PLUS device-set file (phantom, PhantomTo<reference>, other constant transforms)")
    p.add_argument("out_dir", type=_output_folder, metavar="OUT_DIR")
    p.add_argument("--tool-pose", type=_tool_pose, metavar="NAME",
                   help="the tool pose as PLUS names it, e.g. ProbeToTemplate: composed and inverted from the "
                        "transforms the files hold (default ProbeToReference, else the recording's "
                        "DefaultFrameTransformName)")
    p.add_argument("--tool", help="tracked tool frame (default Probe)")
    p.add_argument("--reference", help="reference frame (default Reference)")
    _spacing_argument(p, ", for a recording whose device set has no PLUS segmentation hints; calibration "
                         "refines it")
    _start_depth_argument(p)
    p.set_defaults(func=commands.import_plus)

    p = sub.add_parser("import-frames", help="turn a folder of image files and a table of robot poses into a session")
    p.add_argument("images_dir", type=Path, metavar="IMAGES_DIR",
                   help="PNG, JPEG, TIFF or BMP files, or a scanner's DICOM export (.dcm, one frame per file), "
                        "whose region calibration gives the spacing and start depth where no option does")
    p.add_argument("--poses", type=Path, required=True, metavar="POSES.csv",
                   help="one pose per image: 4x4 or 3x4 matrices (one per row, or stacked one matrix row per "
                        "row), UR pose vectors x y z rx ry rz, or x y z qx qy qz qw; a header naming 'file' and "
                        "'t' columns pairs by name and keeps times (else the i-th pose goes with the i-th image "
                        "in natural order of the names)")
    p.add_argument("out_dir", type=_output_folder, metavar="OUT_DIR")
    p.add_argument("--units", choices=("mm", "m"), help="the poses' translations (default: told from their sizes)")
    p.add_argument("--pose", choices=("flange-to-base", "base-to-flange"), default="flange-to-base",
                   help="what each pose maps: the flange's pose in the robot base frame, as robots report it "
                        "(default), or its inverse")
    _frame_import_arguments(p)
    p.set_defaults(func=commands.import_frames)

    p = sub.add_parser("import-rosbag", help="turn a ROS 1 or ROS 2 bag (an image topic and the arm's poses) into a "
                                             "session")
    p.add_argument("bag", type=Path, metavar="BAG")
    p.add_argument("out_dir", type=_output_folder, metavar="OUT_DIR")
    p.add_argument("--image-topic", required=True, metavar="TOPIC", help="sensor_msgs/Image or CompressedImage")
    poses = p.add_mutually_exclusive_group(required=True)
    poses.add_argument("--pose-topic", metavar="TOPIC", help="geometry_msgs/PoseStamped: the tool in the base frame")
    poses.add_argument("--tf", nargs=2, metavar=("BASE", "TOOL"), help="the tf frames whose chain gives the tool pose")
    p.add_argument("--latency", type=SECONDS, default=0.0, metavar="S",
                   help="how late the images are against the poses (s, default 0): each frame takes the pose at its "
                        "time minus this; calibrate measures it again from the pose stream kept")
    _frame_import_arguments(p)
    p.set_defaults(func=commands.import_rosbag)

    p = sub.add_parser("segment", help="find and label the wire dots in every frame")
    p.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(p)
    p.add_argument("--out", type=_output_path, metavar="FILE", help="output JSON (default SESSION/segmentation.json)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=commands.segment)

    p = sub.add_parser("calibrate", help="solve image_to_tool from a calibration session")
    p.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(p)
    p.add_argument("--out", type=_output_path, metavar="FILE", help="output JSON (default SESSION/calibration.json)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.add_argument("--method", type=_method, choices=["auto", "all-wire", "middle-wire", "thesis"], default="auto",
                   help="objective: auto (default) keeps all-wire where the phantom pose is solved (a robot sweep), "
                        "and where it is known the lowest held-out PRE3D among those that beat middle-wire beyond "
                        "the block-to-block scatter; all-wire (every marker to its wire), middle-wire (PLUS's) or "
                        "thesis (the thesis's; seed is an alias) force one")
    p.add_argument("--tolerance", type=bounds.TOLERANCE_MM.argument, default=DEFAULT_TOLERANCE_MM, metavar="MM",
                   help=f"the calibration is usable when its image corners lie within MM (95 %%; default "
                        f"{DEFAULT_TOLERANCE_MM:g} mm)")

    p.add_argument("--solve-phantom-pose", action="store_true",
                   help="solve phantom_to_base even when the session records it")
    p.add_argument("--arm", choices=ARMS,
                   help="the arm that recorded SESSION, when its manifest does not name one (a lab's own "
                        "recording): its kinematic errors are then fitted with the calibration")
    p.set_defaults(func=commands.calibrate)

    p = sub.add_parser("validate", help="score a calibration on another session")
    p.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(p)
    p.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                   help="calibration JSON, truth.json, or PLUS device-set XML with Image->Probe")
    p.add_argument("--out", type=_output_path, metavar="FILE", help="write the metrics as JSON")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing --out, and apply a calibration made for other images")
    p.set_defaults(func=commands.validate)

    p = sub.add_parser("reconstruct", help="surface point cloud and volume from a sweep session")
    p.add_argument("session", type=Path, metavar="SESSION")
    p.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                   help="calibration JSON, truth.json, or PLUS device-set XML with Image->Probe")
    p.add_argument("--out", type=_output_folder, required=True, metavar="DIR")
    p.add_argument("--cad", type=Path, metavar="MESH.stl", help="compare the surface with this CAD model")
    p.add_argument("--register", action="store_true", help="register the CAD model to the points (ICP) first")
    p.add_argument("--volume-config", type=Path, metavar="DEVICESET.xml",
                   help="PLUS <VolumeReconstruction> settings (default: those in --calibration, else 0.5 mm NN mean)")
    p.add_argument("--voxel", type=_within(0.01, 100, " mm"), metavar="MM",
                   help="output voxel size in mm (default 0.5)")
    p.add_argument("--keep-floor", action="store_true", help="keep the tank floor in the point cloud")
    p.add_argument("--tolerance", type=bounds.TOLERANCE_MM.argument, default=DEFAULT_TOLERANCE_MM, metavar="MM",
                   help=f"with --cad, the volume is usable when its surface lies within MM of the CAD model on "
                        f"average (default {DEFAULT_TOLERANCE_MM:g} mm)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --out folder, and apply a calibration made for other images")
    p.set_defaults(func=commands.reconstruct)

    p = sub.add_parser("selfcheck", help="after a calibration: how far apart one object's surfaces lie when swept "
                                         "from two or more wrist angles", description="Reconstruct every pass of every "
                       "view of one object's sweep, register each to the first view's same pass, and say how far "
                       "apart they sit, what calibration error would explain it and whether to trust the volumes. "
                       "Needs no ground truth. A session's views are those its frames record (the console's "
                       "Self-check, probecal simulate volume --views) or, where they record none, the wrist angles "
                       "the robot held; given several sessions, each is a view.")
    p.add_argument("sessions", type=Path, nargs="+", metavar="SESSION",
                   help="a volume sweep from two or more wrist angles, or one session per wrist angle; each pass's "
                        "frames at most 0.7 mm apart")
    p.add_argument("--calibration", type=Path, required=True, metavar="FILE",
                   help="calibration JSON, truth.json, or PLUS device-set XML with Image->Probe")
    p.add_argument("--out", type=_output_folder, metavar="DIR",
                   help="where report.json and every view's points (view_K.ply, one colour each) go (default "
                        "the first SESSION's selfcheck)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --out folder, and apply a calibration made for other images")
    p.set_defaults(func=commands.selfcheck)

    p = sub.add_parser("phantom", help="the built-in phantoms; build one; check one as built")
    ph = p.add_subparsers(dest="what", required=True, parser_class=OneLineParser)
    q = ph.add_parser("list", help="the built-in phantoms with their size and wire count")
    q.set_defaults(func=phantoms.phantom_list)
    q = ph.add_parser("export", help="a printable frame (STL), drawings, wiring list, build guide and PLUS definition")
    q.add_argument("phantom", nargs="?", default="thesis-4layer", metavar="PHANTOM",
                   help="a built-in phantom (probecal phantom list) or a definition file (.json or PLUS device-set "
                        ".xml); default thesis-4layer")
    q.add_argument("out_dir", type=_output_folder, metavar="DIR")
    q.add_argument("--wire-diameter", type=_within(0.01, 10, " mm"), default=0.3, metavar="MM",
                   help="the line the wires are made of (default 0.3 mm nylon)")
    q.add_argument("--hole-diameter", type=_within(0.01, 20, " mm"), default=0.5, metavar="MM",
                   help="holes for one wire (default 0.5 mm; a hole two wires share is one wire wider)")
    q.add_argument("--force", action="store_true", help="replace an existing DIR")
    q.set_defaults(func=phantoms.phantom_export)
    q = ph.add_parser("check", help="after a calibration: where each wire of the built phantom is, against the "
                                    "definition", description="Locate every wire of the built phantom from a "
                                    "calibrated sweep over it and name the wires off their definition; a wire the "
                                    "scan cannot tell is said so.")
    q.add_argument("session", type=Path, metavar="SESSION")
    _add_segmenter_arguments(q)
    q.add_argument("--calibration", type=Path, metavar="FILE",
                   help="the session's calibration (default SESSION/calibration.json)")
    q.add_argument("--tolerance", type=_within(0.001, 100, " mm"), default=0.2, metavar="MM",
                   help="name the wires farther than this from their definition beyond doubt (default 0.2 mm; "
                        "each offset's standard error comes from 4 runs of consecutive frames)")
    q.add_argument("--out", type=_output_path, metavar="FILE",
                   help="every wire's offsets as JSON (default SESSION/phantom_check.json)")
    q.add_argument("--as-built", type=_output_path, metavar="FILE.json",
                   help="also write the phantom's definition with every wire where the scan found it (those it "
                        "cannot tell as defined)")
    q.add_argument("--force", action="store_true",
                   help="overwrite existing output files, and apply a calibration made for other images")
    q.set_defaults(func=phantoms.phantom_check)

    p = sub.add_parser("temporal-calibrate", help="measure how late the images are relative to the pose stream")
    p.add_argument("session", type=Path, nargs="?", metavar="SESSION",
                   help="a session recorded with --motion continuous (its up-and-down motion and pose stream)")
    p.add_argument("--video", type=Path, metavar="VIDEO.igs.mha", help="PLUS video buffer (frames, timestamps)")
    p.add_argument("--tracker", type=Path, metavar="TRACKER.igs.mha", help="PLUS tracker buffer (poses, timestamps)")
    p.add_argument("--tool", default="Probe", help="tracked tool frame in the tracker buffer (default Probe)")
    p.add_argument("--reference", default="Tracker", help="its reference frame (default Tracker, as PLUS fCal)")
    p.add_argument("--max-lag", type=_within(0.001, 10, " s"), default=0.5, metavar="S",
                   help="latencies searched: within S seconds of zero (default 0.5)")
    p.add_argument("--out", type=_output_path, required=True, metavar="FILE",
                   help="output JSON: image_latency_s and how well it is determined")
    p.add_argument("--force", action="store_true", help="overwrite --out")
    p.set_defaults(func=commands.temporal_calibrate)

    p = sub.add_parser("export-plus", help="write a session as a PLUS .igs.mha sequence")
    p.add_argument("session", type=Path, metavar="SESSION")
    p.add_argument("out", type=_output_path, metavar="OUT.igs.mha")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=commands.export_plus)
    return parser


REMEDY_OPTIONS = {
    Remedy.FORCE: "--force applies it anyway",
    Remedy.START_DEPTH: "--start-depth-mm records it when a session is imported or recorded",
    Remedy.SPACING: "--spacing SX [SY] gives it",
    Remedy.IMAGE_EXTENT: "--depth-mm and --width-mm give the image's",
    Remedy.REGISTER: "--register does so",
    Remedy.CONTINUOUS: "--motion continuous records one",
    Remedy.SWEEP_TIMING: "--speed, --frame-rate and --image-latency set them",
    Remedy.ARM: "--arm names the arm that recorded them",
}
"""The option that does what an InputError's remedy says (core names no option: the console shows
its messages too)."""


def _remedies(exc: Exception) -> str:
    """The options that remedy ``exc``, as clauses to append to its message."""
    return "".join(f"; {REMEDY_OPTIONS[remedy]}" for remedy in getattr(exc, "remedies", ()))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["ursim"]:
        from probecal.app.ursim import main as ursim_main

        return ursim_main(argv[1:])
    args = build_parser().parse_args(_spacing_joined(argv))
    try:
        return args.func(args)
    except (InputError, DeviceError) as exc:  # each names its file, robot or stream
        clear_line()
        print(f"probecal: error: {exc}{_remedies(exc)}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader (head, a pager) went away: nothing left to say to it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as exc:  # a full disk is the user's to fix, as bad input is
        full = no_space(exc)
        if full is None:
            raise
        clear_line()
        print(f"probecal: error: {full}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("probecal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
