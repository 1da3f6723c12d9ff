"""``probecal phantom list|export|check``: the built-in phantoms, everything to build one, and the
check of a built one against its definition. Thin: calls ``core.build`` and
``core.calibration.wirecheck`` and prints what they did."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from probecal.app.commands import _into_folder, _output_file, _replacing, _segment, _warn
from probecal.core.errors import InputError


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
    export = _into_folder(args.out_dir, replacing, lambda folder: export_phantom(phantom, folder, design, path))
    frame, mesh = export.frame, export.mesh
    shared = sum(len(h.wires) > 1 for h in frame.holes)
    print(f"{args.out_dir}: {phantom.name} frame {_size(frame.extent_mm)} mm (x, y, z), "
          f"{'watertight' if mesh.is_watertight else 'NOT watertight'}, {mesh.volume / 1000:.1f} cm3; "
          f"{len(frame.holes)} holes ({shared} shared by two wires), {len(frame.landmarks())} landmark divots")
    print(f"  {', '.join(export.files)}; start with BUILD.md")
    return 0


def _direction(offset: np.ndarray) -> str:
    """The axis an offset mostly points along, e.g. +x."""
    k = int(np.argmax(np.abs(offset)))
    return f"{'+' if offset[k] > 0 else '-'}{'xyz'[k]}"


def _optional(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def phantom_check(args: argparse.Namespace) -> int:
    from probecal.core.calibration.result import load_calibration
    from probecal.core.calibration.validity import check_fits
    from probecal.core.calibration.wirecheck import BLOCKS, MIN_SPAN, check_session
    from probecal.core.io.jsonio import write_json
    from probecal.core.io.phantomfile import dict_from_phantom
    from probecal.core.io.session import load_session

    session = load_session(args.session)
    calibration_file = args.calibration or Path(args.session) / "calibration.json"
    if args.calibration is None and not calibration_file.is_file():
        raise InputError(calibration_file, "not found: run probecal calibrate SESSION first, or give --calibration")
    calibration = load_calibration(calibration_file)
    out = _output_file(args.out if args.out is not None else Path(args.session) / "phantom_check.json", args.force)
    if args.as_built is not None:
        _output_file(args.as_built, args.force)
    _warn(check_fits(calibration.valid_for, calibration_file, session, args.force))
    check = check_session(session, calibration, _segment(session, args), args.tolerance)
    phantom = session.phantom
    assert phantom is not None  # check_session refuses a session without one
    write_json(out, {"session": str(args.session), "calibration": str(calibration_file), **check.to_json()})
    lines = [f"{phantom.name}: {len(check.wires)} wires located from {check.frames_used} frames; how far each sits off "
             "its definition in the middle of the stretch seen, as a move of its holes in the walls' plane, with its "
             f"standard error from {BLOCKS} runs of consecutive frames (mm, phantom frame):",
             f"  {'wire':16s} {'dots':>5s} {'seen (mm)':>11s} {'offset':>7s} {'±':>6s} {'toward':>6s} "
             f"{'verdict':>7s} {'front':>6s} {'back':>6s} {'sag':>6s} {'spread':>6s}"]
    for wire, definition in zip(check.wires, phantom.wires):
        length = np.linalg.norm(definition.back - definition.front)
        seen = "-" if not np.isfinite(wire.seen[0]) else f"{wire.seen[0] * length:.0f}-{wire.seen[1] * length:.0f}"
        front = None if wire.front_mm is None else float(np.linalg.norm(wire.front_mm))
        back = None if wire.back_mm is None else float(np.linalg.norm(wire.back_mm))
        toward = _direction(wire.shift) if np.isfinite(wire.offset_mm) else "-"
        lines.append(f"  {wire.name:16s} {wire.dots:5d} {seen:>11s} {_optional(wire.offset_mm):>7s} "
                     f"{_optional(wire.uncertainty_mm):>6s} {toward:>6s} {check.verdict(wire):>7s} "
                     f"{_optional(front):>6s} {_optional(back):>6s} {_optional(wire.sag_mm):>6s} "
                     f"{_optional(wire.scatter_mm):>6s}")
    off = check.off()
    if off:
        worst = ", ".join(f"{w.name} {w.offset_mm:.2f} mm toward {_direction(w.shift)}" for w in off)
        wires = f"{len(off)} wire{'s' if len(off) > 1 else ''}"
        lines.append(f"{wires} off by more than {check.tolerance_mm:g} mm, beyond doubt: {worst}")
    unsure = check.unsure()
    if unsure:
        lines.append(f"the scan cannot tell whether {', '.join(w.name for w in unsure)} "
                     f"{'lies' if len(unsure) == 1 else 'lie'} within {check.tolerance_mm:g} mm: the offsets of "
                     "runs of frames disagree (±, one standard error) or too few dots; a longer scan with more "
                     "poses tells more")
    if not off and not unsure:
        lines.append(f"every wire lies within {check.tolerance_mm:g} mm of its definition")
    if all(w.sag_mm is None for w in check.wires):
        lines.append(f"ends and sag not told: the dots cover less than {MIN_SPAN:.0%} of each wire, or the scan "
                     "cannot tell the wire; a sweep that travels farther along the wires tells them")
    if args.as_built is not None:
        write_json(args.as_built, dict_from_phantom(check.as_built(phantom)))
        kept = " (the wires it cannot tell as defined)" if check.unsure() else ""
        lines.append(f"the phantom as built{kept}: {args.as_built}")
    lines.append(f"per-wire figures: {out}")
    print("\n".join(lines))
    return 0
