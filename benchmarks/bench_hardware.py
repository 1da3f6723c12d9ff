"""The real robot path (issue target): a 60-pose calibration sweep on ``probecal ursim`` through the
real ur_rtde client, calibrated and compared with the twin's truth and with the same sweep on the
in-process simulated robot.

Run: .venv/bin/python benchmarks/bench_hardware.py [--seeds 3] [--poses 60] [--time-scale 1]
(``--time-scale 1``, the default, runs the controller in real time.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from probecal.core.geometry.transforms import transform_error
from probecal.core.io.session import read_manifest

PROBECAL = Path(sys.executable).parent / "probecal"
HOST = "127.0.0.2"


def run(*args) -> subprocess.CompletedProcess:
    result = subprocess.run([str(PROBECAL), *map(str, args)], capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"probecal {' '.join(map(str, args))} failed: {result.stderr.strip()}")
    return result


def calibrate(session: Path) -> tuple[float, float, float, float]:
    """(translation mm, rotation deg) error against truth, FRE mm and the worst spacing error %."""
    run("calibrate", session, "--out", session / "calibration.json")
    calibration = json.loads((session / "calibration.json").read_text())
    truth = json.loads((session / "truth.json").read_text())
    dt, dr = transform_error(np.array(calibration["image_to_tool_rigid"]), np.array(truth["image_to_tool_rigid"]))
    spacing = max(abs(a / b - 1) for a, b in zip(calibration["pixel_spacing_mm"], truth["pixel_spacing_mm"])) * 100
    return dt, dr, calibration["metrics"]["fre_mm"], spacing


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--time-scale", type=float, default=1.0)
    args = parser.parse_args()
    rows = {"ursim + ur_rtde": [], "in-process robot": []}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for seed in range(args.seeds):
            ursim = subprocess.Popen([str(PROBECAL), "ursim", "--host", HOST, "--time-scale", str(args.time_scale),
                                      "--seed", str(seed)],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            try:
                ursim.stdout.readline()  # "URSim ... listening"
                started = time.monotonic()
                run("sweep", "calibration", tmp / f"ur{seed}", "--robot", f"ur:{HOST}", "--poses", args.poses,
                    "--seed", seed)
                wall = time.monotonic() - started
            finally:
                ursim.terminate()
                ursim.wait(10)
            plan = read_manifest(tmp / f"ur{seed}").plan or {}
            estimate = plan["estimated_robot_time_s"] / plan["poses"]
            stamps = [json.loads(line)["timestamp"] for line in (tmp / f"ur{seed}" / "records.jsonl").open()]
            per_pose = (stamps[-1] - stamps[0]) / (len(stamps) - 1) / args.time_scale
            print(f"seed {seed}: {len(stamps)} frames through ur_rtde, {wall:.1f} s wall-clock in all at time scale "
                  f"{args.time_scale}; {per_pose:.2f} s of robot time per pose between frames (plan estimate "
                  f"{estimate:.2f} s)")
            rows["ursim + ur_rtde"].append(calibrate(tmp / f"ur{seed}"))
            run("sweep", "calibration", tmp / f"sim{seed}", "--robot", "sim", "--time-scale", 0, "--poses", args.poses,
                "--seed", seed)
            rows["in-process robot"].append(calibrate(tmp / f"sim{seed}"))
    for name, values in rows.items():
        a = np.array(values)
        print(f"{name:17s}: image_to_tool_rigid error {a[:, 0].mean():.3f} mm / {a[:, 1].mean():.3f} deg "
              f"(worst {a[:, 0].max():.3f} mm / {a[:, 1].max():.3f} deg), FRE {a[:, 2].mean():.3f} mm, "
              f"spacing error {a[:, 3].mean():.3f} % over {len(a)} seeds")


if __name__ == "__main__":
    main()
