"""Calibration pipeline figures (issue targets): simulator accuracy over seeds, real PLUS data,
and speed (the corner bound's coverage and the objectives in the robot case:
``bench_calibration_bound.py``).

Run: .venv/bin/python benchmarks/bench_calibration.py [--seeds 10] [--poses 60] [--real-only]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.metrics import pre3d, segmentation_error_mm
from probecal.core.calibration.objectives import OBJECTIVES
from probecal.core.calibration.result import load_calibration
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.calibration.validate import validate_session
from probecal.core.geometry.transforms import transform_error
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.io.plusimport import import_plus
from probecal.core.io.plusresults import read_calibration_results

ROOT = Path(__file__).resolve().parent.parent
PLUS = plus_data_dir()
FCAL_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
NWIRE_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"
FCAL_RESULTS = PLUS / "TestImages" / "FreehandCalibration3NWires.results.xml"


def simulator(seeds: int, poses: int, noise: str, tmp: Path) -> None:
    rows, scores = [], []
    for seed in range(seeds):
        session = simulate_calibration(tmp / f"{noise}{seed}", n_poses=poses, seed=seed, noise=noise)
        truth = session.truth()
        sx, sy = truth["pixel_spacing_mm"]
        results = segment_session(session)
        scores.append(segmentation_error_mm(results, truth["frames"], (sx, sy)))
        report = calibrate_session(session, results, with_validation=False)
        cal = report.calibration
        dt, dr = transform_error(cal.image_to_tool_rigid, np.array(truth["image_to_tool_rigid"]))
        spacing_err = max(abs(cal.pixel_spacing_mm[0] / sx - 1), abs(cal.pixel_spacing_mm[1] / sy - 1)) * 100
        rejected_found = sum(1 for i in report.frames_rejected if results[i].found)
        rows.append((cal.metrics["fre_mm"], dt, dr, spacing_err, rejected_found))
    a = np.array(rows, dtype=float)
    total = {k: sum(getattr(s, k) for s in scores) for k in ("frames", "complete", "correct", "mislabelled")}
    errors = np.concatenate([s.errors_mm for s in scores])
    print(f"simulator {noise}: {seeds} seeds x {poses} poses, {total['frames']} frames recorded "
          f"({total['complete']} with every wire in view)")
    print(f"  found and correctly labelled: {total['correct'] / total['complete'] * 100:.2f} % of complete frames "
          f"(target >= 99 %), mislabelled: {total['mislabelled']}")
    print(f"  median centroid error: {np.median(errors):.3f} mm (target <= 0.1)")
    print(f"  FRE: mean {a[:, 0].mean():.3f} mm, worst seed {a[:, 0].max():.3f} mm (target <= 0.25)")
    print(f"  image_to_tool_rigid error: translation mean {a[:, 1].mean():.3f} / max {a[:, 1].max():.3f} mm, "
          f"rotation mean {a[:, 2].mean():.3f} / max {a[:, 2].max():.3f} deg")
    print(f"  pixel spacing error: mean {a[:, 3].mean():.3f} % / max {a[:, 3].max():.3f} % (target <= 0.2 %)")
    print(f"  segmented frames rejected by the calibration: {int(a[:, 4].sum())}")


def _objectives_line(report) -> str:
    rows = report.calibration.metrics["objectives"]
    return ", ".join(f"{name} {row['cv_pre3d_mm']:.3f}" for name, row in rows.items() if row.get("cv_pre3d_mm"))


def real_data(tmp: Path) -> None:
    """fCal 1.2 the robot's way (own segmenter, no PLUS hints but the approximate spacing):
    calibrate on one recording, validate on the other, against PLUS's baseline."""
    calibration = import_plus(PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha", FCAL_CONFIG, tmp / "cal")
    validation = import_plus(PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha", FCAL_CONFIG, tmp / "val")
    baseline = read_calibration_results(FCAL_RESULTS)
    results = {}
    for session, frames, name in ((calibration, baseline.calibration, "calibration"),
                                  (validation, baseline.validation, "validation")):
        results[name] = segment_session(session, segmenter=session_segmenter(session, use_hints=False))
        both = sum(f.found and r.found for f, r in zip(frames, results[name]))
        distances = np.concatenate([
            np.linalg.norm(r.markers - f.points, axis=1) for f, r in zip(frames, results[name]) if f.found and r.found
        ])
        print(f"fCal {name}, no hints: pattern found in {both} of the {sum(f.found for f in frames)} frames PLUS "
              f"found; points within 1 px of PLUS: {(distances <= 1.0).mean() * 100:.1f} % (target >= 95 %)")
    for method in ("auto", *OBJECTIVES):
        report = calibrate_session(calibration, results["calibration"], method, with_validation=False)
        metrics = validate_session(validation, report.calibration, results["validation"])
        sx, sy = report.calibration.pixel_spacing_mm
        objective = report.calibration.metrics["objective"]
        print(f"fCal calibrate ({method}: {objective}) -> validate: PRE3D {metrics['pre3d_mm']:.3f} +- "
              f"{metrics['pre3d_std_mm']:.3f} mm "
              f"(target <= 1.20; PLUS baseline {baseline.pre3d_validation_mm[0]}), spacing {sx:.5f} x {sy:.5f} mm/px")
        if method == "auto":
            print(f"  block cross-validated PRE3D on the calibration recording: {_objectives_line(report)} mm")
    mean, std = pre3d(validation.phantom, np.array([f.points for f in baseline.validation]), validation.poses(),
                      baseline.image_to_probe, validation.phantom_to_base)
    print(f"PRE3D of PLUS's own matrix and points, recomputed: {mean:.4f} +- {std:.4f} mm "
          f"(baseline {baseline.pre3d_validation_mm[0]} +- {baseline.pre3d_validation_mm[1]})")


def nwire_freehand(tmp: Path) -> None:
    """PLUS 1's NwirePhantomFreehand recording (fCal 1.0 phantom, 2 N-wires, no segmentation
    hints, nominal spacing 0.077 mm/px): no separate validation recording, so each objective's
    block cross-validated PRE3D against that of PLUS's Image->Probe on the same frames."""
    session = import_plus(PLUS / "TestImages" / "NwirePhantomFreehand.igs.mha", NWIRE_CONFIG, tmp / "nwire",
                          spacing_mm=0.077)
    results = segment_session(session)
    plus_calibration = load_calibration(NWIRE_CONFIG)
    plus_metrics = validate_session(session, plus_calibration, results)
    print(f"NwirePhantomFreehand: pattern found in {sum(r.found for r in results)} of {len(results)} frames; "
          f"PLUS's Image->Probe on them: PRE3D {plus_metrics['pre3d_mm']:.3f} mm")
    auto = calibrate_session(session, results)
    print(f"NwirePhantomFreehand calibrate (auto: {auto.calibration.metrics['objective']}): image corners "
          f"+-{auto.calibration.metrics['corner_error_95_mm']:.2f} mm (95 %); block cross-validated PRE3D: "
          f"{_objectives_line(auto)} mm")
    corners = image_corners_px(session.image_size)
    for method in OBJECTIVES:
        calibration = calibrate_session(session, results, method, with_validation=False).calibration
        distance = corner_distance_mm(calibration, plus_calibration, corners)
        print(f"NwirePhantomFreehand calibrate ({method}): PRE3D {calibration.metrics['pre3d_mm']:.3f} mm on its "
              f"own frames, image corners up to {distance:.2f} mm from PLUS's matrix")


def speed(tmp: Path) -> None:
    session = simulate_calibration(tmp / "speed", n_poses=200, seed=3, noise="realistic")
    for name, path in (("simulated 200-pose session", session.path), ("fCal 188-frame PLUS session", tmp / "cal")):
        start = time.perf_counter()
        result = subprocess.run([str(Path(sys.executable).parent / "probecal"), "calibrate", str(path), "--out",
                                 str(tmp / "speed.json")], capture_output=True, text=True)
        took = time.perf_counter() - start
        status = "ok" if result.returncode == 0 else f"FAILED: {result.stderr.strip()[-200:]}"
        print(f"probecal calibrate on the {name}: {took:.2f} s wall-clock, loading included (target <= 20 s) "
              f"[{status}]")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--real-only", action="store_true", help="only the real PLUS recordings")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", type=int, default=60)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not args.real_only:
            for noise in ("realistic", "harsh", "bench"):
                simulator(args.seeds, args.poses, noise, tmp)
        real_data(tmp)
        nwire_freehand(tmp)
        if not args.real_only:
            speed(tmp)


if __name__ == "__main__":
    main()
