"""How well ``probecal phantom check`` finds a wire built off its definition (issue 19).

- twin, one wire off: ``bench`` seeds (60 poses, phantom pose solved: the robot's path) with a
  phantom built exactly but for one wire (a different one per seed) whose holes are 0.5 mm off
  along x, as ``probecal simulate calibration --as-built`` images it: which wires the check names
  (tolerance 0.2 mm), the moved wire's offset against the 0.5 mm (error, mm) and the largest
  offset it gives a wire that did not move;
- twin, every wire off: the same with the bench's manufacturing tolerance on every wire end
  (±0.3 mm per axis) and the 0.5 mm wire on top: each wire's offset against the truth, once the
  two are brought onto one phantom pose by least squares (mean and worst, mm): when every wire
  is a little off, no pose of the phantom is more right than another;
- twin, the verdicts: bench seeds as the level builds them (every wire end off), checked with
  the standard errors from each candidate number of runs of consecutive frames (and the dots a
  wire needs in each): how many verdicts the truth contradicts, how many wires are left unsure,
  and how the errors compare with the standard errors (the runs are chosen here, with the real
  tables below and ``bench_console_check.py`` at the console's sweep);
- real recordings (no truth): PLUS's fCal 1.2 calibration and validation recordings and PLUS 1's
  NwirePhantomFreehand, calibrated the robot's way (no hints but the nominal spacing), checked on
  all frames, then on the first and the second half of the frames apart: how far the halves
  disagree per wire (worst, mm) says how far a reported offset can be trusted on real images,
  for every candidate; then perturbed copies of their frames (gain, gamma, speckle, blur, motion, crop, a dot erased),
  each segmented, calibrated and checked: how many wires each names off.

Run: .venv/bin/python benchmarks/bench_phantom_check.py [--seeds 6] [--verdict-seeds 8] [--workers 2]
[--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_calibration import FCAL_CONFIG, NWIRE_CONFIG, PLUS
from bench_real_segmentation import PERTURBATIONS
from bench_wire_sigma import perturbed_results
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.wirecheck import (
    CheckSettings,
    WireCheck,
    check_session,
    offsets_in_wall_plane,
    without_rigid_motion,
)
from probecal.core.errors import InputError
from probecal.core.io.phantomfile import default_phantom
from probecal.core.io.plusimport import import_plus
from probecal.core.twin.levels import BENCH_SETUP, LEVELS
from probecal.core.twin.scanner import twin_scanner

MOVE_MM = 0.5


def on_one_pose(phantom, shifts: np.ndarray, reference: np.ndarray, spans: np.ndarray) -> tuple[np.ndarray, ...]:
    """Wire end shifts (W, 2, 3) brought onto the phantom pose of ``reference`` (least squares),
    then both as (W, 3) offsets in the walls' plane in the middle of each wire's seen stretch."""
    aligned = reference + without_rigid_motion(phantom.lines(), shifts - reference, spans, robust=False)
    return offsets_in_wall_plane(phantom, aligned, spans), offsets_in_wall_plane(phantom, reference, spans)


def true_shifts(phantom, built, spans: np.ndarray) -> np.ndarray:
    """The built phantom's wire end shifts less their rigid motion, as the check removes it."""
    lines = phantom.lines()
    return without_rigid_motion(lines, built.lines() - lines, spans)


def twin_row(seed: int, tolerance_mm: float) -> dict:
    """One bench seed: wire ``seed % 12`` moved ``MOVE_MM`` along x, on top of the manufacturing
    tolerance ``tolerance_mm`` (0: every other wire exact)."""
    phantom = default_phantom()
    level = replace(LEVELS["bench"], setup=replace(BENCH_SETUP, phantom_tolerance_mm=tolerance_mm))
    base = twin_scanner(seed, level).twin.built_phantom or phantom
    moved = seed % phantom.n_wires
    shifts = np.zeros((phantom.n_wires, 2, 3))
    shifts[moved, :, 0] = MOVE_MM
    built = base.moved(shifts)
    with tempfile.TemporaryDirectory() as tmp:
        session = simulate_calibration(Path(tmp) / "s", seed=seed, noise=level, built_phantom=built)
        results = segment_session(session)
        calibration = calibrate_session(session, results, solve_phantom_pose=True,
                                         with_validation=False).calibration
        check = check_session(session, calibration, results)
    spans = np.array([w.seen for w in check.wires])
    found, true = on_one_pose(phantom, check.shifts_mm, true_shifts(phantom, built, spans), spans)
    others = [w.offset_mm for k, w in enumerate(check.wires) if k != moved]
    return {"seed": seed, "moved": phantom.wires[moved].name, "named": [w.name for w in check.off()],
            "offset": check.wires[moved].offset_mm, "others_max": max(others),
            "errors": np.linalg.norm(found - true, axis=1).tolist()}


