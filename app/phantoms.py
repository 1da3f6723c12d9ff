"""``probecal phantom list|export|check``: the built-in phantoms, everything to build one, and the
check of a built one against its definition. Thin: calls ``core.build`` and
``core.calibration.wirecheck`` and prints what they did."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from probecal.app.commands import _into_folder, _output_file, _replacing, _segment, _warn
from probecal.core.errors import InputError

CHECK_COMMANDS = ("probecal sweep calibration SESSION --robot ur:ROBOT --image igtl:SCANNER:18944",
                  "probecal calibrate SESSION",
                  "probecal phantom check SESSION [--as-built FILE.json]")
"""How the build guide tells the builder to sweep, calibrate and check the phantom once built."""


def _size(values) -> str:
    return " x ".join(f"{v:g}" for v in np.round(values, 1))


def phantom_list(args: argparse.Namespace) -> int:
    from probecal.core.build.walls import frame_of
    from probecal.core.io.phantomfile import BUILTIN_PHANTOMS, load_phantom

    for name, path in BUILTIN_PHANTOMS.items():
        phantom = load_phantom(path)
        ends = phantom.lines().reshape(-1, 3)
        print(f"{name:14s} {len(phantom.layers)} N layers, {phantom.n_wires} wires within "
              f"{_size(np.ptp(ends, axis=0))} mm; printed frame {_size(frame_of(phantom, source=path).extent_mm)} "
              f"mm (x, y, z); {path.relative_to(path.parents[2])}")
    return 0


def phantom_export(args: argparse.Namespace) -> int:
    from probecal.core.build.export import export_phantom
    from probecal.core.build.walls import FrameDesign
    from probecal.core.io.phantomfile import load_phantom, phantom_path

    path = phantom_path(args.phantom)
    phantom = load_phantom(path)
    try:
        design = FrameDesign(wire_diameter_mm=args.wire_diameter, hole_diameter_mm=args.hole_diameter)
    except ValueError as exc:
        raise InputError(None, f"--wire-diameter {args.wire_diameter} --hole-diameter {args.hole_diameter}: {exc}")
    replacing = _replacing(args.out_dir, args.force)
    export = _into_folder(args.out_dir, replacing, lambda folder: export_phantom(
        phantom, folder, design, path, check_commands=CHECK_COMMANDS))
    frame, mesh = export.frame, export.mesh
    shared = sum(len(h.wires) > 1 for h in frame.holes)
    print(f"{args.out_dir}: {phantom.name} frame {_size(frame.extent_mm)} mm (x, y, z), "
          f"{'watertight' if mesh.is_watertight else 'NOT watertight'}, {mesh.volume / 1000:.1f} cm3; "
          f"{len(frame.holes)} holes ({shared} shared by two wires), {len(frame.landmarks())} landmark divots")
    print(f"  {', '.join(export.files)}; start with BUILD.md")
    return 0


def phantom_check(args: argparse.Namespace) -> int:
    from probecal.app.report import wire_check_lines
    from probecal.core.calibration.result import load_calibration
    from probecal.core.calibration.validity import check_fits
    from probecal.core.calibration.wirecheck import CheckSettings, check_session
    from probecal.core.io.jsonio import write_json
    from probecal.core.io.phantomfile import dict_from_phantom
    from probecal.core.io.session import load_recorded_session

    session = load_recorded_session(args.session)
    calibration_file = args.calibration or Path(args.session) / "calibration.json"
    if args.calibration is None and not calibration_file.is_file():
        raise InputError(calibration_file, "not found: run probecal calibrate SESSION first, or give --calibration")
    calibration = load_calibration(calibration_file)
    out = _output_file(args.out if args.out is not None else Path(args.session) / "phantom_check.json", args.force)
    if args.as_built is not None:
        _output_file(args.as_built, args.force)
    _warn(check_fits(calibration.valid_for, calibration_file, session, args.force))
    check = check_session(session, calibration, _segment(session, args), CheckSettings(tolerance_mm=args.tolerance))
    phantom = session.phantom
    assert phantom is not None  # check_session refuses a session without one
    write_json(out, {"session": str(args.session), "calibration": str(calibration_file), **check.to_json()})
    lines = wire_check_lines(check, phantom)
    if args.as_built is not None:
        write_json(args.as_built, dict_from_phantom(check.as_built(phantom)))
        kept = " (the wires it cannot tell as defined)" if check.unsure() else ""
        lines.append(f"the phantom as built{kept}: {args.as_built}")
    lines.append(f"per-wire figures: {out}")
    print("\n".join(lines))
    return 0
