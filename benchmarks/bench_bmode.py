"""Frames per second of the B-mode synthesiser for each noise level (design §4: at least 30 fps).

Twelve dots in four N layers at 10-40 mm plus the tank bottom, on the default 384x500 probe and on
an 820x616 one (the PLUS fCal frame size).

Run: .venv/bin/python benchmarks/bench_bmode.py
"""

from __future__ import annotations

import time

import numpy as np

from probecal.core.geometry.probe import LinearProbe
from probecal.core.twin.bmode import BModeRenderer
from probecal.core.twin.imaging import NOISE_LEVELS


def layout(probe: LinearProbe) -> np.ndarray:
    """(12, 2) dot pixels: four N layers at 10, 20, 30, 40 mm, outer wires 30 mm apart."""
    sx, sy = probe.true_spacing_mm
    left = probe.width_mm / 2 - 15.0
    dots = [
        (x / sx, depth / sy)
        for depth, ratio in zip((10.0, 20.0, 30.0, 40.0), (0.3, 0.55, 0.75, 0.4))
        for x in (left, left + 30.0 * ratio, left + 30.0)
    ]
    return np.array(dots)


def fps(renderer: BModeRenderer, dots: np.ndarray, tank_row: float, seconds: float = 2.0) -> float:
    renderer.render(dots, tank_bottom_row=tank_row)
    n, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        renderer.render(dots, tank_bottom_row=tank_row)
        n += 1
    return n / elapsed


def main() -> None:
    for probe in (LinearProbe(), LinearProbe(width_px=820, height_px=616)):
        dots = layout(probe)
        tank_row = 46.0 / probe.true_spacing_mm[1]
        for level in NOISE_LEVELS:
            start = time.perf_counter()
            renderer = BModeRenderer(probe, level, seed=0)
            setup = time.perf_counter() - start
            rate = fps(renderer, dots, tank_row)
            size = f"{probe.width_px}x{probe.height_px}"
            print(f"{size} {level:>9}: {rate:7.1f} frames/s  (setup {1000 * setup:.0f} ms)")


if __name__ == "__main__":
    main()
