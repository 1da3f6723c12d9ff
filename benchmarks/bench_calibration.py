"""Calibration pipeline figures (issue targets): simulator accuracy over seeds, real PLUS data,
and speed.

Run: .venv/bin/python benchmarks/bench_calibration.py [--seeds 10] [--poses 60]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import core  # noqa: F401  (sets BLAS threads before numpy loads)
import numpy as np

from core.calibrate import calibrate_session
from core.metrics import pre3d
from core.plusimport import import_plus
from core.segment import segment_session
from core.simulation import simulate_calibration
from core.transforms import transform_error
from core.validate import validate_session

ROOT = Path(__file__).resolve().parent.parent
PLUS = ROOT.parent / "shared" / "data" / "plus"
FCAL_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
LABEL_TOLERANCE_MM = 1.0


def simulator(seeds: int, poses: int, noise: str, tmp: Path) -> None:
    rows = []
    for seed in range(seeds):
        session = simulate_calibration(tmp / f"{noise}{seed}", n_poses=poses, seed=seed, noise=noise)
        truth = session.truth()
        sx, sy = truth["pixel_spacing_mm"]
        results = segment_session(session)
        correct = wrong = complete = 0
        errors = []
        for result, frame in zip(results, truth["frames"]):
            true_px = np.array([m if m is not None else [np.nan, np.nan] for m in frame["markers_px"]], float)
            if np.isfinite(true_px).all():
                complete += 1
            if not result.found:
                continue
            d = np.hypot((result.markers[:, 0] - true_px[:, 0]) * sx, (result.markers[:, 1] - true_px[:, 1]) * sy)
            if np.all(d < LABEL_TOLERANCE_MM):
                correct += 1
                errors.append(d)
            else:
                wrong += 1
        report = calibrate_session(session, results, "best", with_validation=False)
        cal = report.calibration
        dt, dr = transform_error(cal.image_to_tool_rigid, np.array(truth["image_to_tool_rigid"]))
        spacing_err = max(abs(cal.pixel_spacing_mm[0] / sx - 1), abs(cal.pixel_spacing_mm[1] / sy - 1)) * 100
        rejected_wrong = sum(1 for i in report.frames_rejected if i < len(results) and results[i].found)
        rows.append((len(results), complete, correct, wrong, np.median(np.concatenate(errors)) if errors else np.nan,
                     cal.metrics["fre_mm"], dt, dr, spacing_err, rejected_wrong))
    a = np.array(rows, dtype=float)
    frames, complete, correct, wrong = a[:, 0].sum(), a[:, 1].sum(), a[:, 2].sum(), a[:, 3].sum()
    print(f"simulator {noise}: {seeds} seeds x {poses} poses, {int(frames)} frames recorded "
          f"({int(complete)} with every wire in view)")
    print(f"  found and correctly labelled: {correct / complete * 100:.2f} % of complete frames "
          f"(target >= 99 %), mislabelled: {int(wrong)}")
    print(f"  median centroid error: {np.nanmedian(a[:, 4]):.3f} mm (target <= 0.1)")
    print(f"  FRE: mean {a[:, 5].mean():.3f} mm, worst seed {a[:, 5].max():.3f} mm (target <= 0.25)")
    print(f"  image_to_tool_rigid error: translation mean {a[:, 6].mean():.3f} / max {a[:, 6].max():.3f} mm, "
          f"rotation mean {a[:, 7].mean():.3f} / max {a[:, 7].max():.3f} deg")
    print(f"  pixel spacing error: mean {a[:, 8].mean():.3f} % / max {a[:, 8].max():.3f} % (target <= 0.2 %)")
    print(f"  segmented frames rejected by the calibration: {int(a[:, 9].sum())}")


def plus_baseline_points(section: str) -> list[tuple[bool, np.ndarray]]:
    root = ET.parse(PLUS / "TestImages" / "FreehandCalibration3NWires.results.xml").getroot()
    out = []
    for frame in root.find(f".//{section}").findall("Frame"):
        points = frame.find(".//Segmentation/SegmentedPoints").findall("Point")
        ok = frame.get("SegmentationStatus") == "OK"
        out.append((ok, np.array([[float(v) for v in p.get("Position").split()][:2] for p in points])))
    return out


def real_data(tmp: Path) -> None:
    calibration = import_plus(PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha", FCAL_CONFIG, tmp / "cal")
    validation = import_plus(PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha", FCAL_CONFIG, tmp / "val")
    for session, section in ((calibration, "CalibrationData"), (validation, "ValidationData")):
        results = segment_session(session)
        baseline = plus_baseline_points(section)
        plus_found = sum(ok for ok, _ in baseline)
        both = sum(ok and r.found for (ok, _), r in zip(baseline, results))
        distances = np.concatenate([
            np.linalg.norm(r.markers - pts, axis=1) for (ok, pts), r in zip(baseline, results) if ok and r.found
        ])
        print(f"fCal {section}: pattern found in {both} of the {plus_found} frames PLUS found "
              f"({sum(r.found for r in results)} of {len(results)} in all); points within 1 px of PLUS: "
              f"{(distances <= 1.0).mean() * 100:.1f} % (target >= 95 %), median {np.median(distances):.2f} px")
        if session is calibration:
            cal_results = results
        else:
            val_results = results
    for method in ("seed", "best"):
        report = calibrate_session(calibration, cal_results, method, with_validation=False)
        metrics = validate_session(validation, report.calibration, val_results)
        print(f"fCal calibrate ({method}) -> validate: PRE3D {metrics['pre3d_mm']:.3f} +- {metrics['pre3d_std_mm']:.3f} mm "
              f"(target <= 1.20; PLUS baseline 1.247), spacing {report.calibration.pixel_spacing_mm[0]:.5f} x "
              f"{report.calibration.pixel_spacing_mm[1]:.5f} mm/px")
    plus_points = [p for _, p in plus_baseline_points("ValidationData")]
    root = ET.parse(PLUS / "TestImages" / "FreehandCalibration3NWires.results.xml").getroot()
    from core.transforms import matrix_from_text

    matrix = matrix_from_text(root.find(".//CalibrationResults/Transform").get("Matrix"))
    mean, std = pre3d(validation.phantom, np.array(plus_points), validation.poses(), matrix, validation.phantom_to_base)
    print(f"PRE3D of PLUS's own matrix and points, recomputed: {mean:.4f} +- {std:.4f} mm (baseline 1.24684 +- 0.493905)")


def speed(tmp: Path) -> None:
    session = simulate_calibration(tmp / "speed", n_poses=200, seed=3, noise="realistic")
    for name, path in (("simulated 200-pose session", session.path), ("fCal 188-frame PLUS session", tmp / "cal")):
        start = time.perf_counter()
        result = subprocess.run([str(Path(sys.executable).parent / "probecal"), "calibrate", str(path), "--out",
                                 str(tmp / "speed.json")], capture_output=True, text=True)
        took = time.perf_counter() - start
        status = "ok" if result.returncode == 0 else f"FAILED: {result.stderr.strip()[-200:]}"
        print(f"probecal calibrate on the {name}: {took:.2f} s wall-clock, loading included (target <= 5 s) [{status}]")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", type=int, default=60)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for noise in ("realistic", "harsh"):
            simulator(args.seeds, args.poses, noise, tmp)
        real_data(tmp)
        speed(tmp)


if __name__ == "__main__":
    main()
