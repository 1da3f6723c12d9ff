"""Is ``corner_error_95_mm`` an honest and tight 95 % bound, and how close does the default
calibration come to the truth? (issue 31)

- twin ``bench`` seeds, 60 poses, the robot's way (own segmenter, phantom pose solved, default
  method): the calibrated image corners against the truth (the farthest corner, mm, tool frame),
  the bound and its parts, whether it covers the truth, how far the calibrations from the two
  halves of the sweep lie apart; then, end to end, the same seed's volume sweep of the test object
  reconstructed with that calibration (and with the true one): the surface's mean distance to
  the CAD model (mm);
- ``--freehand``: the same for tracked freehand twin recordings of the fCal 2.0 phantom (a hand's
  smooth path, the tracker's noise and slow drift, the phantom pose known; no volume), like for
  like with PLUS's recordings (``--phantom-registration``: the phantom pose they are given
  registered off the truth);
- ``--arm-unknown``: the robot's sweeps calibrated as a lab's own recordings would be, the arm not
  named in the manifest, so its kinematic errors are not fitted;
- PLUS's tracked N-wire recordings (no PLUS hints but the approximate spacing, phantom pose as
  PLUS registered it): the calibrations from the two halves of each recording, how far apart they
  lie and each half's bound.

With every twin run it also scores the bound map (the same bound at a grid of points over the
image, ``metrics.bound_map``): at each point, the seeds whose true error there lies within the
map's bound, and the least of those over the map (target >= 90 % everywhere), beside the map's
mean bound and the mean true error at each point.

Run: .venv/bin/python benchmarks/bench_calibration_bound.py [--seeds 10] [--first-seed 0] [--poses 60]
     [--no-volume] [--no-real] [--freehand] [--tracker-drift MM,DEG] [--phantom-registration MM,DEG]
     [--arm-unknown]
     [--wire-tolerance MM] [--diagonal-tolerance MM] [--diagonal-shift MM] [--diagonal-turn MM]
     [--diagonal-factor K] [--diagonal-turn-prior MM]
     [--layer-tolerance MM,DEG|X,Y,Z,RX,RY,RZ]
     [--wire-sigma MM] [--layer-sigma MM,DEG] [--write-docs]

``--write-docs`` writes the twin's summary (with the reconstructions when run) under the header of
the command line run.
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_calibration import tracked_recordings
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration, simulate_freehand, simulate_volume
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.objectives import WIRE_PRIOR
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import (
    corner_distance_mm,
    corner_distances_mm,
    image_corners_px,
)
from probecal.core.errors import InputError
from probecal.core.io.phantomfile import load_phantom, phantom_path
from probecal.core.io.plusdata import missing_reason
from probecal.core.twin.levels import BENCH_SETUP, LEVELS, SetupErrors
from probecal.core.volume.cad import session_cad_target
from probecal.core.volume.reconstruct import reconstruct_session

HAND_POSES = 120  # a tracked freehand twin recording's frames, about as many as PLUS's calibration recordings
TABLE = ("twin", "corners, mean of four (mm)", "worst seed", "farthest corner, mean / worst (mm)", "bound covers",
         "bound median / largest (mm)", "halves median / largest (mm)", "bound map covers, least point",
         "bound map, least / largest point (mm, median)")
VOLUME_TABLE = ("surface to CAD, mean (mm)", "with the true calibration (mm)")


def halves(session, results, prior: WirePrior = WIRE_PRIOR) -> tuple[float, list[float], list[str]]:
    """The default calibration (under the all-wire fit's ``prior``) of each half of a recording
    (in recording order): how far apart they put the image corners (mm), each one's bound and
    objective."""
    n = len(results)
    cals = [calibrate_session(session, part, prior=prior).calibration for part in (results[: n // 2], results[n // 2:])]
    return (corner_distance_mm(cals[0], cals[1], image_corners_px(session.image_size)),
            [c.metrics["corner_error_95_mm"] for c in cals], [c.metrics["objective"] for c in cals])


def _mm(value: float | None) -> str:
    return "-" if value is None else format(value, ".3f")


def drift_from(text: str) -> tuple[float, float]:
    """A tracker drift (``SetupErrors.tracker_drift``) from "MM,DEG"."""
    mm, deg = (float(v) for v in text.split(","))
    return mm, deg


def per_axis_from(text: str) -> tuple[float, ...]:
    """A set-up error per axis (``SetupErrors.layer_tolerance``, ``phantom_registration``) from
    ``MM,DEG`` (every axis) or six values (x, y, z mm, then deg about them)."""
    values = tuple(float(v) for v in text.split(","))
    if len(values) == 2:
        return (values[0],) * 3 + (values[1],) * 3
    if len(values) != 6:
        raise argparse.ArgumentTypeError(f"a per-axis error is MM,DEG or six values, got {text!r}")
    return values


def describe(prior: WirePrior) -> str:
    """The all-wire fit's prior in words."""
    layers = "none" if prior.layer_sigma is None else (f"{prior.layer_sigma[0]} mm, "
                                                       f"{np.degrees(prior.layer_sigma[1]):.2f} deg")
    return (f"wire prior {prior.end_sigma_mm} mm, diagonals' {prior.diagonal_factor or 1} times that, layer prior "
            f"{layers}, diagonals' turn prior {prior.diagonal_turn_mm or 'none'}")


def twin_seed(seed: int, poses: int, volume: bool, setup: SetupErrors, prior: WirePrior, freehand: bool = False,
              arm_known: bool = True) -> dict:
    """One bench seed: calibration against the truth, the bound, the halves and (``volume``) the
    reconstruction of the same seed's test-object sweep with it and with the truth; the bench's
    errors replaced by ``setup``, the all-wire fit's ``prior``. ``freehand``: a tracked freehand
    recording of the fCal 2.0 phantom (``simulate_freehand``, ``poses`` frames) instead of the
    robot's sweep. Without ``arm_known`` the robot's sweep is calibrated as a lab's own recording
    of an arm probecal does not know (no ``arm`` in the manifest): its kinematic errors are not
    fitted."""
    noise = replace(LEVELS["bench"], setup=setup)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = (simulate_freehand(tmp / "cal", n_poses=poses, seed=seed, noise=noise,
                                     phantom=load_phantom(phantom_path("fcal-2.0"))) if freehand else
                   simulate_calibration(tmp / "cal", n_poses=poses, seed=seed, noise=noise))
        if not arm_known:
            session = replace(session, manifest=replace(session.manifest, arm=None))
        truth = session.truth()
        true = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
        results = segment_session(session)
        try:
            calibration = calibrate_session(session, results, prior=prior).calibration
            apart = halves(session, results, prior)[0]
        except InputError as exc:  # a phantom built far off may leave too few frames with a pattern found
            return {"seed": seed, "failed": exc.problem}
        m = calibration.metrics
        corners = corner_distances_mm(calibration, true, image_corners_px(session.image_size))
        row = {"seed": seed, "objective": m["objective"], "bound": m["corner_error_95_mm"],
               "error": float(corners.max()), "mean_corner": float(corners.mean()),
               "parts": m["corner_error"], "halves": apart, **map_errors(calibration, true)}
        if volume:
            sweep = simulate_volume(tmp / "vol", seed=seed, noise="bench")
            for name, cal in (("surface", calibration), ("surface_true", load_calibration(sweep.path / "truth.json"))):
                cad = session_cad_target(sweep, phantom_to_base=cal.phantom_to_base)  # where it registered the phantom
                row[name] = reconstruct_session(sweep, cal, tmp / name, cad=cad).report["surface_mean_mm"]
        return row


def map_errors(calibration: Calibration, true: Calibration) -> dict[str, np.ndarray]:
    """The calibration's bound map (mm) with its points (px as the image shows them) and the
    true error at each (mm, tool frame): how far ``calibration`` puts the point from where
    ``true`` does."""
    bound_map = calibration.metrics["bound_map"]
    points = np.array(bound_map["points_px"], dtype=float)
    bounds = np.array(bound_map["bound_mm"], dtype=float)
    set_right = calibration.set_right(points.reshape(-1, 2))
    errors = corner_distances_mm(calibration, true, set_right).reshape(bounds.shape)
    return {"map_points": points, "map_bound": bounds, "map_error": errors}


def print_map(rows: list[dict]) -> int | None:
    """The bound map's coverage over the seeds, point by point (grid rows down the image, labelled
    with their mean depth, px), its mean bound and the mean true error there; the least coverage
    over the map (None when the seeds' grids differ in shape)."""
    shapes = {r["map_bound"].shape for r in rows}
    if len(shapes) != 1:
        print(f"  bound map: the seeds' grids differ in shape ({sorted(shapes)}), not compared point by point")
        return None
    bounds, errors = np.array([r["map_bound"] for r in rows]), np.array([r["map_error"] for r in rows])
    covered = (errors <= bounds).sum(axis=0)
    depth = np.array([r["map_points"][:, :, 1].mean(axis=1) for r in rows]).mean(axis=0)
    print(f"  bound map ({covered.shape[0]} rows x {covered.shape[1]} columns, left to right; rows down the "
          f"image at their mean v px): seeds covered of {len(rows)} | mean bound mm | mean true error mm")
    for k, v in enumerate(depth):
        print(f"  v {v:6.1f}  " + " ".join(f"{c:2d}" for c in covered[k]) + "  | "
              + " ".join(f"{b:.2f}" for b in bounds[:, k].mean(axis=0)) + "  | "
              + " ".join(f"{e:.2f}" for e in errors[:, k].mean(axis=0)))
    least = int(covered.min())
    print(f"  bound map: covers the truth at every point in at least {least} of {len(rows)} seeds "
          f"({100.0 * least / len(rows):.0f} %, target >= 90 %); at the corners the map is "
          f"{np.mean([r['map_bound'][[0, 0, -1, -1], [0, -1, 0, -1]].max() / r['bound'] for r in rows]):.2f} "
          "of the corner bound on average")
    return least


def twin(seeds: int, first_seed: int, poses: int, volume: bool, setup: SetupErrors = BENCH_SETUP,
         prior: WirePrior = WIRE_PRIOR, freehand: bool = False, arm_known: bool = True) -> dict[str, float] | None:
    """The seeds' figures printed; their summary (:func:`summary`), None when no seed calibrated."""
    print(f"twin bench (wire ends built off by +-{setup.phantom_tolerance_mm} mm, diagonals' ends across them by "
          f"+-{setup.diagonal_tolerance_mm} mm, as a whole by +-{setup.diagonal_shift_mm} mm and turned by "
          f"+-{setup.diagonal_turn_mm} mm, "
          f"layers by +-{setup.layer_tolerance[:3]} mm and "
          f"+-{setup.layer_tolerance[3:]} deg, {describe(prior)}), {seeds} seeds "
          f"x {poses} poses, " + ("tracked freehand recordings of the fCal 2.0 phantom (tracker drift "
                                   f"{setup.tracker_drift[0]} mm, {setup.tracker_drift[1]} deg, phantom registered "
                                   f"off by sd {setup.phantom_registration})" if freehand
                                   else "the robot's sweep" + ("" if arm_known else " (the arm not known)"))
          + ", own segmenter: image corners against the truth "
          "(farthest corner, mm), the 95 % bound (the larger of the bootstrap and twice the block jackknife, + in "
          "quadrature what the other objectives on the located "
          "wires, the echo peaks and the loose wire prior add), the two "
          "halves of the sweep" + (", the same seed's test object reconstructed (surface to CAD, mean mm)"
                                   if volume else ""))
    print("  seed  objective   true mm (mean of 4)  bound mm  (bootstrap / jackknife, the other objectives apart / "
          "beyond their scatter (largest), "
          "echo, wires)  halves mm" + ("  surface mm (true calibration)" if volume else ""))
    with ProcessPoolExecutor(max_workers=2) as pool:
        rows = list(pool.map(twin_seed, range(first_seed, first_seed + seeds), [poses] * seeds, [volume] * seeds,
                             [setup] * seeds, [prior] * seeds, [freehand] * seeds, [arm_known] * seeds))
    for r in rows:
        if "failed" in r:
            print(f"  {r['seed']:4d}  not calibrated: {r['failed']}")
    rows = [r for r in rows if "failed" not in r]
    if not rows:
        return None
    for r in rows:
        parts = r["parts"]
        apart = max((v for v in parts["objective_disagreement_mm"].values() if v is not None), default=0.0)
        beyond = max((v for v in parts.get("objective_excess_mm", {}).values() if v is not None), default=0.0)
        echo, wires = parts["echo_peak_disagreement_mm"], parts.get("wire_prior_disagreement_mm")
        line = (f"  {r['seed']:4d}  {r['objective']:<10}  {r['error']:7.3f} ({r['mean_corner']:.3f})  "
                f"{r['bound']:8.3f}  ({parts['bootstrap_95_mm']:.3f} / {_mm(parts.get('jackknife_95_mm'))}, "
                f"{apart:.3f} / {beyond:.3f}, {echo:.3f}, "
                f"{_mm(wires)})  "
                f"{r['halves']:9.3f}")
        if volume:
            line += f"  {r['surface']:.3f} ({r['surface_true']:.3f})"
        print(line + ("" if r["error"] <= r["bound"] else "  NOT COVERED"))
    figures = summary(rows, volume)
    print_summary(figures)
    least = print_map(rows)
    if least is not None:
        figures["map_covered_least"] = least
    return figures


def summary(rows: list[dict], volume: bool) -> dict[str, float]:
    """The calibrated seeds' corners against the truth, the bound's coverage and size, the halves
    apart and (``volume``) the surface to CAD with the calibration and the true one."""
    means, errors, bounds, apart = (np.array([r[key] for r in rows]) for key in ("mean_corner", "error", "bound",
                                                                                   "halves"))
    figures = {"calibrated": len(rows), "corners": means.mean(), "worst": means.max(), "farthest": errors.mean(),
               "farthest_worst": errors.max(), "covered": int((errors <= bounds).sum()),
               "bound_median": np.median(bounds), "bound_largest": bounds.max(), "halves_median": np.median(apart),
               "halves_largest": apart.max(), "map_least": np.median([np.nanmin(r["map_bound"]) for r in rows]),
               "map_largest": np.median([np.nanmax(r["map_bound"]) for r in rows])}
    if volume:
        figures |= {name: np.mean([r[name] for r in rows]) for name in ("surface", "surface_true")}
    return figures


def print_summary(f: dict[str, float]) -> None:
    """The seeds' summary (:func:`summary`) against the targets."""
    print(f"  image corners (mean of the four): {f['corners']:.3f} mm over the seeds (target <= 0.3), worst seed "
          f"{f['worst']:.3f} (target <= 0.5); farthest corner: mean {f['farthest']:.3f}, worst "
          f"{f['farthest_worst']:.3f}; bound: covers the truth in {f['covered']} of {f['calibrated']} seeds (target "
          f">= 90 %), median {f['bound_median']:.3f} mm, largest {f['bound_largest']:.3f}; halves apart: median "
          f"{f['halves_median']:.3f}, largest {f['halves_largest']:.3f} mm")
    if "surface" in f:
        print(f"  end to end: surface to CAD mean {f['surface']:.3f} mm with the calibration "
              f"(target <= 0.40), {f['surface_true']:.3f} with the true one")


def table_row(f: dict[str, float], label: str) -> list[str]:
    """The summary as a row of :data:`TABLE` (and :data:`VOLUME_TABLE` when it has the surface)."""
    row = [label, f"{f['corners']:.2f}", f"{f['worst']:.2f}", f"{f['farthest']:.2f} / {f['farthest_worst']:.2f}",
           f"{f['covered']} of {f['calibrated']}", f"{f['bound_median']:.2f} / {f['bound_largest']:.2f}",
           f"{f['halves_median']:.2f} / {f['halves_largest']:.2f}",
           "-" if "map_covered_least" not in f else f"{f['map_covered_least']} of {f['calibrated']}",
           f"{f['map_least']:.2f} / {f['map_largest']:.2f}"]
    return row + ([f"{f['surface']:.3f}", f"{f['surface_true']:.3f}"] if "surface" in f else [])


def twin_label(seeds: int, calibrated: int, poses: int, freehand: bool, arm_known: bool) -> str:
    """The table's name for the twin run: its recordings, seeds (those calibrated) and poses."""
    kind = "freehand" if freehand else "the robot's sweep" + ("" if arm_known else ", the arm not known")
    count = f"{seeds}" if calibrated == seeds else f"{calibrated} calibrated of {seeds}"
    return f"`bench`, {kind}, {count} seeds × {poses} poses"


def real(tmp: Path) -> None:
    print("PLUS's tracked recordings, the robot's way: the two halves of each recording calibrated alone")
    sessions = tracked_recordings(tmp)
    for name, session in sessions.items():
        results = segment_session(session, segmenter=session_segmenter(session, use_hints=False))
        apart, bounds, chosen = halves(session, results)
        within = "within both bounds" if apart <= min(bounds) else (
            "within one bound" if apart <= max(bounds) else "outside both bounds")
        print(f"  {name}: halves {apart:.2f} mm apart; bounds +-{bounds[0]:.2f} / +-{bounds[1]:.2f} mm "
              f"({chosen[0]} / {chosen[1]}): {within}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--poses", type=int)
    parser.add_argument("--no-volume", action="store_true", help="skip the end-to-end reconstructions")
    parser.add_argument("--no-real", action="store_true", help="skip PLUS's recordings")
    parser.add_argument("--wire-tolerance", type=float, default=BENCH_SETUP.phantom_tolerance_mm, metavar="MM",
                        help="how far the twin's wire end points are built off (default: the bench's)")
    parser.add_argument("--wire-sigma", type=float, default=WIRE_PRIOR.end_sigma_mm, metavar="MM",
                        help="the all-wire fit's wire prior (default: the calibration's)")
    parser.add_argument("--diagonal-tolerance", type=float, default=BENCH_SETUP.diagonal_tolerance_mm, metavar="MM",
                        help="how far the twin's diagonal wires' ends are built off across them (default: the "
                             "bench's)")
    parser.add_argument("--diagonal-shift", type=float, default=BENCH_SETUP.diagonal_shift_mm, metavar="MM",
                        help="how far the twin's diagonal wires are built off across themselves as a whole "
                             "(default: the bench's)")
    parser.add_argument("--diagonal-turn", type=float, default=BENCH_SETUP.diagonal_turn_mm, metavar="MM",
                        help="how far the twin's diagonal wires' ends are turned about their middles, the opposite "
                             "ways (default: the bench's)")
    parser.add_argument("--layer-tolerance", metavar="MM,DEG", type=per_axis_from,
                        default=BENCH_SETUP.layer_tolerance,
                        help="how far the twin's layers are built off as a whole, every axis or six values "
                             "(x, y, z mm, then deg about them; default: the bench's)")
    parser.add_argument("--diagonal-factor", type=float, default=WIRE_PRIOR.diagonal_factor, metavar="K",
                        help="the all-wire fit's prior on the diagonal wires' ends this many times the others' "
                             "(default: the calibration's)")
    parser.add_argument("--diagonal-turn-prior", type=float, default=WIRE_PRIOR.diagonal_turn_mm, metavar="MM",
                        help="the all-wire fit's prior on the diagonal wires' turns about their middles (default: "
                             "the calibration's)")
    parser.add_argument("--freehand", action="store_true",
                        help="tracked freehand twin recordings of the fCal 2.0 phantom instead of the robot's sweeps "
                             "(no volume; --poses defaults to 120)")
    parser.add_argument("--tracker-drift", metavar="MM,DEG", type=drift_from,
                        default=BENCH_SETUP.tracker_drift,
                        help="the freehand twin's slow tracker error, RMS per axis (default: the bench's)")
    parser.add_argument("--phantom-registration", metavar="MM,DEG", type=per_axis_from,
                        default=BENCH_SETUP.phantom_registration,
                        help="the freehand twin's error in the registered phantom pose, sd per axis, every axis or "
                             "six values (x, y, z mm, then deg about them; default: the bench's)")
    parser.add_argument("--arm-unknown", action="store_true",
                        help="calibrate the robot's sweeps as a lab's own recordings of an arm probecal does not "
                             "know: its kinematic errors are not fitted")
    parser.add_argument("--layer-sigma", metavar="MM,DEG",
                        help="a layer prior for the all-wire fit: each layer may move as a whole (default: the "
                             "calibration's)")
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    layer_sigma = WIRE_PRIOR.layer_sigma
    if args.layer_sigma:
        mm, deg = (float(v) for v in args.layer_sigma.split(","))
        layer_sigma = (mm, float(np.radians(deg)))
    setup = replace(BENCH_SETUP, phantom_tolerance_mm=args.wire_tolerance,
                    diagonal_tolerance_mm=args.diagonal_tolerance, diagonal_shift_mm=args.diagonal_shift,
                    diagonal_turn_mm=args.diagonal_turn,
                    layer_tolerance=args.layer_tolerance,
                    tracker_drift=args.tracker_drift, phantom_registration=args.phantom_registration)
    poses = args.poses or (HAND_POSES if args.freehand else 60)
    figures = twin(args.seeds, args.first_seed, poses, not (args.no_volume or args.freehand), setup,
                   WirePrior(args.wire_sigma, args.diagonal_factor, layer_sigma, args.diagonal_turn_prior),
                   args.freehand, not args.arm_unknown)
    if args.write_docs and figures is not None:
        header = TABLE + (VOLUME_TABLE if "surface" in figures else ())
        label = twin_label(args.seeds, figures["calibrated"], poses, args.freehand, not args.arm_unknown)
        row = table_row(figures, label)
        print(f"written: {write_table(command_line(), markdown_table(header, [row]))}", flush=True)
    if args.no_real:
        return
    reason = missing_reason()
    if reason is not None:
        print(f"real recordings skipped: {reason}")
        return
    with tempfile.TemporaryDirectory() as tmp:
        real(Path(tmp))


if __name__ == "__main__":
    main()
