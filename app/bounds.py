"""The bounds of every number a user gives, on the command line or in the console's fields: one
definition for both, so that no value asks for more than a probe, a robot or a scan can have.

The console's fields are checked on the server where they are used, not only in the page: a page
can send any value over its websocket, as a buggy page or a mistyped value could.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass

from probecal.core.errors import InputError
from probecal.core.geometry import probe
from probecal.core.io.jsonio import PIXEL_SPACING_MM


@dataclass(frozen=True)
class Bound:
    """A number from ``low`` to ``high`` ``unit``, finite, and whole when ``whole``."""

    low: float
    high: float
    unit: str = ""
    whole: bool = False

    def _refusal(self, value: object, shown: str) -> str | None:
        """Why ``value`` (written ``shown``) is out of bounds (None: it is within them)."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{shown} is not a number"
        if isinstance(value, float) and not math.isfinite(value):  # an int is finite, however large
            return f"{shown} is not a finite number"
        if self.whole and value != int(value):
            return f"{shown} is not a whole number"
        if not self.low <= value <= self.high:
            return f"{shown} is not within {self.low:g} to {self.high:g}{self.unit}"
        return None

    def check(self, value: object, name: str) -> float:
        """A field's ``value`` (int when ``whole``); InputError naming the field ``name`` when it is
        out of bounds."""
        shown = f"{value:g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else repr(value)
        refusal = self._refusal(value, shown)
        if refusal is not None:
            raise InputError(None, f"{name}: {refusal}")
        assert isinstance(value, (int, float))
        return int(value) if self.whole else float(value)

    @property
    def argument(self) -> Callable[[str], float]:
        """The option's argparse type: the text as a number within the bounds."""
        def number(text: str) -> float:
            value = int(text) if self.whole else float(text)  # ValueError: argparse says "invalid number"
            refusal = self._refusal(value, text)
            if refusal is not None:
                raise argparse.ArgumentTypeError(refusal)
            return value
        number.__name__ = "whole number" if self.whole else "number"  # argparse's word for text that is none
        return number


PORT = Bound(0, 65535, " (0: a free port)", whole=True)
SEED = Bound(0, 2**32 - 1, whole=True)
POSES = Bound(1, 1000, " poses", whole=True)
FRAMES = Bound(1, 1000, " frames", whole=True)
IMAGE_PX = Bound(probe.IMAGE_PX.low, probe.IMAGE_PX.high, probe.IMAGE_PX.unit, whole=True)
LENGTH_MM = Bound(0.1, 1000, " mm")
PROBE_DEPTH_MM = Bound(probe.DEPTH_MM.low, probe.DEPTH_MM.high, probe.DEPTH_MM.unit)
DEPTH_MM = Bound(probe.START_DEPTH_MM.low, probe.START_DEPTH_MM.high, probe.START_DEPTH_MM.unit)
VIEWS = Bound(2, 8, " views", whole=True)
"""The wrist angles a volume sweep's passes are swept from for a self-check: two compare (the
default, 0 and 180 deg), and 8 leaves room for every quarter turn with and without a tilt; each
view sweeps every pass again, so their number multiplies the frames."""
SECONDS = Bound(-10, 10, " s")
PIXEL_SIZE = Bound(*PIXEL_SPACING_MM, " mm")
TOLERANCE_MM = Bound(0.01, 100, " mm")
SPEED = Bound(0.01, 10, " of the UR default")
POSE_RANGE_MM = Bound(0, 50, " mm")
POSE_RANGE_DEG = Bound(0, 45, " deg")