def twin_tables(seeds: int, workers: int) -> None:
    with ProcessPoolExecutor(workers) as pool:
        one = list(pool.map(twin_row, range(seeds), [0.0] * seeds))
        every = list(pool.map(twin_row, range(seeds), [BENCH_SETUP.phantom_tolerance_mm] * seeds))
    print(f"twin (bench, 60 poses, phantom pose solved): one wire's holes {MOVE_MM} mm off along x, every other wire "
          "exact")
    print(f"{'seed':>4s} {'moved wire':>14s} {'offset found':>13s} {'error':>7s} {'others, worst':>14s}  "
          "named off")
    for row in one:
        print(f"{row['seed']:4d} {row['moved']:>14s} {row['offset']:13.3f} {abs(row['offset'] - MOVE_MM):7.3f} "
              f"{row['others_max']:14.3f}  {', '.join(row['named']) or 'none'}")
    right = sum(r["named"] == [r["moved"]] for r in one)
    print(f"the moved wire alone named in {right} of {len(one)} seeds; its offset within "
          f"{max(abs(r['offset'] - MOVE_MM) for r in one):.3f} mm of {MOVE_MM} mm")
    print()
    errors = np.array([r["errors"] for r in every])
    print(f"twin (bench): every wire end off by up to ±{BENCH_SETUP.phantom_tolerance_mm} mm per axis, plus one wire "
          f"{MOVE_MM} mm: each wire's offset against the truth (mm, in the walls' plane, one phantom pose)")
    for row, e in zip(every, errors):
        print(f"  seed {row['seed']}: mean {e.mean():.3f}, worst {e.max():.3f}")
    print(f"  all seeds: mean {errors.mean():.3f}, worst {errors.max():.3f} mm over {errors.size} wires")


CANDIDATES = (CheckSettings(runs=4, min_dots=8), CheckSettings(runs=5, min_dots=7), CheckSettings(runs=6, min_dots=6),
              CheckSettings(runs=8, min_dots=5))
"""Runs of consecutive frames, and the dots a wire needs in each: more runs make a wire's margin
(Student's t for runs less one) smaller, but need more frames to see every wire."""


VERDICT_TABLE = ("runs x dots", "verdicts the truth contradicts", "unsure", "off", r"\|error\| / se, median")


def _candidate(settings: CheckSettings) -> str:
    return f"{settings.runs}x{settings.min_dots}"


def _shipped(name: str) -> str:
    """The candidate's name, bold when probecal uses it."""
    return f"**{name}**" if name == _candidate(CheckSettings()) else name


def verdict_row(seed: int) -> dict:
    """One bench seed as the level builds it (every wire end off by up to ±0.3 mm per axis): for
    each number of runs, how many verdicts the truth contradicts (off with a true offset within
    the tolerance, within with one beyond), how many wires are unsure or off, and the errors over
    their standard errors."""
    phantom = default_phantom()
    level = LEVELS["bench"]
    built = twin_scanner(seed, level).twin.built_phantom or phantom
    row: dict = {"seed": seed}
    with tempfile.TemporaryDirectory() as tmp:
        session = simulate_calibration(Path(tmp) / "s", seed=seed, noise=level)
        results = segment_session(session)
        calibration = calibrate_session(session, results, solve_phantom_pose=True,
                                         with_validation=False).calibration
        for settings in CANDIDATES:
            check = check_session(session, calibration, results, settings)
            spans = np.array([w.seen for w in check.wires])
            found, true = on_one_pose(phantom, check.shifts_mm, true_shifts(phantom, built, spans), spans)
            true_mm, found_mm = np.linalg.norm(true, axis=1), np.linalg.norm(found, axis=1)
            verdicts = [check.verdict(w) for w in check.wires]
            wrong = sum((v == "off" and t <= check.tolerance_mm) or (v == "within" and t > check.tolerance_mm)
                        for v, t in zip(verdicts, true_mm))
            z = np.abs(found_mm - true_mm) / np.array([w.uncertainty_mm for w in check.wires])
            row[_candidate(settings)] = {"wrong": int(wrong), "unsure": verdicts.count("unsure"),
                                         "off": verdicts.count("off"), "z": z}
    return row


def verdict_table(seeds: int, workers: int) -> list[list[str]]:
    """Print the verdicts against the truth per candidate; the rows of :data:`VERDICT_TABLE`."""
    with ProcessPoolExecutor(workers) as pool:
        rows = list(pool.map(verdict_row, range(seeds)))
    wires = default_phantom().n_wires * seeds
    print(f"twin (bench as the level builds it, every wire end off by up to ±{BENCH_SETUP.phantom_tolerance_mm} mm per "
          f"axis): the verdicts against the truth over {seeds} seeds, {wires} wires, by the runs that give the "
          "standard errors")
    print(f"{'runs x dots':>11s} {'wrong':>6s} {'unsure':>7s} {'off':>4s} {'|error| / se, median':>21s} {'worst':>6s}")
    table = []
    for name in map(_candidate, CANDIDATES):
        z = np.concatenate([r[name]["z"] for r in rows])
        counts = [sum(r[name][key] for r in rows) for key in ("wrong", "unsure", "off")]
        print(f"{name:>11s} {counts[0]:6d} {counts[1]:7d} {counts[2]:4d} {np.nanmedian(z):21.2f} {np.nanmax(z):6.1f}")
        table.append([_shipped(name), *map(str, counts), f"{np.nanmedian(z):.2f}"])
    print(f"(probecal uses {_candidate(CheckSettings())})")
    return table


