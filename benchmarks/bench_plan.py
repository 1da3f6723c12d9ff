"""Would another default calibration plan pin the calibration down better in the same UR3 time?
(issue 31, item 5)

On twin ``bench`` seeds, the robot's way (own segmenter, phantom pose solved, default method),
for the default plan and for plans that tilt as the thesis did, reach deeper or take more poses: the image
corners against the truth (mean of the four and the farthest, mm), the 95 % bound and whether it
covers the truth, and the UR3's estimated time for the plan.

Run: .venv/bin/python benchmarks/bench_plan.py [--seeds 4] [--first-seed 0] [--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.plan import THESIS_RANGES, PoseRanges
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.result import load_calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distances_mm, image_corners_px
from probecal.core.errors import InputError

DEFAULT = PoseRanges()
DEFAULT_PLAN = "the default: ±22° about the two horizontal axes, ±15° about z, 60 poses"
PLANS: dict[str, tuple[PoseRanges, int]] = {
    DEFAULT_PLAN: (DEFAULT, 60),
    "the thesis's: ±15° about every axis, 60 poses": (THESIS_RANGES, 60),
    "more depth: ±8 mm along z (the default's tilts)": (PoseRanges((10.0, 10.0, 8.0), DEFAULT.rotation_deg), 60),
    "more poses: 90 (the default's tilts)": (DEFAULT, 90),
}
TABLE = ("plan", "corners, mean of four (mm)", "farthest (mm)", "bound, median (mm)", "bound covers", "UR3 time")


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


def summary(done: list[dict]) -> dict[str, float]:
    """One plan over the seeds it calibrated: corners, bound and how often it covers, UR3 time."""
    return {"mean": float(np.mean([r["mean"] for r in done])), "farthest": max(r["farthest"] for r in done),
            "bound": float(np.median([r["bound"] for r in done])),
            "covered": sum(r["bound"] >= r["farthest"] for r in done),
            "time": float(np.mean([r["time"] for r in done]))}


def table_row(name: str, done: list[dict], failed: int) -> list[str]:
    """The plan's row of the evidence table; the default plan in bold."""
    label = f"**{name}**" if name == DEFAULT_PLAN else name
    label += f" ({failed} seeds failed)" if failed else ""
    if not done:
        return [label, "–", "–", "–", "–", "–"]
    s = summary(done)
    return [label, f"{s['mean']:.3f}", f"{s['farthest']:.3f}", f"{s['bound']:.3f}", f"{s['covered']} of {len(done)}",
            f"{s['time']:.0f} s"]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    jobs = [(name, seed) for name in PLANS for seed in seeds]
    with ProcessPoolExecutor(max_workers=2) as pool:
        rows = list(pool.map(run, *zip(*jobs)))
    print(f"twin bench, seeds {seeds.start}-{seeds.stop - 1}, the robot's way: image corners against the truth (mm), "
          "the 95 % bound, the UR3's estimated time for the plan")
    table = []
    for name in PLANS:
        done = [r for r in rows if r["name"] == name and "failed" not in r]
        failed = [f"seed {r['seed']}: {r['failed']}" for r in rows if r["name"] == name and "failed" in r]
        if done:
            s = summary(done)
            print(f"  {name}: corners {s['mean']:.3f} mean of four, farthest up to {s['farthest']:.3f}; bound median "
                  f"{s['bound']:.3f}, covers {s['covered']} of {len(done)}; UR3 {s['time']:.0f} s")
        for line in failed:
            print(f"  {name}: {line}")
        table.append(table_row(name, done, len(failed)))
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, table))}")


if __name__ == "__main__":
    main()
