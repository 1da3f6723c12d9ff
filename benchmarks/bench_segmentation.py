"""Segmentation figures: the digital twin against truth (as planned, rolled up to 30 degrees about
the wires, with dots clipped at the image's edge, and at a fine scanner's 0.025 mm/px), PLUS's
fCal and VLCUS data against PLUS's own segmentation, tissue frames, and speed.

Run: .venv/bin/python benchmarks/bench_segmentation.py [--seeds 10] [--poses 60] [--only twin,rolled,edge,fine,real]
     [--write-docs]

``--write-docs`` writes the twin's rows (every part but ``real``) into docs/evidence.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

from probecal.core.acquisition.plan import PoseRanges
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.labelling import plus_orientation
from probecal.core.calibration.metrics import SegmentationScore, segmentation_error_mm, thesis_segmentation_error
from probecal.core.calibration.segment import WORK_SPACING_MM, Segmenter, segment_session, session_segmenter
from probecal.core.geometry.probe import LinearProbe
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.io.plusimport import import_plus
from probecal.core.io.plusresults import read_calibration_results, read_segmentation_baseline
from probecal.core.io.sequence import read_sequence

PLUS = plus_data_dir()
IMAGES, CONFIGS = PLUS / "TestImages", PLUS / "ConfigFiles" / "Testing"
FCAL_CONFIG = CONFIGS / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
FCAL = {"ValidationData": IMAGES / "fCal_Test_Validation_3NWires.igs.mha",
        "CalibrationData": IMAGES / "fCal_Test_Calibration_3NWires.igs.mha"}
SECTIONS = {"ValidationData": "validation", "CalibrationData": "calibration"}
FCAL_RESULTS = IMAGES / "FreehandCalibration3NWires.results.xml"
VLCUS = IMAGES / "SegmentationTest_VLCUS_RandomStepperMotionData2.igs.mha"
VLCUS_CONFIG = CONFIGS / "PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber.xml"
VLCUS_BASELINE = IMAGES / "SegmentationTest_VLCUS_RandomStepperMotionData2_Segmentation_baseline.xml"
SPINE = IMAGES / "SpinePhantomFreehand.igs.mha"
TABLE = ("sweep", "seeds × poses", "frames with every wire in view found", "mislabelled",
         "centroid error, median (p95), mm", "frames/s on 2 threads")


def compare_with_plus(results, baseline) -> tuple[int, int, int, np.ndarray]:
    """(frames where both found, we only, PLUS only, point distances in px)."""
    both = ours = theirs = 0
    distances = []
    for r, frame in zip(results, baseline):
        points = frame.points
        both += r.found and points is not None
        ours += r.found and points is None
        theirs += (not r.found) and points is not None
        if r.found and points is not None:
            distances.append(np.linalg.norm(r.markers - points, axis=1))
    return both, ours, theirs, np.concatenate(distances)


def table_row(sweep: str, seeds: int, poses: int, scores: list[SegmentationScore],
              rate: float | None = None) -> list[str]:
    """One sweep's row of the evidence table (``TABLE``); ``rate`` frames/s, if measured."""
    errors = np.concatenate([s.errors_mm for s in scores])
    found = sum(s.found for s in scores) / sum(s.complete for s in scores)
    return [sweep, f"{seeds} × {poses}", f"{found:.2%}".replace("%", " %"), str(sum(s.mislabelled for s in scores)),
            f"{np.median(errors):.4f} ({np.percentile(errors, 95):.4f})", "–" if rate is None else f"{rate:.0f}"]


