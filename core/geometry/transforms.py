"""Rigid transforms as 4x4 homogeneous matrices (mm, degrees at the interface).

Every transform is named ``a_to_b`` and maps points in frame a to frame b.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation, Slerp

from probecal.core.errors import InputError

RIGID_TOLERANCE = 1e-3  # orthonormality of a rotation written to 6 significant digits, as PLUS does
MAX_CONDITION = 1e12  # a 3x3 part this ill-conditioned is singular for inversion


def make_transform(rotation: np.ndarray | Rotation, translation: ArrayLike) -> np.ndarray:
    """A 4x4 transform from a 3x3 rotation matrix (or scipy Rotation) and a translation in mm."""
    if isinstance(rotation, Rotation):
        rotation = rotation.as_matrix()
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def invert_transform(a_to_b: np.ndarray) -> np.ndarray:
    """b_to_a for a rigid a_to_b."""
    r = a_to_b[:3, :3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ a_to_b[:3, 3]
    return out


def transform_points(a_to_b: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """Map (..., 3) points from frame a into frame b (any affine 4x4)."""
    points_a = np.asarray(points_a, dtype=float)
    return points_a @ a_to_b[:3, :3].T + a_to_b[:3, 3]


def rotation_from_rotvec(rotvec_rad: ArrayLike) -> np.ndarray:
    """3x3 rotation from a rotation vector (rad); OpenCV's Rodrigues, fast in tight loops."""
    return cv2.Rodrigues(np.asarray(rotvec_rad, dtype=float).reshape(3, 1))[0]


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices of (..., 3) vectors: ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return out - np.swapaxes(out, -1, -2)


def rotvec_left_jacobian(rotvec_rad: ArrayLike) -> np.ndarray:
    """3x3 ``J`` with ``R(a + da) = exp(skew(J da)) R(a)`` to first order (SO(3)'s left Jacobian)."""
    a = np.asarray(rotvec_rad, dtype=float)
    theta = float(np.linalg.norm(a))
    k = skew(a)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * k
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * (k @ k)


def pose_from_xyz_rotvec(xyz_mm: ArrayLike, rotvec_rad: ArrayLike) -> np.ndarray:
    """4x4 from a position (mm) and a rotation vector (rad), the UR pose convention in mm."""
    return make_transform(Rotation.from_rotvec(rotvec_rad), xyz_mm)


def xyz_rotvec_from_pose(a_to_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (mm) and rotation vector (rad) of a rigid 4x4."""
    return a_to_b[:3, 3].copy(), Rotation.from_matrix(a_to_b[:3, :3]).as_rotvec()


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle of a 3x3 rotation matrix in degrees (0..180), accurate near zero too."""
    return float(rotation_angles_deg(rotation))


def rotation_angles_deg(rotations: np.ndarray) -> np.ndarray:
    """Angles (degrees, 0..180) of rotation matrices (..., 3, 3), accurate near zero too."""
    rotations = np.asarray(rotations, dtype=float)
    if rotations.size == 0:
        return np.zeros(rotations.shape[:-2])
    return np.degrees(Rotation.from_matrix(rotations.reshape(-1, 3, 3)).magnitude()).reshape(rotations.shape[:-2])


def transform_error(a_to_b_est: np.ndarray, a_to_b_true: np.ndarray) -> tuple[float, float]:
    """design §5 hand-eye error: (translation norm in mm, angle of R_est^T R_true in degrees)."""
    dt = float(np.linalg.norm(a_to_b_est[:3, 3] - a_to_b_true[:3, 3]))
    return dt, rotation_angle_deg(a_to_b_est[:3, :3].T @ a_to_b_true[:3, :3])


def interpolate_pose(
    start_tool_to_base: np.ndarray, end_tool_to_base: np.ndarray, fraction: ArrayLike
) -> np.ndarray:
    """The pose(s) a moveL passes at ``fraction`` (0..1, scalar or (n,)): position linear,
    orientation Slerp. Returns a 4x4, or (n, 4, 4) for n fractions."""
    rotations = Rotation.from_matrix(np.stack([start_tool_to_base[:3, :3], end_tool_to_base[:3, :3]]))
    fraction = np.asarray(fraction, dtype=float)
    weight = fraction[..., None]
    poses = np.zeros(fraction.shape + (4, 4))
    poses[..., :3, :3] = Slerp([0.0, 1.0], rotations)(fraction).as_matrix()
    poses[..., :3, 3] = (1.0 - weight) * start_tool_to_base[:3, 3] + weight * end_tool_to_base[:3, 3]
    poses[..., 3, 3] = 1.0
    return poses


def is_rigid(matrix: np.ndarray, tol: float = 1e-4) -> bool:
    """True when a 4x4 is a proper rigid transform (orthonormal rotation, det +1)."""
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        return False
    r = m[:3, :3]
    return (
        np.allclose(r.T @ r, np.eye(3), atol=tol)
        and abs(np.linalg.det(r) - 1.0) < tol
        and np.allclose(m[3], [0, 0, 0, 1], atol=tol)
    )


def check_transform(matrix: ArrayLike, name: str, source: str | Path | None = None, *,
                    rigid: bool = False) -> np.ndarray:
    """``matrix`` as a float 4x4 of finite numbers with the last row 0 0 0 1 and, when ``rigid``, a
    proper rigid transform (orthonormal rotation, det +1, to ``RIGID_TOLERANCE``, as PLUS writes
    them); InputError naming ``source`` and the matrix (``name``) otherwise."""
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(source, f"{name} is not a 4x4 matrix of finite numbers")
    if rigid and not is_rigid(m, tol=RIGID_TOLERANCE):
        raise InputError(source, f"{name} is not a rigid transform (a rotation, a translation, last row 0 0 0 1)")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        raise InputError(source, f"{name}: the last row must be 0 0 0 1")
    return m


def matrix_from_text(text: str) -> np.ndarray:
    """A 4x4 from 16 whitespace-separated numbers, row-major (PLUS style)."""
    values = np.array([float(v) for v in text.split()], dtype=float)
    if values.size != 16:
        raise ValueError(f"expected 16 numbers, got {values.size}")
    return values.reshape(4, 4)


def text_from_matrix(matrix: np.ndarray) -> str:
    """16 numbers, row-major, with full precision (PLUS style)."""
    return " ".join(repr(float(v)) for v in np.asarray(matrix, dtype=float).ravel())


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest a 3x3 matrix in the Frobenius sense (SVD, det +1); (..., 3, 3) stacks
    are taken one by one."""
    u, _, vt = np.linalg.svd(matrix)
    u[..., :, 2] *= np.sign(np.linalg.det(u @ vt))[..., None]
    return u @ vt
