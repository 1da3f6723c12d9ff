"""PLUS-style volume compounding: tracked 2D frames pasted into a 3D voxel volume.

Frames and units (SPEC §2): lengths in mm, transforms are 4x4 ``a_to_b`` matrices. The volume lives
in a "volume" frame (the robot base, or PLUS's ``Reference``). ``image_to_volume`` includes the pixel
spacing, so pixel (u, v) (u = column, v = row) lies at ``image_to_volume @ (u, v, 0, 1)``.
A grid's ``origin_mm`` is the centre of voxel (0, 0, 0); voxel (i, j, k) (x, y, z indices) is centred
at ``origin_mm + (i, j, k) * spacing_mm`` and is stored at ``voxels[k, j, i]``.

Insertion follows PLUS's vtkPlusPasteSliceIntoVolume: NEAREST_NEIGHBOR sends every pixel of the
clip rectangle to its nearest voxel; LINEAR spreads it over the 8 surrounding voxels with trilinear
weights. MEAN keeps the (weighted) mean, MAXIMUM the largest value, LATEST the last one written
(for LINEAR, MAXIMUM and LATEST only touch voxels with a weight of at least 1/8, as PLUS does).
Hole filling is PLUS's STICK kernel (vtkPlusFillHolesInVolume). Frames are consumed one at a time,
so memory is bounded by the volume, not by the number of frames.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import nrrd
import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from probecal.core.errors import InputError
from probecal.core.io.files import replace_atomically
from probecal.core.io.limits import checked_bytes
from probecal.core.io.deviceset import DeviceSet, read_device_set
from probecal.core.io.sequence import read_sequence

INTERPOLATIONS = ("NEAREST_NEIGHBOR", "LINEAR")
COMPOUNDINGS = ("MEAN", "MAXIMUM", "LATEST")
MIN_SPACING_MM = 0.001
COMPOUNDING_BYTES_PER_VOXEL = 16  # MEAN's complex64 moments, the uint8 result, hole filling's copies
LINEAR_MIN_WEIGHT = 0.125  # PLUS: LINEAR MAXIMUM/LATEST write a voxel only at a weight >= 1/8
HOLE_FILL_CHUNK = 1 << 18  # holes examined at once; bounds the memory of hole filling

# PLUS's 13 stick directions (x, y, z steps): one of each +/- pair of the 26-neighbourhood.
STICKS = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, -1, 0],
     [1, 0, -1], [0, 1, -1], [1, 1, 1], [-1, 1, 1], [1, -1, 1], [-1, -1, 1]]
)

Progress = Callable[[int, int], None]


def _triple(values, what: str) -> tuple[float, float, float]:
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
    means the whole image. ``stick_length``/``sticks_to_use``: PLUS STICK hole-filling parameters
    (StickLengthLimit, NumberOfSticksToUse), used when ``fill_holes``.
    """

    spacing_mm: tuple[float, float, float] = (0.5, 0.5, 0.5)
    origin_mm: tuple[float, float, float] | None = None
    extent: tuple[int, int, int, int, int, int] | None = None
    clip_origin_px: tuple[int, int] = (0, 0)
    clip_size_px: tuple[int, int] | None = None
    interpolation: str = "NEAREST_NEIGHBOR"
    compounding: str = "MEAN"
    fill_holes: bool = False
    stick_length: int = 9
    sticks_to_use: int = 1

    def __post_init__(self) -> None:
        def store(name: str, value) -> None:  # normalise to tuples (the dataclass is frozen)
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
        if self.stick_length < 3 or self.sticks_to_use < 1:
            raise ValueError("hole filling needs stick_length >= 3 and sticks_to_use >= 1")

    @classmethod
    def from_plus(
        cls, attributes: Mapping[str, str], hole_filling: Mapping[str, str] | None = None
    ) -> "VolumeSettings":
        """Settings from PLUS ``<VolumeReconstruction>`` attributes (OutputSpacing, OutputOrigin,
        OutputExtent, ClipRectangleOrigin, ClipRectangleSize, Interpolation, CompoundingMode,
        FillHoles; others such as Optimization or NumberOfThreads are ignored; OutputOrigin counts
        only with OutputExtent) and, optionally, the attributes of a STICK ``<HoleFillingElement>``.
        Raises ValueError for malformed values."""

        def numbers(name: str, n: int, kind=float):
            text = attributes.get(name)
            if text is None:
                return None
            try:
                floats = [float(v) for v in text.split()]
            except ValueError:
                raise ValueError(f"{name} is not a list of numbers: {text!r}")
            if not all(math.isfinite(v) for v in floats):
                raise ValueError(f"{name} has a number that is not finite: {text!r}")
            values = tuple(kind(v) for v in floats)
            if len(values) != n:
                raise ValueError(f"{name} needs {n} numbers, got {text!r}")
            return values

        clip_size = numbers("ClipRectangleSize", 2, int)
        fill = attributes.get("FillHoles", "OFF").upper()
        if fill not in ("ON", "OFF"):
            raise ValueError(f"FillHoles must be ON or OFF, got {fill!r}")
        sticks = {}
        if hole_filling is not None:
            try:
                sticks = {
                    "stick_length": int(hole_filling.get("StickLengthLimit", cls.stick_length)),
                    "sticks_to_use": int(hole_filling.get("NumberOfSticksToUse", cls.sticks_to_use)),
                }
            except (ValueError, OverflowError):
                raise ValueError(f"malformed STICK hole filling element {dict(hole_filling)}")
        return cls(
            spacing_mm=numbers("OutputSpacing", 3) or cls.spacing_mm,
            origin_mm=numbers("OutputOrigin", 3) if "OutputExtent" in attributes else None,
            extent=numbers("OutputExtent", 6, int),
            clip_origin_px=numbers("ClipRectangleOrigin", 2, int) or (0, 0),
            clip_size_px=clip_size if clip_size and min(clip_size) > 0 else None,
            interpolation=attributes.get("Interpolation", cls.interpolation).upper(),
            compounding=attributes.get("CompoundingMode", cls.compounding).upper(),
            fill_holes=fill == "ON",
            **sticks,
        )

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