def simulator(tmp: Path, noise: str, seeds: int, poses: int, ranges: PoseRanges | None = None,
              label: str = "") -> list[SegmentationScore]:
    scores = []
    thesis_errors = []
    for seed in range(seeds):
        session = simulate_calibration(tmp / f"{noise}{label}{seed}", n_poses=poses, seed=seed, noise=noise,
                                       ranges=ranges)
        truth = session.truth()
        results = segment_session(session)
        scores.append(segmentation_error_mm(results, truth["frames"], truth["pixel_spacing_mm"]))
        thesis_errors.append(thesis_segmentation_error(results, session.phantom, session.pixel_spacing_mm))
    frames = sum(s.frames for s in scores)
    errors = np.concatenate([s.errors_mm for s in scores])
    total = {k: sum(getattr(s, k) for s in scores)
             for k in ("complete", "found", "correct", "mislabelled", "inaccurate")}
    print(f"simulator {noise:9s}{label} {seeds} seeds x {poses} poses: {frames} frames, "
          f"{total['complete']} with every wire in view")
    print(f"  found {total['found'] / frames:7.2%} ({total['found'] / total['complete']:.2%} of those with every "
          f"wire in view)  found and correctly labelled {total['correct'] / frames:7.2%}")
    print(f"  mislabelled {total['mislabelled']}, right labels but a centroid > 1 mm off {total['inaccurate']}")
    print(f"  centroid error: median {np.median(errors):.4f} mm, p95 {np.percentile(errors, 95):.4f} mm, "
          f"max {errors.max():.3f} mm")
    lateral = np.nanmean([e.lateral_mm for e in thesis_errors])
    axial = np.nanmean([e.axial_mm for e in thesis_errors])
    print(f"  thesis measure (eq. 3.4/3.5, nominal spacing): lateral {lateral:+.3f} mm, axial {axial:+.3f} mm")
    return scores


def fcal(tmp: Path) -> None:
    for section, sequence in FCAL.items():
        session = import_plus(sequence, FCAL_CONFIG, tmp / section)
        results = segment_session(session)
        both, ours, theirs, d = compare_with_plus(results,
                                                  getattr(read_calibration_results(FCAL_RESULTS), SECTIONS[section]))
        print(f"fCal {section:15s} {len(results):3d} frames: found {sum(r.found for r in results)} "
              f"(PLUS {both + theirs}); missed where PLUS found {theirs}; points within 1 px of PLUS "
              f"{np.mean(d < 1):.2%}, within 0.1 px {np.mean(d < 0.1):.2%}, median {np.median(d):.3f} px, "
              f"max {d.max():.3f} px")


def vlcus(tmp: Path) -> None:
    session = import_plus(VLCUS, VLCUS_CONFIG, tmp / "vlcus")
    results = segment_session(session)
    baseline = read_segmentation_baseline(VLCUS_BASELINE)
    both, ours, theirs, d = compare_with_plus(results, baseline)
    agree = len(results) - ours - theirs
    print(f"VLCUS {len(results)} frames: success flags agree with PLUS in {agree} ({agree / len(results):.1%}); "
          f"both found {both}, only we {ours}, only PLUS {theirs}")
    print(f"  points within 0.1 px of PLUS {np.mean(d < 0.1):.2%}, within 1 px {np.mean(d < 1):.2%}, "
          f"within 2 px {np.mean(d < 2):.2%}, median {np.median(d):.3f} px, max {d.max():.3f} px")


def tissue() -> None:
    config = read_device_set(FCAL_CONFIG)
    frames = read_sequence(SPINE).frames
    segmenter = Segmenter.create(config.phantom, (0.078, 0.078), plus_orientation(config.phantom),
                                 config.segmentation.attributes)
    found = sum(segmenter(f).found for f in frames)
    print(f"tissue (SpinePhantomFreehand, fCal segmenter): pattern found in {found} of {len(frames)} frames")


def speed(tmp: Path) -> None:
    session = import_plus(FCAL["CalibrationData"], FCAL_CONFIG, tmp / "speed")
    frames = [session.image(i) for i in range(len(session))]
    for use_roi in (True, False):
        segmenter = Segmenter.for_session(session, use_roi=use_roi)
        segmenter(frames[0])
        start = time.perf_counter()
        for i, frame in enumerate(frames):
            segmenter(frame, i)
        single = (time.perf_counter() - start) / len(frames)
        with ThreadPoolExecutor(max_workers=2) as pool:
            start = time.perf_counter()
            list(pool.map(segmenter, frames, range(len(frames))))
            two = len(frames) / (time.perf_counter() - start)
        label = "with ROI   " if use_roi else "without ROI"
        print(f"speed 820x616 fCal, {label}: {two:6.0f} frames/s on 2 threads, {1 / single:6.0f} frames/s on 1 "
              f"(latency {single * 1e3:.2f} ms/frame)  (target >= 200)")


