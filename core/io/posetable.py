"""Robot pose tables as labs write them: a CSV (or whitespace) file of one pose per frame.

Layouts, told apart by the number of pose values per row (``LAYOUTS``):

- 16: a 4x4 matrix, row-major; 12: a 3x4 matrix (the top three rows), row-major;
- 4 per row, stacked: one matrix row per file row, a 4x4 block per pose when every fourth row is
  ``0 0 0 1``, else a 3x4 block (as MATLAB's ``writematrix`` writes stacked matrices);
- 6: a UR pose vector ``x y z rx ry rz`` (a rotation vector in radians, as ur_rtde and UR's logs
  give it);
- 7: ``x y z qx qy qz qw`` (a unit quaternion, scalar last).

A first row that is not all numbers is a header: a column named ``file``, ``image`` or
``filename`` pairs each pose with an image by name, one named ``t``, ``time`` or ``timestamp``
keeps its time (s); the other columns are the pose values, in order.

Units: ``mm`` or ``m``; where not given they are guessed from the sizes (a robot's flange never
stays within 3 of its base's origin in millimetres, so poses that all do are in metres).
Direction: each pose is ``flange_to_base`` (the flange's pose in the base frame, what a robot
reports) unless given as ``base_to_flange``; a file cannot tell the two apart.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.errors import InputError
from probecal.core.geometry.transforms import RIGID_TOLERANCE, invert_transform, is_rigid, nearest_rotation
from probecal.core.io.files import read_bytes
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.io.limits import PARSED_EXPANSION

LAYOUTS = {
    16: "4x4 matrices, one per row",
    12: "3x4 matrices, one per row",
    6: "UR pose vectors (x y z rx ry rz)",
    7: "positions and quaternions (x y z qx qy qz qw)",
}
STACKED = {4: "stacked 4x4 matrices, one matrix row per row", 3: "stacked 3x4 matrices, one matrix row per row"}
UNITS = {"mm": 1.0, "m": 1000.0}
DIRECTIONS = ("flange-to-base", "base-to-flange")
FILE_COLUMNS = ("file", "image", "filename", "image_file", "frame")
TIME_COLUMNS = ("t", "time", "timestamp", "stamp", "time_s")
MAX_VALUE = MAX_MAGNITUDE / UNITS["m"]
"""The largest value (in size) a pose table may hold: a position in metres stays within what a
session holds in mm, and a time in s within what it holds in s."""
METRES_BELOW = 3.0  # every translation under this: the table is in metres (a flange is never this near its base in mm)
QUATERNION_TOLERANCE = 1e-3


@dataclass(frozen=True)
class PoseTable:
    """The poses of a table (``(N, 4, 4)`` ``flange_to_base``, mm), how they were read, and the
    image file names and times (s) of its rows when it names them."""

    flange_to_base: np.ndarray
    layout: str
    units: str
    units_guessed: bool
    direction: str
    files: list[str] | None = None
    times_s: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.flange_to_base)

    def summary(self) -> str:
        guessed = " (guessed from the sizes)" if self.units_guessed else ""
        return f"{len(self)} poses as {self.layout}, in {self.units}{guessed}, {self.direction}"


def _rows(path: Path, text: str) -> list[tuple[int, list[str]]]:
    """(line number, cells) of every row that is not empty or a ``#`` comment; cells split at
    commas, semicolons or tabs (the first of them the file uses), else at white space."""
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise InputError(path, "no poses in the file")
    sample = "\n".join(line for _, line in lines[:5])
    delimiter = next((d for d in (",", ";", "\t") if d in sample), None)
    rows = []
    for n, line in lines:
        if delimiter is None:
            cells = line.split()
        else:
            cells = next(csv.reader(io.StringIO(line), delimiter=delimiter, skipinitialspace=True))
        rows.append((n, [c.strip() for c in cells]))
    return rows


def is_number(text: str) -> bool:
    """Whether ``text`` reads as a number."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def _numbers(path: Path, line: int, cells: list[str]) -> np.ndarray:
    try:
        values = np.array([float(c) for c in cells])
    except ValueError:
        bad = next(c for c in cells if not is_number(c))
        raise InputError(path, f"line {line}: {bad!r} is not a number") from None
    if not np.all(np.abs(values) <= MAX_VALUE):
        bad = next(v for v in values if not abs(v) <= MAX_VALUE)
        raise InputError(path, f"line {line}: {bad:g} is not a finite number at most {MAX_VALUE:g} in size")
    return values


def _rigid(path: Path, line: int, matrix: np.ndarray) -> np.ndarray:
    """The matrix with its rotation made exactly orthonormal; InputError unless it is a rigid
    transform to ``RIGID_TOLERANCE`` (what six significant digits hold)."""
    if not is_rigid(matrix, tol=RIGID_TOLERANCE):
        raise InputError(path, f"line {line}: the matrix is not a rotation and a translation (rigid transform)")
    out = matrix.copy()
    out[:3, :3] = nearest_rotation(matrix[:3, :3])
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


