"""Volumes where the object is: the arm identified with the calibration and applied to the sweep.

For each twin ``bench`` seed: the robot's calibration sweep (the default plan) is calibrated, which
fits the arm's kinematic errors with it; the same seed's test object is swept and reconstructed,
every frame's flange put where the fitted arm puts it. Printed per seed:

- the image corners against the truth (mean of the four, mm);
- surface to CAD (mean, mm) with the CAD model placed where it sits relative to the phantom as
  the calibration registered it: the frame the robot's own measurements define (the score that
  matters: a navigation or overlay registered through the phantom lives there);
- the same with the CAD model at its true pose in the robot's base frame (the score before);
- the true calibration, with the arm and the phantom fitted around it (the calibration's joint
  fit with the calibration held at the truth): surface to CAD in the frame of the phantom so
  registered;
- the true calibration with the arm not identified (the reported poses) and the phantom
  registered with it (each frame's registration mapped through its reported pose and the true
  calibration, then averaged): in that frame, and at the true base pose (the score before);
- the UR3 time of the calibration plan.

Then how far the image centre lands from where it is (in the phantom's frame as each registered
it) at poses across the workspace box, by distance from the phantom: the estimated calibration
through its fitted arm, and the true calibration with the arm not identified. Then every DH
deviation fitted against the twin's truth, parameter by parameter (RMS over the
seeds), each marked with how many seeds' calibrations report it determined by the poses on its
own (``metrics.arm_undetermined``). d1 and joint 1's zero move everything the robot measures,
the phantom included, so no measurement of the robot's can find them; the fit leaves them where
its prior puts them.

Run: .venv/bin/python benchmarks/bench_arm.py [--seeds 10] [--first-seed 0] [--poses 60] [--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table
from scipy.spatial.transform import Rotation

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.frames import observations
from probecal.core.calibration.handeye import y_from_known_x
from probecal.core.calibration.jointfit import refine
from probecal.core.calibration.kinematics import arm_deviation, arm_poses, deviation_json
from probecal.core.calibration.objectives import WIRE_PRIOR
from probecal.core.calibration.register import register_frame
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.calibration.segment import FrameResult, segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distances_mm, image_corners_px
from probecal.core.geometry.transforms import invert_transform, make_transform
from probecal.core.io.session import Session
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.safety import load_workspace
from probecal.core.robot.ur3 import UR3, ArmModel, Unreachable, closest_ik
from probecal.core.twin.scanner import twin_scanner
from probecal.core.volume.cad import CadTarget, session_cad_target
from probecal.core.volume.reconstruct import reconstruct_session

PARAMETERS = ("theta", "d", "a", "alpha")
UNITS = {"theta": "deg", "d": "mm", "a": "mm", "alpha": "deg"}
TABLE = ("seed", "corners (mm)", "surface to CAD, phantom as registered (mm)", "at the true base pose (mm)",
         "true calibration, arm fitted: registered (mm)", "arm not identified: registered (mm)",
         "at the true base pose (mm)", "UR3 time (s)")
FIGURES = ("corners", "surface", "surface_base", "true_fitted", "true_registered", "true_base")


@dataclass(frozen=True)
class SeedFigures:
    seed: int
    corners: float
    surface: float
    surface_base: float
    true_fitted: float
    true_registered: float
    true_base: float
    robot_s: float
    workspace: dict[str, tuple[float, float]]  # distance bin: (fitted, not identified) median error (mm)
    fitted: dict[str, np.ndarray]  # DH deviations the calibration fitted (deg, mm)
    truth: dict[str, np.ndarray]  # the twin's
    undetermined: list[str]  # the deviations the calibration reports the poses leave undetermined


def registered_phantom(session: Session, results: list[FrameResult], calibration: Calibration) -> np.ndarray:
    """``phantom_to_base`` (mm) as the reported poses and ``calibration`` place each frame's
    registration, averaged over the frames."""
    assert session.phantom is not None
    m, n = [], []
    for r in results:
        registration = register_frame(session.phantom, r.markers, calibration.pixel_spacing_mm) if r.found else None
        pose = session.records[r.index].tool_to_base
        if registration is not None and pose is not None:
            m.append(pose)
            n.append(registration.image_to_phantom)
    return y_from_known_x(np.array(m), np.array(n), calibration.image_to_tool_rigid)


def fitted_around(session: Session, results: list[FrameResult], true: Calibration, y0: np.ndarray) -> Calibration:
    """``true`` with the arm's deviations and the phantom pose the all-wire fit finds with the
    calibration held there."""
    assert session.phantom is not None and session.manifest.arm is not None
    obs, _ = observations(session, results)
    fit = refine(session.phantom, obs.markers_px, obs.tool_to_base, true.image_to_tool_rigid, y0,
                 true.pixel_spacing_mm, solve_spacing=False, prior=WIRE_PRIOR, kinematics=obs.kinematics,
                 hold_x=True)
    assert fit.kinematic_units is not None
    return replace(true, phantom_to_base=fit.phantom_to_base,
                   arm=deviation_json(session.manifest.arm, fit.kinematic_units))


def placed(sweep: Session, calibration: Calibration) -> CadTarget:
    """The sweep's CAD model where it sits relative to the phantom as ``calibration`` registered it."""
    cad = session_cad_target(sweep, phantom_to_base=calibration.phantom_to_base)
    assert cad is not None
    return cad


