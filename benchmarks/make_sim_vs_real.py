"""Side-by-side picture for the README: a real PLUS fCal frame next to the twin's view of the
default phantom from one calibration pose, at ``bench`` (the default level) and at ``realistic``.

All are resampled to the real frame's pixel spacing (0.078 mm/px) so they share one physical
scale; 5 mm ticks on the left edge of each panel. Writes docs/img/sim_vs_real.png.

Run: .venv/bin/python benchmarks/make_sim_vs_real.py
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import SimpleITK as sitk

from probecal.core.acquisition.plan import calibration_plan
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.ur3 import closest_ik
from probecal.core.twin.scanner import twin_scanner

ROOT = Path(__file__).resolve().parent.parent

PLUS_IMAGES = plus_data_dir() / "TestImages"
REAL = PLUS_IMAGES / "fCal_Test_Calibration_3NWires.igs.mha"
REAL_FRAME = 94
REAL_SPACING_MM = 0.078  # PLUS ApproximateSpacingMmPerPixel for this recording
REAL_ORIGIN_ROW = -5  # the transducer origin lies 5 px above row 0 (Image->TransducerOriginPixel)
REAL_COLS = (164, 655)  # the beam-formed region, 491 px = 38.3 mm
DEPTH_MM = 47.0
OUT = ROOT / "docs" / "img" / "sim_vs_real.png"


def real_panel() -> np.ndarray:
    """The real frame cropped to the ultrasound region, from the probe face to DEPTH_MM."""
    frames = sitk.GetArrayFromImage(sitk.ReadImage(str(REAL)))
    rows = int(round(DEPTH_MM / REAL_SPACING_MM))
    frame = frames[REAL_FRAME]
    top = np.zeros((-REAL_ORIGIN_ROW, REAL_COLS[1] - REAL_COLS[0]), np.uint8)
    return np.vstack([top, frame[: rows + REAL_ORIGIN_ROW, REAL_COLS[0] : REAL_COLS[1]]])


def sim_panel(level: str, seed: int = 3, pose: int = 4) -> np.ndarray:
    """The twin's frame of the default phantom at one pose of a calibration plan."""
    scanner = twin_scanner(seed, level)
    twin = scanner.twin
    reported = calibration_plan(twin.nominal, 10, seed=seed).poses[pose]
    actual = twin.actual_tool_to_base(reported, closest_ik(reported, HOME_JOINTS))
    frame, _ = scanner.calibration_frame(actual, np.random.default_rng(seed))
    sx, sy = twin.pixel_spacing_mm
    size = (round(twin.probe.width_mm / REAL_SPACING_MM), round(twin.probe.height_px * sy / REAL_SPACING_MM))
    resized = cv2.resize(frame, size, interpolation=cv2.INTER_LINEAR)
    return resized[: int(round(DEPTH_MM / REAL_SPACING_MM))]


def framed(img: np.ndarray, caption: str) -> np.ndarray:
    """Pad a panel, add 5 mm depth ticks on its left and a caption above it."""
    pad = np.full((img.shape[0] + 40, img.shape[1] + 20), 40, np.uint8)
    pad[30:-10, 10:-10] = img
    for k in range(0, int(DEPTH_MM) + 1, 5):
        y = 30 + int(round(k / REAL_SPACING_MM))
        cv2.line(pad, (0, y), (7 if k % 10 else 9, y), 200, 1)
    cv2.putText(pad, caption, (10, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 230, 1, cv2.LINE_AA)
    return pad


def main() -> None:
    panels = [framed(real_panel(), "real: PLUS fCal, L14-5 in water"),
              framed(sim_panel("bench"), "twin: bench (default)"),
              framed(sim_panel("realistic"), "twin: realistic, same pose")]
    height = max(p.shape[0] for p in panels)
    gap = np.full((height, 6), 40, np.uint8)
    padded = [np.pad(p, ((0, height - p.shape[0]), (0, 0)), constant_values=40) for p in panels]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT), np.hstack([padded[0], gap, padded[1], gap, padded[2]]))
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
