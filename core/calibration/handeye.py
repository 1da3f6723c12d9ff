"""Hand-eye / robot-world calibration: solve ``M_i X = Y N_i`` (design §1 step 5).

``M_i`` = ``tool_to_base`` (robot or tracker), ``X`` = ``image_to_tool_rigid``,
``Y`` = ``phantom_to_base``, ``N_i`` = ``image_to_phantom`` (registration). All 4x4, mm.

- :func:`qr24`: the thesis's linear least squares over the 24 entries of X's and Y's top 3x4
  blocks (derived afresh; the thesis's eq. 3.20 is garbled), then a proper SVD projection onto
  rotations and the translations re-solved with the rotations fixed.
- :func:`refine`: a joint nonlinear fit of X, Y (unless known) and the pixel spacing (sx, sy),
  or for a fan image the sound speed's stretch of its beams' depths, with a robust loss, to one
  of two objectives: ``all-wire`` (every marker's distance to its wire) or ``middle-wire``
  (PLUS's: each middle dot's distance to the middle-wire point that the N's dot ratio gives, in
  the phantom frame).
- :func:`opencv_shah`: OpenCV's ``calibrateRobotWorldHandEye`` (SHAH), as a baseline.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from probecal.core.calibration.kinematics import ArmKinematics
from probecal.core.calibration.metrics import middle_wire_points
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom, wire_axes, wire_offsets
from probecal.core.geometry.probe import image_mm_from_pixels
from probecal.core.geometry.transforms import (
    invert_transform,
    make_transform,
    nearest_rotation,
    rotation_from_rotvec,
    rotvec_left_jacobian,
    skew,
)

FIRST_PASS_SCALE_MM = 1.0  # Huber loss: residuals beyond the scale count linearly, not squared
SCALE_PER_MEDIAN = 4.0  # second pass: scale = this many times the median marker distance
MIN_SCALE_MM = 0.05
# A fit that starts from a previous one (the bootstrap's refits, the echo-peak and loose-prior
# refits) stops once a step changes the cost by less than this fraction (least_squares' ftol; its
# default 1e-8 holds the others): one step fewer, a third of the bootstrap's time, and 2e-5 mm at
# the image corners (230 twin frames).
REFIT_FTOL = 1e-5


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


FIT_OBJECTIVES = ("all-wire", "middle-wire")


@dataclass(frozen=True)
class Refined:
    """Result of the joint fit: X (rigid), Y, spacing and the residual distances (mm): (F, W) of
    every marker to its wire (``all-wire``) or (F, L) of every middle dot to its middle-wire point
    (``middle-wire``); NaN where missing. With the wires fitted, ``wire_shifts_mm`` (W, 2, 3)
    holds how far each wire's front and back end points sit off the definition (phantom frame).
    With the arm's kinematics fitted, ``kinematic_units`` holds its deviations
    (:mod:`core.calibration.kinematics`, units of their prior's standard deviation)."""

    image_to_tool_rigid: np.ndarray
    phantom_to_base: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    residuals_mm: np.ndarray
    wire_shifts_mm: np.ndarray | None = None
    kinematic_units: np.ndarray | None = None
    stretch: float | None = None  # a fan image's: its beams' depths below the face over what it shows


class PreviousFit(Protocol):
    """What :func:`refine` starts from besides X, Y and the spacing: a :class:`Refined` or an
    objective's solution."""

    wire_shifts_mm: np.ndarray | None
    kinematic_units: np.ndarray | None


def _pose_params(t: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(t[:3, :3]).as_rotvec(), t[:3, 3]])


def _pose(params: np.ndarray) -> np.ndarray:
    return make_transform(rotation_from_rotvec(params[:3]), params[3:6])


def phantom_points_from_pixels(tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray, spacing_mm,
                               pixels: np.ndarray) -> np.ndarray:
    """(F, K, 3) phantom-frame points (mm) of (F, K, 2) pixels, mapped by ``Y^-1 M_i X diag(sx, sy, 1)``."""
    return _phantom_points(tool_to_base, x, y, image_mm_from_pixels(pixels, spacing_mm))


def _phantom_points(tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray, image_mm: np.ndarray) -> np.ndarray:
    """(F, K, 3) phantom-frame points (mm) of (F, K, 3) image-frame points, mapped by ``Y^-1 M_i X``."""
    image_to_phantom = np.einsum("ij,fjk,kl->fil", invert_transform(y), tool_to_base, x)
    return np.einsum("fij,fwj->fwi", image_to_phantom[:, :3, :3], image_mm) + image_to_phantom[:, None, :3, 3]


