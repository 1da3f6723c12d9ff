"""The calibration pipeline: labelled markers and poses in, a validated ``image_to_tool`` out.

Frames whose pattern was not found or whose pose is invalid are left out. Two methods:

- ``seed``: per-frame registration by N-wire ratios and ICP, QR24 with SVD orthonormalisation,
  the scanner's nominal pixel spacing (the seed never estimates it);
- ``best``: exact point-to-wire registration, QR24 as a start, then a robust joint fit of X, Y
  and (sx, sy) to every marker; frames that still disagree are rejected and the fit repeated.

With a known ``phantom_to_base`` (PLUS's PhantomToReference) Y is held fixed unless asked.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from core.calibration import Calibration
from core.errors import InputError
from core.handeye import marker_offsets, opencv_shah, qr24, refine, x_from_known_y
from core.metrics import identity_error, pre3d
from core.phantom import Phantom
from core.register import register_frame
from core.session import Session

METHODS = ("seed", "best")
MIN_FRAMES = 6
MIN_SECOND_AXIS_DEG = 2.0  # rotations must spread over two axes at least this much
REJECT_FLOOR_MM = 1.0
REJECT_FACTOR = 5.0
HOLDOUT_FRACTION = 0.2


@dataclass
class Observations:
    """Frames usable for calibration: markers (F, W, 2) px with NaN where missing, flange poses
    (F, 4, 4), the frames' indices in the session and, once registered, each frame's
    ``image_to_phantom`` (F, 4, 4; NaN where it failed) and FRE (F,)."""

    markers_px: np.ndarray
    tool_to_base: np.ndarray
    indices: np.ndarray
    image_to_phantom: np.ndarray | None = None
    fre_mm: np.ndarray | None = None

    def subset(self, keep) -> "Observations":
        return Observations(
            self.markers_px[keep], self.tool_to_base[keep], self.indices[keep],
            None if self.image_to_phantom is None else self.image_to_phantom[keep],
            None if self.fre_mm is None else self.fre_mm[keep],
        )

    def registered(self, phantom: Phantom, spacing, method: str) -> "Observations":
        """A copy with every frame registered at ``spacing`` by ``method``'s registration."""
        n = np.full((len(self), 4, 4), np.nan)
        fre = np.full(len(self), np.nan)
        for i, markers in enumerate(self.markers_px):
            reg = register_frame(phantom, markers, spacing, method)
            if reg is not None:
                n[i], fre[i] = reg.image_to_phantom, reg.fre_mm
        return Observations(self.markers_px, self.tool_to_base, self.indices, n, fre)

    def __len__(self) -> int:
        return len(self.indices)


@dataclass
class Solution:
    """One solve: X, Y, spacing, and each used frame's mean marker-to-wire distance (mm)."""

    image_to_tool_rigid: np.ndarray
    phantom_to_base: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    residual_mm: np.ndarray  # (F,) mean marker-to-wire distance with the calibration
    rejected: dict[int, str] = field(default_factory=dict)  # session index -> reason


def observations(session: Session, results) -> tuple[Observations, dict[int, str]]:
    """Frames with a found pattern and a valid pose; the others with the reason they are out."""
    keep, left_out = [], {}
    for r in results:
        record = session.records[r.index]
        if not r.found:
            left_out[r.index] = f"pattern not found: {r.reason}"
        elif not record.pose_valid:
            left_out[r.index] = "no valid pose"
        else:
            keep.append(r)
    markers = np.array([r.markers for r in keep], dtype=float).reshape(len(keep), session.phantom.n_wires, 2)
    poses = np.array([session.records[r.index].tool_to_base for r in keep]).reshape(len(keep), 4, 4)
    return Observations(markers, poses, np.array([r.index for r in keep], dtype=int)), left_out


def initial_spacing(session: Session, obs: Observations, phantom: Phantom) -> tuple[float, float]:
    """The scanner's nominal spacing if recorded, else PLUS's approximate spacing hint, else an
    estimate from the outer-dot distances against the outer-wire separations (sx = sy)."""
    if session.pixel_spacing_mm is not None:
        return session.pixel_spacing_mm
    hints = session.manifest.get("segmentation_hints") or {}
    if hints.get("ApproximateSpacingMmPerPixel"):
        value = float(hints["ApproximateSpacingMmPerPixel"])
        return value, value
    ratios = []
    for k, layer in enumerate(phantom.layers):
        separation = np.linalg.norm(np.cross(layer.wires[0].direction, layer.wires[2].front - layer.wires[0].front))
        span = np.linalg.norm(obs.markers_px[:, 3 * k + 2] - obs.markers_px[:, 3 * k], axis=1)
        ratios.append(separation / span)
    value = float(np.nanmedian(np.concatenate(ratios)))
    return value, value


