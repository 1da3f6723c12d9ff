"""Temporal calibration (issue 17): the image latency measured by ``core.temporal`` against the
answers that are known.

- PLUS's water-tank recording (a probe moved up and down over the tank floor, video and tracker
  in two buffers): the latency against PLUS's ``TrackerLagSec`` (image latency = -TrackerLagSec),
  the same recording with its video timestamps moved by known amounts (the latency must move by
  the same amount), each third of the recording alone (blocks of consecutive frames: the
  estimate must not hang on one stretch of the motion), and the frames perturbed as in
  ``bench_real_segmentation.py`` (gain, gamma, speckle, blur, motion).

Run: .venv/bin/python benchmarks/bench_temporal.py
"""

from __future__ import annotations

import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
from bench_real_segmentation import PERTURBATIONS  # noqa: E402

import probecal.core  # noqa: E402, F401  (sets BLAS threads before numpy loads)
from probecal.core.io.plusdata import plus_data_dir  # noqa: E402
from probecal.core.temporal.echo import floor_echo_rows  # noqa: E402
from probecal.core.temporal.lag import estimate_latency, principal_motion  # noqa: E402
from probecal.core.temporal.plusbuffers import plus_latency, read_plus_buffers  # noqa: E402

SHIFTS_S = (-0.1, -0.03, 0.02, 0.05, 0.15)


def water_tank() -> None:
    images = plus_data_dir() / "TestImages"
    video = images / "WaterTankBottomTranslationVideoBuffer.igs.mha"
    tracker = images / "WaterTankBottomTranslationTrackerBuffer-trimmed.igs.mha"
    baseline = ET.parse(images / "TemporalCalibrationResultsBaseline.xml").getroot()
    plus_s = -float(baseline.get("TrackerLagSec"))
    start = time.perf_counter()
    found = plus_latency(video, tracker)
    took = time.perf_counter() - start
    print(f"PLUS water tank: image latency {found.image_latency_s * 1000:.2f} ms "
          f"(+- {found.std_error_s * 1000:.2f} ms standard error), PLUS {plus_s * 1000:.2f} ms "
          f"(-TrackerLagSec): off by {(found.image_latency_s - plus_s) * 1000:+.2f} ms (target within 2 ms); "
          f"correlation {found.correlation:+.4f}, residual {found.residual:.3f}, peak half-width "
          f"{found.peak_halfwidth_s * 1000:.0f} ms, {found.frames_used} frames used, {found.frames_rejected} "
          f"rejected; {took:.2f} s")
    for shift in SHIFTS_S:
        moved = plus_latency(video, tracker, video_shift_s=shift).image_latency_s - found.image_latency_s
        print(f"  video timestamps moved {shift * 1000:+5.0f} ms: latency moved {moved * 1000:+8.2f} ms "
              f"(error {(moved - shift) * 1000:+.3f} ms, target within 2 ms)")
    buffers = read_plus_buffers(video, tracker)
    motion = principal_motion(buffers.positions_mm)
    echo = floor_echo_rows(buffers.frames)
    thirds = np.array_split(np.arange(len(echo)), 3)
    for k, block in enumerate(thirds):
        part = np.full(len(echo), np.nan)
        part[block] = echo[block]
        est = estimate_latency(buffers.frame_times, part, buffers.pose_times, motion)
        print(f"  block {k + 1} of 3 (frames {block[0]}-{block[-1]}): {est.image_latency_s * 1000:.2f} ms "
              f"(+- {est.std_error_s * 1000:.2f}), off PLUS by {(est.image_latency_s - plus_s) * 1000:+.2f} ms")
    rng = np.random.default_rng(0)
    for name, perturb in PERTURBATIONS.items():
        if name in ("as recorded", "crop 10 %", "one dot erased"):
            continue
        frames = np.stack([perturb(f, None, rng)[0] for f in buffers.frames])
        est = estimate_latency(buffers.frame_times, floor_echo_rows(frames), buffers.pose_times, motion)
        print(f"  frames {name:12s}: {est.image_latency_s * 1000:.2f} ms, off PLUS by "
              f"{(est.image_latency_s - plus_s) * 1000:+.2f} ms, {est.frames_rejected} frames rejected")


def main() -> None:
    water_tank()


if __name__ == "__main__":
    main()