def _valid_pose(image_to_volume: np.ndarray | None) -> bool:
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
        lo, hi = settings.extent[0::2], settings.extent[1::2]
        origin = np.array(settings.origin_mm or (0.0, 0.0, 0.0)) + np.array(lo, float) * np.array(spacing)
        return _checked_grid(tuple(origin.tolist()), spacing, [b - a + 1 for a, b in zip(lo, hi)])
    if image_size is None:
        raise ValueError("the image size is needed to fit the volume to the frames")
    x0, y0, x1, y1 = settings.clip_rectangle(*image_size)
    corners = np.array([[x0, y0, 0, 1], [x0, y1, 0, 1], [x1, y0, 0, 1], [x1, y1, 0, 1]], float).T
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for pose in image_to_volume:
        if _valid_pose(pose):
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


class _Scratch:
    """Arrays for one image size, reused frame after frame so that inserting allocates nothing
    large: pixel coordinates of the clip rectangle and per-pixel working buffers. ``pairs`` holds
    (weight * value, weight) per pixel; viewed as complex64 it is added to the MEAN accumulator in
    one scatter-add."""

    def __init__(self, clip: tuple[int, int, int, int], linear: bool):
        x0, y0, x1, y1 = clip
        self.clip = clip
        self.u = np.arange(x0, x1 + 1, dtype=np.float32)
        self.v = np.arange(y0, y1 + 1, dtype=np.float32)[:, None]
        shape = (y1 - y0 + 1, x1 - x0 + 1)
        self.coords = np.empty((3, *shape), np.float32)
        self.index = np.empty((3, *shape), np.intp)
        self.pairs = np.ones((shape[0] * shape[1], 2), np.float32)  # nearest neighbour: weight 1
        if linear:
            self.low = np.empty((3, *shape), np.float32)
            self.values = np.empty(shape[0] * shape[1], np.float32)
            self.w_zy = np.empty(shape[0] * shape[1], np.float32)


