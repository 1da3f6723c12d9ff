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
   image corners: the mean over the frames (what a calibration would inherit) and the scatter;
7. where the poses rotate enough to solve it, both objectives with the phantom pose solved too
   (PLUS's registration of it set aside).

Then, on twin ``bench`` seeds the robot's way (phantom pose solved), each objective's held-out
PRE3D against the definition next to its image corners' true error: the figure a choice between
them could rest on, against the truth.

Run: .venv/bin/python benchmarks/bench_objectives.py [--seeds 4]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
from bench_calibration import FCAL_SETS, NWIRE_CONFIG, PLUS, import_fcal  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import probecal.core  # noqa: E402, F401  (sets BLAS threads before numpy loads)
import probecal.core.calibration.objectives as objectives  # noqa: E402
from probecal.core.acquisition.pairing import paired_again  # noqa: E402
from probecal.core.acquisition.simulate import simulate_calibration  # noqa: E402
from probecal.core.calibration.handeye import marker_offsets  # noqa: E402
from probecal.core.calibration.register import ratio_registration, refine_on_wires  # noqa: E402
from probecal.core.calibration.result import Calibration  # noqa: E402
from probecal.core.calibration.segment import segment_session, session_segmenter  # noqa: E402
from probecal.core.calibration.solve import calibrate_session, initial_spacing, observations, tracked_latency  # noqa: E402
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px  # noqa: E402
from probecal.core.errors import InputError  # noqa: E402
from probecal.core.geometry.probe import image_mm_from_pixels  # noqa: E402
from probecal.core.geometry.transforms import make_transform, transform_points  # noqa: E402
from probecal.core.io.plusdata import missing_reason  # noqa: E402
from probecal.core.io.plusimport import import_plus  # noqa: E402


def _fit(session, obs, spacing, objective, phantom=None, known=True):
    phantom = phantom or session.phantom
    start = obs.registered(phantom, spacing, objectives.REGISTRATION[objective])
    return objectives.fit(phantom, start, spacing, objective, session.phantom_to_base if known else None)


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
    sessions = {}
    for bench in FCAL_SETS:
        sessions[f"{bench.name} calibration"], sessions[f"{bench.name} validation"] = import_fcal(bench, tmp)
    sessions["NwirePhantomFreehand"] = import_plus(PLUS / "TestImages" / "NwirePhantomFreehand.igs.mha", NWIRE_CONFIG,
                                                   tmp / "nwire", spacing_mm=0.077)
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
        saved = objectives.WIRE_SIGMA_MM
        for label, frames in (("as recorded", obs), ("at the latency", at_latency)):
            objectives.WIRE_SIGMA_MM = 0.0
            aw, mw = _fit(session, frames, spacing, "all-wire"), _fit(session, frames, spacing, "middle-wire")
            apart, axes = _apart(aw.calibration, mw.calibration, corners)
            print(f"  {label}: all-wire and middle-wire {apart:.2f} mm apart at the corners (at most {axes[0]:.2f} "
                  f"lateral, {axes[1]:.2f} axial, {axes[2]:.2f} out of plane)")
        for sigma in (0.05, 0.2):
            objectives.WIRE_SIGMA_MM = sigma
            aw = _fit(session, at_latency, spacing, "all-wire")
            mw = _fit(session, at_latency, spacing, "middle-wire", aw.wires(session.phantom))
            shift = float(np.linalg.norm(aw.wire_shifts_mm, axis=2).max())
            print(f"  wires located (prior {sigma} mm, moved up to {shift:.2f} mm): middle-wire on them "
                  f"{_apart(aw.calibration, mw.calibration, corners)[0]:.2f} mm from all-wire")
        objectives.WIRE_SIGMA_MM = 0.0
        held = _fit(session, at_latency, spacing, "all-wire")
        rotvec, shift, before, after = _phantom_move(session, at_latency, held)
        print(f"  phantom moved rigidly with the mount held: {np.round(rotvec, 2)} deg, {np.round(shift, 2)} mm; "
              f"markers {before:.3f} -> {after:.3f} mm from their wires")
        systematic, scatter = _plane_disagreement(session.phantom, obs, spacing, corners)
        print(f"  frame by frame, no tracker: the ratio plane and the on-wire plane {np.round(systematic, 2)} mm apart "
              f"on average (lateral, axial, out of plane; farthest corner), scattering {scatter:.2f} mm out of plane")
        try:
            solved = [_fit(session, at_latency, spacing, m, known=False).calibration
                      for m in ("all-wire", "middle-wire")]
            print(f"  phantom pose solved too: all-wire and middle-wire {_apart(*solved, corners)[0]:.2f} mm apart")
        except InputError as exc:
            print(f"  phantom pose not solvable from these poses: {exc}")
        objectives.WIRE_SIGMA_MM = saved


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


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()
    reason = missing_reason()
    if reason is None:
        with tempfile.TemporaryDirectory() as tmp:
            real(Path(tmp))
    else:
        print(f"real recordings skipped: {reason}")
    twin(args.seeds)


if __name__ == "__main__":
    main()
