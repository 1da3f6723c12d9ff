"""Do the real phantoms' diagonals turn within their layers? (issue 31, item 1)

Each N's ratio reads where the image crosses the wires; a diagonal turned about its middle within
its layer reads that position off by an amount that grows from the middle to either end. No single
frame shows it (the N keeps its shape), but a freehand sweep along the wires does, against the
tracker. The all-wire fit is run on every PLUS tracked recording (the robot's way: own segmenter,
no PLUS hints but the approximate spacing, phantom pose as PLUS registered it) with its wires'
usual prior, then with each diagonal also free to turn (``WirePrior.diagonal_turn_mm``), and
prints:

- the turn it finds per layer (mm at each end, across the diagonal, the back end's way);
- each objective's held-out PRE3D over blocks of consecutive frames, against the definition (the
  yardstick ``auto`` chooses by), and what ``auto`` keeps;
- all-wire and middle-wire apart at the image corners, and all-wire's two halves apart (mm);
- on the fCal calibration recordings, the validation PRE3D on PLUS's own points (at the latency
  the calibration measured) of all-wire and of the default, against PLUS's.

Run: .venv/bin/python benchmarks/bench_diagonal_turn.py [--turn MM]
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_calibration import FCAL_SETS, plus_points_pre3d, tracked_recordings

import probecal.core  # noqa: F401  (sets BLAS threads before numpy loads)
import probecal.core.calibration.objectives as objectives
from probecal.core.acquisition.pairing import paired_again
from probecal.core.calibration.frames import initial_spacing, observations
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.io.plusresults import read_calibration_results


def layer_turns(session, results, prior: WirePrior, latency_s: float | None) -> np.ndarray:
    """(L,) how far (mm) the all-wire fit turns each layer's diagonal: half the difference of its
    back and front ends' shifts across it within the layer."""
    if latency_s:
        session = paired_again(session, latency_s)
    phantom = session.phantom
    obs, _ = observations(session, results)
    spacing0 = initial_spacing(session, obs, phantom)
    solution = objectives.fit(phantom, obs.registered(phantom, spacing0, "point-to-wire"), spacing0, "all-wire",
                              session.phantom_to_base, prior=prior)
    return phantom.diagonal_turns(solution.wire_shifts_mm)


def recording(name: str, session, results, prior: WirePrior, validation=None) -> None:
    corners = image_corners_px(session.image_size)
    auto = calibrate_session(session, results, with_validation=False, prior=prior).calibration
    rows = auto.metrics["objectives"]
    forced = {m: calibrate_session(session, results, m, with_validation=False, prior=prior).calibration
              for m in ("all-wire", "middle-wire")}
    n = len(results)
    halves = [calibrate_session(session, part, "all-wire", with_validation=False, prior=prior).calibration
              for part in (results[: n // 2], results[n // 2:])]
    turns = layer_turns(session, results, prior, forced["all-wire"].image_latency_s)
    print(f"  {name}: turns {', '.join(f'{t:+.2f}' for t in turns)} mm; held-out PRE3D all-wire "
          f"{rows['all-wire']['cv_pre3d_mm']:.3f}, middle-wire {rows['middle-wire']['cv_pre3d_mm']:.3f} "
          f"(auto keeps {auto.metrics['objective']}); objectives "
          f"{corner_distance_mm(forced['all-wire'], forced['middle-wire'], corners):.2f} mm apart, all-wire's halves "
          f"{corner_distance_mm(halves[0], halves[1], corners):.2f}")
    if validation is not None:
        session_v, baseline = validation
        all_wire, default = (plus_points_pre3d(session_v, c, baseline)[0] for c in (forced["all-wire"], auto))
        print(f"    validation PRE3D on PLUS's points: all-wire {all_wire:.3f}, default {default:.3f} mm "
              f"(PLUS {baseline.pre3d_validation_mm[0]:.3f})")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--turn", type=float, default=0.5, metavar="MM",
                        help="the diagonals' turn prior (1 sd at each end) of the second run")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sessions = tracked_recordings(Path(tmp))
        results = {name: segment_session(s, segmenter=session_segmenter(s, use_hints=False))
                   for name, s in sessions.items()}
        validations = {f"{bench.name} calibration": (sessions[f"{bench.name} validation"],
                                                      read_calibration_results(bench.results)) for bench in FCAL_SETS}
        for turn in (None, args.turn):
            prior = replace(objectives.WIRE_PRIOR, diagonal_turn_mm=turn)
            print("the wires' usual prior" if turn is None else f"each diagonal also free to turn ({turn} mm, 1 sd)")
            for name, session in sessions.items():
                recording(name, session, results[name], prior, validations.get(name))


if __name__ == "__main__":
    main()