class _ImageScale:
    """How :func:`refine` maps pixels (F, K, 2) to image mm and which parameters it fits for it:
    log sx and log sy (pixel (u, v) at (u sx, v sy)); or, for a fan image, the log of the stretch
    k of its beams' depths below the face, its square pixels at their nominal spacing s (pixel p
    at s (f + k (p - f)), f where p's beam leaves the face: a scanner converts echo times to
    depths at its own sound speed, which turns no beam)."""

    def __init__(self, pixels: np.ndarray, spacing0_mm, fan: Fan | None):
        self.pixels, self.fan, self.spacing0 = pixels, fan, np.asarray(spacing0_mm, dtype=float)
        self.face = None if fan is None else fan.face_points(pixels)

    @property
    def n_params(self) -> int:
        return 2 if self.fan is None else 1

    def initial(self) -> np.ndarray:
        return np.log(self.spacing0) if self.fan is None else np.zeros(1)

    def spacing(self, params: np.ndarray) -> np.ndarray:
        return np.exp(params) if self.fan is None else self.spacing0

    def points(self, params: np.ndarray) -> np.ndarray:
        """(F, K, 3) image-frame points (mm)."""
        if self.face is None:
            return image_mm_from_pixels(self.pixels, np.exp(params))
        return image_mm_from_pixels(self.face + np.exp(params[0]) * (self.pixels - self.face), self.spacing0)

    def derivatives(self, params: np.ndarray) -> np.ndarray:
        """(F, K, 2, n) the image-frame points' in-plane derivatives by the parameters."""
        if self.face is None:
            scaled = self.pixels * np.exp(params)
            return scaled[..., :, None] * np.eye(2)
        return (np.exp(params[0]) * (self.pixels - self.face) * self.spacing0)[..., None]


def marker_offsets(
    phantom: Phantom, markers_px: np.ndarray, tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray, spacing_mm
) -> np.ndarray:
    """(F, W, 3) perpendicular offset (mm) of every marker, mapped by
    ``Y^-1 M_i X diag(sx, sy, 1)``, from its wire's line."""
    return wire_offsets(phantom.lines(), phantom_points_from_pixels(tool_to_base, x, y, spacing_mm, markers_px))


def wire_prior_whitening(phantom: Phantom, across: np.ndarray, end_sigma_mm: float | np.ndarray,
                          layer_sigma: tuple[float, float] | None = None,
                          diagonal_turn_mm: float | None = None) -> np.ndarray:
    """(4W, 4W) the square root of the inverse covariance of the wires' end-point shifts across
    their wires (``across``: (W, 3, 2) unit vectors; shifts ordered wire, end, direction): each end
    point off by ``end_sigma_mm`` (1 sd per axis; one value, or one per wire) alone, with
    ``layer_sigma`` (translation mm, rotation rad; 1 sd per axis) every layer also moved rigidly
    about its centre, its three wires together (a layer strung or glued off its place), and with
    ``diagonal_turn_mm`` every layer's diagonal also turned about its middle within the layer, its
    two ends that far (1 sd) across it the opposite ways (what sets an N's ratio changes along
    the wires, which no single frame shows)."""
    n = 4 * len(across)
    ends = np.repeat(np.broadcast_to(np.asarray(end_sigma_mm, dtype=float), (len(across),)), 4)
    if layer_sigma is None and diagonal_turn_mm is None:  # independent ends: a diagonal prior
        return np.diag(1.0 / ends)
    covariance = np.diag(ends**2)
    if diagonal_turn_mm is not None:
        for k in range(len(phantom.layers)):
            offsets = np.zeros((len(phantom.layers), 2))
            offsets[k] = (-1.0, 1.0)
            turn = np.einsum("wij,wei->wej", across, phantom.diagonal_shifts(offsets)).ravel()
            covariance += diagonal_turn_mm**2 * np.outer(turn, turn)
    if layer_sigma is not None:
        lines, first = phantom.lines(), 0  # (W, 2, 3)
        for layer in phantom.layers:
            wires = slice(first, first + len(layer.wires))
            first += len(layer.wires)
            centre = lines[wires].reshape(-1, 3).mean(axis=0)
            # d(shift across) / d(rotation vector, translation) of every end point of the layer
            rotation = -np.einsum("wij,weik->wejk", across[wires], skew(lines[wires] - centre))  # (w, 2, 2, 3)
            translation = np.broadcast_to(across[wires].transpose(0, 2, 1)[:, None], rotation.shape)
            block = np.zeros((n, 3))
            for jacobian, sigma in ((rotation, layer_sigma[1]), (translation, layer_sigma[0])):
                block[4 * wires.start:4 * wires.stop] = jacobian.reshape(-1, 3)
                covariance += sigma**2 * block @ block.T
    values, vectors = np.linalg.eigh(covariance)
    return (vectors / np.sqrt(values)) @ vectors.T


