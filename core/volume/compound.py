"""PLUS-style volume compounding: tracked 2D frames pasted into a 3D voxel volume.

Frames and units (SPEC §2): lengths in mm, transforms are 4x4 ``a_to_b`` matrices. The volume lives
in a "volume" frame (the robot base, or PLUS's ``Reference``) on a ``core.volume.grid`` lattice.
``image_to_volume`` includes the pixel spacing, so pixel (u, v) (u = column, v = row) lies at
``image_to_volume @ (u, v, 0, 1)``.

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
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

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
            n = shape[0] * shape[1]
            self.low = np.empty((3, *shape), np.float32)
            self.flat = np.empty(shape, np.float64)
            self.values = np.empty(n, np.float32)
            self.w_zy = np.empty(n, np.float32)
            self.value = np.full(n, 1j, np.complex64)  # pixel value + 1j: (value, weight) once weighted
            self.along_x = np.empty((2, n), np.complex64)
            self.zy = np.zeros(n, np.complex64)
            self.corner = np.empty(n, np.complex64)


LANES = 2
"""MEAN compounding splits each frame into this many bands of rows, compounded side by side into
an accumulator each (numpy's scatter-add releases the GIL), summed when the volume is read."""
_LANE_POOL = ThreadPoolExecutor(LANES, thread_name_prefix="compound")


def _bands(clip: tuple[int, int, int, int], lanes: int) -> list[tuple[int, int, int, int]]:
    """The clip rectangle (x0, y0, x1, y1, inclusive) cut into ``lanes`` bands of rows."""
    x0, y0, x1, y1 = clip
    edges = np.linspace(y0, y1 + 1, min(lanes, y1 - y0 + 1) + 1).round().astype(int)
    return [(x0, int(a), x1, int(b) - 1) for a, b in zip(edges[:-1], edges[1:])]


class Compounder:
    """Accumulates frames into a fixed grid, one frame at a time (nothing per frame is kept).

    MEAN keeps, per voxel, the sum of weight * value and the sum of weights (a complex64: real and
    imaginary part; weights are 1 for NEAREST_NEIGHBOR, trilinear for LINEAR), in ``LANES``
    accumulators that bands of rows of each frame are compounded into side by side; memory is
    ``LANES`` times the voxels' 8 bytes, whatever the number of frames. MAXIMUM and LATEST keep
    the voxel values and a "hit" mask, a frame's rows in order.
    """

    def __init__(self, settings: VolumeSettings, grid: VolumeGrid):
        self.settings = settings
        self.grid = grid
        self.frames_inserted = 0
        self._linear = settings.interpolation == "LINEAR"
        self._mean = settings.compounding == "MEAN"
        n = math.prod(grid.shape)
        if self._mean:
            self._lanes = [np.zeros(n, np.complex64) for _ in range(LANES)]
        else:
            self._values = np.zeros(n, np.uint8)
            self._hit = np.zeros(n, bool)
        self._scratch: dict[tuple[int, int], list[_Scratch]] = {}

    def insert(self, image: np.ndarray, image_to_volume: np.ndarray | None) -> bool:
        """Paste one uint8 (H, W) frame at pose ``image_to_volume`` (pixels -> volume mm).

        Returns False, leaving the volume untouched, when the pose is missing or not finite.
        """
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(f"frames must be uint8 (H, W) arrays, got {image.dtype} {image.shape}")
        if not valid_pose(image_to_volume):
            return False
        height, width = image.shape
        if (width, height) not in self._scratch:
            clip = self.settings.clip_rectangle(width, height)
            bands = _bands(clip, LANES) if self._mean else [clip]
            self._scratch[(width, height)] = [_Scratch(band, self._linear) for band in bands]
        to_index = self.grid.volume_to_index @ np.asarray(image_to_volume, float)
        insert = self._insert_linear if self._linear else self._insert_nearest
        if self._mean:
            jobs = [_LANE_POOL.submit(insert, image, to_index, scratch, lane)
                    for scratch, lane in zip(self._scratch[(width, height)], self._lanes)]
            for job in jobs:
                job.result()
        else:
            insert(image, to_index, self._scratch[(width, height)][0], None)
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

    def _insert_nearest(self, image: np.ndarray, to_index: np.ndarray, scratch: _Scratch,
                        moments: np.ndarray | None) -> None:
        """Nearest-neighbour insertion of the scratch's clip of ``image`` (into ``moments`` for MEAN)."""
        x0, y0, x1, y1 = scratch.clip
        pixels = image[y0 : y1 + 1, x0 : x1 + 1]
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
        if moments is not None:
            pairs = scratch.pairs[: flat.size]
            pairs[:, 0] = values
            np.add.at(moments, flat, pairs.view(np.complex64).ravel())
        else:
            self._paste(flat, values, 0)

    def _insert_linear(self, image: np.ndarray, to_index: np.ndarray, scratch: _Scratch,
                       moments: np.ndarray | None) -> None:
        """Trilinear insertion of the scratch's clip of ``image`` (into ``moments`` for MEAN)."""
        x0, y0, x1, y1 = scratch.clip
        pixels = image[y0 : y1 + 1, x0 : x1 + 1]
        nz, ny, nx = self.grid.shape
        coords = self._coordinates(to_index, scratch, 0.0)
        # PLUS pastes a pixel only when all 8 surrounding voxels exist; the others get weight 0.
        outside = self._outside(coords, [nx - 1, ny - 1, nz - 1], strict=False)
        low, flat = scratch.low, scratch.flat
        for k, n in ((2, nz), (1, ny), (0, nx)):
            np.floor(coords[k], out=low[k])
            # in range for every pixel (those outside get weight 0); the far face keeps a +1 neighbour
            np.clip(low[k], 0, max(n - 2, 0), out=low[k])
        # The flat index of the low corner, exact in float64 (below 2**53 voxels).
        np.multiply(low[2], float(ny), out=flat)
        flat += low[1]
        flat *= nx
        flat += low[0]
        base = scratch.index[0].ravel()
        np.copyto(base, flat.ravel(), casting="unsafe")
        for k in range(3):
            np.subtract(coords[k], low[k], out=coords[k])  # weight of the +1 neighbour
            np.subtract(1, coords[k], out=low[k])  # weight of the low neighbour
        if outside is not None:
            low[0][outside] = 0
            coords[0][outside] = 0
        strides = [stride if n > 1 else 0 for stride, n in ((ny * nx, nz), (nx, ny), (1, nx))]
        weights_zyx = [(low[k].ravel(), coords[k].ravel()) for k in range(3)]
        if moments is not None:
            self._spread_mean(pixels, weights_zyx, base, strides, scratch, moments)
            return
        values, w_zy, weight = scratch.values, scratch.w_zy, scratch.pairs[:, 1]
        values[:] = pixels.ravel()
        for a in (0, 1):
            for b in (0, 1):
                np.multiply(weights_zyx[2][a], weights_zyx[1][b], out=w_zy)
                for c in (0, 1):
                    offset = a * strides[0] + b * strides[1] + c * strides[2]
                    np.multiply(w_zy, weights_zyx[0][c], out=weight)
                    keep = weight >= LINEAR_MIN_WEIGHT
                    self._paste(base[keep], values[keep].astype(np.uint8), offset)

    @staticmethod
    def _spread_mean(pixels: np.ndarray, weights_zyx: list[tuple[np.ndarray, np.ndarray]], base: np.ndarray,
                     strides: list[int], scratch: _Scratch, moments: np.ndarray) -> None:
        """MEAN trilinear insertion: each corner adds ``w * (v + 1j)`` (weight times value, and the
        weight) with ``w = w_z w_y w_x``; ``(v + 1j) w_x`` is formed once per frame for both x
        neighbours, so a corner costs one complex product and its scatter-add."""
        value, along_x, zy, corner = scratch.value, scratch.along_x, scratch.zy, scratch.corner
        value.real = pixels.ravel()
        for c in (0, 1):
            np.multiply(value, weights_zyx[0][c], out=along_x[c])
        for a in (0, 1):
            for b in (0, 1):
                np.multiply(weights_zyx[2][a], weights_zyx[1][b], out=zy.real)
                for c in (0, 1):
                    np.multiply(along_x[c], zy, out=corner)
                    # the accumulator is viewed from the corner's offset on
                    np.add.at(moments[a * strides[0] + b * strides[1] + c * strides[2]:], base, corner)

    def _paste(self, flat: np.ndarray, values: np.ndarray, offset: int) -> None:
        """MAXIMUM or LATEST compounding of uint8 ``values`` into voxels ``flat + offset`` (1-D)."""
        voxels, hit = self._values[offset:], self._hit[offset:]
        if self.settings.compounding == "MAXIMUM":
            np.maximum.at(voxels, flat, values)
        else:
            voxels[flat] = values
        hit[flat] = True

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

    def bright_voxels(self, threshold: int, max_points: int) -> tuple[np.ndarray, np.ndarray]:
        """Centres (N, 3; volume frame mm) and values of the voxels compounded so far whose value
        is at least ``threshold``, at most ``max_points`` of them (evenly taken): a live view of the
        volume as it grows, without hole filling."""
        if self._mean:
            values, filled = self._mean_values()
        else:
            values, filled = self._values, self._hit
        bright = np.flatnonzero(filled & (values >= threshold))
        bright = bright[:: max(1, -(-bright.size // max_points))]
        zyx = np.array(np.unravel_index(bright, self.grid.shape), float)
        centres = zyx[::-1].T * np.array(self.grid.spacing_mm) + np.array(self.grid.origin_mm)
        return centres, values[bright]

    def result(self) -> Volume:
        """The compounded volume (hole-filled when the settings ask for it)."""
        if self._mean:
            values, filled = self._mean_values()
        else:
            filled, values = self._hit, self._values.copy()
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


def _stick_values(position, padded_filled, padded_values, offsets, step_lengths, stick_length, sticks_used):
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


