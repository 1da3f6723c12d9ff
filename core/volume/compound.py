"""PLUS-style volume compounding: tracked 2D frames pasted into a 3D voxel volume.

Frames and units (design §2): lengths in mm, transforms are 4x4 ``a_to_b`` matrices. The volume lives
in a "volume" frame (the robot base, or PLUS's ``Reference``) on a ``core.volume.grid`` lattice.
``image_to_volume`` includes the pixel spacing, so pixel (u, v) (u = column, v = row) lies at
``image_to_volume @ (u, v, 0, 1)``.

Insertion follows PLUS's vtkPlusPasteSliceIntoVolume: NEAREST_NEIGHBOR sends every pixel of the
clip rectangle (and of the clipping fan, when the settings give one: ``core.volume.grid.Fan``) to
its nearest voxel; LINEAR spreads it over the 8 surrounding voxels with trilinear
weights. MEAN keeps the (weighted) mean, MAXIMUM the largest value, LATEST the last one written
(for LINEAR, MAXIMUM and LATEST only touch voxels with a weight of at least 1/8, as PLUS does).
Hole filling is PLUS's STICK kernel (vtkPlusFillHolesInVolume). Frames are consumed one at a time,
so memory is bounded by the volume, not by the number of frames.

Insertion loops over pixels in kernels compiled by numba (no Python objects, the GIL released);
each takes a band of the frame and the same band of the fan's mask (``kept``: 0 skips a pixel; an
empty mask keeps every one):
a pixel's coordinates are computed in float32 as PLUS does, and MEAN frames are split into
``LANES`` bands of rows compounded side by side, so both cores work on each frame.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from scipy import ndimage

from probecal.core.volume.grid import (
    Volume,
    VolumeGrid,
    VolumeSettings,
    output_grid,
    valid_pose,
)

LINEAR_MIN_WEIGHT = 0.125  # PLUS: LINEAR MAXIMUM/LATEST write a voxel only at a weight >= 1/8
HOLE_FILL_CHUNK = 1 << 18  # holes examined at once; bounds the memory of hole filling

# PLUS's 13 stick directions (x, y, z steps): one of each +/- pair of the 26-neighbourhood.
STICKS = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, -1, 0],
     [1, 0, -1], [0, 1, -1], [1, 1, 1], [-1, 1, 1], [1, -1, 1], [-1, -1, 1]]
)

Progress = Callable[[int, int], None]


LANES = 2
"""MEAN compounding splits each frame into this many bands of rows, compounded side by side (the
kernels below release the GIL) into an accumulator each, summed when the volume is read."""
_LANE_POOL = ThreadPoolExecutor(LANES, thread_name_prefix="compound")


@numba.njit(nogil=True, cache=True)
def _coordinate(to_index: np.ndarray, k: int, u: float, v: float, shift: float) -> np.float32:
    """Continuous voxel coordinate ``k`` (x, y, z) + ``shift`` of pixel (u, v), in float32 as PLUS
    computes it: ``a u + (b v + (c + shift))``."""
    a, b, c = np.float32(to_index[k, 0]), np.float32(to_index[k, 1]), np.float32(to_index[k, 3] + shift)
    return np.float32(a * np.float32(u)) + np.float32(np.float32(b * np.float32(v)) + c)


@numba.njit(nogil=True, cache=True, inline="always")
def nearest_voxel(to_index: np.ndarray, u: int, v: int, shape: tuple[int, int, int]) -> int:
    """The flat index of pixel (u, v)'s nearest voxel, or -1 when it lies outside the grid."""
    nz, ny, nx = shape
    x, y, z = (_coordinate(to_index, 0, u, v, 0.5), _coordinate(to_index, 1, u, v, 0.5),
               _coordinate(to_index, 2, u, v, 0.5))
    if 0 <= x < nx and 0 <= y < ny and 0 <= z < nz:
        return (int(z) * ny + int(y)) * nx + int(x)
    return -1


@numba.njit(nogil=True, cache=True, inline="always")
def _cell(to_index: np.ndarray, u: int, v: int, shape: tuple[int, int, int]) -> tuple:
    """Pixel (u, v)'s trilinear cell: the flat index of its lowest voxel (-1 when the pixel lies
    outside the grid) and the pixel's fractions (fx, fy, fz) within the cell."""
    nz, ny, nx = shape
    x, y, z = (_coordinate(to_index, 0, u, v, 0.0), _coordinate(to_index, 1, u, v, 0.0),
               _coordinate(to_index, 2, u, v, 0.0))
    if not (0 <= x <= nx - 1 and 0 <= y <= ny - 1 and 0 <= z <= nz - 1):
        return -1, np.float32(0.0), np.float32(0.0), np.float32(0.0)
    lx, ly, lz = (min(np.floor(x), np.float32(max(nx - 2, 0))), min(np.floor(y), np.float32(max(ny - 2, 0))),
                  min(np.floor(z), np.float32(max(nz - 2, 0))))
    return ((int(lz) * ny + int(ly)) * nx + int(lx), np.float32(x - lx), np.float32(y - ly),
            np.float32(z - lz))