def _poses_per_row(path: Path, lines: list[int], values: np.ndarray) -> np.ndarray:
    """(N, 4, 4) from one pose per row of ``values`` (N, k), k a key of ``LAYOUTS``."""
    k = values.shape[1]
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    if k in (16, 12):
        poses[:, : k // 4] = values.reshape(len(values), k // 4, 4)
        return np.array([_rigid(path, n, p) for n, p in zip(lines, poses)])
    poses[:, :3, 3] = values[:, :3]
    if k == 6:
        poses[:, :3, :3] = Rotation.from_rotvec(values[:, 3:]).as_matrix()
        return poses
    norms = np.linalg.norm(values[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_TOLERANCE)
    if len(bad):
        raise InputError(path, f"line {lines[bad[0]]}: the quaternion is not a unit one (norm {norms[bad[0]]:.4g})")
    poses[:, :3, :3] = Rotation.from_quat(values[:, 3:]).as_matrix()
    return poses


def _stacked(path: Path, lines: list[int], values: np.ndarray) -> tuple[np.ndarray, str]:
    """(N, 4, 4) and the layout of matrices stacked one matrix row per file row (4 values each)."""
    n = len(values)
    if n % 4 == 0 and np.allclose(values[3::4], [0, 0, 0, 1], atol=RIGID_TOLERANCE):
        size = 4
    elif n % 3 == 0:
        size = 3
    else:
        raise InputError(path, f"{n} rows of 4 numbers: not a stack of 3x4 or 4x4 matrices (the row count divides "
                               "by neither, or a 4x4 block's last row is not 0 0 0 1)")
    blocks = values.reshape(n // size, size, 4)
    poses = np.tile(np.eye(4), (len(blocks), 1, 1))
    poses[:, :size] = blocks
    return np.array([_rigid(path, lines[i * size], p) for i, p in enumerate(poses)]), STACKED[size]


def read_pose_table(path: str | Path, units: str | None = None, direction: str = DIRECTIONS[0]) -> PoseTable:
    """The poses of the table at ``path`` (see the module docstring) as ``flange_to_base`` in mm;
    ``units`` ``mm`` or ``m`` (None: guessed), ``direction`` one of ``DIRECTIONS``. InputError
    naming the file and the line for anything it cannot read."""
    path = Path(path)
    try:
        text = read_bytes(path, PARSED_EXPANSION).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(path, "not a text file of poses") from None
    rows = _rows(path, text)
    header = None
    if not all(is_number(c) for c in rows[0][1]):
        header, rows = [c.lower() for c in rows[0][1]], rows[1:]
        if not rows:
            raise InputError(path, "a header and no poses")
    file_col = next((header.index(c) for c in FILE_COLUMNS if header and c in header), None)
    time_col = next((header.index(c) for c in TIME_COLUMNS if header and c in header), None)
    width = len(header) if header else len(rows[0][1])
    for n, cells in rows:
        if len(cells) != width:
            first = "the header has" if header else "the first row has"
            raise InputError(path, f"line {n}: {len(cells)} values where {first} {width}")
    pose_cols = [i for i in range(width) if i not in (file_col, time_col)]
    lines = [n for n, _ in rows]
    values = np.array([_numbers(path, n, [cells[i] for i in pose_cols]) for n, cells in rows]).reshape(len(rows), -1)
    k = values.shape[1]
    if k in LAYOUTS:
        poses, layout = _poses_per_row(path, lines, values), LAYOUTS[k]
    elif k == 4 and file_col is None and time_col is None:
        poses, layout = _stacked(path, lines, values)
    else:
        raise InputError(path, f"{k} pose values per row: expected 16 (4x4), 12 (3x4), 7 (x y z qx qy qz qw), "
                               "6 (x y z rx ry rz) or 4 (stacked matrices, without file or time columns)")
    if units is None:
        units = "m" if np.abs(poses[:, :3, 3]).max() < METRES_BELOW else "mm"
        guessed = True
    elif units in UNITS:
        guessed = False
    else:
        raise ValueError(f"units must be one of {', '.join(UNITS)}")
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {', '.join(DIRECTIONS)}")
    poses[:, :3, 3] *= UNITS[units]
    if direction == "base-to-flange":
        poses = np.array([invert_transform(p) for p in poses])
    files = [rows[i][1][file_col] for i in range(len(rows))] if file_col is not None else None
    times = None
    if time_col is not None:
        times = np.array([_numbers(path, n, [cells[time_col]])[0] for n, cells in rows])
    return PoseTable(poses, layout, units, guessed, direction, files, times)

