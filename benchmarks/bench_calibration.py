"""Calibration pipeline figures (issue targets): simulator accuracy over seeds, real PLUS data,
and speed (the corner bound's coverage and the objectives in the robot case:
``bench_calibration_bound.py``).

Run: .venv/bin/python benchmarks/bench_calibration.py [--seeds 10] [--poses 60] [--real-only | --speed-only]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.pairing import paired_at_latency
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.metrics import pre3d, segmentation_error_mm
from probecal.core.calibration.objectives import OBJECTIVES
from probecal.core.calibration.result import Calibration, calibration_from_matrix, load_calibration
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.calibration.validate import validate_session
from probecal.core.geometry.probe import LinearProbe
from probecal.core.geometry.transforms import transform_error
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.io.plusimport import import_plus
from probecal.core.io.plusresults import read_calibration_results
from probecal.core.io.session import Session

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


@dataclass(frozen=True)
class FcalSet:
    """One of PLUS's fCal benches: a calibration and a validation recording, the device set and
    PLUS's own results (its matrix, its points and its validation PRE3D)."""

    name: str
    calibration: str
    validation: str
    config: Path
    results: Path


FCAL_SETS = (
    FcalSet("fCal 1.2", "fCal_Test_Calibration_3NWires", "fCal_Test_Validation_3NWires", FCAL_CONFIG, FCAL_RESULTS),
    FcalSet("fCal 2.0", "fCal_Test_Calibration_3NWires_fCal2.0", "fCal_Test_Validation_3NWires_fCal2.0",
            PLUS / "ConfigFiles" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_2.0.xml",
            PLUS / "TestImages" / "FreehandCalibration3NWires_fCal2.0.results.xml"),
)


def import_fcal(bench: FcalSet, tmp: Path) -> tuple[Session, Session]:
    """The bench's calibration and validation recordings imported with its device set."""
    return tuple(import_plus(PLUS / "TestImages" / f"{stem}.igs.mha", bench.config, tmp / f"{bench.name}-{part}")
                 for part, stem in (("cal", bench.calibration), ("val", bench.validation)))  # type: ignore[return-value]


def import_nwire(tmp: Path) -> Session:
    """PLUS 1's NwirePhantomFreehand recording imported with its device set and the scanner's
    nominal spacing (its device set has no segmentation hints)."""
    return import_plus(PLUS / "TestImages" / "NwirePhantomFreehand.igs.mha", NWIRE_CONFIG, tmp / "nwire",
                       spacing_mm=(0.077, 0.077))


def tracked_recordings(tmp: Path) -> dict[str, Session]:
    """Every tracked N-wire recording of PLUS's, imported: both fCal benches' calibration and
    validation recordings and NwirePhantomFreehand."""
    sessions = {}
    for bench in FCAL_SETS:
        sessions[f"{bench.name} calibration"], sessions[f"{bench.name} validation"] = import_fcal(bench, tmp)
    sessions["NwirePhantomFreehand"] = import_nwire(tmp)
    return sessions


def plus_points_pre3d(validation: Session, calibration: Calibration, baseline) -> tuple[float, float]:
    """PRE3D (mean, std, mm) of ``calibration`` on PLUS's own validation points, as the issue
    scores it: the validation frames paired with the calibration's image latency when it has one
    (:func:`core.acquisition.pairing.paired_at_latency`), else as recorded."""
    paired, _ = paired_at_latency(validation, calibration.image_latency_s)
    frames = [(i, f) for i, f in enumerate(baseline.validation) if f.found and paired.records[i].pose_valid]
    return pre3d(validation.phantom, np.array([f.points for _, f in frames]),
                 np.array([paired.records[i].tool_to_base for i, _ in frames]), calibration.image_to_tool,
                 validation.phantom_to_base)


REAL_TABLE = ("bench", "default chooses", "validation PRE3D at the latency (mm)", "as recorded (mm)", "PLUS (mm)")


