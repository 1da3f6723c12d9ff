"""How far the ``all-wire`` fit lets the wires move (``core.calibration.objectives.WIRE_SIGMA_MM``), chosen on
the real recordings and the ``bench`` twin together (issue 15), never on one alone.

For each prior (0: the wires held at their definition) and each recording, the all-wire
objective alone is cross-validated in blocks of consecutive frames (``core.calibration.crossval``): the
held-out frames' PRE3D against the wires as the other blocks located them. That is all the real
recordings can say; the twin adds the truth: the calibrated image corners against where the true
calibration puts them (mean of four corners, mm).

- real: PLUS's fCal 1.2 calibration recording (no hints but the nominal spacing; its validation
  recording validates too, against the definition, as PLUS does) and PLUS 1's
  NwirePhantomFreehand recording;
- twin: ``bench`` seeds, 60 poses, phantom pose solved (the robot's path).

A second table checks that the gain is not bound to one set of images: the real calibration
frames perturbed as in ``bench_real_segmentation.py`` (gain, gamma, speckle, blur, motion),
segmented afresh the robot's way, calibrated with the wires held (0) and at the
default prior; fCal validated on its untouched validation recording, NwirePhantomFreehand
cross-validated.

Run: .venv/bin/python benchmarks/bench_wire_sigma.py [--sigmas 0,0.025,0.05,0.1,0.2] [--seeds 6] [--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from bench_calibration import FCAL_CONFIG, PLUS, import_nwire
from bench_real_segmentation import PERTURBATIONS
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
import probecal.core.calibration.objectives as objectives
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.crossval import cross_validate, summary
from probecal.core.calibration.frames import initial_spacing, observations
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import Segmenter, segment_session, session_segmenter, tuning_sample
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distances_mm, image_corners_px
from probecal.core.calibration.validate import validate_session
from probecal.core.io.plusimport import import_plus

DEFAULT_SIGMA = objectives.WIRE_SIGMA_MM
TABLE = ("wire prior (mm)", "fCal 1.2 held out", "fCal 1.2 validation", "NwirePhantomFreehand held out",
         "`bench` held out", "`bench` corners (worst)")


def prior_cell(sigma: float) -> str:
    """A wire prior in the table: 0 is the wires held, the default in bold."""
    if sigma == 0:
        return "0 (held)"
    return f"**{sigma:g}**" if sigma == DEFAULT_SIGMA else f"{sigma:g}"


def held_out_pre3d(session, results, solve_y: bool, prior: WirePrior) -> float:
    """The all-wire objective's block cross-validated PRE3D (mm) under the wires' ``prior``."""
    phantom = session.phantom
    obs, _ = observations(session, results)
    spacing0 = initial_spacing(session, obs, phantom)
    start = obs.registered(phantom, spacing0, objectives.REGISTRATION["all-wire"])
    known_y = None if solve_y else session.phantom_to_base
    return summary(phantom, cross_validate(phantom, start, spacing0, "all-wire", known_y, prior=prior),
                   start)["pre3d_mm"]


def twin_row(sigma: float, seed: int, poses: int) -> tuple[float, float]:
    """One bench seed at one prior: held-out PRE3D and the corners against the truth (mm)."""
    prior = WirePrior(sigma)
    with tempfile.TemporaryDirectory() as tmp:
        session = simulate_calibration(Path(tmp) / "s", n_poses=poses, seed=seed, noise="bench")
        truth = session.truth()
        true_cal = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
        results = segment_session(session)
        cal = calibrate_session(session, results, "all-wire", solve_phantom_pose=True,
                                with_validation=False, prior=prior).calibration
        corners = corner_distances_mm(cal, true_cal, image_corners_px(session.image_size)).mean()
        return held_out_pre3d(session, results, True, prior), float(corners)


def perturbed_results(session, name: str, seed: int = 0) -> list:
    """The session's frames perturbed by ``name``, segmented by a segmenter tuned on them (no
    hints but the nominal spacing)."""
    rng = np.random.default_rng(seed)
    clean = session_segmenter(session, use_hints=False)
    frames = []
    for i in range(len(session)):
        found = clean(session.image(i), i)
        frames.append(PERTURBATIONS[name](session.image(i), found.markers if found.found else None, rng)[0])
    segmenter = Segmenter.for_session(session, use_hints=False).tune(tuning_sample(frames))
    return [segmenter(frame, i) for i, frame in enumerate(frames)]


def perturbed_table(fcal, fval, val_results, nwire, sigmas: tuple[float, float]) -> None:
    """fCal validation PRE3D and NwirePhantomFreehand held-out PRE3D (mm) on perturbed copies,
    with the patterns found (fCal / Nwire frames)."""
    print(f"perturbed copies of the real calibration frames, wires held (0) -> at {sigmas[1]} mm")
    print(f"{'perturbation':15s} {'patterns found':>15s} {'fCal validation':>22s} {'Nwire held out':>22s}")
    for name in PERTURBATIONS:
        if name in ("crop 10 %", "one dot erased"):
            continue  # a moved image origin is another calibration; a dot gone from every frame leaves none
        fcal_results, nwire_results = perturbed_results(fcal, name), perturbed_results(nwire, name)
        found = f"{sum(r.found for r in fcal_results)} / {sum(r.found for r in nwire_results)}"
        cells = []
        for sigma in sigmas:
            prior = WirePrior(sigma)
            calibration = calibrate_session(fcal, fcal_results, "all-wire", with_validation=False,
                                            prior=prior).calibration
            cells.append(f"{validate_session(fval, calibration, val_results)['pre3d_mm']:.3f}")
            cells.append(f"{held_out_pre3d(nwire, nwire_results, False, prior):.3f}")
        print(f"{name:15s} {found:>15s} {cells[0]:>12s} -> {cells[2]:>6s} {cells[1]:>15s} -> {cells[3]:>6s}",
              flush=True)


def sigma_table(fcal, fval, nwire, segmented: dict, sigmas: list[float], args) -> list[list[str]]:
    """The held-out figures of every prior on the real recordings and the twin's seeds, printed;
    the rows of :data:`TABLE`."""
    print(f"all-wire objective, held-out PRE3D (mm, blocks of consecutive frames); twin: bench, "
          f"{args.seeds} seeds x {args.poses} poses, corners vs the truth (mm)")
    print(f"{'wire sigma mm':>13s} {'fCal held out':>14s} {'fCal validation':>16s} {'Nwire held out':>15s} "
          f"{'bench held out':>15s} {'bench corners':>14s} {'worst seed':>11s}")
    seeds = range(args.seeds)
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        for sigma in sigmas:
            prior = WirePrior(sigma)
            fcal_cv = held_out_pre3d(fcal, segmented["cal"], False, prior)
            calibration = calibrate_session(fcal, segmented["cal"], "all-wire", with_validation=False,
                                            prior=prior).calibration
            validation = validate_session(fval, calibration, segmented["val"])["pre3d_mm"]
            nwire_cv = held_out_pre3d(nwire, segmented["nwire"], False, prior)
            twin = np.array(list(pool.map(twin_row, [sigma] * len(seeds), seeds, [args.poses] * len(seeds))))
            print(f"{sigma:13.3f} {fcal_cv:14.3f} {validation:16.3f} {nwire_cv:15.3f} {twin[:, 0].mean():15.3f} "
                  f"{twin[:, 1].mean():14.3f} {twin[:, 1].max():11.3f}", flush=True)
            rows.append([prior_cell(sigma), f"{fcal_cv:.3f}", f"{validation:.3f}", f"{nwire_cv:.3f}",
                         f"{twin[:, 0].mean():.3f}", f"{twin[:, 1].mean():.3f} ({twin[:, 1].max():.3f})"])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sigmas", default="0,0.025,0.05,0.1,0.2")
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--perturbed-only", action="store_true", help="only the table of perturbed real frames")
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    sigmas = [float(s) for s in args.sigmas.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        fcal = import_plus(PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha", FCAL_CONFIG, tmp / "cal")
        fval = import_plus(PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha", FCAL_CONFIG, tmp / "val")
        nwire = import_nwire(tmp)
        segmented = {name: segment_session(s, segmenter=session_segmenter(s, use_hints=False))
                     for name, s in (("cal", fcal), ("val", fval), ("nwire", nwire))}
        if not args.perturbed_only:
            rows = sigma_table(fcal, fval, nwire, segmented, sigmas, args)
            if args.write_docs:
                print(f"written: {write_table(command_line(), markdown_table(TABLE, rows))}", flush=True)
        perturbed_table(fcal, fval, segmented["val"], nwire, (0.0, DEFAULT_SIGMA))


if __name__ == "__main__":
    main()