class Compounder:
    """Accumulates frames into a fixed grid, one frame at a time (nothing per frame is kept).

    MEAN keeps, per voxel, the sum of weight * value and the sum of weights (a complex64: real and
    imaginary part; weights are 1 for NEAREST_NEIGHBOR, trilinear for LINEAR). MAXIMUM and LATEST
    keep the voxel values and a "hit" mask.
    """

    def __init__(self, settings: VolumeSettings, grid: VolumeGrid):
        self.settings = settings
        self.grid = grid
        self.frames_inserted = 0
        self._linear = settings.interpolation == "LINEAR"
        n = math.prod(grid.shape)
        if settings.compounding == "MEAN":
            self._moments = np.zeros(n, np.complex64)
        else:
            self._values = np.zeros(n, np.uint8)
            self._hit = np.zeros(n, bool)
        self._scratch: dict[tuple[int, int], _Scratch] = {}

    def insert(self, image: np.ndarray, image_to_volume: np.ndarray | None) -> bool:
        """Paste one uint8 (H, W) frame at pose ``image_to_volume`` (pixels -> volume mm).

        Returns False, leaving the volume untouched, when the pose is missing or not finite.
        """
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"frames must be uint8 (H, W) arrays, got {image.dtype} {image.shape}")
        if not _valid_pose(image_to_volume):
            return False
        height, width = image.shape
        if (width, height) not in self._scratch:
            clip = self.settings.clip_rectangle(width, height)
            self._scratch[(width, height)] = _Scratch(clip, self._linear)
        scratch = self._scratch[(width, height)]
        x0, y0, x1, y1 = scratch.clip
        pixels = image[y0 : y1 + 1, x0 : x1 + 1]
        to_index = self.grid.volume_to_index @ np.asarray(image_to_volume, float)
        if self._linear:
            self._insert_linear(pixels, to_index, scratch)
        else:
            self._insert_nearest(pixels, to_index, scratch)
        self.frames_inserted += 1
        return True

    @staticmethod
    def _coordinates(to_index: np.ndarray, scratch: _Scratch, shift: float) -> np.ndarray:
        """Continuous voxel coordinates (x, y, z) + ``shift`` of every pixel, into scratch.coords."""
        for k in range(3):
            a, b, _, c = (float(x) for x in to_index[k])  # python floats keep the float32 arithmetic
            np.add(a * scratch.u, b * scratch.v + (c + shift), out=scratch.coords[k])
        return scratch.coords

    @staticmethod
    def _outside(coords: np.ndarray, high: list[float], strict: bool) -> np.ndarray | None:
        """Mask of pixels outside 0 <= coordinate < high (<= high if not strict) on some axis, or
        None if there are none; coordinates are affine in the pixel, so the corners decide that."""
        def inside(c, h):
            return (c >= 0) & ((c < h) if strict else (c <= h))

        height, width = coords.shape[1:]
        corners = (slice(None, None, height - 1 or 1), slice(None, None, width - 1 or 1))
        if all(inside(c[corners], h).all() for c, h in zip(coords, high)):
            return None
        mask = inside(coords[0], high[0])
        for c, h in zip(coords[1:], high[1:]):
            mask &= inside(c, h)
        return ~mask

    def _insert_nearest(self, pixels: np.ndarray, to_index: np.ndarray, scratch: _Scratch) -> None:
        nz, ny, nx = self.grid.shape
        coords = self._coordinates(to_index, scratch, 0.5)  # floor(c + 0.5) is the nearest voxel
        outside = self._outside(coords, [nx, ny, nz], strict=True)
        np.copyto(scratch.index, coords, casting="unsafe")  # truncation = floor where c >= 0
        ix, iy, flat = scratch.index
        flat *= ny
        flat += iy
        flat *= nx
        flat += ix
        values = pixels
        if outside is not None:
            keep = ~outside
            flat, values = flat[keep], values[keep]
        flat, values = flat.ravel(), values.ravel()
        if self.settings.compounding == "MEAN":
            pairs = scratch.pairs[: flat.size]
            pairs[:, 0] = values
            np.add.at(self._moments, flat, pairs.view(np.complex64).ravel())
        else:
            self._paste(flat, values, 0)

    def _insert_linear(self, pixels: np.ndarray, to_index: np.ndarray, scratch: _Scratch) -> None:
        nz, ny, nx = self.grid.shape
        coords = self._coordinates(to_index, scratch, 0.0)
        # PLUS pastes a pixel only when all 8 surrounding voxels exist; the others get weight 0.
        outside = self._outside(coords, [nx - 1, ny - 1, nz - 1], strict=False)
        low, base, step = scratch.low, scratch.index[0], scratch.index[1]
        base.fill(0)
        for k, n in ((2, nz), (1, ny), (0, nx)):
            np.floor(coords[k], out=low[k])
            # in range for every pixel (those outside get weight 0); the far face keeps a +1 neighbour
            np.clip(low[k], 0, max(n - 2, 0), out=low[k])
            base *= n
            np.copyto(step, low[k], casting="unsafe")
            base += step
            np.subtract(coords[k], low[k], out=coords[k])  # weight of the +1 neighbour
            np.subtract(1, coords[k], out=low[k])  # weight of the low neighbour
        if outside is not None:
            low[0][outside] = 0
            coords[0][outside] = 0
        strides = [stride if n > 1 else 0 for stride, n in ((ny * nx, nz), (nx, ny), (1, nx))]
        weights_zyx = [(low[k].ravel(), coords[k].ravel()) for k in range(3)]
        base = base.ravel()
        values, w_zy, pairs = scratch.values, scratch.w_zy, scratch.pairs
        values[:] = pixels.ravel()
        for a in (0, 1):
            for b in (0, 1):
                np.multiply(weights_zyx[2][a], weights_zyx[1][b], out=w_zy)
                for c in (0, 1):
                    offset = a * strides[0] + b * strides[1] + c * strides[2]
                    weight = np.multiply(w_zy, weights_zyx[0][c], out=pairs[:, 1])
                    if self.settings.compounding == "MEAN":
                        np.multiply(weight, values, out=pairs[:, 0])
                        # the accumulator is viewed from the corner's offset on
                        np.add.at(self._moments[offset:], base, pairs.view(np.complex64).ravel())
                    else:
                        keep = weight >= LINEAR_MIN_WEIGHT
                        self._paste(base[keep], values[keep].astype(np.uint8), offset)

    def _paste(self, flat: np.ndarray, values: np.ndarray, offset: int) -> None:
        """MAXIMUM or LATEST compounding of uint8 ``values`` into voxels ``flat + offset`` (1-D)."""
        voxels, hit = self._values[offset:], self._hit[offset:]
        if self.settings.compounding == "MAXIMUM":
            np.maximum.at(voxels, flat, values)
        else:
            voxels[flat] = values
        hit[flat] = True

    def result(self) -> Volume:
        """The compounded volume (hole-filled when the settings ask for it)."""
        if self.settings.compounding == "MEAN":
            filled = self._moments.imag > 0
            values = np.zeros(filled.size, np.uint8)
            moments = self._moments[filled]
            values[filled] = np.clip(np.rint(moments.real / moments.imag), 0, 255)
        else:
            filled, values = self._hit, self._values.copy()
        values, filled = values.reshape(self.grid.shape), filled.reshape(self.grid.shape)
        if self.settings.fill_holes:
            values = fill_holes(values, filled, self.settings.stick_length, self.settings.sticks_to_use)
        return Volume(values, self.grid.origin_mm, self.grid.spacing_mm)


