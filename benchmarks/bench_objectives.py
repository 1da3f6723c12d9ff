"""What splits the calibration objectives on real recordings? The evidence behind issue 31.

On every tracked N-wire recording of PLUS's (the robot's way: own segmenter, no PLUS hints but the
approximate spacing, the phantom pose as PLUS registered it), each recording on its own:

1. the poses: how far they rotate (RMS degrees about the two principal axes) and move (mm);
2. the image latency the calibration measures (:func:`core.calibration.latency.fitted_latency`)
   and the markers' mean distance to their wires with the frames as recorded and at it;
3. all-wire against middle-wire (wires held): how far apart they put the image corners, split
   along the image's axes (lateral, axial, out of plane), as recorded and at the latency;
4. the same with the wires located (all-wire's fit, each end free across its wire under a prior of
   0.05 and 0.2 mm) and middle-wire fitted to those wires;
5. a rigid move of the phantom (its registered pose) fitted with the mount held: how far it
   moves and how much closer the markers come to their wires;
6. with no tracker at all, frame by frame: the image plane placed from the N ratios alone (the
   middle-wire points) against the plane that puts every dot on its wire (all-wire's), at the
   image corners: the mean over the frames (what a calibration would inherit) and the scatter,
   at the nominal spacing and at the spacing all-wire fits;
7. with no tracker either, the spacing the frames themselves ask for: the lateral and axial
   factors on the nominal spacing at which single frames put their dots closest to their wires
   (every fourth frame; a grid of 0.02, then of 0.005);
8. single frames through the tracker: each frame's plane on the wires (at an objective's spacing)
   mapped by its tracked pose and the phantom pose gives that frame's own ``image_to_tool``; how
   far the frames' mean puts the image corners from each objective's fit, how far single frames
   scatter out of plane, and how far their means over 9 frames in a row do (where the wires and
   the tracker drift apart along the recording);
9. where the poses rotate enough to solve it, both objectives with the phantom pose solved too
   (PLUS's registration of it set aside).

Last, tracked freehand recordings of the twin (``simulate_freehand``: a hand's path spread like
those recordings, a tracker's noise) of the fCal 2.0 phantom with its pose known, the phantom as
the bench builds it and built further off (wires +-0.6 mm; layers slid along their wires;
diagonals off across themselves), and tracked with more errors: which of them splits the
objectives, the halves and the single frames as the real recordings do.

Before that, on twin ``bench`` seeds the robot's way (phantom pose solved), each objective's held-out
PRE3D against the definition next to its image corners' true error: the figure a choice between
them could rest on, against the truth.

Run: .venv/bin/python benchmarks/bench_objectives.py [--seeds 4]
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_calibration import tracked_recordings
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
import probecal.core.calibration.objectives as objectives
from probecal.core.acquisition.pairing import paired_again
from probecal.core.acquisition.simulate import simulate_calibration, simulate_freehand
from probecal.core.calibration.frames import initial_spacing, observations, tracked_latency
from probecal.core.calibration.handeye import marker_offsets
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.register import ratio_registration, refine_on_wires, register_frame
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.errors import InputError
from probecal.core.geometry.probe import image_mm_from_pixels
from probecal.core.geometry.transforms import make_transform, transform_points
from probecal.core.io.phantomfile import load_phantom, phantom_path
from probecal.core.io.plusdata import missing_reason
from probecal.core.twin.levels import BENCH_SETUP, LEVELS
from probecal.core.twin.twin import pose_noise

HELD = WirePrior(0.0)  # the wires held at their definition


def _fit(session, obs, spacing, objective, phantom=None, known=True, prior=HELD):
    phantom = phantom or session.phantom
    start = obs.registered(phantom, spacing, objectives.REGISTRATION[objective])
    return objectives.fit(phantom, start, spacing, objective, session.phantom_to_base if known else None,
                          prior=prior)


def _plane_disagreement(phantom, obs, spacing, corners) -> tuple[np.ndarray, float]:
    """Per frame, the image plane from the dot ratios (:func:`ratio_registration`) against the
    plane on the wires (:func:`refine_on_wires` from it), at the image corners in the ratio
    plane's axes: the largest component of their mean over the frames (lateral, axial, out of
    plane, mm) and the largest frame-to-frame standard deviation out of plane (mm)."""
    corners_mm = image_mm_from_pixels(corners, spacing)
    apart = []
    for markers in obs.markers_px:
        points = image_mm_from_pixels(markers, spacing)
        ratio = ratio_registration(phantom, points, markers)
        if ratio is None:
            continue
        valid = np.flatnonzero(np.all(np.isfinite(markers), axis=1))
        on_wires = refine_on_wires(phantom, ratio, points[valid], valid)
        apart.append((transform_points(on_wires, corners_mm) - transform_points(ratio, corners_mm)) @ ratio[:3, :3])
    apart = np.array(apart)  # (F, 4, 3)
    return np.abs(apart.mean(axis=0)).max(axis=0), float(apart[..., 2].std(axis=0).max())


def _frame_spacing(phantom, obs, spacing) -> tuple[np.ndarray, float]:
    """The (lateral, axial) factors on ``spacing`` at which single frames, each placed on the wires
    alone, put their dots closest to their wires (median over every fourth frame), and that median
    distance (mm)."""
    frames = obs.markers_px[::4]

    def misfit(factors: np.ndarray) -> float:
        registered = (register_frame(phantom, markers, np.asarray(spacing) * factors) for markers in frames)
        return float(np.median(np.concatenate([r.residuals_mm for r in registered if r is not None])))

    best = np.ones(2)
    for step in (0.02, 0.005):
        grid = [best + step * np.array([i, j]) for i in range(-3, 4) for j in range(-3, 4)]
        best = min(grid, key=misfit)
    return best, misfit(best)


DRIFT_FRAMES = 9  # single frames averaged over this many in a row: what changes slowly along a recording


def single_frames(phantom, phantom_to_base, obs, solution, corners) -> tuple[float, float, float]:
    """How far the mean of the frames' own ``image_to_tool`` (each frame's plane on the wires at
    ``solution``'s spacing, mapped by its tracked pose and the phantom pose) puts the image corners
    from ``solution``'s (farthest corner, mm), the largest standard deviation of single frames out
    of plane (mm), and that of their means over ``DRIFT_FRAMES`` frames in a row (mm): where the
    wires and the tracker drift apart along the recording, not the frames' own jitter."""
    spacing = solution.pixel_spacing_mm
    corners_mm = image_mm_from_pixels(corners, spacing)
    x = solution.image_to_tool_rigid
    moved = []
    for markers, tool_to_base in zip(obs.markers_px, obs.tool_to_base):
        registration = register_frame(phantom, markers, spacing)
        if registration is None:
            continue
        own = np.linalg.inv(tool_to_base) @ phantom_to_base @ registration.image_to_phantom
        moved.append((transform_points(own, corners_mm) - transform_points(x, corners_mm)) @ x[:3, :3])
    moved = np.array(moved)  # (F, 4, 3) in the fit's image axes, in recording order
    window = np.ones(DRIFT_FRAMES) / DRIFT_FRAMES
    drift = [np.convolve(moved[:, c, 2], window, mode="valid").std() for c in range(len(corners))]
    return float(np.linalg.norm(moved.mean(axis=0), axis=1).max()), float(moved[..., 2].std(axis=0).max()), max(drift)


