"""Digital-twin figures: synthesis frames/s and the acquisition-plan duration estimate.

Run: .venv/bin/python benchmarks/bench_simulator.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from probecal.core.acquisition.plan import calibration_plan
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.robot.simulated import SimulatedRobot
from probecal.core.twin.bmode import BModeRenderer
from probecal.core.twin.twin import make_twin


def synthesis_fps(noise: str, n_frames: int = 200) -> float:
    """Frames/s for the live loop: robot pose -> true wire crossings -> B-mode frame."""
    twin = make_twin(0)
    plan = calibration_plan(twin.nominal, 60, seed=0)
    robot = SimulatedRobot(seed=0, time_scale=0.0)
    robot.connect()
    renderer = BModeRenderer(twin.probe, noise, 0)
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    for k in range(n_frames):
        robot.move_linear(plan.poses[k % len(plan.poses)])
        markers = twin.markers_px(robot.tool_to_base())
        renderer.render(markers[np.all(np.isfinite(markers), axis=1)], rng=rng)
    return n_frames / (time.perf_counter() - start)


def main() -> None:
    twin = make_twin(0)
    print(f"probe image {twin.probe.width_px}x{twin.probe.height_px} px, "
          f"true spacing {twin.probe.true_spacing_mm[0]:.4f} x {twin.probe.true_spacing_mm[1]:.4f} mm/px")
    for noise in ("none", "realistic", "harsh"):
        print(f"synthesis ({noise:9s}): {synthesis_fps(noise):7.1f} frames/s  (target >= 30)")
    for n in (30, 60, 120):
        t0 = time.perf_counter()
        plan = calibration_plan(twin.nominal, n, seed=0)
        took = time.perf_counter() - t0
        print(f"calibration plan, {n:3d} poses: estimated UR3 time {plan.duration_s:6.1f} s "
              f"({plan.duration_s / n:.2f} s/pose), planned in {took:.2f} s")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        session = simulate_calibration(Path(tmp) / "s", n_poses=60, seed=0, noise="realistic")
        took = time.perf_counter() - t0
    print(f"simulate calibration (60 poses, realistic, written to disk): {took:.2f} s, "
          f"{len(session) / took:.1f} frames/s end to end")


if __name__ == "__main__":
    main()