def fill_holes(values: np.ndarray, filled: np.ndarray, stick_length: int = 9, sticks_to_use: int = 1) -> np.ndarray:
    """PLUS's STICK hole filling (vtkPlusFillHolesInVolume): each empty voxel looks along the 13
    lines through it (axes, face and space diagonals) for the nearest filled voxel ahead (a steps)
    and behind (b steps), with a + b + 1 <= ``stick_length``. As in PLUS such a stick is
    a + b + 1 voxels long (times the step length for diagonals), the shortest stick wins, and ties,
    and up to ``sticks_to_use`` sticks, are averaged with weights 1/length. A stick's value is the
    linear interpolation between its ends, (b * ahead + a * behind) / (a + b) (PLUS's formula leans
    towards the "ahead" end). Voxels no stick spans stay empty.
    ``values`` uint8 (nz, ny, nx) and ``filled`` bool of the same shape; returns a new array.
    """
    reach = stick_length - 2  # the furthest an end can be while the other end is at least 1 away
    out = values.copy()
    if reach < 1 or not filled.any():
        return out
    near = ndimage.maximum_filter(filled, size=2 * reach + 1, mode="constant")
    holes = np.flatnonzero(near & ~filled)
    if holes.size == 0:
        return out
    padded_filled = np.pad(filled, reach).ravel()
    padded_values = np.pad(values, reach).ravel()
    py, px = filled.shape[1] + 2 * reach, filled.shape[2] + 2 * reach
    offsets = STICKS[:, 2] * py * px + STICKS[:, 1] * px + STICKS[:, 0]
    step_lengths = np.linalg.norm(STICKS, axis=1)
    flat_out = out.reshape(-1)
    for start in range(0, holes.size, HOLE_FILL_CHUNK):
        chunk = holes[start : start + HOLE_FILL_CHUNK]
        z, y, x = np.unravel_index(chunk, filled.shape)
        position = ((z + reach) * py + (y + reach)) * px + (x + reach)  # in the padded volume
        value, ok = _stick_values(
            position, padded_filled, padded_values, offsets, step_lengths, stick_length, sticks_to_use
        )
        flat_out[chunk[ok]] = value[ok]
    return out