def check_pose_set(tool_to_base: np.ndarray, solve_y: bool) -> None:
    """Refuse pose sets that cannot determine the calibration."""
    if len(tool_to_base) < MIN_FRAMES:
        raise InputError(None, f"too few usable poses: {len(tool_to_base)} (at least {MIN_FRAMES} needed)")
    if not solve_y:
        return
    rotvecs = Rotation.from_matrix(tool_to_base[0, :3, :3].T @ tool_to_base[:, :3, :3]).as_rotvec(degrees=True)
    spread = np.linalg.svd(rotvecs - rotvecs.mean(axis=0), compute_uv=False) / np.sqrt(len(rotvecs))
    if spread[0] < MIN_SECOND_AXIS_DEG:
        raise InputError(None, f"degenerate pose set: the poses hardly rotate (spread {spread[0]:.2f} deg); "
                               "rotate the probe about at least two axes")
    if spread[1] < MIN_SECOND_AXIS_DEG:
        raise InputError(
            None,
            f"degenerate pose set: the rotations turn about a single axis (spread {spread[0]:.1f} deg "
            f"about one, {spread[1]:.2f} deg about the others); rotate about at least two axes",
        )


def solve(
    phantom: Phantom,
    obs: Observations,
    spacing0: tuple[float, float],
    method: str,
    known_phantom_to_base: np.ndarray | None = None,
) -> Solution:
    """Calibrate from observations registered at ``spacing0`` (see the module docstring)."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}")
    ok = np.all(np.isfinite(obs.image_to_phantom.reshape(len(obs), -1)), axis=1)
    rejected = {int(obs.indices[i]): "too few complete N patterns to register" for i in np.flatnonzero(~ok)}
    obs = obs.subset(ok)
    n = obs.image_to_phantom
    solve_y = known_phantom_to_base is None
    check_pose_set(obs.tool_to_base, solve_y)
    if solve_y:
        x, y = qr24(obs.tool_to_base, n)
    else:
        y = known_phantom_to_base
        x = x_from_known_y(obs.tool_to_base, n, y)
    if method == "seed":
        offsets = marker_offsets(phantom, np.nan_to_num(obs.markers_px), obs.tool_to_base, x, y, spacing0)
        distances = np.where(np.all(np.isfinite(obs.markers_px), axis=2), np.linalg.norm(offsets, axis=2), np.nan)
        return Solution(x, y, spacing0, np.nanmean(distances, axis=1), rejected)
    result = refine(phantom, obs.markers_px, obs.tool_to_base, x, y, spacing0, solve_y=solve_y)
    per_frame = np.nanmedian(result.residuals_mm, axis=1)
    limit = max(REJECT_FLOOR_MM, REJECT_FACTOR * float(np.median(per_frame)))
    bad = per_frame > limit
    if bad.any() and (~bad).sum() >= MIN_FRAMES:
        for i in np.flatnonzero(bad):
            rejected[int(obs.indices[i])] = f"disagrees with the calibration ({per_frame[i]:.2f} mm from the wires)"
        obs = obs.subset(~bad)
        result = refine(
            phantom, obs.markers_px, obs.tool_to_base, result.image_to_tool_rigid, result.phantom_to_base,
            result.pixel_spacing_mm, solve_y=solve_y,
        )
    return Solution(
        result.image_to_tool_rigid, result.phantom_to_base, result.pixel_spacing_mm,
        np.nanmean(result.residuals_mm, axis=1), rejected,
    )


def holdout_errors(phantom: Phantom, solution: Solution, held: Observations) -> dict:
    """Errors on held-out (registered) frames: the seed's eq. 4.1 identity error and PRE3D."""
    errors = [
        identity_error(solution.image_to_tool_rigid, solution.phantom_to_base, m, ni)
        for m, ni in zip(held.tool_to_base, held.image_to_phantom)
        if np.all(np.isfinite(ni))
    ]
    calibration = Calibration(solution.image_to_tool_rigid, solution.pixel_spacing_mm)
    pre_mean, _ = pre3d(phantom, held.markers_px, held.tool_to_base, calibration.image_to_tool, solution.phantom_to_base)
    return {
        "identity_translation_mm": float(np.mean([e.translation_mm for e in errors])) if errors else None,
        "identity_rotation_deg": float(np.mean([e.rotation_deg for e in errors])) if errors else None,
        "pre3d_mm": pre_mean,
    }


def error_curve(phantom: Phantom, obs: Observations, held_obs: Observations, spacing0, method: str, known_y,
                seed: int = 0) -> list[dict]:
    """Seed Fig. 4.5: errors on a fixed held-out set as the number of calibration poses grows.
    ``obs`` is registered at ``spacing0``; ``held_obs`` (the same frames) at the final spacing."""
    order = np.random.default_rng(seed).permutation(len(obs))
    n_hold = max(3, int(round(HOLDOUT_FRACTION * len(obs))))
    held, train = held_obs.subset(order[:n_hold]), obs.subset(order[n_hold:])
    steps = sorted({n for n in (MIN_FRAMES, 10, 15, 20, 30, 45, 60, 90, 120, 180, len(train)) if MIN_FRAMES <= n <= len(train)})
    curve = []
    for n in steps:
        try:
            solution = solve(phantom, train.subset(np.arange(n)), spacing0, method, known_y)
        except InputError:
            continue
        curve.append({"poses": n, **holdout_errors(phantom, solution, held)})
    return curve


