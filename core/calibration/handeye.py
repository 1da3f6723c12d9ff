"""Hand-eye / robot-world calibration: solve ``M_i X = Y N_i`` (design §1 step 5).

``M_i`` = ``tool_to_base`` (robot or tracker), ``X`` = ``image_to_tool_rigid``,
``Y`` = ``phantom_to_base``, ``N_i`` = ``image_to_phantom`` (registration). All 4x4, mm.

- :func:`qr24`: the thesis's linear least squares over the 24 entries of X's and Y's top 3x4
  blocks (derived afresh; the thesis's eq. 3.20 is garbled), then a proper SVD projection onto
  rotations and the translations re-solved with the rotations fixed.
- :func:`core.calibration.jointfit.refine` then fits them jointly with the pixel spacing.
- :func:`opencv_shah`: OpenCV's ``calibrateRobotWorldHandEye`` (SHAH), as a baseline.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.geometry.phantom import Phantom, wire_offsets
from probecal.core.geometry.probe import Spacing, image_mm_from_pixels
from probecal.core.geometry.transforms import invert_transform, make_transform, nearest_rotation, rotation_from_rotvec


def solve_translations(rx: np.ndarray, ry: np.ndarray, m: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """With the rotations fixed, the least-squares translations of X and Y:
    ``R_Mi t_X - t_Y = R_Y t_Ni - t_Mi`` stacked over all poses."""
    a = np.concatenate([np.hstack([mi[:3, :3], -np.eye(3)]) for mi in m])
    b = np.concatenate([ry @ ni[:3, 3] - mi[:3, 3] for mi, ni in zip(m, n)])
    t = np.linalg.lstsq(a, b, rcond=None)[0]
    return t[:3], t[3:]


def qr24(m: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The thesis's QR24: X and Y from ``M_i X = Y N_i`` by linear least squares, orthonormalised.

    Unknowns z = [vec(R_X), t_X, vec(R_Y), t_Y] (column-major vec). Per pose:
    ``(I kron R_M) vec(R_X) - (R_N^T kron I) vec(R_Y) = 0`` (9 rows) and
    ``R_M t_X - (t_N^T kron I) vec(R_Y) - t_Y = -t_M`` (3 rows).
    """
    rows, rhs = [], []
    eye = np.eye(3)
    for mi, ni in zip(m, n):
        rm, tm, rn, tn = mi[:3, :3], mi[:3, 3], ni[:3, :3], ni[:3, 3]
        rows.append(np.hstack([np.kron(eye, rm), np.zeros((9, 3)), -np.kron(rn.T, eye), np.zeros((9, 3))]))
        rhs.append(np.zeros(9))
        rows.append(np.hstack([np.zeros((3, 9)), rm, -np.kron(tn[None, :], eye), -eye]))
        rhs.append(-tm)
    q, r = np.linalg.qr(np.concatenate(rows))
    z = np.linalg.solve(r, q.T @ np.concatenate(rhs))
    rx = nearest_rotation(z[:9].reshape(3, 3, order="F"))
    ry = nearest_rotation(z[12:21].reshape(3, 3, order="F"))
    tx, ty = solve_translations(rx, ry, m, n)
    return make_transform(rx, tx), make_transform(ry, ty)


def x_from_known_y(m: np.ndarray, n: np.ndarray, y: np.ndarray) -> np.ndarray:
    """X when Y is known (PLUS's case): the rotation mean and translation mean of
    ``X_i = M_i^-1 Y N_i``."""
    xs = np.array([invert_transform(mi) @ y @ ni for mi, ni in zip(m, n)])
    return make_transform(nearest_rotation(xs[:, :3, :3].sum(axis=0)), xs[:, :3, 3].mean(axis=0))


def y_from_known_x(m: np.ndarray, n: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Y when X is known (the phantom registered with a given calibration): the rotation mean and
    translation mean of ``Y_i = M_i X N_i^-1``."""
    ys = np.array([mi @ x @ invert_transform(ni) for mi, ni in zip(m, n)])
    return make_transform(nearest_rotation(ys[:, :3, :3].sum(axis=0)), ys[:, :3, 3].mean(axis=0))


def opencv_shah(m: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's robot-world/hand-eye solver (SHAH). In its terms camera = image, world = phantom,
    gripper = tool: cTw = N^-1, gTb = M^-1, and it returns wTb = Y^-1 and cTg = X^-1."""
    world_to_cam = [invert_transform(ni) for ni in n]
    base_to_gripper = [invert_transform(mi) for mi in m]
    r_b2w, t_b2w, r_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(
        [w[:3, :3] for w in world_to_cam], [w[:3, 3] for w in world_to_cam],
        [b[:3, :3] for b in base_to_gripper], [b[:3, 3] for b in base_to_gripper],
        method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    )
    base_to_world = make_transform(r_b2w, np.ravel(t_b2w))
    gripper_to_cam = make_transform(r_g2c, np.ravel(t_g2c))
    return invert_transform(gripper_to_cam), invert_transform(base_to_world)


def pose_params(t: np.ndarray) -> np.ndarray:
    """A rigid transform (4, 4) as its rotation vector (rad) and translation (mm)."""
    return np.concatenate([Rotation.from_matrix(t[:3, :3]).as_rotvec(), t[:3, 3]])


def pose_from_params(params: np.ndarray) -> np.ndarray:
    """The rigid transform (4, 4) of :func:`pose_params`."""
    return make_transform(rotation_from_rotvec(params[:3]), params[3:6])


def phantom_points_from_pixels(tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray, spacing_mm: Spacing,
                               pixels: np.ndarray) -> np.ndarray:
    """(F, K, 3) phantom-frame points (mm) of (F, K, 2) pixels, mapped by ``Y^-1 M_i X diag(sx, sy, 1)``."""
    return phantom_points(tool_to_base, x, y, image_mm_from_pixels(pixels, spacing_mm))


def phantom_points(tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray, image_mm: np.ndarray) -> np.ndarray:
    """(F, K, 3) phantom-frame points (mm) of (F, K, 3) image-frame points, mapped by ``Y^-1 M_i X``."""
    image_to_phantom = np.einsum("ij,fjk,kl->fil", invert_transform(y), tool_to_base, x)
    return np.einsum("fij,fwj->fwi", image_to_phantom[:, :3, :3], image_mm) + image_to_phantom[:, None, :3, 3]


def marker_offsets(
    phantom: Phantom, markers_px: np.ndarray, tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray,
    spacing_mm: Spacing
) -> np.ndarray:
    """(F, W, 3) perpendicular offset (mm) of every marker, mapped by
    ``Y^-1 M_i X diag(sx, sy, 1)``, from its wire's line."""
    return wire_offsets(phantom.lines(), phantom_points_from_pixels(tool_to_base, x, y, spacing_mm, markers_px))
