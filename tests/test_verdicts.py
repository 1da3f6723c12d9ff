"""The verdicts every result leads with (app.report), the same for the command line and the console:
each case a user meets, judged against the tolerance the user owns."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import t as student_t

from probecal.app.report import (
    Verdict,
    calibration_verdict,
    poses_needed,
    reconstruction_verdict,
    wire_check_verdict,
)
from probecal.core.calibration.result import Calibration, CalibrationMetrics, CornerError
from probecal.core.calibration.wirecheck import TAIL, CheckSettings, WireCheck, WireFound, poses_to_tell


def _calibration(bound: float | None, weak: list[str] | None = None, used: int = 40) -> Calibration:
    metrics = CalibrationMetrics(fre_mm=0.13, frames_used=used, frames_total=used, corner_error_95_mm=bound,
                                 weakly_determined=weak or [])
    return Calibration(np.eye(4), (0.1, 0.1), metrics=metrics)


def test_a_calibration_within_its_tolerance_is_usable_and_one_beyond_says_how_many_poses():
    good = calibration_verdict(_calibration(0.56), 1.0)
    assert good == Verdict(True, "Calibration usable: image corners within ±0.56 mm (95 %), under your 1.0 mm "
                                 "tolerance; 40 of 40 frames.", 1.0)
    bad = calibration_verdict(_calibration(1.46, used=8), 1.0)
    assert bad.usable is False and bad.headline.startswith("Not usable: image corners within ±1.46 mm (95 %), over "
                                                           "your 1.0 mm tolerance; 8 of 8 frames.")
    assert bad.next_step == f"record a calibration sweep of about {poses_needed(1.46, 1.0, 8)} poses"
    assert 8 < poses_needed(1.46, 1.0, 8) <= 30 and poses_needed(1.46, 1.0, 8) % 5 == 0
    assert calibration_verdict(_calibration(0.56), 0.5).usable is False  # the user's tolerance decides


def test_a_bound_that_more_poses_cannot_close_says_what_sets_it():
    """A tracked recording whose objectives disagree far beyond their scatter (PLUS's fCal 1.2 the
    robot's way: all-wire 5.7 mm from middle-wire at the corners) is not told to sweep more."""
    calibration = _calibration(7.16, used=182)
    calibration.metrics["corner_error"] = CornerError(
        bootstrap_95_mm=1.05, jackknife_95_mm=1.47, objective_disagreement_mm={"all-wire": 5.68, "thesis": 0.9},
        objective_excess_mm={"all-wire": 5.68, "thesis": 0.2}, fold_spread_mm={}, echo_peak_disagreement_mm=0.25,
        wire_prior_disagreement_mm=None, resamples=40, failed_resamples=0)
    verdict = calibration_verdict(calibration)
    assert verdict.usable is False and verdict.next_step.startswith(
        "the all-wire objective puts the image corners 5.68 mm away, which more poses do not close")
    calibration.metrics["corner_error"]["objective_excess_mm"]["all-wire"] = 0.0  # within its own scatter
    assert calibration_verdict(calibration).next_step == f"record a calibration sweep of about " \
                                                         f"{poses_needed(7.16, 1.0, 182)} poses"


def test_a_calibration_the_poses_do_not_pin_down_is_not_usable_however_small_its_bound():
    weak = calibration_verdict(_calibration(0.4, ["the poses rotate little about a second axis"]))
    assert weak.usable is False and "the poses do not pin the calibration down" in weak.headline
    assert "tilts the probe more" in weak.next_step


def test_a_calibration_without_figures_has_no_verdict():
    assert calibration_verdict(Calibration(np.eye(4), (0.1, 0.1))).usable is None
    assert calibration_verdict(_calibration(None)).usable is None


def _report(**figures) -> dict:
    return {"frames": 200, "surface_points": 5000, **figures}


def test_a_partial_scan_says_so_first_whatever_its_surface_error():
    partial = reconstruction_verdict(_report(coverage={"recorded": 48, "planned": 200, "unit": "poses"},
                                             surface_mean_mm=0.386, surface_p95_mm=0.9, cad_to_points_mean_mm=2.98))
    assert partial.usable is False
    assert partial.headline.startswith("Partial volume: 48 of 200 planned poses scanned, so parts of the object are "
                                       "missing (the CAD model lies 2.98 mm from the nearest point on average)")


def test_a_whole_scan_is_judged_by_its_surface_and_by_how_much_of_the_object_it_covers():
    whole = {"coverage": {"recorded": 200, "planned": 200, "unit": "poses"}}
    good = reconstruction_verdict(_report(**whole, surface_mean_mm=0.56, surface_p95_mm=0.7,
                                          cad_to_points_mean_mm=0.55))
    assert good.usable is True and good.headline.startswith("Volume usable: surface 0.56 mm from the CAD model")
    far = reconstruction_verdict(_report(**whole, surface_mean_mm=1.4, surface_p95_mm=2.0, cad_to_points_mean_mm=1.3))
    assert far.usable is False and "over your 1.0 mm tolerance" in far.headline
    holes = reconstruction_verdict(_report(**whole, surface_mean_mm=0.3, surface_p95_mm=0.5,
                                           cad_to_points_mean_mm=1.5))
    assert holes.usable is False and holes.headline.startswith("Partial volume: surface 0.30 mm")
    assert reconstruction_verdict(_report()).usable is None  # no CAD model to judge by


def _wire(k: int, offset: float, error: float, runs: int = 4, dots: int = 40, scatter: float = 0.05) -> WireFound:
    shift = np.array([offset, 0.0, 0.0])
    return WireFound(f"w{k}", "layer", dots, (0.2, 0.8), shift, shift, error, runs, None, None, None, scatter)


def _check(wires: list[WireFound]) -> WireCheck:
    return WireCheck(wires, CheckSettings(tolerance_mm=0.2), 40, np.zeros((len(wires), 2, 3)))


def test_the_phantom_check_names_the_wires_off_by_their_labels_and_the_poses_that_would_tell_the_rest():
    wires = [_wire(0, 0.5, 0.01), _wire(1, 0.05, 0.005), _wire(2, 0.26, 0.03), *(_wire(k, 0.05, 0.005)
                                                                                  for k in range(3, 12))]
    check = _check(wires)
    assert [check.verdict(w) for w in wires[:3]] == ["off", "within", "unsure"]
    verdict = wire_check_verdict(check)
    assert verdict.usable is False
    assert verdict.headline == ("Phantom off its definition: 1L 0.50 mm, beyond the 0.2 mm tolerance; the scan "
                                "cannot tell 1R.")
    more = poses_to_tell(check)
    assert more is not None and more.wires == ["w2"] and more.untold == []
    assert verdict.next_step == f"sweep about {more.poses} poses in all to tell the rest"
    # A wire beyond the tolerance is off once its offset clears its margin (Student's t at 3
    # degrees of freedom times its standard error), which falls as one over the root of the poses.
    t = student_t.ppf(1.0 - TAIL, 3)
    assert 40 * (t * 0.03 / 0.26) ** 2 < more.poses <= 1.1 * 40 * (t * 0.03 / 0.26) ** 2 + 5


def test_a_wire_at_the_tolerance_or_seen_too_seldom_is_said_so():
    at_tolerance = _check([_wire(0, 0.2, 0.02), *(_wire(k, 0.05, 0.005) for k in range(1, 12))])
    more = poses_to_tell(at_tolerance)
    assert more is not None and more.poses is None and more.untold == ["w0"]
    assert wire_check_verdict(at_tolerance).next_step == ("no longer sweep would tell them: their offsets lie at "
                                                          "the tolerance")
    seldom = _check([_wire(0, float("nan"), float("nan"), runs=1, dots=8), *(_wire(k, 0.05, 0.005)
                                                                            for k in range(1, 12))])
    assert poses_to_tell(seldom).poses == pytest.approx(5 * np.ceil(1.1 * 40 * CheckSettings().min_frames / 8 / 5))
    told = _check([_wire(k, 0.05, 0.005) for k in range(12)])
    assert poses_to_tell(told) is None and wire_check_verdict(told).usable is True
