"""Temporal calibration (issue 17): the image latency measured by ``core.temporal`` against the
answers that are known.

- PLUS's water-tank recording (a probe moved up and down over the tank floor, video and tracker
  in two buffers): the latency against PLUS's ``TrackerLagSec`` (image latency = -TrackerLagSec),
  the same recording with its video timestamps moved by known amounts (the latency must move by
  the same amount), each third of the recording alone (blocks of consecutive frames: the
  estimate must not hang on one stretch of the motion), and the frames perturbed as in
  ``bench_real_segmentation.py`` (gain, gamma, speckle, blur, motion) or with a frame grabber's
  overlay burnt in (a text band and a depth scale).
- The twin's continuous calibration sweep (``simulate calibration --motion continuous``) with an
  unknown latency drawn between 20 and 150 ms: the latency ``probecal calibrate`` measures on the
  up-and-down motion against the truth, the calibrated ``image_to_tool`` against the truth, and
  the UR3 time of the whole procedure, beside the stop-and-go sweep of the same seed; at the
  ``realistic`` level with the latency and 2 ms of jitter added (the temporal errors alone) and
  at ``bench`` (every bench error: robot kinematics, phantom tolerance, slice thickness).
- A continuous volume sweep at 20 mm/s on a rig whose images run 80 ms late, reconstructed with
  the calibration (and latency) its own continuous calibration sweep measured, against the same
  on a latency-free rig: the mean surface error to the CAD model must agree within 0.05 mm; the
  80 ms sweep reconstructed as recorded (the latency ignored) shows what is at stake.

Run: .venv/bin/python benchmarks/bench_temporal.py [--seeds 6] [--poses 60] [--volume-seeds 3] [--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_real_segmentation import PERTURBATIONS
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.solve import segment_and_calibrate
from probecal.core.geometry.transforms import transform_error
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.temporal.echo import floor_echo_rows
from probecal.core.temporal.lag import estimate_latency, principal_motion
from probecal.core.temporal.plusbuffers import PlusBuffers, plus_latency, read_plus_buffers
from probecal.core.twin.levels import LEVELS
from probecal.core.volume.cad import session_cad_target
from probecal.core.volume.reconstruct import reconstruct_session

SHIFTS_S = (-0.1, -0.03, 0.02, 0.05, 0.15)
TABLE = ("recording", "probecal's image latency", "the truth, or PLUS's")
WATER_TANK = "PLUS's water-tank buffers (video and tracker)"
PERTURBED = (*(n for n in PERTURBATIONS if n not in ("as recorded", "crop 10 %", "one dot erased")), "overlay")
TWIN_ERRORS = {"realistic": " with 2 ms of jitter", "bench": ""}


def water_tank() -> list[list[str]]:
    """Print the water tank's latencies against PLUS's; the rows of :data:`TABLE`."""
    images = plus_data_dir() / "TestImages"
    video = images / "WaterTankBottomTranslationVideoBuffer.igs.mha"
    tracker = images / "WaterTankBottomTranslationTrackerBuffer-trimmed.igs.mha"
    lag = ET.parse(images / "TemporalCalibrationResultsBaseline.xml").getroot().get("TrackerLagSec")
    plus_s = -float(lag)
    start = time.perf_counter()
    found = plus_latency(video, tracker)
    took = time.perf_counter() - start
    print(f"PLUS water tank: image latency {found.image_latency_s * 1000:.2f} ms "
          f"(+- {found.std_error_s * 1000:.2f} ms standard error), PLUS {plus_s * 1000:.2f} ms "
          f"(-TrackerLagSec): off by {(found.image_latency_s - plus_s) * 1000:+.2f} ms (target within 2 ms); "
          f"correlation {found.correlation:+.4f}, residual {found.residual:.3f}, peak half-width "
          f"{found.peak_halfwidth_s * 1000:.0f} ms, {found.frames_used} frames used, {found.frames_rejected} "
          f"rejected; {took:.2f} s")
    plus = f"PLUS: {plus_s * 1000:+.1f} ms"
    buffers = read_plus_buffers(video, tracker)
    return [[WATER_TANK, f"{found.image_latency_s * 1000:+.1f} ms (± {found.std_error_s * 1000:.1f})",
             f"PLUS: `TrackerLagSec = {lag}`, so {plus_s * 1000:+.1f} ms"],
            shifted(video, tracker, found.image_latency_s),
            ["the same, each third alone", thirds(buffers, plus_s), plus],
            [f"the same, frames perturbed: {', '.join(PERTURBED)}", perturbed(buffers, plus_s), plus]]


def shifted(video: Path, tracker: Path, latency_s: float) -> list[str]:
    """Print how far the latency moves with the video timestamps moved by each of SHIFTS_S; a row."""
    errors = []
    for shift in SHIFTS_S:
        moved = plus_latency(video, tracker, video_shift_s=shift).image_latency_s - latency_s
        errors.append(moved - shift)
        print(f"  video timestamps moved {shift * 1000:+5.0f} ms: latency moved {moved * 1000:+8.2f} ms "
              f"(error {errors[-1] * 1000:+.3f} ms, target within 2 ms)")
    return [f"the same, video timestamps moved by {min(SHIFTS_S) * 1000:+.0f} to {max(SHIFTS_S) * 1000:+.0f} ms",
            f"moves by the shift within {max(np.abs(errors).max() * 1000, 0.001):.3f} ms", "the shift"]


def latency_range(latencies_s: list[float]) -> str:
    """The latencies found (s) as a range in ms, or one value when they agree to 0.1 ms."""
    low, high = f"{min(latencies_s) * 1000:+.1f}", f"{max(latencies_s) * 1000:+.1f}"
    return f"{low} ms every time" if low == high else f"{low} to {high} ms"


def thirds(buffers: PlusBuffers, plus_s: float) -> str:
    """Print the latency of each third of the recording alone; their range."""
    motion = principal_motion(buffers.positions_mm)
    echo = floor_echo_rows(buffers.frames)
    found = []
    for k, block in enumerate(np.array_split(np.arange(len(echo)), 3)):
        part = np.full(len(echo), np.nan)
        part[block] = echo[block]
        est = estimate_latency(buffers.frame_times, part, buffers.pose_times, motion)
        found.append(est.image_latency_s)
        print(f"  block {k + 1} of 3 (frames {block[0]}-{block[-1]}): {est.image_latency_s * 1000:.2f} ms "
              f"(+- {est.std_error_s * 1000:.2f}), off PLUS by {(est.image_latency_s - plus_s) * 1000:+.2f} ms")
    return latency_range(found)


def perturbed(buffers: PlusBuffers, plus_s: float) -> str:
    """Print the latency with the frames perturbed each way in PERTURBED; their range."""
    rng = np.random.default_rng(0)
    overlay = np.zeros_like(buffers.frames[0])
    overlay[20:60, 40:400] = 255  # a frame grabber's text band and a depth scale down one side
    overlay[60:600:25, 790:805] = 255
    perturbations = {**PERTURBATIONS, "overlay": lambda im, t, rng: (np.maximum(im, overlay), t)}
    motion = principal_motion(buffers.positions_mm)
    found = []
    for name in PERTURBED:
        frames = np.stack([perturbations[name](f, None, rng)[0] for f in buffers.frames])
        est = estimate_latency(buffers.frame_times, floor_echo_rows(frames), buffers.pose_times, motion)
        found.append(est.image_latency_s)
        print(f"  frames {name:12s}: {est.image_latency_s * 1000:.2f} ms, off PLUS by "
              f"{(est.image_latency_s - plus_s) * 1000:+.2f} ms, {est.frames_rejected} frames rejected")
    return latency_range(found)


def twin_run(job: tuple[str, int, str, int]) -> tuple:
    """(true latency s, measured latency s or None, image_to_tool error mm, deg, UR3 time s, frames)
    of one simulated sweep and its calibration."""
    noise, seed, motion, poses = job
    latency = float(np.random.default_rng([seed, 17]).uniform(0.02, 0.15))
    level = LEVELS[noise]
    if noise == "realistic":  # the temporal errors alone: latency and 2 ms of timestamp jitter
        level = replace(level, setup=replace(level.setup, timestamp_jitter_s=0.002))
    with tempfile.TemporaryDirectory() as tmp:
        session = simulate_calibration(Path(tmp) / "s", n_poses=poses, seed=seed, noise=level, motion=motion,
                                       image_latency_s=latency)
        calibration = segment_and_calibrate(session).calibration
        truth = np.array(session.truth()["image_to_tool_rigid"])
        dt, dr = transform_error(calibration.image_to_tool_rigid, truth)
        return latency, calibration.image_latency_s, dt, dr, session.manifest.robot_time_s, len(session)


def twin(seeds: int, poses: int) -> list[list[str]]:
    """Print each twin seed's latency and calibration, continuous and stop-and-go; the rows of
    :data:`TABLE`."""
    jobs = [(noise, seed, motion, poses) for noise in ("realistic", "bench") for seed in range(seeds)
            for motion in ("continuous", "stop")]
    with ProcessPoolExecutor(2) as pool:
        runs = dict(zip(jobs, pool.map(twin_run, jobs)))
    print(f"\ntwin: {poses} poses, latency drawn between 20 and 150 ms per seed (realistic: with 2 ms of jitter)")
    print(f"{'level':10s} {'seed':>4s} {'true ms':>8s} {'found ms':>9s} {'error ms':>9s}   "
          f"{'continuous mm / deg':>20s} {'UR3 s':>6s} {'frames':>6s}   {'stop-and-go mm / deg':>21s} {'UR3 s':>6s}")
    rows = []
    for noise in ("realistic", "bench"):
        errors, within = [], []
        for seed in range(seeds):
            latency, found, dt, dr, robot_s, frames = runs[(noise, seed, "continuous", poses)]
            _, _, sdt, sdr, stop_s, _ = runs[(noise, seed, "stop", poses)]
            errors.append((found - latency) * 1000)
            within.append(dt <= 0.3 and dr <= 0.15)
            print(f"{noise:10s} {seed:4d} {latency * 1000:8.1f} {found * 1000:9.2f} {errors[-1]:+9.2f}   "
                  f"{dt:11.3f} / {dr:6.3f} {robot_s:6.1f} {frames:6d}   {sdt:12.3f} / {sdr:6.3f} {stop_s:6.1f}")
        print(f"{noise}: latency error max {np.abs(errors).max():.2f} ms (target within 2 ms), image_to_tool within "
              f"0.3 mm / 0.15 deg in {sum(within)} of {seeds} seeds")
        rows.append([f"the twin's continuous calibration sweeps, `{noise}`{TWIN_ERRORS[noise]} ({seeds} seeds)",
                     f"within {np.abs(errors).max():.2f} ms of the truth", "the truth, drawn between 20 and 150 ms"])
    return rows


def volume_run(job: tuple[str, int, float]) -> tuple[float, float | None, float, float]:
    """(measured latency s, mean surface error mm, p95 mm, mean error with the latency ignored
    mm) of one rig: a continuous calibration sweep, then a continuous volume sweep at 20 mm/s."""
    noise, seed, latency = job
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        calibration = segment_and_calibrate(simulate_calibration(
            tmp / "cal", n_poses=60, seed=seed, noise=noise, motion="continuous", image_latency_s=latency)).calibration
        sweep = simulate_volume(tmp / "vol", seed=seed, noise=noise, motion="continuous", image_latency_s=latency)
        cad = session_cad_target(sweep)
        paired = reconstruct_session(sweep, calibration, tmp / "r", cad=cad).report
        ignored = reconstruct_session(sweep, replace(calibration, image_latency_s=None), tmp / "i", cad=cad).report
        return (calibration.image_latency_s, paired["surface_mean_mm"], paired["surface_p95_mm"],
                ignored["surface_mean_mm"])


def volume(seeds: int) -> list[list[str]]:
    """Print each seed's surface error on the 80 ms and the latency-free rig; the rows of
    :data:`TABLE` (the latency the 80 ms rig's calibration sweep measured)."""
    jobs = [(noise, seed, latency) for noise in ("realistic", "bench") for seed in range(seeds)
            for latency in (0.0, 0.08)]
    with ProcessPoolExecutor(2) as pool:
        runs = dict(zip(jobs, pool.map(volume_run, jobs)))
    print("\nvolume sweeps at 20 mm/s, continuous, each rig calibrated by its own continuous sweep; surface error "
          "to the CAD model, mean / 95th percentile mm")
    print(f"{'level':10s} {'seed':>4s} {'latency-free rig':>20s} {'80 ms rig':>24s} {'difference':>11s} "
          f"{'80 ms, latency ignored':>23s}")
    rows = []
    for noise in ("realistic", "bench"):
        gaps, latencies = [], []
        for seed in range(seeds):
            _, free_mean, free_p95, _ = runs[(noise, seed, 0.0)]
            found, late_mean, late_p95, ignored = runs[(noise, seed, 0.08)]
            gaps.append(late_mean - free_mean)
            latencies.append(found)
            print(f"{noise:10s} {seed:4d} {free_mean:11.3f} / {free_p95:.3f} {late_mean:9.3f} / {late_p95:.3f} "
                  f"({found * 1000:.1f} ms) {gaps[-1]:+11.3f} {ignored:23.3f}")
        print(f"{noise}: the 80 ms rig's mean surface error within {np.abs(gaps).max():.3f} mm of the latency-free "
              f"rig's (target 0.05 mm)")
        rows.append([f"the twin's continuous calibration sweeps before a volume sweep, `{noise}` ({seeds} seeds)",
                     latency_range(latencies), "+80.0 ms"])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--volume-seeds", type=int, default=3)
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    rows = [*water_tank(), *twin(args.seeds, args.poses), *volume(args.volume_seeds)]
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, rows))}")


if __name__ == "__main__":
    main()