def fine_frames(tmp: Path, seeds: int, poses: int) -> list[tuple[str, list[SegmentationScore], float]]:
    """Twin frames of a scanner that resamples to 0.025 mm/px (1536x2000 px, 3.1 Mpx: what a
    2001x1501 frame at that spacing holds): found and centroid error against the truth, and
    frames/s on frames in memory, binned to about the working resolution (the default) and at
    full cost; per the two, its label, scores and median frames/s."""
    probe = replace(LinearProbe(), width_px=1536, height_px=2000)
    sessions = [simulate_calibration(tmp / f"fine{seed}", n_poses=poses, seed=seed, noise="bench", probe=probe)
                for seed in range(seeds)]
    measured = []
    for work_mm in (WORK_SPACING_MM, 0.0):
        scores, rates = [], []
        for session in sessions:
            segmenter = session_segmenter(session, work_spacing_mm=work_mm)
            n = segmenter.binning
            label = f"binned {n} x {n} ({0.025 * n:.3f} mm/px)" if n > 1 else "at full cost"
            frames = [session.image(i) for i in range(len(session))]
            with ThreadPoolExecutor(max_workers=2) as pool:
                start = time.perf_counter()
                results = list(pool.map(segmenter, frames, range(len(frames))))
                rates.append(len(frames) / (time.perf_counter() - start))
            truth = session.truth()
            scores.append(segmentation_error_mm(results, truth["frames"], truth["pixel_spacing_mm"]))
        errors = np.concatenate([s.errors_mm for s in scores])
        found = sum(s.found for s in scores)
        print(f"fine frames 1536x2000 at 0.025 mm/px, {label}: {seeds} seeds x {poses} poses, "
              f"found {found / sum(s.frames for s in scores):.2%} ({found / sum(s.complete for s in scores):.2%} of "
              f"those with every wire in view), mislabelled {sum(s.mislabelled for s in scores)}, centroid error "
              f"median {np.median(errors):.4f} mm, p95 {np.percentile(errors, 95):.4f} mm; {np.median(rates):.0f} "
              f"frames/s on 2 threads (target >= 200)")
        measured.append((label, scores, float(np.median(rates))))
    return measured


def twin_rows(tmp: Path, parts: set[str], seeds: int, poses: int) -> list[list[str]]:
    """Run the twin's ``parts`` (all but ``real``), printing their figures; their table rows."""
    rows = []
    if "twin" in parts:
        for noise in ("realistic", "harsh"):
            rows.append(table_row(f"as planned, `{noise}`", seeds, poses, simulator(tmp, noise, seeds, poses)))
    if "rolled" in parts:
        scores = simulator(tmp, "bench", seeds, poses, PoseRanges(rotation_deg=(22.0, 30.0, 15.0)), " rolled +-30 deg")
        rows.append(table_row("rolled up to ±30° about the wires", seeds, poses, scores))
    if "edge" in parts:
        scores = simulator(tmp, "bench", seeds, poses, PoseRanges((16.0, 10.0, 3.0), margin_mm=0.0),
                           " dots at the image edge")
        rows.append(table_row("dots at the image's edge (±16 mm across)", seeds, poses, scores))
    if "fine" in parts:
        fine_seeds = min(seeds, 3)
        for label, scores, rate in fine_frames(tmp, fine_seeds, poses):
            rows.append(table_row(f"1536 × 2000 px at 0.025 mm/px, {label}", fine_seeds, poses, scores, rate))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--only", help="comma-separated parts: twin, rolled (sweeps rolled 30 degrees about the "
                                       "wires), edge (poses that put dots at the image's edge, clipped), fine "
                                       "(0.025 mm/px frames), real")
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        parts = set(args.only.split(",")) if args.only else {"twin", "rolled", "edge", "fine", "real"}
        rows = twin_rows(tmp, parts, args.seeds, args.poses)
        if "real" in parts and PLUS.is_dir():
            fcal(tmp)
            vlcus(tmp)
            tissue()
            speed(tmp)
        elif "real" in parts:
            print(f"PLUS data not found at {PLUS}: real-data figures skipped")
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, rows))}")


if __name__ == "__main__":
    main()