def _nearest_filled(position, padded_filled, padded_values, offset: int, limit: np.ndarray):
    """Steps (0 = none found) and value of the nearest filled voxel from each position along
    ``offset``, searching at most ``limit`` steps (per position)."""
    steps = np.zeros(position.size, np.int16)
    found_values = np.zeros(position.size, np.float32)
    todo = np.flatnonzero(limit > 0)
    j = 1
    while todo.size:
        probe = position[todo] + j * offset
        hit = padded_filled[probe]
        steps[todo[hit]] = j
        found_values[todo[hit]] = padded_values[probe[hit]]
        todo = todo[~hit]
        j += 1
        todo = todo[limit[todo] >= j]
    return steps, found_values


def _stick_values(position, padded_filled, padded_values, offsets, step_lengths, stick_length, sticks_to_use):
    """(value uint8, found bool) for hole voxels at padded flat ``position``."""
    n = position.size
    weights = np.zeros((len(offsets), n))
    values = np.zeros((len(offsets), n), np.float32)
    furthest = np.full(n, stick_length - 2)
    for s, (offset, step) in enumerate(zip(offsets, step_lengths)):
        ahead, ahead_value = _nearest_filled(position, padded_filled, padded_values, offset, furthest)
        behind, behind_value = _nearest_filled(
            position, padded_filled, padded_values, -offset, np.where(ahead > 0, stick_length - 1 - ahead, 0)
        )
        good = (ahead > 0) & (behind > 0)
        ahead, behind = ahead[good].astype(np.float32), behind[good].astype(np.float32)
        length = ahead + behind + 1  # PLUS counts the voxels the stick covers
        weights[s, good] = 1.0 / (length * step)
        values[s, good] = (behind * ahead_value[good] + ahead * behind_value[good]) / (ahead + behind)
    total, norm = np.zeros(n), np.zeros(n)
    used = np.zeros(n, int)
    for _ in range(sticks_to_use):
        best = weights.max(axis=0)
        pick = (weights == best) & (best > 0) & (used < sticks_to_use)
        if not pick.any():
            break
        total += (pick * weights * values).sum(axis=0)
        norm += (pick * weights).sum(axis=0)
        used += pick.sum(axis=0)
        weights[pick] = 0
    ok = norm > 0
    result = np.zeros(n, np.uint8)
    result[ok] = np.clip(np.rint(total[ok] / norm[ok]), 0, 255)
    return result, ok