def _mapping_jacobian(tool_to_base: np.ndarray, params: np.ndarray, x: np.ndarray, y: np.ndarray,
                      points: np.ndarray, scale_derivatives: np.ndarray | None, solve_y: bool) -> np.ndarray:
    """(F, K, 3, P) derivative of :func:`_phantom_points` of image ``points`` (F, K, 3) by
    :func:`refine`'s parameters: X's rotation vector and translation, then Y's (if solved), then the
    image scale's (if solved; ``scale_derivatives`` (F, K, 2, n), :class:`_ImageScale`)."""
    ry_t = y[:3, :3].T
    to_phantom = np.einsum("ij,fjk->fik", ry_t, tool_to_base[:, :3, :3])  # R_Y^T R_Mi
    rotated = points @ x[:3, :3].T  # R_X s
    shape = points.shape[:2] + (3, 3)
    blocks = [
        -np.einsum("fij,fkjl->fkil", to_phantom, skew(rotated)) @ rotvec_left_jacobian(params[:3]),
        np.broadcast_to(to_phantom[:, None], shape),
    ]
    if solve_y:
        in_base = np.einsum("fij,fkj->fki", tool_to_base[:, :3, :3], rotated + x[:3, 3]) + tool_to_base[:, None, :3, 3]
        blocks += [ry_t @ skew(in_base - y[:3, 3]) @ rotvec_left_jacobian(params[6:9]), np.broadcast_to(-ry_t, shape)]
    if scale_derivatives is not None:
        axes = to_phantom @ x[:3, :3]  # image x and y axes in the phantom frame
        blocks.append(axes[:, None, :, :2] @ scale_derivatives)
    return np.concatenate(blocks, axis=-1)


