"""The joint fit: X = ``image_to_tool_rigid``, Y = ``phantom_to_base`` (unless known) and the pixel
spacing (sx, sy), or for a fan image the sound speed's stretch of its beams' depths, fitted with
a robust loss to one of two objectives: ``all-wire`` (every marker's distance to its wire) or
``middle-wire`` (PLUS's: each middle dot's distance to the middle-wire point that the N's dot
ratio gives, in the phantom frame). All mm.

:func:`refine` runs it in passes, each a :class:`_Pass` over one :class:`_Problem`: a first pass
at a generous robust scale (skipped when a previous fit gives the start), a second at a few
times the median residual (with the arm's kinematic deviations, when the arm is known), and for
``all-wire`` under a :class:`WirePrior` a last pass that also locates the wires.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from scipy.optimize import least_squares

from probecal.core.calibration.handeye import phantom_points, pose_from_params, pose_params
from probecal.core.calibration.kinematics import ArmKinematics
from probecal.core.calibration.metrics import middle_wire_points
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom, wire_axes
from probecal.core.geometry.probe import Spacing, image_mm_from_pixels
from probecal.core.geometry.transforms import rotvec_left_jacobian, skew

FIT_OBJECTIVES = ("all-wire", "middle-wire")
FIRST_PASS_SCALE_MM = 1.0  # Huber loss: residuals beyond the scale count linearly, not squared
SCALE_PER_MEDIAN = 4.0  # second pass: scale = this many times the median marker distance
MIN_SCALE_MM = 0.05
# A fit that starts from a previous one (the bootstrap's refits, the echo-peak and loose-prior
# refits) stops once a step changes the cost by less than this fraction (least_squares' ftol; its
# default 1e-8 holds the others): one step fewer, a third of the bootstrap's time, and 2e-5 mm at
# the image corners (230 twin frames).
REFIT_FTOL = 1e-5
MAX_EVALUATIONS = 200
MEDIAN_PER_NOISE = 1.18  # the median distance of isotropic 2D noise over its per-axis sd


@dataclass(frozen=True)
class WirePrior:
    """How far a built phantom's wires may sit off its definition (1 sd per axis), the prior under
    which the ``all-wire`` fit's last pass locates them: each end point across its wire by
    ``end_sigma_mm`` (0 holds the wires), each diagonal's ends ``diagonal_factor`` times as far
    (None: as far as the others' ends), each layer moved rigidly about its centre, its wires
    together, by ``layer_sigma`` (mm, rad; None: no layer moves but by its wires) and each
    diagonal turned about its middle within its layer, its ends ``diagonal_turn_mm`` across it
    the opposite ways (None: no turn)."""

    end_sigma_mm: float = 0.0
    diagonal_factor: float | None = None
    layer_sigma: tuple[float, float] | None = None
    diagonal_turn_mm: float | None = None

    def per_wire_mm(self, n_wires: int) -> float | np.ndarray:
        """Each wire's end-point sd (mm): one value, or (W,) with the diagonals' apart."""
        if self.diagonal_factor is None:
            return self.end_sigma_mm
        diagonal = np.arange(n_wires) % 3 == 1
        return np.where(diagonal, self.diagonal_factor * self.end_sigma_mm, self.end_sigma_mm)

    @property
    def locates(self) -> bool:
        """Whether every wire may move under this prior."""
        return self.end_sigma_mm > 0.0 and (self.diagonal_factor is None or self.diagonal_factor > 0.0)

    def whitening(self, phantom: Phantom, across: np.ndarray) -> np.ndarray:
        """(4W, 4W) the square root of the inverse covariance of the wires' end-point shifts across
        their wires (``across``: (W, 3, 2) unit vectors; shifts ordered wire, end, direction)."""
        ends = np.repeat(np.broadcast_to(np.asarray(self.per_wire_mm(len(across)), dtype=float), (len(across),)), 4)
        if self.layer_sigma is None and self.diagonal_turn_mm is None:  # independent ends: a diagonal prior
            return np.diag(1.0 / ends)
        covariance = np.diag(ends**2)
        if self.diagonal_turn_mm is not None:
            _add_turns(covariance, phantom, across, self.diagonal_turn_mm)
        if self.layer_sigma is not None:
            _add_layers(covariance, phantom, across, self.layer_sigma)
        values, vectors = np.linalg.eigh(covariance)
        return (vectors / np.sqrt(values)) @ vectors.T


def _add_turns(covariance: np.ndarray, phantom: Phantom, across: np.ndarray, turn_mm: float) -> None:
    """Add to ``covariance`` (4W, 4W) the end-point shifts of every layer's diagonal turned about
    its middle, its ends ``turn_mm`` (1 sd) across it the opposite ways (what sets an N's ratio
    changes along the wires, which no single frame shows)."""
    for k in range(len(phantom.layers)):
        offsets = np.zeros((len(phantom.layers), 2))
        offsets[k] = (-1.0, 1.0)
        turn = np.einsum("wij,wei->wej", across, phantom.diagonal_shifts(offsets)).ravel()
        covariance += turn_mm**2 * np.outer(turn, turn)


def _add_layers(covariance: np.ndarray, phantom: Phantom, across: np.ndarray, layer_sigma: tuple[float, float]) -> None:
    """Add to ``covariance`` (4W, 4W) the end-point shifts of every layer moved rigidly about its
    centre by ``layer_sigma`` (translation mm, rotation rad; 1 sd per axis), its wires together."""
    n = len(covariance)
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


@dataclass(frozen=True)
class Refined:
    """Result of the joint fit: X (rigid), Y, spacing and the residual distances (mm): (F, W) of
    every marker to its wire (``all-wire``) or (F, L) of every middle dot to its middle-wire point
    (``middle-wire``); NaN where missing. With the wires fitted, ``wire_shifts_mm`` (W, 2, 3)
    holds how far each wire's front and back end points sit off the definition (phantom frame).
    With the arm's kinematics fitted, ``kinematic_units`` holds its deviations
    (:mod:`core.calibration.kinematics`, units of their prior's standard deviation) and
    ``kinematic_determined``, when asked for, how far the markers determine each
    (:meth:`_Pass.determined`)."""

    image_to_tool_rigid: np.ndarray
    phantom_to_base: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    residuals_mm: np.ndarray
    wire_shifts_mm: np.ndarray | None = None
    kinematic_units: np.ndarray | None = None
    stretch: float | None = None  # a fan image's: its beams' depths below the face over what it shows
    kinematic_determined: np.ndarray | None = None


class PreviousFit(Protocol):
    """What :func:`refine` starts from besides X, Y and the spacing: a :class:`Refined` or an
    objective's solution."""

    wire_shifts_mm: np.ndarray | None
    kinematic_units: np.ndarray | None
    stretch: float | None


class _ImageScale:
    """How :func:`refine` maps pixels (F, K, 2) to image mm and which parameters it fits for it:
    log sx and log sy (pixel (u, v) at (u sx, v sy)); or, for a fan image, the log of the stretch
    k of its beams' depths below the face, its square pixels at their nominal spacing s (pixel p
    at s (f + k (p - f)), f where p's beam leaves the face: a scanner converts echo times to
    depths at its own sound speed, which turns no beam)."""

    def __init__(self, pixels: np.ndarray, spacing0_mm: Spacing, fan: Fan | None):
        self.pixels, self.fan, self.spacing0 = pixels, fan, np.asarray(spacing0_mm, dtype=float)
        self.face = None if fan is None else fan.face_points(pixels)

    @property
    def n_params(self) -> int:
        return 2 if self.fan is None else 1

    def initial(self, stretch0: float) -> np.ndarray:
        return np.log(self.spacing0) if self.fan is None else np.zeros(1) + np.log(stretch0)

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


@dataclass(frozen=True)
class _Problem:
    """What every pass fits, and to what: the markers' pixels (F, K, 2; zero where not ``valid``),
    the targets (``all-wire``: each wire's front end (W, 3) with its ``direction`` and
    ``length``, ``project`` (W, 2, 3) onto the two unit vectors ``across`` it; ``middle-wire``:
    each middle dot's middle-wire point (F, L, 3), no projection), the flange poses (F, 4, 4),
    Y held at ``y0`` unless ``solve_y``, X held at ``held_x`` when given, and the arm's kinematics if
    they are fitted."""

    image: _ImageScale
    valid: np.ndarray
    targets: np.ndarray
    direction: np.ndarray | None
    length: np.ndarray | None
    across: np.ndarray | None
    project: np.ndarray | None
    tool_to_base: np.ndarray
    y0: np.ndarray
    solve_y: bool
    kinematics: ArmKinematics | None
    held_x: np.ndarray | None = None

    @classmethod
    def of(cls, phantom: Phantom, markers_px: np.ndarray, objective: str,
           image_scale: tuple[Sequence[float] | np.ndarray,
           Fan | None], tool_to_base: np.ndarray, y0: np.ndarray, solve_y: bool,
           kinematics: ArmKinematics | None, held_x: np.ndarray | None = None) -> _Problem:
        if objective == "all-wire":
            targets, direction, length, project = wire_axes(phantom.lines())
            across = np.linalg.svd(project)[0][..., :2]  # (W, 3, 2): two unit vectors across each wire
            # A marker's offset from its wire has no component along it: its two components
            # across the wire are the residuals (a third, always zero, would only cost time).
            project = across.transpose(0, 2, 1)
            pixels = markers_px
            valid = np.all(np.isfinite(pixels), axis=2)
        else:
            pixels, targets, direction, length, across, project = markers_px[:, 1::3], \
                middle_wire_points(phantom, markers_px), None, None, None, None
            valid = np.all(np.isfinite(pixels), axis=2) & np.all(np.isfinite(targets), axis=2)
        image = _ImageScale(np.where(valid[..., None], pixels, 0.0), *image_scale)
        return cls(image, valid, targets, direction, length, across, project, tool_to_base, y0, solve_y, kinematics,
                   held_x)

    @property
    def n_pose(self) -> int:
        return self.y_at + (6 if self.solve_y else 0)

    @property
    def y_at(self) -> int:
        """Where Y's parameters start: after X's, unless X is held."""
        return 0 if self.held_x is not None else 6

    @property
    def n_kin(self) -> int:
        return 0 if self.kinematics is None else self.kinematics.n_params

    @property
    def n_wires(self) -> int:
        return len(self.targets) if self.across is not None else 0

    def along(self, points: np.ndarray) -> np.ndarray:
        """(F, W) fraction of the way along each wire of every point (F, W, 3)."""
        assert self.direction is not None and self.length is not None
        return np.einsum("fwi,wi->fw", points - self.targets, self.direction) / self.length


@dataclass(frozen=True)
class _Pass:
    """One pass of the joint fit: what its parameter vector holds after the poses (X's rotation
    vector and translation, then Y's if solved), and the priors' weights. The log image scale
    while ``spacing_free`` (else ``held_scale``), the arm's deviations while ``kin_free`` (under
    their prior, ``kin_weight``: the markers' noise (mm) per prior unit), then the wires'
    end-point shifts across them while ``wires_free`` (under ``prior``: the markers' noise (mm)
    times the wire prior's whitening)."""

    problem: _Problem
    spacing_free: bool
    held_scale: np.ndarray
    kin_free: bool = False
    kin_weight: float = 0.0
    wires_free: bool = False
    prior: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def kin_at(self) -> int:
        return self.problem.n_pose + (self.problem.image.n_params if self.spacing_free else 0)

    @property
    def wires_at(self) -> int:
        return self.kin_at + (self.problem.n_kin if self.kin_free else 0)

    def unpack(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """X, Y, the image scale's parameters and the flange poses (F, 4, 4) of ``p``."""
        problem = self.problem
        x = pose_from_params(p[:6]) if problem.held_x is None else problem.held_x
        y = pose_from_params(p[problem.y_at:problem.y_at + 6]) if problem.solve_y else problem.y0
        scale = p[problem.n_pose:self.kin_at] if self.spacing_free else self.held_scale
        poses = problem.tool_to_base
        if problem.kinematics is not None and self.kin_free:
            poses = problem.kinematics.poses(p[self.kin_at:self.wires_at])
        return x, y, scale, poses

    def across_shifts(self, p: np.ndarray) -> np.ndarray:
        """(W, 2, 2) end-point shifts of the wires along their two across directions (zero while
        they are held)."""
        if not self.wires_free:
            return np.zeros((self.problem.n_wires, 2, 2))
        return p[self.wires_at:].reshape(-1, 2, 2)

    def mapped(self, p: np.ndarray) -> np.ndarray:
        x, y, scale, poses = self.unpack(p)
        return phantom_points(poses, x, y, self.problem.image.points(scale))

    def offsets(self, p: np.ndarray) -> np.ndarray:
        """(F, K, 2 or 3) every marker's offset from its target (mm)."""
        problem, points = self.problem, self.mapped(p)
        if problem.project is None:
            return points - problem.targets
        t, ends = problem.along(points), self.across_shifts(p)
        moved = ends[None, :, 0] + t[..., None] * (ends[None, :, 1] - ends[None, :, 0])
        return np.einsum("wij,fwj->fwi", problem.project, points - problem.targets) - moved

    def distances(self, p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(self.offsets(p), axis=2)

    def noise(self, p: np.ndarray) -> float:
        """The markers' noise (mm, 1 sd per axis) that ``p`` leaves, from their median distance."""
        return max(float(np.median(self.distances(p)[self.problem.valid])) / MEDIAN_PER_NOISE,
                   MIN_SCALE_MM / SCALE_PER_MEDIAN)

    def residuals(self, p: np.ndarray) -> np.ndarray:
        return np.concatenate([self.offsets(p)[self.problem.valid].ravel(),
                               self.kin_weight * p[self.kin_at:self.wires_at], self.prior @ p[self.wires_at:]])

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        problem = self.problem
        x, y, scale, poses = self.unpack(p)
        points = problem.image.points(scale)
        derivatives = problem.image.derivatives(scale) if self.spacing_free else None
        j = _mapping_jacobian(poses, p, x, y, points, derivatives, problem.solve_y, problem.held_x is None)
        if self.kin_free:
            j = np.concatenate([j, self._kinematic_jacobian(x, y, points)], axis=-1)
        if problem.project is not None:
            j = self._projected(j, p)
        rows = [j[problem.valid].reshape(-1, len(p))]
        k = self.wires_at
        for first, last, weight in ((self.kin_at, k, self.kin_weight * np.eye(k - self.kin_at)),
                                    (k, len(p), self.prior)):
            if last > first:
                block = np.zeros((last - first, len(p)))
                block[:, first:last] = weight
                rows.append(block)
        return np.concatenate(rows)

    def _kinematic_jacobian(self, x: np.ndarray, y: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(F, K, 3, n) the phantom-frame points' derivatives by the arm's deviations."""
        kinematics = self.problem.kinematics
        assert kinematics is not None
        in_tool = points @ x[:3, :3].T + x[:3, 3]  # (F, K, 3)
        d = kinematics.jacobian  # (F, 4, 4, n)
        rotation = np.einsum("ij,fjkn->fkin", y[:3, :3].T, d[:, :3, :3])  # (F, 3, 3, n): k, then i, n
        j_kin = (in_tool @ rotation.reshape(len(d), 3, -1)).reshape(in_tool.shape + (self.problem.n_kin,))
        return j_kin + np.einsum("ij,fjn->fin", y[:3, :3].T, d[:, :3, 3])[:, None]

    def _projected(self, j: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The Jacobian of the offsets across the wires, with the wires' shifts' own columns."""
        problem = self.problem
        assert problem.direction is not None and problem.length is not None and problem.project is not None
        ends = self.across_shifts(p)
        slant = np.einsum("wi,wj->wij", ends[:, 1] - ends[:, 0], problem.direction / problem.length[:, None])
        j = (problem.project - slant)[None] @ j
        if not self.wires_free:
            return j
        t = problem.along(self.mapped(p))
        n_wires = problem.n_wires
        wires = np.zeros(t.shape + (2, n_wires, 2, 2))
        for w in range(n_wires):
            wires[:, w, :, w, 0] = -(1.0 - t[:, w, None, None]) * np.eye(2)
            wires[:, w, :, w, 1] = -t[:, w, None, None] * np.eye(2)
        return np.concatenate([j, wires.reshape(t.shape + (2, -1))], axis=-1)

    def solve(self, start: np.ndarray, f_scale: float, ftol: float = 1e-8) -> np.ndarray:
        """The parameters that minimise this pass's robust (Huber) cost at ``f_scale`` mm."""
        return least_squares(self.residuals, start, jac=self.jacobian, loss="huber", f_scale=f_scale, x_scale="jac",
                             max_nfev=MAX_EVALUATIONS, ftol=ftol).x

    def refined(self, p: np.ndarray) -> Refined:
        x, y, scale, _ = self.unpack(p)
        residuals_mm = self.distances(p)
        residuals_mm[~self.problem.valid] = np.nan
        spacing = self.problem.image.spacing(scale)
        shifts = None
        if self.wires_free:
            assert self.problem.across is not None
            shifts = np.einsum("wij,wej->wei", self.problem.across, self.across_shifts(p))
        return Refined(x, y, (float(spacing[0]), float(spacing[1])), residuals_mm, shifts,
                       p[self.kin_at:self.wires_at] if self.kin_free else None,
                       None if self.problem.image.fan is None else float(np.exp(scale[0])))

    def determined(self, p: np.ndarray) -> np.ndarray:
        """Per arm deviation, the share of its prior's variance that the markers remove at ``p``
        (Gauss-Newton): near 0 where the poses tell nothing of it, so the fit leaves it where the
        table puts it, such as d1 and joint 1's zero, which move the phantom with the arm; near 1
        where they pin it."""
        j = self.jacobian(p)
        variance = np.diag(np.linalg.pinv(j.T @ j))[self.kin_at:self.wires_at]
        return np.clip(1.0 - variance * self.kin_weight**2, 0.0, 1.0)


def _mapping_jacobian(tool_to_base: np.ndarray, params: np.ndarray, x: np.ndarray, y: np.ndarray,
                      points: np.ndarray, scale_derivatives: np.ndarray | None, solve_y: bool,
                      solve_x: bool = True) -> np.ndarray:
    """(F, K, 3, P) derivative of the phantom-frame points of image ``points`` (F, K, 3), mapped
    by ``Y^-1 M_i X``, by :func:`refine`'s parameters: X's rotation vector and translation (if
    solved), then Y's (if solved), then the image scale's (if solved; ``scale_derivatives``
    (F, K, 2, n), :class:`_ImageScale`)."""
    ry_t = y[:3, :3].T
    to_phantom = np.einsum("ij,fjk->fik", ry_t, tool_to_base[:, :3, :3])  # R_Y^T R_Mi
    rotated = points @ x[:3, :3].T  # R_X s
    shape = points.shape[:2] + (3, 3)
    blocks = [
        -np.einsum("fij,fkjl->fkil", to_phantom, skew(rotated)) @ rotvec_left_jacobian(params[:3]),
        np.broadcast_to(to_phantom[:, None], shape),
    ] if solve_x else []
    if solve_y:
        y_at = 6 if solve_x else 0
        in_base = np.einsum("fij,fkj->fki", tool_to_base[:, :3, :3], rotated + x[:3, 3]) + tool_to_base[:, None, :3, 3]
        blocks += [ry_t @ skew(in_base - y[:3, 3]) @ rotvec_left_jacobian(params[y_at:y_at + 3]),
                   np.broadcast_to(-ry_t, shape)]
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
    spacing0_mm: Spacing,
    solve_y: bool = True,
    solve_spacing: bool = True,
    objective: str = "all-wire",
    prior: WirePrior = WirePrior(),
    kinematics: ArmKinematics | None = None,
    previous: PreviousFit | None = None,
    fan: Fan | None = None,
    hold_x: bool = False,
    determine_arm: bool = False,
) -> Refined:
    """Joint robust fit of X (unless ``hold_x``: held at ``x0``), Y (unless known) and (sx, sy) over
    all frames to ``objective``
    (see the module docstring), with the analytic Jacobian. ``markers_px`` is (F, W, 2) in phantom
    wire order with NaN for missing markers. The middle-wire points are computed once: a dot ratio
    along a line survives any scaling, so they do not depend on the spacing.

    With ``prior`` locating (``all-wire`` only) a last pass also fits where the wires are (see
    :class:`WirePrior`). A wire seen from many poses is located by the poses themselves, so a
    wire built off its definition no longer pulls the calibration along. That pass holds the
    spacing where the definition set it: wires that move together could otherwise stretch the
    pattern and trade that for the spacing.

    With ``kinematics`` the flange poses are the arm's (``core.calibration.kinematics``):
    ``tool_to_base`` is then only what the controller reported, and after the first pass the
    arm's kinematic deviations are fitted too, under their prior (one unit per parameter).

    ``previous`` (a fit of the same objective to much the same frames, whose X, Y and spacing are
    then ``x0``, ``y0`` and ``spacing0_mm``) starts every pass where it ended, arm, wires and
    stretch included, and the first pass, there to come near from a rough start, is skipped.

    With ``fan`` (a fan image's, in its pixels) the spacing stays at ``spacing0_mm`` (the
    scanner's, square pixels) and what is solved instead is the stretch of the beams' depths below
    the face (:class:`_ImageScale`), which the result holds.

    ``determine_arm``: with the arm's deviations fitted, also say how far the markers determine
    each (``Refined.kinematic_determined``), at the cost of one more Jacobian."""
    if objective not in FIT_OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}")
    markers_px = np.asarray(markers_px, dtype=float)
    problem = _Problem.of(phantom, markers_px, objective, (spacing0_mm, fan), tool_to_base, y0, solve_y, kinematics,
                          x0 if hold_x else None)
    stretch0 = 1.0 if previous is None or previous.stretch is None else previous.stretch
    first = _Pass(problem, solve_spacing, problem.image.initial(stretch0))
    p0 = np.concatenate([[] if hold_x else pose_params(x0), pose_params(y0) if solve_y else [],
                         first.held_scale if solve_spacing else []])
    # The noise level differs a lot between a clean simulation and a freehand recording, so the
    # robust scale is set from the data: a first pass at a generous scale (or a previous fit), then
    # a second pass at a few times the median residual distance, which still discounts
    # mislabelled markers.
    start = p0 if previous is not None else first.solve(p0, FIRST_PASS_SCALE_MM)
    robust, start = _with_arm(first, start, previous)
    scale = max(MIN_SCALE_MM, SCALE_PER_MEDIAN * float(np.median(robust.distances(start)[problem.valid])))
    robust = replace(robust, kin_weight=robust.noise(start))
    ftol = 1e-8 if previous is None else REFIT_FTOL
    fitted = robust.solve(start, scale, ftol)
    final = robust
    if problem.project is not None and prior.locates:
        final, start = _with_wires(phantom, robust, fitted, prior, previous)
        fitted = final.solve(start, scale, ftol)
    refined = final.refined(fitted)
    if determine_arm and final.kin_free:
        refined = replace(refined, kinematic_determined=final.determined(fitted))
    return refined


def _with_arm(first: _Pass, p: np.ndarray, previous: PreviousFit | None) -> tuple[_Pass, np.ndarray]:
    """The second pass and its start from the first's ``p``: with the arm's deviations freed
    (from the previous fit's, else zero) when its kinematics are known."""
    if first.problem.kinematics is None:
        return first, p
    units = None if previous is None else previous.kinematic_units
    return replace(first, kin_free=True), np.concatenate([p, np.zeros(first.problem.n_kin) if units is None else units])


def _with_wires(phantom: Phantom, robust: _Pass, p: np.ndarray, prior: WirePrior,
                previous: PreviousFit | None) -> tuple[_Pass, np.ndarray]:
    """The last pass and its start from the second's ``p``: the image scale held where the second
    left it, the wires' shifts freed (from where the previous fit located them, else zero) under
    ``prior`` weighted by the noise the second pass left."""
    across = robust.problem.across
    assert across is not None
    noise = robust.noise(p)
    _, _, scale, _ = robust.unpack(p)
    kin_weight = noise if robust.problem.kinematics is not None else robust.kin_weight
    located = _Pass(robust.problem, False, scale, robust.kin_free, kin_weight, True,
                    noise * prior.whitening(phantom, across))
    shifts = previous.wire_shifts_mm if previous is not None else None
    wires0 = np.zeros(4 * len(across)) if shifts is None else np.einsum("wij,wei->wej", across, shifts).ravel()
    start = np.concatenate([p[:robust.problem.n_pose], p[robust.kin_at:robust.wires_at], wires0])
    return located, start