def reconstruct_sequence(
    frames: Iterable[np.ndarray],
    image_to_volume: Iterable[np.ndarray | None],
    settings: VolumeSettings,
    progress: Progress | None = None,
    grid: VolumeGrid | None = None,
) -> Volume:
    """Compound frames (uint8 (H, W), consumed one at a time) at their poses (pixels -> volume mm;
    None or NaN skips the frame). Without ``grid`` the lattice comes from ``output_grid`` (the
    poses are read first, which is cheap; the image size is taken from the first frame).
    ``progress(done, total)`` is called after each frame. Raises ValueError when there are no
    frames, no valid pose, or a different number of frames and poses."""
    poses = list(image_to_volume)
    if not poses:
        raise ValueError("no frames to reconstruct")
    frames = iter(frames)
    first = next(frames, None)
    if first is None:
        raise ValueError("no frames to reconstruct")
    if grid is None:
        grid = output_grid(settings, (np.shape(first)[1], np.shape(first)[0]), poses)
    elif not any(_valid_pose(p) for p in poses):
        raise ValueError("no frame has a valid pose, so there is nothing to reconstruct")
    compounder = Compounder(settings, grid)
    frames = itertools.chain([first], frames)
    for done, pose in enumerate(poses, start=1):
        frame = next(frames, None)
        if frame is None:
            raise ValueError(f"{done - 1} frames but {len(poses)} poses")
        compounder.insert(frame, pose)
        if progress:
            progress(done, len(poses))
    if next(frames, None) is not None:
        raise ValueError(f"more frames than the {len(poses)} poses")
    return compounder.result()


def settings_from_device_set(config: DeviceSet) -> VolumeSettings | None:
    """The volume settings of a device set's ``<VolumeReconstruction>`` with its STICK hole
    filling, or None when it has none. Raises InputError naming the file."""
    if config.volume_reconstruction is None:
        return None
    try:
        return VolumeSettings.from_plus(config.volume_reconstruction, config.hole_filling)
    except ValueError as exc:
        raise InputError(config.path, f"VolumeReconstruction: {exc}")


def reconstruct_plus(
    sequence_file: str | Path, config_file: str | Path, progress: Progress | None = None
) -> Volume:
    """Reconstruct a PLUS ``.igs.mha`` with a device-set XML's ``<VolumeReconstruction>`` settings,
    PLUS-style: the volume frame is the config's ReferenceCoordinateFrame ("Reference" by
    default), ``image_to_reference = ToolToReference @ ImageToTool`` with ImageToTool (e.g.
    Image->Probe, includes the pixel spacing) from the config's CoordinateDefinitions and
    ToolToReference per frame from the sequence (composed from ...ToTracker if needed). Frames
    with an invalid transform or image status are skipped. Raises InputError naming the file."""
    sequence_file, config_file = Path(sequence_file), Path(config_file)
    config = read_device_set(config_file)
    settings = settings_from_device_set(config)
    if settings is None:
        raise InputError(config_file, "no <VolumeReconstruction> element")
    attributes = config.volume_reconstruction
    image = attributes.get("ImageCoordinateFrame", "Image")
    reference = attributes.get("ReferenceCoordinateFrame", "Reference")
    seq = read_sequence(sequence_file)
    image_to_reference = None
    for (source, tool), image_to_tool in config.transforms.items():
        found = seq.transform(tool, reference) if source == image else None
        if found is not None:
            tool_to_reference, valid = found
            image_to_reference = [m @ image_to_tool if ok else None for m, ok in zip(tool_to_reference, valid)]
            break
    if image_to_reference is None:
        raise InputError(
            config_file,
            f"no {image}->tool transform whose tool->{reference} pose is in {sequence_file.name} "
            f"(sequence transforms: {', '.join(sorted(seq.transforms)) or 'none'})",
        )
    if seq.image_ok is not None:
        image_to_reference = [m if ok else None for m, ok in zip(image_to_reference, seq.image_ok)]
    try:
        return reconstruct_sequence(iter(seq.frames), image_to_reference, settings, progress)
    except ValueError as exc:
        raise InputError(sequence_file, str(exc))