def _apart(a: Calibration, b: Calibration, corners: np.ndarray) -> tuple[float, np.ndarray]:
    """The farthest corner's distance (mm) and, over the corners, the largest component of the
    difference along the image's lateral, axial and out-of-plane axes (mm, ``a``'s image frame)."""
    points = np.column_stack([corners, np.zeros(len(corners))])
    moved = (transform_points(b.image_to_tool, points) - transform_points(a.image_to_tool, points))
    return corner_distance_mm(a, b, corners), np.abs(moved @ a.image_to_tool_rigid[:3, :3]).max(axis=0)


def _phantom_move(session, obs, solution) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The rigid move of the phantom (rotation vector deg, translation mm, phantom frame) that
    brings the markers closest to their wires with the mount held, and the markers' median
    distance (mm) before and after."""
    valid = np.all(np.isfinite(obs.markers_px), axis=2)

    def distances(p: np.ndarray) -> np.ndarray:
        moved = session.phantom_to_base @ make_transform(Rotation.from_rotvec(p[:3]), p[3:])
        offsets = marker_offsets(session.phantom, np.nan_to_num(obs.markers_px), obs.tool_to_base,
                                 solution.image_to_tool_rigid, moved, solution.pixel_spacing_mm)
        return offsets[valid].ravel()

    fit = least_squares(distances, np.zeros(6), loss="huber", f_scale=0.5)
    median = [float(np.median(np.linalg.norm(distances(p).reshape(-1, 3), axis=1))) for p in (np.zeros(6), fit.x)]
    return np.degrees(fit.x[:3]), fit.x[3:], median[0], median[1]


def real(tmp: Path) -> None:
    sessions = tracked_recordings(tmp)
    for name, session in sessions.items():
        results = segment_session(session, segmenter=session_segmenter(session, use_hints=False))
        obs, _ = observations(session, results)
        spacing = initial_spacing(session, obs, session.phantom)
        corners = image_corners_px(session.image_size)
        rotation = objectives.rotation_spread_deg(obs.tool_to_base)
        motion = np.linalg.svd(obs.tool_to_base[:, :3, 3] - obs.tool_to_base[:, :3, 3].mean(axis=0),
                               compute_uv=False) / np.sqrt(len(obs))
        print(f"{name}: {len(obs)} frames; poses rotate {rotation[0]:.1f} / {rotation[1]:.1f} deg RMS about their two "
              f"main axes and move {motion[0]:.1f} / {motion[1]:.1f} mm RMS")
        latency = tracked_latency(session, obs, session.phantom, spacing, session.phantom_to_base)
        print(f"  image latency {latency.image_latency_s * 1000:.0f} +- {latency.std_error_s * 1000:.0f} ms: markers "
              f"{latency.residual_at_zero_mm:.3f} mm from their wires as recorded, {latency.residual_mm:.3f} at it")
        at_latency, _ = observations(paired_again(session, latency.image_latency_s), results)
        for label, frames in (("as recorded", obs), ("at the latency", at_latency)):
            aw, mw = _fit(session, frames, spacing, "all-wire"), _fit(session, frames, spacing, "middle-wire")
            apart, axes = _apart(aw.calibration, mw.calibration, corners)
            print(f"  {label}: all-wire and middle-wire {apart:.2f} mm apart at the corners (at most {axes[0]:.2f} "
                  f"lateral, {axes[1]:.2f} axial, {axes[2]:.2f} out of plane)")
        for sigma in (0.05, 0.2):
            aw = _fit(session, at_latency, spacing, "all-wire", prior=WirePrior(sigma))
            mw = _fit(session, at_latency, spacing, "middle-wire", aw.wires(session.phantom), prior=WirePrior(sigma))
            shift = float(np.linalg.norm(aw.wire_shifts_mm, axis=2).max())
            print(f"  wires located (prior {sigma} mm, moved up to {shift:.2f} mm): middle-wire on them "
                  f"{_apart(aw.calibration, mw.calibration, corners)[0]:.2f} mm from all-wire")
        held = _fit(session, at_latency, spacing, "all-wire")
        rotvec, shift, before, after = _phantom_move(session, at_latency, held)
        print(f"  phantom moved rigidly with the mount held: {np.round(rotvec, 2)} deg, {np.round(shift, 2)} mm; "
              f"markers {before:.3f} -> {after:.3f} mm from their wires")
        for label, at in (("nominal", spacing), ("all-wire's", held.pixel_spacing_mm)):
            systematic, scatter = _plane_disagreement(session.phantom, obs, at, corners)
            print(f"  frame by frame, no tracker, at the {label} spacing: the ratio plane and the on-wire plane "
                  f"{np.round(systematic, 2)} mm apart on average (lateral, axial, out of plane; farthest corner), "
                  f"scattering {scatter:.2f} mm out of plane")
        factors, misfit = _frame_spacing(session.phantom, obs, spacing)
        fitted = np.asarray(held.pixel_spacing_mm) / np.asarray(spacing)
        print(f"  the spacing single frames ask for: nominal x {factors[0]:.3f} lateral, x {factors[1]:.3f} axial "
              f"(dots {misfit:.3f} mm from their wires); all-wire fits x {fitted[0]:.3f}, x {fitted[1]:.3f}")
        middle = _fit(session, at_latency, spacing, "middle-wire")
        for name, solution in (("all-wire", held), ("middle-wire", middle)):
            mean, scatter, drift = single_frames(session.phantom, session.phantom_to_base, at_latency, solution,
                                                  corners)
            print(f"  single frames through the tracker at {name}'s spacing: their mean {mean:.2f} mm from "
                  f"{name}'s fit, single frames scattering {scatter:.2f} mm out of plane, their means over "
                  f"{DRIFT_FRAMES} frames {drift:.2f} mm")
        try:
            solved = [_fit(session, at_latency, spacing, m, known=False).calibration
                      for m in ("all-wire", "middle-wire")]
            print(f"  phantom pose solved too: all-wire and middle-wire {_apart(*solved, corners)[0]:.2f} mm apart")
        except InputError as exc:
            print(f"  phantom pose not solvable from these poses: {exc}")


def twin(seeds: int) -> None:
    print(f"twin bench, {seeds} seeds x 60 poses, phantom pose solved: held-out PRE3D against the definition (mm) "
          "and the image corners' true error (farthest corner, mm)")
    for seed in range(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            session = simulate_calibration(Path(tmp) / "s", n_poses=60, seed=seed, noise="bench")
            truth = session.truth()
            true = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
            results = segment_session(session)
            report = calibrate_session(session, results, with_validation=False)
            cells = []
            for name, row in report.calibration.metrics["objectives"].items():
                forced = calibrate_session(session, results, name, with_validation=False).calibration
                error = corner_distance_mm(forced, true, image_corners_px(session.image_size))
                cells.append(f"{name} {row['cv_pre3d_mm']:.3f} / {error:.3f}")
            print(f"  seed {seed}: " + ", ".join(cells) + f"; auto keeps {report.calibration.metrics['objective']}")


def _known_pose_fits(phantom, obs, spacing, phantom_to_base) -> dict[str, objectives.Solution]:
    """All-wire and middle-wire fitted to ``obs`` with the phantom pose known."""
    start = obs.registered(phantom, spacing, "point-to-wire")
    return {name: objectives.fit(phantom, start, spacing, name, phantom_to_base)
            for name in ("all-wire", "middle-wire")}


def _tracked(obs, phantom_to_base, error: str, rng: np.random.Generator):
    """``obs`` and the phantom pose as a tracked recording with ``error`` would report them:
    ``noise``, every pose off by 0.1 deg and 0.2 mm (sd per axis); ``scale``, the rotations about
    the mean pose read 5 % too large; ``registration``, the phantom pose 1 deg about its vertical
    and 1 mm off."""
    poses = obs.tool_to_base.copy()
    if error == "noise":
        for pose in poses:
            pose[:] = pose @ pose_noise(rng, 0.2, 0.1)
    if error == "scale":
        rotations = Rotation.from_matrix(poses[:, :3, :3])
        mean = rotations.mean()
        poses[:, :3, :3] = (mean * Rotation.from_rotvec(1.05 * (mean.inv() * rotations).as_rotvec())).as_matrix()
    if error == "registration":
        phantom_to_base = phantom_to_base @ make_transform(Rotation.from_euler("z", 1.0, degrees=True), [1.0, 0, 0])
    return objectives.Observations(obs.markers_px, poses, obs.indices), phantom_to_base


FREEHAND_VARIANTS = {
    "the bench": {},
    "wires +-0.6 mm": {"phantom_tolerance_mm": 0.6},
    "layers slid +-1 mm along the wires, turned +-1 deg": {"layer_tolerance": (0.0, 1.0, 0.0, 0.0, 0.0, 1.0)},
    "diagonals' ends +-1 mm across": {"diagonal_tolerance_mm": 1.0},
}
"""The freehand twin's phantoms: the bench's, and built off in ways a frame shows (wires) or not."""


def freehand_twin(seeds: int) -> None:
    """Tracked freehand recordings of the twin (``simulate_freehand``: a hand's path, a tracker's
    noise) on the fCal 2.0 phantom, its pose known (the true one, as registered), built off as
    ``FREEHAND_VARIANTS`` says: the objectives' disagreement, their image corners against the truth,
    the two halves, and the single frames through the poses (as for the real recordings)."""
    phantom = load_phantom(phantom_path("fcal-2.0"))
    print("twin bench, tracked freehand recordings (a hand's path, spread like PLUS's), fCal 2.0 phantom, "
          "phantom pose known")
    for variant, errors in FREEHAND_VARIANTS.items():
        noise = replace(LEVELS["bench"], setup=replace(BENCH_SETUP, **errors))
        for seed in range(1, seeds + 1):
            with tempfile.TemporaryDirectory() as tmp:
                session = simulate_freehand(Path(tmp) / "s", seed=seed, noise=noise, phantom=phantom)
                truth = session.truth()
                true = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
                phantom_to_base = session.phantom_to_base
                try:
                    obs, _ = observations(session, segment_session(session))
                    spacing = initial_spacing(session, obs, phantom)
                    halves = np.arange(len(obs)) < len(obs) // 2
                    whole, first, second = (_known_pose_fits(phantom, frames, spacing, phantom_to_base)
                                            for frames in (obs, obs.subset(halves), obs.subset(~halves)))
                except InputError as exc:
                    print(f"  {variant}, seed {seed}: {exc.problem}")
                    continue
                corners = image_corners_px(session.image_size)
                rotation = objectives.rotation_spread_deg(obs.tool_to_base)
                cells = []
                for name, solution in whole.items():
                    halves_apart = corner_distance_mm(first[name].calibration, second[name].calibration, corners)
                    _, scatter, drift = single_frames(phantom, phantom_to_base, obs, solution, corners)
                    cells.append(f"{name} {corner_distance_mm(solution.calibration, true, corners):.2f} to the truth, "
                                 f"halves {halves_apart:.2f} apart, single frames {scatter:.2f}, over "
                                 f"{DRIFT_FRAMES} frames {drift:.2f}")
                apart = _apart(whole["all-wire"].calibration, whole["middle-wire"].calibration, corners)[0]
                print(f"  {variant}, seed {seed}: {len(obs)} frames rotating {rotation[0]:.1f} / "
                      f"{rotation[1]:.1f} deg; objectives {apart:.2f} mm apart; " + "; ".join(cells))
                if not errors:
                    rng = np.random.default_rng(seed)
                    cells = []
                    for error in ("noise", "scale", "registration"):
                        frames, reported = _tracked(obs, phantom_to_base, error, rng)
                        fitted = _known_pose_fits(phantom, frames, spacing, reported)
                        cells.append(f"{error} {_apart(*(f.calibration for f in fitted.values()), corners)[0]:.2f}")
                    print("    tracked with more errors, objectives apart (mm): " + ", ".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--freehand-seeds", type=int, default=2)
    args = parser.parse_args()
    reason = missing_reason()
    if reason is None:
        with tempfile.TemporaryDirectory() as tmp:
            real(Path(tmp))
    else:
        print(f"real recordings skipped: {reason}")
    twin(args.seeds)
    freehand_twin(args.freehand_seeds)


if __name__ == "__main__":
    main()
