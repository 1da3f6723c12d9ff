"""The volume's lattice and how it is compounded: PLUS's ``<VolumeReconstruction>`` settings, the
output grid fitted to the frames, and the compounded volume itself.

The volume lives in a "volume" frame (the robot base, or PLUS's ``Reference``), lengths in mm. A
grid's ``origin_mm`` is the centre of voxel (0, 0, 0); voxel (i, j, k) (x, y, z indices) is centred
at ``origin_mm + (i, j, k) * spacing_mm`` and is stored at ``voxels[k, j, i]``."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.io.deviceset import DeviceSet, plus_fan, plus_numbers
from probecal.core.io.limits import checked_bytes
from probecal.core.volume.fanangles import FanAutoDetect, detected_fan_angles

INTERPOLATIONS = ("NEAREST_NEIGHBOR", "LINEAR")
COMPOUNDINGS = ("MEAN", "MAXIMUM", "LATEST")
MIN_SPACING_MM = 0.001
COMPOUNDING_BYTES_PER_VOXEL = 16  # MEAN's complex64 moments, the uint8 result, hole filling's copies


def _triple(values: Iterable[float], what: str) -> tuple[float, float, float]:
    out = tuple(float(v) for v in values)
    if len(out) != 3:
        raise ValueError(f"{what} needs 3 values, got {len(out)}")
    return out


@dataclass(frozen=True)
class VolumeSettings:
    """How to compound (the PLUS ``<VolumeReconstruction>`` options that probecal honours).

    ``spacing_mm``: voxel size (x, y, z). ``extent`` (PLUS OutputExtent: inclusive voxel index
    ranges x0 x1 y0 y1 z0 z1) with ``origin_mm`` (PLUS OutputOrigin: the centre of voxel index
    (0, 0, 0), volume frame, mm; (0, 0, 0) if not given) fixes the grid; without an extent the grid
    is fitted to the frames. ``clip_origin_px``/``clip_size_px``: the pixel rectangle used, which
    like PLUS includes column ``x0 + width`` and row ``y0 + height`` (clamped to the image); None
    means the whole image. ``fan``: PLUS's fan-shaped clipping, applied besides the rectangle
    (None: none), its angles narrowed to each frame's content with ``fan_auto_detect`` (PLUS's
    EnableFanAnglesAutoDetect). ``stick_length``/``sticks_used``: PLUS STICK hole-filling parameters
    (StickLengthLimit, NumberOfSticksToUse), used when ``fill_holes``.
    """

    spacing_mm: tuple[float, float, float] = (0.5, 0.5, 0.5)
    origin_mm: tuple[float, float, float] | None = None
    extent: tuple[int, int, int, int, int, int] | None = None
    clip_origin_px: tuple[int, int] = (0, 0)
    clip_size_px: tuple[int, int] | None = None
    fan: Fan | None = None
    fan_auto_detect: FanAutoDetect | None = None
    interpolation: str = "NEAREST_NEIGHBOR"
    compounding: str = "MEAN"
    fill_holes: bool = False
    stick_length: int = 9
    sticks_used: int = 1

    def __post_init__(self) -> None:
        def store(name: str, value: object) -> None:  # normalise to tuples (the dataclass is frozen)
            object.__setattr__(self, name, value)

        spacing = _triple(self.spacing_mm, "spacing_mm")
        if not all(np.isfinite(spacing)) or min(spacing) < MIN_SPACING_MM:
            raise ValueError(f"voxel spacing must be at least {MIN_SPACING_MM} mm, got {spacing}")
        store("spacing_mm", spacing)
        if self.extent is not None:
            extent = tuple(int(v) for v in self.extent)
            if len(extent) != 6 or any(extent[2 * a + 1] < extent[2 * a] for a in range(3)):
                raise ValueError(f"extent must be x0 x1 y0 y1 z0 z1 with x0 <= x1 etc., got {self.extent}")
            store("extent", extent)
        elif self.origin_mm is not None:
            raise ValueError("an output origin needs an output extent (PLUS OutputExtent)")
        if self.origin_mm is not None:
            origin = _triple(self.origin_mm, "origin_mm")
            if not all(np.isfinite(origin)):
                raise ValueError(f"output origin must be finite, got {self.origin_mm}")
            store("origin_mm", origin)
        store("clip_origin_px", tuple(int(v) for v in self.clip_origin_px))
        if self.clip_size_px is not None:
            size = tuple(int(v) for v in self.clip_size_px)
            if len(size) != 2 or min(size) < 0:
                raise ValueError(f"clip rectangle size must be two non-negative numbers, got {self.clip_size_px}")
            store("clip_size_px", size)
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {self.interpolation!r}")
        if self.compounding not in COMPOUNDINGS:
            raise ValueError(f"compounding must be one of {COMPOUNDINGS}, got {self.compounding!r}")
        if self.stick_length < 3 or self.sticks_used < 1:
            raise ValueError("hole filling needs stick_length >= 3 and sticks_used >= 1")

    @classmethod
    def from_plus(
        cls, attributes: Mapping[str, str], hole_filling: Mapping[str, str] | None = None
    ) -> VolumeSettings:
        """Settings from PLUS ``<VolumeReconstruction>`` attributes (OutputSpacing, OutputOrigin,
        OutputExtent, ClipRectangleOrigin, ClipRectangleSize, FanAnglesDeg, FanOriginPixel,
        FanRadiusStartPixel, FanRadiusStopPixel (and their deprecated names FanAngles, FanOrigin,
        FanDepth), EnableFanAnglesAutoDetect with FanAnglesAutoDetectBrightnessThreshold and
        FanAnglesAutoDetectFilterRadiusPixel, Interpolation, CompoundingMode, FillHoles; others such as Optimization or
        NumberOfThreads are ignored; OutputOrigin counts only with OutputExtent) and, optionally, the
        attributes of a STICK ``<HoleFillingElement>``. Raises ValueError for malformed values."""

        numbers = functools.partial(plus_numbers, attributes)
        clip_size = numbers("ClipRectangleSize", 2, int)
        fan, auto_detect = plus_fan(attributes), None
        auto = attributes.get("EnableFanAnglesAutoDetect", "FALSE").upper()
        if auto not in ("TRUE", "FALSE"):
            raise ValueError(f"EnableFanAnglesAutoDetect must be TRUE or FALSE, got {auto!r}")
        if fan is not None and auto == "TRUE":
            brightness = numbers("FanAnglesAutoDetectBrightnessThreshold", 1)
            radius = numbers("FanAnglesAutoDetectFilterRadiusPixel", 1, int)
            auto_detect = FanAutoDetect(brightness[0] if brightness else FanAutoDetect.brightness,
                                        radius[0] if radius else FanAutoDetect.filter_radius_px)
        fill = attributes.get("FillHoles", "OFF").upper()
        if fill not in ("ON", "OFF"):
            raise ValueError(f"FillHoles must be ON or OFF, got {fill!r}")
        sticks = {}
        if hole_filling is not None:
            try:
                sticks = {
                    "stick_length": int(hole_filling.get("StickLengthLimit", cls.stick_length)),
                    "sticks_used": int(hole_filling.get("NumberOfSticksToUse", cls.sticks_used)),
                }
            except (ValueError, OverflowError):
                raise ValueError(f"malformed STICK hole filling element {dict(hole_filling)}")
        return cls(
            spacing_mm=numbers("OutputSpacing", 3) or cls.spacing_mm,
            origin_mm=numbers("OutputOrigin", 3) if "OutputExtent" in attributes else None,
            extent=numbers("OutputExtent", 6, int),
            clip_origin_px=numbers("ClipRectangleOrigin", 2, int) or (0, 0),
            clip_size_px=clip_size if clip_size and min(clip_size) > 0 else None,
            fan=fan,
            fan_auto_detect=auto_detect,
            interpolation=attributes.get("Interpolation", cls.interpolation).upper(),
            compounding=attributes.get("CompoundingMode", cls.compounding).upper(),
            fill_holes=fill == "ON",
            **sticks,
        )

    def kept_pixels(self, image: np.ndarray) -> np.ndarray | None:
        """(H, W) uint8, 1 where a pixel of ``image`` (uint8 (H, W), MF) lies in the fan (its
        angles narrowed to the frame's content when the fan auto-detects them); an empty array
        without a fan (the clip rectangle alone says which pixels count); None when auto-detection
        finds the frame blank (PLUS leaves it out)."""
        fan = self.fan
        if fan is None:
            return np.zeros((0, 0), np.uint8)
        if self.fan_auto_detect is not None:
            angles = detected_fan_angles(image, fan.origin_px, fan.radius_start_px, fan.radius_stop_px,
                                         fan.angles_deg, self.fan_auto_detect)
            if angles is None:
                return None
            fan = replace(fan, angles_deg=angles)
        return fan.mask(image.shape[1], image.shape[0]).astype(np.uint8)

    @property
    def fixed_fan(self) -> bool:
        """Whether every frame of one size keeps the same pixels (no fan-angle auto-detection)."""
        return self.fan is None or self.fan_auto_detect is None

    def clip_rectangle(self, width: int, height: int) -> tuple[int, int, int, int]:
        """Inclusive pixel bounds (x0, y0, x1, y1) of the clip rectangle in a width x height image.
        Raises ValueError if the rectangle misses the image."""
        x0, y0 = max(0, self.clip_origin_px[0]), max(0, self.clip_origin_px[1])
        x1, y1 = width - 1, height - 1
        if self.clip_size_px is not None:
            x1 = min(x1, self.clip_origin_px[0] + self.clip_size_px[0])
            y1 = min(y1, self.clip_origin_px[1] + self.clip_size_px[1])
        if x1 < x0 or y1 < y0:
            raise ValueError(f"the clip rectangle misses the {width}x{height} px image")
        return x0, y0, x1, y1


@dataclass(frozen=True)
class VolumeGrid:
    """A voxel lattice in the volume frame: ``origin_mm`` is the centre of voxel (0, 0, 0) (mm),
    ``spacing_mm`` the voxel size (x, y, z), ``shape`` the array shape (nz, ny, nx)."""

    origin_mm: tuple[float, float, float]
    spacing_mm: tuple[float, float, float]
    shape: tuple[int, int, int]

    @property
    def volume_to_index(self) -> np.ndarray:
        """4x4 mapping volume-frame mm to continuous voxel indices (x, y, z)."""
        out = np.diag([1.0 / s for s in self.spacing_mm] + [1.0])
        out[:3, 3] = -np.array(self.origin_mm) / np.array(self.spacing_mm)
        return out


@dataclass(frozen=True)
class Volume:
    """Compounded voxels, uint8 (nz, ny, nx), 0 where nothing was inserted. ``origin_mm`` is the
    centre of voxel (0, 0, 0) in the volume frame (mm), ``spacing_mm`` the voxel size (x, y, z)."""

    voxels: np.ndarray
    origin_mm: tuple[float, float, float]
    spacing_mm: tuple[float, float, float]


def valid_pose(image_to_volume: np.ndarray | None) -> bool:
    return (
        image_to_volume is not None
        and np.shape(image_to_volume) == (4, 4)
        and bool(np.all(np.isfinite(image_to_volume)))
    )


def output_grid(
    settings: VolumeSettings,
    image_size: tuple[int, int] | None = None,
    image_to_volume: Iterable[np.ndarray | None] = (),
) -> VolumeGrid:
    """The output lattice: from the settings' extent when given, else fitted to the frames.

    Fitting is PLUS's: the origin is the lowest corner, over all frames with a valid pose, of the
    clip rectangle of an ``image_size`` = (width, height) px image; the grid then has
    round(range / spacing) + 1 voxels per axis, the smallest grid holding the nearest voxel of every
    clipped pixel. (This reproduces PLUS's reference volumes, e.g. 147 x 106 x 105 voxels at origin
    (-74.52, 165.57, 29.07) mm for SpinePhantomFreehand.) Invalid poses (None, NaN) are skipped;
    ValueError if none is valid.
    """
    spacing = settings.spacing_mm
    if settings.extent is not None:
        first, last = settings.extent[0::2], settings.extent[1::2]
        origin = np.array(settings.origin_mm or (0.0, 0.0, 0.0)) + np.array(first, float) * np.array(spacing)
        return _checked_grid(tuple(origin.tolist()), spacing, [b - a + 1 for a, b in zip(first, last)])
    if image_size is None:
        raise ValueError("the image size is needed to fit the volume to the frames")
    x0, y0, x1, y1 = settings.clip_rectangle(*image_size)
    corners = np.array([[x0, y0, 0, 1], [x0, y1, 0, 1], [x1, y0, 0, 1], [x1, y1, 0, 1]], float).T
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for pose in image_to_volume:
        if valid_pose(pose):
            points = (np.asarray(pose, float) @ corners)[:3]
            lo, hi = np.minimum(lo, points.min(axis=1)), np.maximum(hi, points.max(axis=1))
    if not np.all(np.isfinite(lo)):
        raise ValueError("no frame has a valid pose, so there is nothing to reconstruct")
    counts = [math.floor(r / s + 0.5) + 1 for r, s in zip((hi - lo).tolist(), spacing)]
    return _checked_grid(tuple(lo.tolist()), spacing, counts)


def _checked_grid(origin_mm: tuple[float, float, float], spacing_mm: tuple[float, float, float],
                  counts_xyz: list[int]) -> VolumeGrid:
    """The grid of ``counts_xyz`` voxels, InputError when compounding it would pass the memory limit
    (exact integers, so no size can overflow)."""
    nx, ny, nz = counts_xyz
    checked_bytes(None, f"a volume of {nx} x {ny} x {nz} voxels of {' x '.join(f'{s:g}' for s in spacing_mm)} mm",
                  (nz, ny, nx), COMPOUNDING_BYTES_PER_VOXEL)
    return VolumeGrid(origin_mm, spacing_mm, (nz, ny, nx))


def settings_from_device_set(config: DeviceSet) -> VolumeSettings | None:
    """The volume settings of a device set's ``<VolumeReconstruction>`` with its STICK hole
    filling, or None when it has none. Raises InputError naming the file."""
    if config.volume_reconstruction is None:
        return None
    try:
        return VolumeSettings.from_plus(config.volume_reconstruction, config.hole_filling)
    except ValueError as exc:
        raise InputError(config.path, f"VolumeReconstruction: {exc}")