def real_data(tmp: Path) -> list[list[str]]:
    """PLUS's fCal benches the robot's way (own segmenter, no PLUS hints but the approximate
    spacing): calibrate on one recording, validate on the other with PLUS's points, against
    PLUS's baseline; with the image latency the calibration measured applied to the validation
    recording, and with its frames as recorded. The default's rows of :data:`REAL_TABLE`."""
    rows = []
    for bench in FCAL_SETS:
        calibration, validation = import_fcal(bench, tmp)
        baseline = read_calibration_results(bench.results)
        results = {}
        for session, frames, part in ((calibration, baseline.calibration, "calibration"),
                                      (validation, baseline.validation, "validation")):
            results[part] = segment_session(session, segmenter=session_segmenter(session, use_hints=False))
            both = sum(f.found and r.found for f, r in zip(frames, results[part]))
            distances = np.concatenate([np.linalg.norm(r.markers - f.points, axis=1)
                                        for f, r in zip(frames, results[part]) if f.found and r.found])
            print(f"{bench.name} {part}, no hints: pattern found in {both} of the {sum(f.found for f in frames)} "
                  f"frames PLUS found; points within 1 px of PLUS: {(distances <= 1.0).mean() * 100:.1f} %")
        plus_mean, _ = plus_points_pre3d(validation, calibration_from_matrix(baseline.image_to_probe, bench.results),
                                         baseline)
        print(f"{bench.name}: PLUS's own matrix on its validation points: PRE3D {plus_mean:.3f} mm "
              f"(baseline {baseline.pre3d_validation_mm[0]})")
        for method in ("auto", *OBJECTIVES):
            report = calibrate_session(calibration, results["calibration"], method, with_validation=method == "auto")
            cal, m = report.calibration, report.calibration.metrics
            at_latency = plus_points_pre3d(validation, cal, baseline)
            as_recorded = plus_points_pre3d(validation, replace(cal, image_latency_s=None), baseline)
            sx, sy = cal.pixel_spacing_mm
            print(f"{bench.name} calibrate ({method}: {m['objective']}) -> validate on PLUS's points: PRE3D "
                  f"{at_latency[0]:.3f} +- {at_latency[1]:.3f} mm at the measured latency, {as_recorded[0]:.3f} as "
                  f"recorded (PLUS {baseline.pre3d_validation_mm[0]}); spacing {sx:.5f} x {sy:.5f} mm/px")
            if method == "auto":
                rows.append([bench.name, m["objective"], f"{at_latency[0]:.3f}", f"{as_recorded[0]:.3f}",
                             f"{plus_mean:.3f}"])
                latency = m.get("temporal", {})
                print(f"  image latency {latency.get('image_latency_s', 0) * 1000:.1f} +- "
                      f"{latency.get('std_error_s', 0) * 1000:.1f} ms (markers {latency.get('residual_at_zero_mm')} mm "
                      f"from their wires as recorded, {latency.get('residual_mm')} at it); block cross-validated "
                      f"PRE3D against the definition: {_objectives_line(report)} mm; image corners "
                      f"+-{m['corner_error_95_mm']:.2f} mm (95 %)")
    return rows


def nwire_freehand(tmp: Path) -> None:
    """PLUS 1's NwirePhantomFreehand recording (fCal 1.0 phantom, 2 N-wires, no segmentation
    hints, nominal spacing 0.077 mm/px): no separate validation recording, so each objective's
    block cross-validated PRE3D against that of PLUS's Image->Probe on the same frames."""
    session = import_nwire(tmp)
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
    # A fine scanner's frames: 1536 x 2000 px at 0.025 mm/px, what a 2001 x 1501 frame holds.
    fine = simulate_calibration(tmp / "fine", n_poses=230, seed=0, noise="bench",
                                probe=replace(LinearProbe(), width_px=1536, height_px=2000))
    fcal = tmp / f"{FCAL_SETS[0].name}-cal"
    if not fcal.exists():
        import_fcal(FCAL_SETS[0], tmp)
    for name, path, target in (("simulated 200-pose session", session.path, 20),
                               ("fCal 188-frame PLUS session", fcal, 20),
                               ("simulated 230-pose session of 1536x2000 frames at 0.025 mm/px", fine.path, 10)):
        start = time.perf_counter()
        result = subprocess.run([str(Path(sys.executable).parent / "probecal"), "calibrate", str(path), "--out",
                                 str(tmp / f"{path.name}-speed.json")], capture_output=True, text=True)
        took = time.perf_counter() - start
        status = (f"FAILED: {result.stderr.strip()[-200:]}" if result.returncode
                  else "within the target" if took <= target else "OVER the target")
        print(f"probecal calibrate on the {name}: {took:.2f} s wall-clock, loading included "
              f"(target <= {target} s) [{status}]")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--real-only", action="store_true", help="only the real PLUS recordings")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--speed-only", action="store_true", help="only calibrate's wall-clock time")
    parser.add_argument(WRITE_DOCS, action="store_true",
                        help="with --real-only: write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.speed_only:
            speed(tmp)
            return
        if not args.real_only:
            for noise in ("realistic", "harsh", "bench"):
                simulator(args.seeds, args.poses, noise, tmp)
        rows = real_data(tmp)
        if args.write_docs and args.real_only:
            print(f"written: {write_table(command_line(), markdown_table(REAL_TABLE, rows))}")
        nwire_freehand(tmp)
        if not args.real_only:
            speed(tmp)


if __name__ == "__main__":
    main()
