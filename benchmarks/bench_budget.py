"""The error budget of a robotic N-wire calibration on the twin: each bench effect (``core.twin.levels``)
switched on alone over ``realistic`` (a perfect set-up), then all together (``bench``); every run
simulates a calibration sweep, segments it with probecal's own segmenter and calibrates with the
default method (phantom pose solved, as on the robot).

Printed per row, over the seeds: the pattern found (% of frames), PRE3D on the calibration frames
(mm), and the calibrated image corners against where the true calibration puts them (mm, tool
frame): the mean of the four corners averaged over the seeds and for the worst seed, the farthest
corner averaged over the seeds, and the mean again when the calibration is given the true dots
(what no segmenter can improve: the robot's and the phantom's errors).

Run: .venv/bin/python benchmarks/bench_budget.py [--seeds 10] [--poses 60] [--only bench] [--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import FrameResult, segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distances_mm, image_corners_px
from probecal.core.twin.levels import BENCH_SETUP, LEVELS, Level, SetupErrors

REALISTIC, BENCH = LEVELS["realistic"], LEVELS["bench"]
THIN = replace(BENCH.imaging, elevation_fwhm_mm=0.0, wire_roughness=0.0, wire_diameter_mm=0.0, incidence_loss_db=0.0,
               incidence_widening=0.0, ringdown_db=-np.inf)


def _imaging(**fields) -> Level:
    return replace(REALISTIC, imaging=replace(REALISTIC.imaging, **fields))


def _setup(**fields) -> Level:
    return replace(REALISTIC, setup=SetupErrors(**fields))


EFFECTS: dict[str, Level] = {
    "none (`realistic`: a perfect set-up)": REALISTIC,
    "bench dots and noise": replace(REALISTIC, noise=BENCH.noise, imaging=THIN),
    "slice thickness, rough wires": _imaging(**{k: getattr(BENCH.imaging, k) for k in (
        "elevation_fwhm_mm", "elevation_focus_mm", "elevation_divergence", "wire_roughness", "wire_diameter_mm")}),
    "angle-dependent echoes": _imaging(incidence_loss_db=BENCH.imaging.incidence_loss_db,
                                       incidence_widening=BENCH.imaging.incidence_widening),
    "ring-down under wires": _imaging(ringdown_db=BENCH.imaging.ringdown_db, ringdown_mm=BENCH.imaging.ringdown_mm),
    "water temperature": _setup(water_temperature_c=BENCH_SETUP.water_temperature_c),
    "robot kinematic errors": _setup(dh_length_mm=BENCH_SETUP.dh_length_mm, dh_angle_deg=BENCH_SETUP.dh_angle_deg),
    "phantom tolerance": _setup(phantom_tolerance_mm=BENCH_SETUP.phantom_tolerance_mm),
    "latency and jitter": _setup(image_latency_s=BENCH_SETUP.image_latency_s,
                                 timestamp_jitter_s=BENCH_SETUP.timestamp_jitter_s),
    "all (`bench`)": BENCH,
}
TABLE = ("effect", "found %", "PRE3D (mm)", "corners mean (mm)", "worst seed", "farthest", "given the true dots")


def true_dots(session) -> list[FrameResult]:
    """Segmentation results that are the truth: every wire's true pixel, frames with a wire out
    of view not found."""
    out = []
    for frame in session.truth()["frames"]:
        markers = np.array([m if m is not None else [np.nan, np.nan] for m in frame["markers_px"]], float)
        found = bool(np.isfinite(markers).all())
        out.append(FrameResult(frame["index"], found, markers if found else None, "truth", np.empty((0, 2))))
    return out


def run(name: str, seed: int, poses: int) -> tuple[float, ...]:
    """One seed: found fraction, calibration-frame PRE3D (mm), and the image corners against
    the truth (mm): mean and farthest of the four, then their mean calibrating on the true dots."""
    with tempfile.TemporaryDirectory() as tmp:
        session = simulate_calibration(Path(tmp) / "s", n_poses=poses, seed=seed, noise=EFFECTS[name])
        truth = session.truth()
        true_cal = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
        corners = image_corners_px(session.image_size)
        results = segment_session(session)
        cal = calibrate_session(session, results, with_validation=False).calibration
        floor = calibrate_session(session, true_dots(session), with_validation=False).calibration
        distances = corner_distances_mm(cal, true_cal, corners)
        return (np.mean([r.found for r in results]), cal.metrics["pre3d_mm"], distances.mean(), distances.max(),
                corner_distances_mm(floor, true_cal, corners).mean())


def summary(rows: np.ndarray) -> tuple[float, ...]:
    """One effect over the seeds (one row each from ``run``): found %, mean PRE3D, the corners'
    mean and its worst seed, the farthest corner's mean, and the corners' mean given the true dots."""
    return (100 * rows[:, 0].mean(), rows[:, 1].mean(), rows[:, 2].mean(), rows[:, 2].max(), rows[:, 3].mean(),
            rows[:, 4].mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--only", help="comma-separated row names (or words in them) to run")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    names = [n for n in EFFECTS if not args.only or any(w in n for w in args.only.split(","))]
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    print(f"error budget: {args.seeds} seeds x {args.poses} poses, default method, phantom pose solved")
    print(f"{'':36s} {'':8s} {'':9s} {'image corners vs the truth, mm':>46s}")
    print(f"{'effect':36s} {'found %':>8s} {'PRE3D mm':>9s} {'mean':>8s} {'worst seed':>11s} {'farthest':>9s} "
          f"{'given true dots':>16s}")
    table = []
    with ProcessPoolExecutor(args.workers) as pool:
        for name in names:
            rows = np.array(list(pool.map(run, [name] * len(seeds), seeds, [args.poses] * len(seeds))))
            figures = summary(rows)
            print(f"{name:36s} {figures[0]:8.1f} {figures[1]:9.3f} {figures[2]:8.3f} {figures[3]:11.3f} "
                  f"{figures[4]:9.3f} {figures[5]:16.3f}", flush=True)
            table.append([name, f"{figures[0]:.1f}", *(f"{f:.3f}" for f in figures[1:])])
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, table))}")


if __name__ == "__main__":
    main()