def write_volume(volume: Volume, path: str | Path) -> None:
    """Write ``.mha`` (SimpleITK) or ``.nrrd`` (pynrrd), atomically, so 3D Slicer opens it in place.

    ``origin_mm`` is the centre of voxel (0, 0, 0) in the volume (base / reference) frame, in mm,
    with an identity direction. Like PLUS, the volume-frame axes are written as the file's patient
    axes: ``.mha`` gets Offset = origin, TransformMatrix = identity (MetaImage is LPS), and ``.nrrd``
    gets ``space: left-posterior-superior``, ``space origin`` = origin, ``space directions`` =
    diag(spacing). Both open identically: a point at volume (x, y, z) mm appears in Slicer at LPS
    (x, y, z), i.e. RAS (-x, -y, z), the same place as PLUS's own ``.mha`` output.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    voxels = np.ascontiguousarray(volume.voxels, dtype=np.uint8)
    origin = [float(v) for v in volume.origin_mm]
    spacing = [float(v) for v in volume.spacing_mm]
    if suffix == ".mha":
        def write(tmp: Path) -> None:
            image = sitk.GetImageFromArray(voxels)
            image.SetOrigin(origin)
            image.SetSpacing(spacing)
            sitk.WriteImage(image, str(tmp), useCompression=True)
    elif suffix == ".nrrd":
        header = {
            "type": "uint8",
            "dimension": 3,
            "space": "left-posterior-superior",
            "space directions": np.diag(spacing),
            "space origin": np.array(origin),
            "kinds": ["domain", "domain", "domain"],
            "encoding": "gzip",
        }

        def write(tmp: Path) -> None:
            nrrd.write(str(tmp), voxels, header, index_order="C")
    else:
        raise ValueError(f"{path}: volumes are written as .nrrd or .mha")
    replace_atomically(path, write)


def read_volume(path: str | Path) -> Volume:
    """Read a ``.mha``/``.nrrd`` volume written by ``write_volume`` or PLUS (axis-aligned, uint8).
    Raises InputError for a missing file or a rotated or non-uint8 volume."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        if path.suffix.lower() == ".nrrd":
            data, header = nrrd.read(str(path), index_order="C")
            directions = np.asarray(header.get("space directions", np.eye(3)), float)
            origin = tuple(float(v) for v in header.get("space origin", (0.0, 0.0, 0.0)))
            if header.get("space", "left-posterior-superior") != "left-posterior-superior":
                raise InputError(path, f"unsupported space {header['space']!r} (expected left-posterior-superior)")
        else:
            image = sitk.ReadImage(str(path))
            data = sitk.GetArrayFromImage(image)
            directions = np.array(image.GetDirection()).reshape(3, 3) * np.array(image.GetSpacing())
            origin = tuple(image.GetOrigin())
    except (RuntimeError, nrrd.NRRDError) as exc:
        raise InputError(path, f"unreadable volume ({exc})")
    spacing = np.diag(directions)
    if data.ndim != 3 or data.dtype != np.uint8:
        raise InputError(path, f"expected a 3D uint8 volume, got {data.dtype} {data.shape}")
    if not np.allclose(directions, np.diag(spacing)) or min(spacing) <= 0:
        raise InputError(path, "only axis-aligned volumes (identity direction) are supported")
    return Volume(data, origin, tuple(float(s) for s in spacing))
