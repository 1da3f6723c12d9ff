"""The ``probecal`` command line (SPEC §6). Thin: parses arguments, calls ``core``, reports.

Bad input exits with code 2 and one line naming the file and the problem.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from app.progress import Progress
from core.errors import InputError


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


def _fresh_output_dir(path: Path) -> Path:
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise InputError(path, "output folder exists and is not empty")
    return path


def cmd_serve(args: argparse.Namespace) -> int:
    from app.console import serve

    serve(host=args.host, port=args.port, robot=args.robot, image=args.image)
    return 0


def cmd_simulate_calibration(args: argparse.Namespace) -> int:
    from core.phantom import load_phantom
    from core.simulation import simulate_calibration

    phantom = load_phantom(args.phantom) if args.phantom else None
    out = _fresh_output_dir(args.out_dir)
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
    from core.simulation import simulate_volume

    out = _fresh_output_dir(args.out_dir)
    session = simulate_volume(out, seed=args.seed, noise=args.noise, progress=Progress("simulating volume sweeps"))
    plan = session.manifest["plan"]
    print(
        f"{session.path}: {len(session)} frames in {plan['passes']} passes, estimated UR3 time "
        f"{plan['estimated_robot_time_s']:.0f} s, CAD mesh {session.manifest['cad_mesh']}"
    )
    return 0


def cmd_import_plus(args: argparse.Namespace) -> int:
    from core.plusimport import import_plus

    session = import_plus(
        args.sequence, args.config, args.out_dir, tool=args.tool, reference=args.reference,
        progress=Progress("importing frames"),
    )
    valid = sum(r.pose_valid for r in session.records)
    phantom = session.phantom.name if session.phantom else "none"
    known = "known" if session.phantom_to_base is not None else "unknown"
    print(f"{session.path}: {len(session)} frames ({valid} with a valid pose), phantom {phantom}, phantom pose {known}")
    return 0


def cmd_export_plus(args: argparse.Namespace) -> int:
    from core.plusimport import export_plus
    from core.session import load_session

    if args.out.exists():
        raise InputError(args.out, "output file exists")
    session = load_session(args.session)
    export_plus(session, args.out, progress=Progress("exporting frames"))
    print(f"{args.out}: {len(session)} frames with ProbeToReference transforms")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="probecal", description="Robot-guided ultrasound probe calibration and volume scanning.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("serve", help="start the browser console")
    p.add_argument("--robot", default="sim", help="robot backend: sim (default)")
    p.add_argument("--image", default="sim", help="image source: sim (default)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("simulate", help="record a session on the digital twin")
    sim = p.add_subparsers(dest="what", required=True, parser_class=_Parser)
    q = sim.add_parser("calibration", help="a calibration sweep over the N-wire phantom")
    q.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    q.add_argument("--poses", type=_positive_int, default=60, help="number of poses (default 60)")
    q.add_argument("--seed", type=_nonnegative_int, default=0, help="random seed (default 0)")
    q.add_argument("--noise", choices=["none", "realistic", "harsh"], default="realistic")
    q.add_argument("--phantom", type=Path, help="phantom definition (.json or PLUS device-set .xml)")
    q.set_defaults(func=cmd_simulate_calibration)
    q = sim.add_parser("volume", help="straight sweeps over the 3D-printed test object")
    q.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    q.add_argument("--seed", type=_nonnegative_int, default=0, help="random seed (default 0)")
    q.add_argument("--noise", choices=["none", "realistic", "harsh"], default="realistic")
    q.set_defaults(func=cmd_simulate_volume)

    p = sub.add_parser("import-plus", help="turn a PLUS .igs.mha recording into a session")
    p.add_argument("sequence", type=Path, metavar="SEQUENCE.igs.mha")
    p.add_argument("--config", type=Path, metavar="DEVICESET.xml", help="PLUS device-set file (phantom, PhantomToReference)")
    p.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    p.add_argument("--tool", default="Probe", help="tracked tool frame (default Probe)")
    p.add_argument("--reference", default="Reference", help="reference frame (default Reference)")
    p.set_defaults(func=cmd_import_plus)

    p = sub.add_parser("export-plus", help="write a session as a PLUS .igs.mha sequence")
    p.add_argument("session", type=Path, metavar="SESSION")
    p.add_argument("out", type=Path, metavar="OUT.igs.mha")
    p.set_defaults(func=cmd_export_plus)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"probecal: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("probecal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
