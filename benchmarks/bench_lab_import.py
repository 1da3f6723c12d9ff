"""A robot recording as a lab keeps it, end to end through the command line: a twin sweep of a
fine scanner (2001 x 1501 px frames, about 0.025 mm/px) written as JPEG files named as a lab's
script names them ("final (N).jpg") with its poses as stacked 3x4 matrices (MATLAB's
writematrix), then ``probecal import-frames`` and ``probecal calibrate --arm UR3`` (the phantom
pose solved, as on a robot). Prints the times, the frames found against the frames that show
every wire, and the image corners against the twin's truth.

Run: .venv/bin/python benchmarks/bench_lab_import.py [--seeds 2] [--poses 230] [--write-docs]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.result import load_calibration
from probecal.core.calibration.uncertainty import image_corners_px
from probecal.core.geometry.probe import LinearProbe
from probecal.core.geometry.transforms import transform_points

PROBECAL = Path(sys.executable).parent / "probecal"
WIDTH, HEIGHT = 1501, 2001
TABLE = ("seed", "import (s)", "calibrate (s)", "image corners from the truth, mean (max), mm", "bound (mm)")


def run(*args) -> float:
    """Wall-clock seconds of one probecal command; exits on failure."""
    start = time.perf_counter()
    result = subprocess.run([str(PROBECAL), *map(str, args)], capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"probecal {args[0]} failed: {result.stderr.strip()}")
    return time.perf_counter() - start


def lab_recording(session, folder: Path) -> Path:
    """The sweep's frames as JPEG files and its poses as stacked 3x4 matrices; the pose table."""
    frames = folder / "frames"
    frames.mkdir(parents=True)
    rows = []
    for i, record in enumerate(session.records):
        cv2.imwrite(str(frames / f"final ({i + 1}).jpg"), session.image(i), [cv2.IMWRITE_JPEG_QUALITY, 95])
        rows.extend(record.tool_to_base[:3])
    table = folder / "poses.csv"
    np.savetxt(table, np.array(rows), delimiter=",", fmt="%.10g")
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--poses", type=int, default=230)
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    probe = LinearProbe(width_px=WIDTH, height_px=HEIGHT)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            folder = Path(tmp) / f"lab{seed}"
            twin = simulate_calibration(folder / "twin", n_poses=args.poses, seed=seed, noise="bench", probe=probe)
            table = lab_recording(twin, folder)
            sx, sy = twin.probe.nominal_spacing_mm
            imported = folder / "imported"
            import_s = run("import-frames", folder / "frames", "--poses", table, imported, "--spacing", sx, sy)
            calibrate_s = run("calibrate", imported, "--arm", "UR3")
            calibration = load_calibration(imported / "calibration.json")
            truth = twin.truth()
            whole = sum(all(m is not None and None not in m for m in f["markers_px"]) for f in truth["frames"])
            used = calibration.metrics["frames_used"]
            rejected = calibration.metrics["rejected_frames"]
            found = len(twin) - sum("pattern not found" in why for why in rejected.values())
            corners = np.column_stack([image_corners_px(twin.image_size), np.zeros(4)])
            error = np.linalg.norm(transform_points(calibration.image_to_tool, corners)
                                   - transform_points(np.array(truth["image_to_tool"]), corners), axis=1)
            print(f"seed {seed}: {len(twin)} JPEG frames of {WIDTH}x{HEIGHT} px at {sx:.4f} x {sy:.4f} mm/px; "
                  f"import-frames {import_s:.1f} s, calibrate {calibrate_s:.1f} s (target <= 10 s); pattern found "
                  f"in {found} frames of the {whole} that show every wire ({used} used); image corners "
                  f"{error.mean():.3f} mm mean, {error.max():.3f} max from the truth, bound "
                  f"+-{calibration.metrics['corner_error_95_mm']:.2f} mm")
            rows.append([str(seed), f"{import_s:.1f}", f"{calibrate_s:.1f}", f"{error.mean():.3f} ({error.max():.3f})",
                         f"±{calibration.metrics['corner_error_95_mm']:.2f}"])
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, rows))}")


if __name__ == "__main__":
    main()
