"""Convex probe on the twin (issue 33): the fan's pattern found, the fan's corners from the truth
after calibration, and a volume sweep of the test object against its CAD with the true and the
estimated calibration; a linear probe's figures are ``bench_calibration.py``'s and
``bench_volume.py``'s.

The truth of a fan corner is where the medium puts it: the scanner shows each echo's depth below
the curved face shrunk by the sound speeds, which no affine ImageToProbe can follow exactly, so
a fan calibration also holds the stretch of the beams' depths (``core.calibration.result.Calibration``),
and the line on the affine ImageToProbe written for PLUS gives what that matrix alone comes to, and
how close any affine map can come.

Run: .venv/bin/python benchmarks/bench_convex.py [--seeds 10] [--poses 60] [--noise bench] [--volume-seeds 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.metrics import segmentation_error_mm
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.geometry.probe import BUILTIN_PROBES, DEFAULT_PROBE, ConvexProbe
from probecal.core.geometry.transforms import transform_points
from probecal.core.volume.cad import CadTarget, session_cad_target
from probecal.core.volume.reconstruct import reconstruct_session


def in_tool(calibration: Calibration, pixels: np.ndarray, shown: bool = False) -> np.ndarray:
    """Where a calibration puts pixels (tool frame, mm): exactly, or (``shown``) by its affine map
    of the pixels as shown."""
    if shown:
        return transform_points(calibration.shown_image_to_tool, np.column_stack([pixels, np.zeros(len(pixels))]))
    right = calibration.set_right(pixels)
    return transform_points(calibration.image_to_tool, np.column_stack([right, np.zeros(len(right))]))


def calibration(seeds: int, poses: int, noise: str, probe: ConvexProbe, tmp: Path) -> dict[int, object]:
    corners = probe.fan.corners_px()
    rows, scores, estimates = [], [], {}
    for seed in range(seeds):
        start = time.perf_counter()
        session = simulate_calibration(tmp / f"c{noise}{seed}", n_poses=poses, seed=seed, noise=noise, probe=probe)
        truth = session.truth()
        results = segment_session(session)
        scores.append(segmentation_error_mm(results, truth["frames"], truth["pixel_spacing_mm"]))
        cal = calibrate_session(session, results, with_validation=False).calibration
        estimates[seed] = cal
        true = load_calibration(session.path / "truth.json")
        error = np.linalg.norm(in_tool(cal, corners) - in_tool(true, corners), axis=1)
        shown = np.linalg.norm(in_tool(cal, corners, shown=True) - in_tool(true, corners), axis=1)
        affine = np.linalg.norm(in_tool(true, corners, shown=True) - in_tool(true, corners), axis=1)
        rows.append((error.mean(), error.max(), affine.mean(), time.perf_counter() - start, shown.mean(),
                     cal.stretch / true.stretch - 1.0))
        print(f"  seed {seed}: fan corners {error.mean():.3f} mm mean ({error.max():.3f} at most); found "
              f"{sum(r.found for r in results)} of {len(results)} frames", flush=True)
    if not rows:  # --seeds 0: the volumes alone
        return estimates
    a = np.array(rows)
    total = {k: sum(getattr(s, k) for s in scores) for k in ("frames", "complete", "correct", "mislabelled")}
    errors = np.concatenate([s.errors_mm for s in scores])
    print(f"convex {probe.radius_mm:g} mm / {probe.fov_deg:g} deg, {probe.depth_mm:g} mm deep, {noise}, "
          f"{seeds} seeds x {poses} poses: pattern found in {total['correct']} of {total['complete']} frames with "
          f"every wire in the fan ({100 * total['correct'] / max(total['complete'], 1):.1f} %, target >= 95 %), "
          f"{total['mislabelled']} mislabelled; centroids {np.median(errors):.3f} mm median "
          f"(p95 {np.percentile(errors, 95):.3f}) from the wires")
    print(f"  fan corners from the truth: {a[:, 0].mean():.3f} mm mean (worst seed {a[:, 0].max():.3f}, largest "
          f"corner {a[:, 1].max():.3f}) [target <= 0.5]; the stretch {1000 * np.abs(a[:, 5]).mean():.1f} per mille "
          f"off the truth (mean; worst {1000 * np.abs(a[:, 5]).max():.1f}); {a[:, 3].mean():.1f} s per seed "
          f"(simulate, segment, calibrate)")
    print(f"  the same by the affine ImageToProbe written for PLUS: {a[:, 4].mean():.3f} mm mean; the closest "
          f"affine map to the truth comes {a[:, 2].mean():.3f} mm from it (its limit)")
    return estimates


def volume(seeds: int, noise: str, poses: int, probe: ConvexProbe, estimates: dict, tmp: Path) -> None:
    """Volume sweeps of seeds 0.. at level ``noise``, reconstructed with the true calibration and
    with the one the same seed's calibration sweep at that level gives (``estimates``' where they
    came from that level); and for comparison the default linear probe's sweep of the same seeds
    with its true calibration."""
    rows: dict[str, list] = {"true": [], "estimated": [], "linear": [], "registered": []}
    for seed in range(seeds):
        linear = simulate_volume(tmp / f"l{noise}{seed}", seed=seed, noise=noise)
        report = reconstruct_session(linear, load_calibration(linear.path / "truth.json"), tmp / f"rl{noise}{seed}",
                                     cad=session_cad_target(linear)).report
        rows["linear"].append((report["surface_mean_mm"], report["surface_p95_mm"], False))
        session = simulate_volume(tmp / f"v{noise}{seed}", seed=seed, noise=noise, probe=probe)
        cad = session_cad_target(session)
        estimated = estimates.get(seed)
        if estimated is None:
            sweep = simulate_calibration(tmp / f"c{noise}{seed}", n_poses=poses, seed=seed, noise=noise, probe=probe)
            estimated = calibrate_session(sweep, segment_session(sweep), with_validation=False).calibration
        cals = {"true": load_calibration(session.path / "truth.json"), "estimated": estimated}
        for name, cal in cals.items():
            report = reconstruct_session(session, cal, tmp / f"r{noise}{seed}{name}", cad=cad).report
            inside = report["volume"].get("fan") is not None
            rows[name].append((report["surface_mean_mm"], report["surface_p95_mm"], inside))
        assert cad is not None
        report = reconstruct_session(session, cals["true"], tmp / f"r{noise}{seed}reg",
                                     cad=CadTarget(cad.mesh, cad.object_to_base, register=True)).report
        rows["registered"].append((report["surface_mean_mm"], report["surface_p95_mm"], False))
    for name, target in (("true", "0.3"), ("estimated", "0.5")):
        if rows[name]:
            a = np.array(rows[name], dtype=float)
            print(f"convex volume sweep, {name} calibration ({len(a)} seeds, {noise}): surface points -> CAD "
                  f"{a[:, 0].mean():.3f} mm mean (worst seed {a[:, 0].max():.3f}), p95 {a[:, 1].mean():.3f} mm "
                  f"[target <= {target}]; clipped to the fan in {int(a[:, 2].sum())} of {len(a)}")
    a = np.array(rows["registered"], dtype=float)
    print(f"  the same with the CAD placed by ICP (reconstruct --register), which leaves out where the arm puts "
          f"the sweep as a whole: {a[:, 0].mean():.3f} mm mean (worst seed {a[:, 0].max():.3f}), p95 "
          f"{a[:, 1].mean():.3f} mm")
    a = np.array(rows["linear"], dtype=float)
    print(f"  beside it, {DEFAULT_PROBE}'s sweeps of the same seeds with the true calibration: "
          f"{a[:, 0].mean():.3f} mm mean (worst seed {a[:, 0].max():.3f}), p95 {a[:, 1].mean():.3f} mm")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--noise", default="bench")
    parser.add_argument("--volume-seeds", type=int, default=3)
    parser.add_argument("--volume-noise", nargs="+", default=["realistic", "bench"],
                        help="levels of the volume sweeps (bench_volume.py's is realistic; bench's arm is off its "
                             "kinematic table, which no calibration of the mount corrects)")
    parser.add_argument("--probe", default="convex-50", choices=[k for k, p in BUILTIN_PROBES.items()
                                                                 if isinstance(p, ConvexProbe)])
    args = parser.parse_args()
    probe = BUILTIN_PROBES[args.probe]
    assert isinstance(probe, ConvexProbe)
    with tempfile.TemporaryDirectory() as tmp:
        estimates = calibration(args.seeds, args.poses, args.noise, probe, Path(tmp))
        for noise in args.volume_noise if args.volume_seeds else ():
            volume(args.volume_seeds, noise, args.poses, probe, estimates if noise == args.noise else {}, Path(tmp))
    return None


if __name__ == "__main__":
    sys.exit(main())
