"""Is ``corner_error_95_mm`` a 95 % bound, and which objective wins where? Twin runs mixing
objectives, noise levels and pose counts (phantom pose solved, as on the robot): the true corner
error (image corners mapped by the estimate and by the truth, spacing included) against the bound;
then the real fCal 1.2 recordings: every objective, tracked (PLUS's PhantomToReference) and robot
case (phantom pose solved), scored on the separate validation recording, and the time
``probecal calibrate`` takes.

Run: .venv/bin/python benchmarks/bench_calibration_bound.py [--runs 20] [--first-seed 100]
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
from probecal.core.calibration.metrics import pre3d
from probecal.core.calibration.objectives import OBJECTIVES
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session, observations
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.geometry.transforms import transform_error
from probecal.core.io.plusdata import missing_reason, plus_data_dir
from probecal.core.io.plusimport import import_plus

PLUS = plus_data_dir()
FCAL_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
METHODS = ("auto", "all-wire", "middle-wire", "thesis")
NOISES = ("none", "realistic", "harsh")
POSES = (15, 25, 40, 60)


def twin_runs(runs: int, first_seed: int, tmp: Path) -> None:
    print(f"twin: {runs} runs, phantom pose solved; true corner error against the 95 % bound")
    print("  seed  noise      poses  method       objective    true mm  bound mm  (bootstrap, objectives, echo peaks)  "
          "vs truth mm/deg  CV PRE3D  weak")
    covered, ratios = [], []
    for r in range(runs):
        seed, noise, poses, method = first_seed + r, NOISES[r % 3], POSES[r % 4], METHODS[(r // 2) % 4]
        session = simulate_calibration(tmp / f"twin{seed}", n_poses=poses, seed=seed, noise=noise)
        truth = session.truth()
        true_cal = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
        report = calibrate_session(session, segment_session(session), method)
        cal, m = report.calibration, report.calibration.metrics
        error = corner_distance_mm(cal, true_cal, image_corners_px(session.image_size))
        bound = m["corner_error_95_mm"]
        covered.append(error <= bound)
        ratios.append(error / bound)
        dt, dr = transform_error(cal.image_to_tool_rigid, true_cal.image_to_tool_rigid)
        parts = m["corner_error"]
        disagreement = max(parts["objective_disagreement_mm"].values(), default=0.0)
        echo = parts["echo_peak_disagreement_mm"] or 0.0
        print(f"  {seed:4d}  {noise:<9}  {poses:5d}  {method:<11}  {m['objective']:<11}  {error:7.3f}  {bound:8.3f}  "
              f"({parts['bootstrap_95_mm']:.3f}, {disagreement:.3f}, {echo:.3f})  {dt:8.3f} / {dr:.3f}  "
              f"{m['cv_pre3d_mm']:8.3f}  "
              f"{len(report.weakly_determined)}{'' if error <= bound else '  NOT COVERED'}")
    print(f"  coverage: true corner error within the bound in {sum(covered)} of {runs} runs "
          f"({100 * np.mean(covered):.0f} %, target >= 90 %); true/bound median {np.median(ratios):.2f}, "
          f"max {np.max(ratios):.2f}")


def fcal(tmp: Path) -> None:
    cal = import_plus(PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha", FCAL_CONFIG, tmp / "cal")
    val = import_plus(PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha", FCAL_CONFIG, tmp / "val")
    cal_results, val_results = segment_session(cal), segment_session(val)
    val_obs, _ = observations(val, val_results)
    print("fCal 1.2 (our segmentation with PLUS's hints), PRE3D on the validation recording (PLUS: 1.247 mm)")
    for solve in (False, True):
        case = "robot case, phantom pose solved" if solve else "tracked case, PhantomToReference known"
        report = calibrate_session(cal, cal_results, "auto", solve_phantom_pose=solve)
        m = report.calibration.metrics
        print(f"  {case}: auto keeps {m['objective']} ({m['objective_choice']}); "
              f"image corners +-{m['corner_error_95_mm']:.2f} mm (95 %)")
        for reason in report.weakly_determined:
            print(f"    weakly determined: {reason}")
        for objective in OBJECTIVES:
            calibration = calibrate_session(cal, cal_results, objective, solve_phantom_pose=solve,
                                            with_validation=False).calibration
            y = calibration.phantom_to_base if solve else val.phantom_to_base
            mean, std = pre3d(val.phantom, val_obs.markers_px, val_obs.tool_to_base, calibration.image_to_tool, y)
            cv = m["objectives"][objective]["cv_pre3d_mm"]
            print(f"    {objective:<12} validation PRE3D {mean:.3f} +- {std:.3f} mm, block CV PRE3D {cv:.3f} mm")


def cli_speed(tmp: Path) -> None:
    probecal = str(Path(sys.executable).parent / "probecal")
    for extra in ([], ["--solve-phantom-pose"]):
        start = time.perf_counter()
        result = subprocess.run([probecal, "calibrate", str(tmp / "cal"), "--out", str(tmp / "speed.json"), *extra],
                                capture_output=True, text=True)
        took = time.perf_counter() - start
        status = "ok" if result.returncode == 0 else f"FAILED: {result.stderr.strip()[-200:]}"
        print(f"probecal calibrate {' '.join(extra)} on the 188-frame fCal session: {took:.1f} s wall-clock, "
              f"segmentation and loading included [{status}]")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=100)
    parser.add_argument("--skip-fcal", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        twin_runs(args.runs, args.first_seed, tmp)
        if args.skip_fcal:
            return
        reason = missing_reason()
        if reason is not None:
            print(f"fCal figures skipped: {reason}")
            return
        fcal(tmp)
        cli_speed(tmp)


if __name__ == "__main__":
    main()