@numba.njit(nogil=True, cache=True, inline="always")
def _strides(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """Flat-index steps to a cell's next voxel along z, y and x (0 along an axis of one voxel)."""
    nz, ny, nx = shape
    return ny * nx if nz > 1 else 0, nx if ny > 1 else 0, 1 if nx > 1 else 0


@numba.njit(nogil=True, cache=True)
def _nearest_mean(pixels: np.ndarray, kept: np.ndarray, x0: int, y0: int, to_index: np.ndarray,
                  shape: tuple[int, int, int], moments: np.ndarray) -> None:
    """NEAREST_NEIGHBOR MEAN: pixel (x0 + column, y0 + row) of ``pixels`` adds (value, 1) to its
    nearest voxel's moments, if that voxel exists."""
    for row in range(pixels.shape[0]):
        for column in range(pixels.shape[1]):
            if kept.size and not kept[row, column]:
                continue
            voxel = nearest_voxel(to_index, x0 + column, y0 + row, shape)
            if voxel >= 0:
                moments[voxel] += np.complex64(complex(pixels[row, column], 1.0))


@numba.njit(nogil=True, cache=True)
def _linear_mean(pixels: np.ndarray, kept: np.ndarray, x0: int, y0: int, to_index: np.ndarray,
                 shape: tuple[int, int, int], moments: np.ndarray) -> None:
    """LINEAR MEAN: pixel (x0 + column, y0 + row) adds ``w * (value + 1j)`` to each of the 8 voxels
    around it, ``w`` its trilinear weight, if all 8 exist (PLUS's rule)."""
    strides = _strides(shape)
    for row in range(pixels.shape[0]):
        for column in range(pixels.shape[1]):
            if kept.size and not kept[row, column]:
                continue
            base, fx, fy, fz = _cell(to_index, x0 + column, y0 + row, shape)
            if base < 0:
                continue
            value = np.float32(pixels[row, column])
            for a in range(2):
                wz = fz if a else np.float32(1 - fz)
                for b in range(2):
                    wzy = np.float32(wz * (fy if b else np.float32(1 - fy)))
                    for c in range(2):
                        wx = fx if c else np.float32(1 - fx)
                        weight = np.float32(wx * wzy)
                        moments[base + a * strides[0] + b * strides[1] + c * strides[2]] += np.complex64(
                            complex(np.float32(np.float32(value * wx) * wzy), weight))


@numba.njit(nogil=True, cache=True)
def _paste(values: np.ndarray, stamps: np.ndarray, voxel: int, value: np.uint8, stamp: int, latest: bool,
           keep: bool) -> None:
    """MAXIMUM (or, ``latest``, LATEST) compounding of one value into one voxel when ``keep``,
    which then carries ``stamp`` (when it was written); without branches on the data (voxels
    start at 0, so the maximum needs no test of whether one was written)."""
    old = values[voxel]
    new = value if latest else max(old, value)
    values[voxel] = new if keep else old
    stamps[voxel] = stamp if keep else stamps[voxel]


@numba.njit(nogil=True, cache=True)
def _nearest_paste(pixels: np.ndarray, kept: np.ndarray, x0: int, y0: int, to_index: np.ndarray,
                   shape: tuple[int, int, int], latest: bool, stamp: int, values: np.ndarray,
                   stamps: np.ndarray) -> None:
    """NEAREST_NEIGHBOR MAXIMUM or LATEST, pixel after pixel in rows."""
    for row in range(pixels.shape[0]):
        for column in range(pixels.shape[1]):
            if kept.size and not kept[row, column]:
                continue
            voxel = nearest_voxel(to_index, x0 + column, y0 + row, shape)
            if voxel >= 0:
                _paste(values, stamps, voxel, pixels[row, column], stamp, latest, True)


@numba.njit(nogil=True, cache=True)
def _linear_paste(pixels: np.ndarray, kept: np.ndarray, x0: int, y0: int, to_index: np.ndarray,
                  shape: tuple[int, int, int], latest: bool, stamp: int, values: np.ndarray,
                  stamps: np.ndarray) -> None:
    """LINEAR MAXIMUM or LATEST: each of the 8 voxels around a pixel whose trilinear weight is at
    least ``LINEAR_MIN_WEIGHT`` takes the pixel's value (PLUS's rule), pixel after pixel."""
    strides = _strides(shape)
    for row in range(pixels.shape[0]):
        for column in range(pixels.shape[1]):
            if kept.size and not kept[row, column]:
                continue
            base, fx, fy, fz = _cell(to_index, x0 + column, y0 + row, shape)
            if base < 0:
                continue
            for a in range(2):
                wz = fz if a else np.float32(1 - fz)
                for b in range(2):
                    wzy = np.float32(wz * (fy if b else np.float32(1 - fy)))
                    for c in range(2):
                        keep = np.float32((fx if c else np.float32(1 - fx)) * wzy) >= LINEAR_MIN_WEIGHT
                        _paste(values, stamps, base + a * strides[0] + b * strides[1] + c * strides[2],
                               pixels[row, column], stamp, latest, keep)


def _bands(clip: tuple[int, int, int, int], lanes: int) -> list[tuple[int, int, int, int]]:
    """The clip rectangle (x0, y0, x1, y1, inclusive) cut into ``lanes`` bands of rows."""
    x0, y0, x1, y1 = clip
    edges = np.linspace(y0, y1 + 1, min(lanes, y1 - y0 + 1) + 1).round().astype(int)
    return [(x0, int(a), x1, int(b) - 1) for a, b in zip(edges[:-1], edges[1:])]


class Compounder:
    """Accumulates frames into a fixed grid, one frame at a time (nothing per frame is kept).

    Each frame's rows are cut into ``LANES`` bands compounded side by side, each into its own
    accumulator, merged when the volume is read; memory is ``LANES`` times the voxels' bytes,
    whatever the number of frames. MEAN keeps, per voxel, the sum of weight * value and the sum
    of weights (a complex64: real and imaginary part; weights are 1 for NEAREST_NEIGHBOR,
    trilinear for LINEAR). MAXIMUM and LATEST keep the voxel values and when each was last
    written (0: never; a later frame, or a later band of the same frame, is later), so that the
    lanes merge to the largest or the latest value.
    """

    def __init__(self, settings: VolumeSettings, grid: VolumeGrid):
        self.settings = settings
        self.grid = grid
        self.frames_inserted = 0
        self._fan_mask: tuple[tuple[int, ...], np.ndarray | None] | None = None
        self._linear = settings.interpolation == "LINEAR"
        self._mean = settings.compounding == "MEAN"
        n = math.prod(grid.shape)
        if self._mean:
            self._lanes = [np.zeros(n, np.complex64) for _ in range(LANES)]
        else:
            self._values = [np.zeros(n, np.uint8) for _ in range(LANES)]
            self._stamps = [np.zeros(n, np.int32) for _ in range(LANES)]

    def insert(self, image: np.ndarray, image_to_volume: np.ndarray | None) -> bool:
        """Paste one uint8 (H, W) frame at pose ``image_to_volume`` (pixels -> volume mm).

        Returns False, leaving the volume untouched, when the pose is missing or not finite, or
        when the fan's angle auto-detection finds the frame blank.
        """
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"frames must be uint8 (H, W) arrays, got {image.dtype} {image.shape}")
        if not valid_pose(image_to_volume):
            return False
        height, width = image.shape
        clip = self.settings.clip_rectangle(width, height)
        kept = self._kept(image)
        if kept is None:  # a blank frame, which PLUS's fan-angle auto-detection leaves out
            return False
        to_index = self.grid.volume_to_index @ np.asarray(image_to_volume, float)
        windows = [(slice(y0, y1 + 1), slice(x0, x1 + 1)) for x0, y0, x1, y1 in _bands(clip, LANES)]
        bands = [image[window] for window in windows]
        masks = [kept[window] if kept.size else kept for window in windows]
        corners = [(x0, y0) for x0, y0, _, _ in _bands(clip, LANES)]
        if self._mean:
            kernel = _linear_mean if self._linear else _nearest_mean
            jobs = [_LANE_POOL.submit(kernel, band, mask, x0, y0, to_index, self.grid.shape, lane)
                    for band, mask, (x0, y0), lane in zip(bands, masks, corners, self._lanes)]
        else:
            paste = _linear_paste if self._linear else _nearest_paste
            latest = self.settings.compounding == "LATEST"
            jobs = [_LANE_POOL.submit(paste, band, mask, x0, y0, to_index, self.grid.shape, latest,
                                      self.frames_inserted * LANES + k + 1, values, stamps)
                    for k, (band, mask, (x0, y0), values, stamps) in enumerate(zip(bands, masks, corners,
                                                                                      self._values, self._stamps))]
        for job in jobs:
            job.result()
        self.frames_inserted += 1
        return True

    def _kept(self, image: np.ndarray) -> np.ndarray | None:
        """:meth:`VolumeSettings.kept_pixels` of ``image``, made once per frame size when the fan
        does not depend on the frame's content."""
        if not self.settings.fixed_fan:
            return self.settings.kept_pixels(image)
        if self._fan_mask is None or self._fan_mask[0] != image.shape:
            self._fan_mask = (image.shape, self.settings.kept_pixels(image))
        return self._fan_mask[1]

    def _mean_values(self) -> tuple[np.ndarray, np.ndarray]:
        """(values uint8, filled bool), flat: each voxel's rounded mean so far (MEAN compounding)."""
        total = self._lanes[0].copy()
        for lane in self._lanes[1:]:
            total += lane
        filled = total.imag > 0
        values: np.ndarray = np.zeros(filled.size, np.uint8)
        moments = total[filled]
        values[filled] = np.clip(np.rint(moments.real / moments.imag), 0, 255)
        return values, filled

    def _pasted_values(self) -> tuple[np.ndarray, np.ndarray]:
        """(values uint8, filled bool), flat: MAXIMUM's largest value or LATEST's latest, over the lanes."""
        stamps = np.stack(self._stamps)
        filled = stamps.max(axis=0) > 0
        if self.settings.compounding == "MAXIMUM":
            return np.max(np.stack(self._values), axis=0), filled
        return np.choose(stamps.argmax(axis=0), self._values), filled

    def bright_voxels(self, threshold: int, max_points: int) -> tuple[np.ndarray, np.ndarray]:
        """Centres (N, 3; volume frame mm) and values of the voxels compounded so far whose value
        is at least ``threshold``, at most ``max_points`` of them (evenly taken): a live view of the
        volume as it grows, without hole filling."""
        values, filled = self._mean_values() if self._mean else self._pasted_values()
        bright = np.flatnonzero(filled & (values >= threshold))
        bright = bright[:: max(1, -(-bright.size // max_points))]
        zyx = np.array(np.unravel_index(bright, self.grid.shape), float)
        centres = zyx[::-1].T * np.array(self.grid.spacing_mm) + np.array(self.grid.origin_mm)
        return centres, values[bright]

    def result(self) -> Volume:
        """The compounded volume (hole-filled when the settings ask for it)."""
        values, filled = self._mean_values() if self._mean else self._pasted_values()
        values, filled = values.reshape(self.grid.shape), filled.reshape(self.grid.shape)
        if self.settings.fill_holes:
            values = fill_holes(values, filled, self.settings.stick_length, self.settings.sticks_used)
        return Volume(values, self.grid.origin_mm, self.grid.spacing_mm)


def fill_holes(values: np.ndarray, filled: np.ndarray, stick_length: int = 9, sticks_used: int = 1) -> np.ndarray:
    """PLUS's STICK hole filling (vtkPlusFillHolesInVolume): each empty voxel looks along the 13
    lines through it (axes, face and space diagonals) for the nearest filled voxel ahead (a steps)
    and behind (b steps), with a + b + 1 <= ``stick_length``. As in PLUS such a stick is
    a + b + 1 voxels long (times the step length for diagonals), the shortest stick wins, and ties,
    and up to ``sticks_used`` sticks, are averaged with weights 1/length. A stick's value is the
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
            position, padded_filled, padded_values, offsets, step_lengths, stick_length, sticks_used
        )
        flat_out[chunk[ok]] = value[ok]
    return out


def _nearest_filled(position: np.ndarray, padded_filled: np.ndarray, padded_values: np.ndarray, offset: int,
                    limit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def _stick_values(position: np.ndarray, padded_filled: np.ndarray, padded_values: np.ndarray, offsets: np.ndarray,
                  step_lengths: np.ndarray, stick_length: float, sticks_used: int) -> tuple[np.ndarray, np.ndarray]:
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
    for _ in range(sticks_used):
        best = weights.max(axis=0)
        pick = (weights == best) & (best > 0) & (used < sticks_used)
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
    elif not any(valid_pose(p) for p in poses):
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