def refine(
    phantom: Phantom,
    markers_px: np.ndarray,
    tool_to_base: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    spacing0_mm,
    solve_y: bool = True,
    solve_spacing: bool = True,
    objective: str = "all-wire",
    wire_sigma_mm: float | np.ndarray = 0.0,
    layer_sigma: tuple[float, float] | None = None,
    diagonal_turn_mm: float | None = None,
    kinematics: ArmKinematics | None = None,
    previous: PreviousFit | None = None,
    fan: Fan | None = None,
    stretch0: float = 1.0,
) -> Refined:
    """Joint robust fit of X, Y (unless known) and (sx, sy) over all frames to ``objective``
    (see the module docstring), with the analytic Jacobian. ``markers_px`` is (F, W, 2) in phantom
    wire order with NaN for missing markers. The middle-wire points are computed once: a dot ratio
    along a line survives any scaling, so they do not depend on the spacing.

    With ``wire_sigma_mm`` > 0 (``all-wire`` only; one value or one per wire) a last pass also
    fits where the wires are: each end point may move across its wire, under a Gaussian prior of
    that standard deviation per axis (a built phantom's tolerance). A wire seen from many poses is located by the poses
    themselves, so a wire built off its definition no longer pulls the calibration along. That
    pass holds the spacing where the definition set it: wires that move together could otherwise
    stretch the pattern and trade that for the spacing. With ``layer_sigma`` (translation mm,
    rotation rad, 1 sd per axis) each layer may also move rigidly, its wires together, under that
    prior, and with ``diagonal_turn_mm`` each diagonal may turn within its layer
    (:func:`wire_prior_whitening`).

    With ``kinematics`` the flange poses are the arm's (``core.calibration.kinematics``):
    ``tool_to_base`` is then only what the controller reported, and after the first pass the
    arm's kinematic deviations are fitted too, under their prior (one unit per parameter).

    ``previous`` (a fit of the same objective to much the same frames, whose X, Y and spacing are
    then ``x0``, ``y0`` and ``spacing0_mm``) starts every pass where it ended, arm and wires
    included, and the first pass, there to come near from a rough start, is skipped.

    With ``fan`` (a fan image's, in its pixels) the spacing stays at ``spacing0_mm`` (the
    scanner's, square pixels) and what is solved instead is the stretch of the beams' depths below
    the face (:class:`_ImageScale`; from ``stretch0``), which the result holds."""
    if objective not in FIT_OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}")
    markers_px = np.asarray(markers_px, dtype=float)
    if objective == "all-wire":
        pixels = markers_px
        targets, direction, length, project = wire_axes(phantom.lines())
        across = np.linalg.svd(project)[0][..., :2]  # (W, 3, 2): two unit vectors across each wire
        # A marker's offset from its wire has no component along it: its two components across
        # the wire are the residuals (a third, always zero, would only cost time).
        project = across.transpose(0, 2, 1)  # (W, 2, 3)
        valid = np.all(np.isfinite(pixels), axis=2)
    else:
        pixels, targets, project = markers_px[:, 1::3], middle_wire_points(phantom, markers_px), None
        valid = np.all(np.isfinite(pixels), axis=2) & np.all(np.isfinite(targets), axis=2)
    filled = np.where(valid[..., None], pixels, 0.0)
    image = _ImageScale(filled, spacing0_mm, fan)
    n_pose, n_wires = 12 if solve_y else 6, phantom.n_wires
    n_kin = 0 if kinematics is None else kinematics.n_params
    # What the parameter vector holds after the poses: the log spacing while it is solved, the
    # arm's deviations while they are fitted, then (last pass) the wires' end-point shifts, with
    # the spacing held where the definition set it. The closures below read these and the
    # priors' weights as the passes rebind them.
    spacing_free, kin_free, wires_free = solve_spacing, False, False
    held_scale: np.ndarray = image.initial() + (np.log(stretch0) if fan is not None else 0.0)
    kin_weight = 0.0  # weight of the arm's prior: the markers' noise (mm) per prior unit
    prior = np.zeros((0, 0))  # the wires' prior: the markers' noise (mm) times its whitening
    p0 = np.concatenate([_pose_params(x0), _pose_params(y0) if solve_y else [],
                         held_scale if solve_spacing else []])

    def kin_at() -> int:
        return n_pose + (image.n_params if spacing_free else 0)

    def wires_at() -> int:
        return kin_at() + (n_kin if kin_free else 0)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        x = _pose(p[:6])
        y = _pose(p[6:12]) if solve_y else y0
        scale = p[n_pose:kin_at()] if spacing_free else held_scale
        poses = tool_to_base if kinematics is None or not kin_free else kinematics.poses(p[kin_at():wires_at()])
        return x, y, scale, poses

    def across_shifts(p: np.ndarray) -> np.ndarray:
        """(W, 2, 2) end-point shifts of the wires along their two across directions (zero while
        they are held)."""
        if not wires_free:
            return np.zeros((n_wires, 2, 2))
        return p[wires_at():].reshape(-1, 2, 2)

    def shifts(p: np.ndarray) -> np.ndarray:
        """(W, 2, 3) end-point shifts of the wires in the phantom frame."""
        return np.einsum("wij,wej->wei", across, across_shifts(p))

    def along(points: np.ndarray) -> np.ndarray:
        """(F, W) fraction of the way along each wire of every point (F, W, 3)."""
        return np.einsum("fwi,wi->fw", points - targets, direction) / length

    def mapped(p: np.ndarray) -> np.ndarray:
        x, y, scale, poses = unpack(p)
        return _phantom_points(poses, x, y, image.points(scale))

    def offsets(p: np.ndarray) -> np.ndarray:
        points = mapped(p)
        if project is None:
            return points - targets
        t, ends = along(points), across_shifts(p)
        moved = ends[None, :, 0] + t[..., None] * (ends[None, :, 1] - ends[None, :, 0])
        return np.einsum("wij,fwj->fwi", project, points - targets) - moved

    def residuals(p: np.ndarray) -> np.ndarray:
        return np.concatenate([offsets(p)[valid].ravel(), kin_weight * p[kin_at():wires_at()],
                               prior @ p[wires_at():]])

    def jacobian(p: np.ndarray) -> np.ndarray:
        x, y, scale, poses = unpack(p)
        points = image.points(scale)
        j = _mapping_jacobian(poses, p, x, y, points, image.derivatives(scale) if spacing_free else None, solve_y)
        if kin_free:
            assert kinematics is not None
            in_tool = points @ x[:3, :3].T + x[:3, 3]  # (F, K, 3)
            d = kinematics.jacobian  # (F, 4, 4, n)
            rotation = np.einsum("ij,fjkn->fkin", y[:3, :3].T, d[:, :3, :3])  # (F, 3, 3, n): k, then i, n
            j_kin = (in_tool @ rotation.reshape(len(d), 3, -1)).reshape(in_tool.shape + (n_kin,))
            j = np.concatenate([j, j_kin + np.einsum("ij,fjn->fin", y[:3, :3].T, d[:, :3, 3])[:, None]], axis=-1)
        if project is not None:
            ends = across_shifts(p)
            slant = np.einsum("wi,wj->wij", ends[:, 1] - ends[:, 0], direction / length[:, None])
            j = (project - slant)[None] @ j
        k = wires_at()
        if wires_free:
            t = along(mapped(p))
            wires = np.zeros(t.shape + (2, n_wires, 2, 2))
            for w in range(n_wires):
                wires[:, w, :, w, 0] = -(1.0 - t[:, w, None, None]) * np.eye(2)
                wires[:, w, :, w, 1] = -t[:, w, None, None] * np.eye(2)
            j = np.concatenate([j, wires.reshape(t.shape + (2, -1))], axis=-1)
        rows = [j[valid].reshape(-1, len(p))]
        for first, last, weight in ((kin_at(), k, kin_weight * np.eye(k - kin_at())), (k, len(p), prior)):
            if last > first:
                block = np.zeros((last - first, len(p)))
                block[:, first:last] = weight
                rows.append(block)
        return np.concatenate(rows)

    def distances(p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(offsets(p), axis=2)

    # The noise level differs a lot between a clean simulation and a freehand recording, so the
    # robust scale is set from the data: a first pass at a generous scale (or a previous fit), then
    # a second pass at a few times the median residual distance, which still discounts
    # mislabelled markers.
    units, located = (None, None) if previous is None else (previous.kinematic_units, previous.wire_shifts_mm)
    if previous is None:
        start = least_squares(residuals, p0, jac=jacobian, loss="huber", f_scale=FIRST_PASS_SCALE_MM, x_scale="jac",
                              max_nfev=200).x
    else:
        start = p0
    if kinematics is not None:
        kin_free = True
        start = np.concatenate([start, np.zeros(n_kin) if units is None else units])
    median = float(np.median(distances(start)[valid]))
    scale = max(MIN_SCALE_MM, SCALE_PER_MEDIAN * median)
    # The median distance of isotropic 2D noise is 1.18 times its per-axis deviation.
    noise = max(median / 1.18, MIN_SCALE_MM / SCALE_PER_MEDIAN)
    kin_weight = noise
    ftol = 1e-8 if previous is None else REFIT_FTOL
    fit = least_squares(residuals, start, jac=jacobian, loss="huber", f_scale=scale, x_scale="jac", max_nfev=200,
                        ftol=ftol)
    wired = bool(np.all(np.asarray(wire_sigma_mm) > 0.0)) and project is not None
    if wired:
        noise = max(float(np.median(distances(fit.x)[valid])) / 1.18, MIN_SCALE_MM / SCALE_PER_MEDIAN)
        prior = noise * wire_prior_whitening(phantom, across, wire_sigma_mm, layer_sigma, diagonal_turn_mm)
        if kinematics is not None:
            kin_weight = noise
        held_scale = unpack(fit.x)[2]
        kin = fit.x[kin_at():wires_at()]
        spacing_free, wires_free = False, True
        wires0 = np.zeros(4 * n_wires) if located is None else np.einsum("wij,wei->wej", across, located).ravel()
        start = np.concatenate([fit.x[:n_pose], kin, wires0])
        fit = least_squares(residuals, start, jac=jacobian, loss="huber", f_scale=scale, x_scale="jac", max_nfev=200,
                            ftol=ftol)
    x, y, fitted_scale, _ = unpack(fit.x)
    residuals_mm = distances(fit.x)
    residuals_mm[~valid] = np.nan
    spacing = image.spacing(fitted_scale)
    return Refined(x, y, (float(spacing[0]), float(spacing[1])), residuals_mm, shifts(fit.x) if wired else None,
                   None if not kin_free else fit.x[kin_at():wires_at()],
                   None if fan is None else float(np.exp(fitted_scale[0])))
