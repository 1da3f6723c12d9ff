"""Would another default calibration plan pin the calibration down better in the same UR3 time?
(issue 31, item 5)

On twin ``bench`` seeds, the robot's way (own segmenter, phantom pose solved, default method),
for the default plan and for plans that tilt as the thesis did, reach deeper or take more poses: the image
corners against the truth (mean of the four and the farthest, mm), the 95 % bound and whether it
covers the truth, and the UR3's estimated time for the plan.

Run: .venv/bin/python benchmarks/bench_plan.py [--seeds 4] [--first-seed 0]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.plan import THESIS_RANGES, PoseRanges
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.result import load_calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distances_mm, image_corners_px
from probecal.core.errors import InputError

DEFAULT = PoseRanges()
PLANS: dict[str, tuple[PoseRanges, int]] = {
    "default (+-22/22/15 deg, +-10/10/3 mm, 60 poses)": (DEFAULT, 60),
    "the thesis's (+-15 deg about every axis)": (THESIS_RANGES, 60),
    "more depth (+-8 mm along z)": (PoseRanges((10.0, 10.0, 8.0), DEFAULT.rotation_deg), 60),
    "more poses (90)": (DEFAULT, 90),
}


def run(name: str, seed: int) -> dict:
    """One plan on one seed: corners against the truth, the bound, the UR3 time."""
    ranges, poses = PLANS[name]
    with tempfile.TemporaryDirectory() as tmp:
        try:
            session = simulate_calibration(Path(tmp) / "s", n_poses=poses, seed=seed, noise="bench", ranges=ranges)
            calibration = calibrate_session(session, segment_session(session)).calibration
        except (InputError, ValueError) as exc:
            return {"name": name, "seed": seed, "failed": str(exc)}
        true = load_calibration(session.path / "truth.json")
        corners = corner_distances_mm(calibration, true, image_corners_px(session.image_size))
        return {"name": name, "seed": seed, "mean": float(corners.mean()), "farthest": float(corners.max()),
                "bound": calibration.metrics["corner_error_95_mm"], "time": session.manifest.robot_time_s}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=0)
    args = parser.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    jobs = [(name, seed) for name in PLANS for seed in seeds]
    with ProcessPoolExecutor(max_workers=2) as pool:
        rows = list(pool.map(run, *zip(*jobs)))
    print(f"twin bench, seeds {seeds.start}-{seeds.stop - 1}, the robot's way: image corners against the truth (mm), "
          "the 95 % bound, the UR3's estimated time for the plan")
    for name in PLANS:
        done = [r for r in rows if r["name"] == name and "failed" not in r]
        failed = [f"seed {r['seed']}: {r['failed']}" for r in rows if r["name"] == name and "failed" in r]
        if done:
            mean, farthest = np.mean([r["mean"] for r in done]), max(r["farthest"] for r in done)
            covered = sum(r["bound"] >= r["farthest"] for r in done)
            print(f"  {name}: corners {mean:.3f} mean of four, farthest up to {farthest:.3f}; bound median "
                  f"{np.median([r['bound'] for r in done]):.3f}, covers {covered} of {len(done)}; UR3 "
                  f"{np.mean([r['time'] for r in done]):.0f} s")
        for line in failed:
            print(f"  {name}: {line}")


if __name__ == "__main__":
    main()