def halves(session, results, calibration, settings: CheckSettings) -> tuple[np.ndarray, WireCheck]:
    """The check on all frames, and how far the two halves of the frames disagree per wire (mm)."""
    whole = check_session(session, calibration, results, settings)
    middle = len(results) // 2
    parts = [check_session(session, calibration, part, settings) for part in (results[:middle], results[middle:])]
    spans = np.array([w.seen for w in whole.wires])
    second, first = on_one_pose(session.phantom, parts[1].shifts_mm, parts[0].shifts_mm, spans)
    return np.linalg.norm(second - first, axis=1), whole


def real_sessions(folder: Path) -> dict:
    """PLUS's tracked N-wire recordings, imported into ``folder``: both fCal 1.2 recordings and
    PLUS 1's NwirePhantomFreehand (at the scanner's nominal spacing: its device set has no hints).
    The stepper and probe-rotation recordings are segmentation tests, not calibration sweeps."""
    images = PLUS / "TestImages"
    return {
        "fCal 1.2 calibration": import_plus(images / "fCal_Test_Calibration_3NWires.igs.mha", FCAL_CONFIG,
                                            folder / "cal"),
        "fCal 1.2 validation": import_plus(images / "fCal_Test_Validation_3NWires.igs.mha", FCAL_CONFIG,
                                           folder / "val"),
        "NwirePhantomFreehand": import_plus(images / "NwirePhantomFreehand.igs.mha", NWIRE_CONFIG, folder / "nwire",
                                            spacing_mm=(0.077, 0.077)),
    }


def real_table() -> None:
    print("real recordings, calibrated and checked the robot's way (no hints but the nominal spacing)")
    with tempfile.TemporaryDirectory() as tmp:
        sessions = real_sessions(Path(tmp))
        for name, session in sessions.items():
            results = segment_session(session, segmenter=session_segmenter(session, use_hints=False))
            calibration = calibrate_session(session, results, with_validation=False).calibration
            print(f"{name}: {sum(r.found for r in results)} frames with the pattern")
            for settings in CANDIDATES:
                gaps, whole = halves(session, results, calibration, settings)
                print(f"  {_candidate(settings)} {'wire':10s} {'offset':>7s} {'± (1 se)':>9s} {'verdict':>8s} "
                      f"{'halves apart':>13s} {'spread':>7s}")
                for wire, gap in zip(whole.wires, gaps):
                    print(f"      {wire.name:10s} {wire.offset_mm:7.3f} {wire.uncertainty_mm:9.3f} "
                          f"{whole.verdict(wire):>8s} {gap:13.3f} {wire.scatter_mm:7.3f}")
                print(f"  halves apart: mean {gaps.mean():.3f}, worst {gaps.max():.3f} mm; "
                      f"{len(whole.off())} off, {len(whole.unsure())} unsure")


def perturbed_table() -> None:
    """Wires named off on perturbed copies of the real recordings' frames, each copy segmented,
    calibrated and checked the robot's way: none can be backed by those recordings."""
    print("real recordings, perturbed copies: wires named off and unsure (off:unsure; none named off is right: the "
          "recordings cannot back one), for the runs x dots " + " / ".join(map(_candidate, CANDIDATES)))
    with tempfile.TemporaryDirectory() as tmp:
        sessions = real_sessions(Path(tmp))
        print(f"  {'perturbation':16s} " + " ".join(f"{name:>28s}" for name in sessions))
        for perturbation in PERTURBATIONS:
            cells = []
            for session in sessions.values():
                results = perturbed_results(session, perturbation)
                try:
                    calibration = calibrate_session(session, results, with_validation=False).calibration
                except InputError:  # too few patterns found to calibrate
                    cells.append(f"{sum(r.found for r in results)} patterns: no calibration")
                    continue
                checks = [check_session(session, calibration, results, settings) for settings in CANDIDATES]
                cells.append(" / ".join(f"{len(check.off())}:{len(check.unsure())}" for check in checks))
            print(f"  {perturbation:16s} " + " ".join(f"{cell:>28s}" for cell in cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--verdict-seeds", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    twin_tables(args.seeds, args.workers)
    print()
    table = verdict_table(args.verdict_seeds, args.workers)
    print()
    real_table()
    print()
    perturbed_table()
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(VERDICT_TABLE, table))}")


if __name__ == "__main__":
    main()