def surface(sweep: Session, calibration: Calibration, cad: CadTarget, folder: Path) -> float:
    return float(reconstruct_session(sweep, calibration, folder, cad=cad).report["surface_mean_mm"])


CORNERS_BEFORE_MM = 0.193
"""The default plan's corners on seeds 0-9 before the arm was applied to sweeps
(``bench_plan.py --seeds 10``, docs/evidence/calibration.md), to the 3 decimals it is given in."""
WORKSPACE_POSES = 400
DISTANCE_BINS_MM = (0.0, 60.0, 120.0, 200.0, np.inf)
IMAGE_CENTRE_MM = np.array([19.0, 20.0, 0.0, 1.0])


def workspace_poses(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Reported flange poses (P, 4, 4) across the workspace box, the probe pointing down, turned
    about the vertical by up to 90 deg either way and tilted by up to 20 deg, and their joints
    (P, 6), reachable ones only."""
    rng = np.random.default_rng([seed, 55])
    box = load_workspace()
    poses, joints = [], []
    for _ in range(WORKSPACE_POSES):
        turn = Rotation.from_euler("zyx", [rng.uniform(-90, 90), rng.uniform(-20, 20), rng.uniform(-20, 20)],
                                   degrees=True)
        pose = make_transform(turn * Rotation.from_matrix(np.diag([1.0, -1.0, -1.0])),
                              rng.uniform(box.box_min_mm, box.box_max_mm))
        try:
            joints.append(closest_ik(pose, HOME_JOINTS))
        except Unreachable:
            continue
        poses.append(pose)
    return np.array(poses), np.array(joints)


def workspace_errors(seed: int, calibration: Calibration,
                     not_identified: Calibration) -> dict[str, tuple[float, float]]:
    """Median distance (mm) of the image centre from where it is, in the phantom's frame as each
    calibration registered it, at poses across the workspace (:func:`workspace_poses`), by the
    image centre's distance from the phantom's centre."""
    twin = twin_scanner(seed, "bench").twin
    poses, joints = workspace_poses(seed)
    true_y = invert_transform(twin.phantom_to_base)
    actual = np.array([twin.actual_tool_to_base(p, q) for p, q in zip(poses, joints)])
    truth = np.einsum("ij,pjk,k->pi", true_y, actual, twin.image_to_tool_rigid @ IMAGE_CENTRE_MM)[:, :3]
    assert calibration.arm is not None and calibration.phantom_to_base is not None
    assert not_identified.phantom_to_base is not None
    fitted = arm_poses(joints, arm_deviation(calibration.arm), ArmModel(UR3))
    errors = [np.linalg.norm(np.einsum("ij,pjk,k->pi", invert_transform(c.phantom_to_base), m,
                                       c.image_to_tool_rigid @ IMAGE_CENTRE_MM)[:, :3] - truth, axis=1)
              for c, m in ((calibration, fitted), (not_identified, poses))]
    distance = np.linalg.norm(truth - twin.phantom.center(), axis=1)
    bins = {}
    for low, high in zip(DISTANCE_BINS_MM[:-1], DISTANCE_BINS_MM[1:]):
        inside = (distance >= low) & (distance < high)
        if inside.any():
            bins[f"{low:.0f}-{high:.0f}"] = (float(np.median(errors[0][inside])), float(np.median(errors[1][inside])))
    return bins


def dh_of(values: dict) -> dict[str, np.ndarray]:
    return {name: np.asarray(values[f"{name}_{UNITS[name]}"], dtype=float) for name in PARAMETERS}


def seed_figures(seed: int, poses: int) -> SeedFigures:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = simulate_calibration(tmp / "cal", n_poses=poses, seed=seed, noise="bench")
        truth = session.truth()
        results = segment_session(session)
        calibration = calibrate_session(session, results).calibration
        assert calibration.arm is not None, "the twin's sessions name their arm"
        true = load_calibration(session.path / "truth.json")
        corners = corner_distances_mm(calibration, true, image_corners_px(session.image_size)).mean()
        sweep = simulate_volume(tmp / "vol", seed=seed, noise="bench")
        at_base = session_cad_target(sweep)
        assert at_base is not None
        true_registered = replace(true, phantom_to_base=registered_phantom(session, results, true))
        true_fitted = fitted_around(session, results, true, true_registered.phantom_to_base)
        return SeedFigures(
            seed, float(corners),
            surface(sweep, calibration, placed(sweep, calibration), tmp / "registered"),
            surface(sweep, calibration, at_base, tmp / "base"),
            surface(sweep, true_fitted, placed(sweep, true_fitted), tmp / "true_fitted"),
            surface(sweep, true_registered, placed(sweep, true_registered), tmp / "true_registered"),
            surface(sweep, true, at_base, tmp / "true_base"),
            float(session.manifest.robot_time_s or 0.0),
            workspace_errors(seed, calibration, true_registered),
            dh_of(calibration.arm), dh_of(truth["setup"]["dh_deviation"]),
            calibration.metrics.get("arm_undetermined") or [])


def print_workspace(rows: list[SeedFigures]) -> None:
    print("  across the workspace: the image centre off where it is (median over the poses, mean over the seeds, mm), "
          "by its distance from the phantom (mm):")
    for name in rows[0].workspace:
        seen = [r.workspace[name] for r in rows if name in r.workspace]
        fitted, plain = np.mean(seen, axis=0)
        print(f"    {name:>8}: through the fitted arm {fitted:.3f}; true calibration, arm not identified {plain:.3f}")


def print_dh(rows: list[SeedFigures]) -> None:
    print("  the arm's DH deviations, fitted against the truth (RMS over the seeds; the truth's RMS in brackets; "
          "the seeds whose calibration reports it determined in square brackets):")
    for name, symbol in zip(PARAMETERS, ("θ", "d", "a", "α")):
        error = np.sqrt(np.mean([(r.fitted[name] - r.truth[name]) ** 2 for r in rows], axis=0))
        size = np.sqrt(np.mean([r.truth[name] ** 2 for r in rows], axis=0))
        determined = [sum(f"{symbol}{joint}" not in r.undetermined for r in rows) for joint in range(1, 7)]
        cells = "  ".join(f"{e:.4f} ({s:.4f}) [{k}]" for e, s, k in zip(error, size, determined))
        print(f"    {name:5s} ({UNITS[name]}), joints 1-6: {cells}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    print(f"twin bench, {args.seeds} seeds x {args.poses} poses, the arm fitted with the calibration and applied "
          "to the test object's sweep: surface to CAD, mean mm")
    print("  seed  corners  registered  base   | true cal.: arm fitted  not identified  base  | UR3 s")
    with ProcessPoolExecutor(max_workers=2) as pool:
        rows = list(pool.map(seed_figures, seeds, [args.poses] * len(seeds)))
    mean = {name: float(np.mean([getattr(r, name) for r in rows])) for name in (*FIGURES, "robot_s")}
    for label, f in [*((f"{r.seed:4d}", vars(r)) for r in rows), ("mean", mean)]:
        print(f"  {label:>4}  {f['corners']:7.3f}  {f['surface']:10.3f}  {f['surface_base']:5.3f}  |  "
              f"{f['true_fitted']:19.3f}  {f['true_registered']:14.3f}  {f['true_base']:5.3f} | {f['robot_s']:5.1f}")
    print(f"  targets: surface to CAD as registered <= 0.25 mm with the estimated calibration: "
          f"{'ok' if mean['surface'] <= 0.25 else 'OVER'}; <= 0.15 with the true one: "
          f"{'ok' if mean['true_fitted'] <= 0.15 else 'OVER'}; corners no worse than the "
          f"{CORNERS_BEFORE_MM} mm before: {'ok' if round(mean['corners'], 3) <= CORNERS_BEFORE_MM else 'OVER'}")
    print_workspace(rows)
    print_dh(rows)
    if args.write_docs:
        table = [[label, *(f"{f[n]:.3f}" for n in FIGURES), f"{f['robot_s']:.0f}"]
                 for label, f in [*((str(r.seed), vars(r)) for r in rows), ("mean", mean)]]
        print(f"written: {write_table(command_line(), markdown_table(TABLE, table))}", flush=True)


if __name__ == "__main__":
    main()