def cross_validate(phantom: Phantom, obs: Observations, held_obs: Observations, spacing0, method: str, known_y,
                   folds: int = 5, seed: int = 0) -> dict:
    """Leave-p-out cross-validation (p = one fold of the frames): mean held-out errors.
    Registrations as for :func:`error_curve`."""
    order = np.random.default_rng(seed + 1).permutation(len(obs))
    rows = []
    for fold in np.array_split(order, folds):
        train = np.setdiff1d(order, fold)
        try:
            solution = solve(phantom, obs.subset(train), spacing0, method, known_y)
        except InputError:
            continue
        rows.append(holdout_errors(phantom, solution, held_obs.subset(fold)))
    summary = {"folds": len(rows), "held_out_per_fold": int(len(obs) // folds)}
    for key in ("identity_translation_mm", "identity_rotation_deg", "pre3d_mm"):
        values = [r[key] for r in rows if r[key] is not None]
        summary[key] = float(np.mean(values)) if values else None
    return summary


@dataclass
class CalibrationReport:
    calibration: Calibration
    frames_total: int
    frames_used: list[int]
    frames_rejected: dict[int, str]
    curve: list[dict]
    shah: dict | None


def calibrate_session(
    session: Session,
    results,
    method: str = "best",
    solve_phantom_pose: bool = False,
    with_validation: bool = True,
    progress: Callable[[str], None] | None = None,
) -> CalibrationReport:
    """Calibrate a segmented session; raises InputError with a clear message on unusable input."""
    say = progress or (lambda _msg: None)
    if len(session) == 0:
        raise InputError(session.path, "session has no frames")
    phantom = session.phantom
    if phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    obs, left_out = observations(session, results)
    if len(obs) == 0:
        reasons = sorted(set(left_out.values()))
        raise InputError(session.path, f"no usable frame among {len(session)} ({'; '.join(reasons[:3])})")
    known_y = None if solve_phantom_pose else session.phantom_to_base
    spacing0 = initial_spacing(session, obs, phantom)
    say(f"registering {len(obs)} frames")
    obs = obs.registered(phantom, spacing0, method)
    say(f"solving with {len(obs)} frames ({method} method)")
    try:
        solution = solve(phantom, obs, spacing0, method, known_y)
    except InputError as exc:
        raise InputError(session.path, exc.problem)
    rejected = {**left_out, **solution.rejected}
    used = [int(i) for i in obs.indices if int(i) not in solution.rejected]
    calibration = Calibration(solution.image_to_tool_rigid, solution.pixel_spacing_mm, solution.phantom_to_base)
    used_obs = obs.subset(np.isin(obs.indices, used))
    # Frames registered again at the calibrated spacing: the FRE to report, and held-out frames.
    final_obs = used_obs.registered(phantom, solution.pixel_spacing_mm, method)
    pre_mean, pre_std = pre3d(phantom, used_obs.markers_px, used_obs.tool_to_base, calibration.image_to_tool, solution.phantom_to_base)
    metrics = {
        "method": method,
        "frames_total": len(session),
        "frames_used": len(used),
        "frames_rejected": len(rejected),
        "fre_mm": float(np.nanmean(final_obs.fre_mm)),
        "fre_per_frame_mm": {int(i): None if np.isnan(f) else round(float(f), 4)
                             for i, f in zip(final_obs.indices, final_obs.fre_mm)},
        "calibration_residual_mm": float(np.nanmean(solution.residual_mm)),
        "pre3d_mm": pre_mean,
        "pre3d_std_mm": pre_std,
        "phantom_pose": "solved" if known_y is None else "known",
        "initial_pixel_spacing_mm": list(spacing0),
    }
    curve, shah = [], None
    if with_validation:
        say("cross-validating")
        metrics["cross_validation"] = cross_validate(phantom, used_obs, final_obs, spacing0, method, known_y)
        curve = error_curve(phantom, used_obs, final_obs, spacing0, method, known_y)
        if known_y is None:
            n = final_obs.image_to_phantom
            ok = np.all(np.isfinite(n.reshape(len(n), -1)), axis=1)
            x_shah, y_shah = opencv_shah(used_obs.tool_to_base[ok], n[ok])
            shah = {"image_to_tool_rigid": x_shah, "phantom_to_base": y_shah}
    metrics["error_vs_poses"] = curve
    calibration = replace(calibration, metrics=metrics)
    return CalibrationReport(calibration, len(session), used, rejected, curve, shah)
