"""A volume compounded while a sweep records it: the console's live view of the volume growing.

Frames go in as they are recorded, at the flange pose paired with them (``tool_to_base``, mm)
through a calibration's ``image_to_tool`` (pixels to tool mm); the lattice is fitted to the
plan's poses before the sweep starts, so it holds every frame the sweep can take.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from probecal.core.volume.compound import Compounder
from probecal.core.volume.grid import VolumeSettings, output_grid

LIVE_SETTINGS = VolumeSettings(spacing_mm=(0.5, 0.5, 0.5), interpolation="NEAREST_NEIGHBOR", compounding="MEAN",
                               fill_holes=False)
BRIGHT_LEVEL = 128
"""Voxels at least this bright (the display's half gray level: surfaces) are shown."""
MAX_POINTS = 60_000
REFRESH_S = 0.5
"""How often (s) the live view is redrawn while frames go in."""


class LiveVolume:
    """Frames compounded as they come (``insert``); ``due`` says when the view should be redrawn
    and ``points`` gives it the bright voxels (base frame, mm) and their gray levels."""

    def __init__(self, plan_tool_to_base: list[np.ndarray], image_to_tool: np.ndarray, image_size: tuple[int, int],
                 settings: VolumeSettings = LIVE_SETTINGS):
        self.image_to_tool = np.asarray(image_to_tool, float)
        grid = output_grid(replace(settings, fill_holes=False), image_size,
                           [pose @ self.image_to_tool for pose in plan_tool_to_base])
        self.compounder = Compounder(settings, grid)
        self._drawn_at = -np.inf

    @property
    def frames(self) -> int:
        return self.compounder.frames_inserted

    def insert(self, image: np.ndarray, tool_to_base: np.ndarray) -> None:
        self.compounder.insert(image, tool_to_base @ self.image_to_tool)

    def due(self) -> bool:
        """True at most every ``REFRESH_S``: time to redraw (and the clock is restarted)."""
        now = time.monotonic()
        if now - self._drawn_at < REFRESH_S:
            return False
        self._drawn_at = now
        return True

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The bright voxels so far: centres (N, 3) base mm and gray levels (N,) uint8."""
        return self.compounder.bright_voxels(BRIGHT_LEVEL, MAX_POINTS)
