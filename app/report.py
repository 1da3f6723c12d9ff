"""A calibration's report, and a built phantom's check, in words: the same lines for the command
line (``probecal calibrate``, ``probecal phantom check``) and the console, every figure with its
meaning and unit (mm, degrees, mm/px, ms)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from probecal.core.calibration.kinematics import DEVIATION_NAMES
from probecal.core.calibration.result import BoundMap, Calibration, CalibrationMetrics, CurvePoint, VerdictJSON
from probecal.core.calibration.wirecheck import MIN_SPAN, WireCheck, WireFound, poses_to_tell
from probecal.core.geometry.phantom import Phantom, wire_label
from probecal.core.volume.reconstruct import ReconstructionReport
from probecal.core.volume.selfcheck import SelfCheckReport


@dataclass(frozen=True)
class Table:
    """Figures in columns under ``header``, after a ``title``: the first column names the row when
    ``named`` (set to the left), the others are figures; ``marked`` is the row set apart (the chosen
    objective), with ``mark``."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    marked: int | None = None
    mark: str = ""
    named: bool = True

    def columns(self, keep: Sequence[int]) -> Table:
        """The table with only the columns ``keep`` (indices), for a narrow panel."""
        return replace(self, header=tuple(self.header[k] for k in keep),
                       rows=tuple(tuple(row[k] for k in keep) for row in self.rows))


Block = str | Table
"""A report's parts: sentences and tables."""


def table_lines(table: Table) -> list[str]:
    """The table as text: its title, then its columns aligned (the first to the left), indented."""
    cells = [table.header, *table.rows]
    widths = [max(len(row[k]) for row in cells) for k in range(len(table.header))]
    lines = [f"  {table.title}"] if table.title else []
    for i, row in enumerate(cells):
        text = "  ".join(cell.ljust(w) if k == 0 and table.named else cell.rjust(w)
                         for k, (cell, w) in enumerate(zip(row, widths)))
        lines.append(f"    {text}" + (f"  {table.mark}" if table.marked is not None and i - 1 == table.marked else ""))
    return lines


def text_lines(blocks: Sequence[Block], indent: str = "") -> list[str]:
    """A report as the command line prints it: every sentence after ``indent``, every table aligned."""
    return [line for block in blocks
            for line in (table_lines(block) if isinstance(block, Table) else [indent + block])]


def _number(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _curve_table(curve: list[CurvePoint]) -> Table:
    rows = tuple((str(row["poses"]), _number(row["identity_translation_mm"]), _number(row["identity_rotation_deg"]),
                  _number(row["pre3d_mm"])) for row in curve)
    return Table("error vs poses, on frames held out of each fit (hand-eye error, PRE3D):",
                 ("poses", "mm", "deg", "PRE3D mm"), rows, named=False)


def _arm_line(model: str, correction_mm: float, undetermined: list[str] | None) -> str:
    """What the arm's fitted kinematic errors do, and which of them the poses determine."""
    line = (f"arm: the {model}'s kinematic errors fitted with the calibration move the image centre up to "
            f"{correction_mm:.3f} mm from where the reported poses put it; sweeps by this arm are reconstructed "
            "through them")
    if undetermined is not None:
        determined = [name for name in DEVIATION_NAMES if name not in undetermined]
        line += (f"; these poses determine {', '.join(determined) or 'none of its DH deviations'} on their own, "
                 f"the other {len(undetermined)} only in their combined effect near the poses, each staying near "
                 "the table's value (volumes are in the fitted arm's base frame)")
    return line


def _objective_table(m: CalibrationMetrics) -> Table:
    """The objectives side by side: PRE3D on held-out blocks of consecutive frames, spacing, rejections."""
    names = list(m["objectives"])
    rows = tuple((name, _number(row["cv_pre3d_mm"]), " x ".join(f"{v:.5f}" for v in row["pixel_spacing_mm"]),
                  str(row["frames_rejected"])) for name, row in m["objectives"].items())
    return Table("the objectives, PRE3D on blocks of consecutive frames held out of the fit:",
                 ("objective", "PRE3D mm", "spacing mm/px", "rejected"), rows,
                 names.index(m["objective"]) if m["objective"] in names else None, "<- kept")


def _corner_line(m: CalibrationMetrics) -> str:
    parts = m["corner_error"]
    excess = parts.get("objective_excess_mm", {})

    def other(name: str, d: float | None) -> str:
        beyond = excess.get(name)
        scatter = "" if beyond is None else (" (within its own scatter)" if beyond <= 0.005
                                             else f" ({beyond:.2f} mm beyond its own scatter)")
        return f"{name} {_number(d, 2)} mm{scatter}"

    disagree = ", ".join(other(name, d) for name, d in parts["objective_disagreement_mm"].items())
    echo = parts["echo_peak_disagreement_mm"]
    wires = parts.get("wire_prior_disagreement_mm")
    jackknife = parts.get("jackknife_95_mm")
    return (f"the image-corner bound ±{_number(m['corner_error_95_mm'], 2)} mm (95 %, tool frame) is the largest of: "
            f"refits on resampled blocks ±{_number(parts['bootstrap_95_mm'], 2)} mm"
            + (f", on the blocks of consecutive frames left out ±{jackknife:.2f} mm" if jackknife is not None else "")
            + (f", the other objectives {disagree}" if disagree else "")
            + (f", markers at their echoes' peaks {echo:.2f} mm" if echo is not None else "")
            + (f", wires held loosely to their definition {wires:.2f} mm" if wires is not None else ""))


def _bound_map_line(bound_map: BoundMap) -> str:
    """Where over the image the bound is least and largest (the bound map's points, px)."""
    points = [(b, p) for bounds, row in zip(bound_map["bound_mm"], bound_map["points_px"])
              for b, p in zip(bounds, row) if b is not None]
    (least, at_least), (largest, at_largest) = min(points), max(points)
    return (f"the 95 % bound over the image ({len(points)} points, metrics.bound_map): from ±{least:.2f} mm at "
            f"({at_least[0]:.0f}, {at_least[1]:.0f}) px to ±{largest:.2f} mm at ({at_largest[0]:.0f}, "
            f"{at_largest[1]:.0f}) px")


def _latency_line(t: Mapping[str, Any]) -> str:
    """The image latency a calibration measured: on the up-and-down motion (echo against motion),
    or by its own fit to a tracked recording's moving frames."""
    figure = f"image latency {t['image_latency_s'] * 1000:.1f} ± {t['std_error_s'] * 1000:.1f} ms"
    if "correlation" in t:
        return (f"{figure} (measured on {t['frames_used']} frames of the up-and-down motion, echo-motion correlation "
                f"{abs(t['correlation']):.4f}); every frame paired again with it, and later sweeps and "
                "reconstructions use it")
    fitted = (f"{figure} (fitted: the frames paired with their tracked poses at every lag within "
              f"{t['searched_s']:g} s; markers {t['residual_at_zero_mm']:.3f} mm from their wires as recorded, "
              f"{t['residual_mm']:.3f} mm at the latency)")
    if t["applied"]:
        return f"{fitted}; every frame paired again with it, and validations and reconstructions use it"
    return f"{fitted}; within its standard error of zero, so the frames are used as recorded"


DEFAULT_TOLERANCE_MM = 1.0
"""How far the image corners may be off (mm, 95 %) for a calibration to be usable, unless the
user sets another tolerance: a millimetre is what navigation and volume work with a linear probe
commonly accept."""
POSES_STEP = 5


@dataclass(frozen=True)
class Verdict:
    """A result's answer to the user's question, is it good enough to use: ``usable`` (None: there
    is nothing to judge it by), a ``headline`` saying why, the ``next_step`` when it is not, and the
    ``tolerance_mm`` it was judged against."""

    usable: bool | None
    headline: str
    tolerance_mm: float
    next_step: str = ""

    @property
    def text(self) -> str:
        """The headline and the next step, as one line."""
        return self.headline + (f" Next: {self.next_step}." if self.next_step else "")

    def to_json(self) -> VerdictJSON:
        return VerdictJSON(usable=self.usable, text=self.text, tolerance_mm=self.tolerance_mm)


def _mm(value: float) -> str:
    """A tolerance as the user would write it: 1.0, 0.5, 0.25."""
    return f"{value:.1f}" if round(value, 1) == value else f"{value:g}"


def poses_needed(bound_mm: float, tolerance_mm: float, poses: int) -> int:
    """About how many poses bring a corner bound of ``bound_mm`` from ``poses`` under
    ``tolerance_mm``: a bound from independent frames shrinks about as one over the square root
    of their number (rounded up to :data:`POSES_STEP`, a fifth more for the margin)."""
    needed = 1.2 * poses * (bound_mm / tolerance_mm) ** 2
    return int(min(1000, POSES_STEP * np.ceil(needed / POSES_STEP)))


def _closing_step(m: CalibrationMetrics, tolerance_mm: float) -> str:
    """What would bring a bound over the tolerance under it: what more poses cannot close first (an
    objective, beyond its own scatter, or the echoes' peaks putting the corners elsewhere), else
    more poses, the bound then being the frames' random error."""
    parts = m.get("corner_error")
    bound = m["corner_error_95_mm"] or 0.0
    if parts is None:
        return f"record a calibration sweep of about {poses_needed(bound, tolerance_mm, m['frames_used'])} poses"
    excess = parts.get("objective_excess_mm") or {}
    others = {**{f"the {name} objective": excess.get(name, d) if excess.get(name) is not None else d
                 for name, d in parts["objective_disagreement_mm"].items()},
              "the markers at their echoes' peaks": parts["echo_peak_disagreement_mm"],
              "the wires held loosely": parts.get("wire_prior_disagreement_mm")}
    name, far = max(((k, v) for k, v in others.items() if v is not None), key=lambda item: item[1],
                    default=("another fit", 0.0))
    if far > tolerance_mm:
        return (f"{name} puts the image corners {far:.2f} mm away, which more poses do not close: check the "
                "phantom definition, the pixel spacing and the segmentation (--verbose lists the bound's parts)")
    return f"record a calibration sweep of about {poses_needed(bound, tolerance_mm, m['frames_used'])} poses"


def calibration_verdict(calibration: Calibration, tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> Verdict:
    """Usable when the image corners' 95 % bound lies within ``tolerance_mm`` and the poses pin the
    calibration down; otherwise why not, and what to record next."""
    m = calibration.metrics
    if "fre_mm" not in m:
        return Verdict(None, "No verdict: this calibration carries no accuracy figures (it was made elsewhere).",
                       tolerance_mm, "check it on a calibration sweep (probecal validate)")
    frames = f"{m['frames_used']} of {m['frames_total']} frames"
    bound = m.get("corner_error_95_mm")
    if bound is None:
        return Verdict(None, f"No verdict: the calibration was not validated, so it has no accuracy bound; {frames}.",
                       tolerance_mm, "calibrate again with its validation")
    within = f"image corners within ±{bound:.2f} mm (95 %)"
    if bound > tolerance_mm:
        return Verdict(False, f"Not usable: {within}, over your {_mm(tolerance_mm)} mm tolerance; {frames}.",
                       tolerance_mm, _closing_step(m, tolerance_mm))
    weak = m.get("weakly_determined") or []
    if weak:
        return Verdict(False, f"Not usable: the poses do not pin the calibration down ({weak[0]}); {within}; "
                              f"{frames}.", tolerance_mm, "record a sweep that tilts the probe more about both image "
                                                          "axes")
    return Verdict(True, f"Calibration usable: {within}, under your {_mm(tolerance_mm)} mm tolerance; {frames}.",
                   tolerance_mm)


COVERAGE_FACTOR = 2.0
"""A scan covers its object when the CAD model lies no farther from the nearest point, on average,
than this many times the points lie from the CAD model (at least ``MIN_SURFACE_MM``): on the twin
a whole scan gives about the same both ways, a scan stopped at a quarter of its poses six times
more."""
MIN_SURFACE_MM = 0.25


def _scanned(report: ReconstructionReport) -> str:
    coverage = report.get("coverage")
    if coverage is None:
        return f"{report['frames']} frames"
    return f"{coverage['recorded']} of {coverage['planned']} planned {coverage['unit']}"


def cad_to_points_text(report: ReconstructionReport) -> str:
    """The CAD-to-points figures (mean / 95th percentile, mm), or why there are none."""
    mean, p95 = report.get("cad_to_points_mean_mm"), report.get("cad_to_points_p95_mm")
    return "none under the scan" if mean is None or p95 is None else f"{mean:.3f} / {p95:.3f} mm"


def self_check_verdict(report: SelfCheckReport) -> Verdict:
    """Trust the volumes when the views agree (``core.volume.selfcheck``), with what the offsets
    say; judged against the check's largest offset."""
    trust = "Trust the volumes: " if report["trusted"] else "Do not trust the volumes: "
    return Verdict(report["trusted"], trust + report["cause"], report["max_offset_mm"])


def reconstruction_verdict(report: ReconstructionReport, tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> Verdict:
    """Usable when the whole plan was scanned and, with a CAD model, the surface lies within
    ``tolerance_mm`` of it on average and covers it; a partial scan says so first."""
    coverage, scanned = report.get("coverage"), _scanned(report)
    gap = report.get("cad_to_points_mean_mm")
    missing = "" if gap is None else f" (the CAD model lies {gap:.2f} mm from the nearest point on average)"
    if coverage is not None and coverage["recorded"] < coverage["planned"]:
        return Verdict(False, f"Partial volume: {scanned} scanned, so parts of the object are missing{missing}.",
                       tolerance_mm, "resume the scan and reconstruct again")
    if "surface_mean_mm" not in report:
        return Verdict(None, f"Volume reconstructed from {scanned}: {report['surface_points']} surface points; no "
                             "CAD model to judge it against.", tolerance_mm)
    mean = report["surface_mean_mm"]
    if gap is None:
        return Verdict(False, f"Not usable: no face of the CAD model lies under the scanned surface, which is "
                              f"{mean:.2f} mm from it on average; {scanned}.", tolerance_mm,
                       "check where the object is placed and the calibration")
    surface = f"surface {mean:.2f} mm from the CAD model on average (95th percentile {report['surface_p95_mm']:.2f} mm)"
    if mean > tolerance_mm:
        return Verdict(False, f"Not usable: {surface}, over your {_mm(tolerance_mm)} mm tolerance; {scanned}.",
                       tolerance_mm, "check the calibration's verdict and where the CAD model is placed")
    if gap > COVERAGE_FACTOR * max(mean, MIN_SURFACE_MM):
        return Verdict(False, f"Partial volume: {surface}, but parts of the object are missing{missing}; {scanned}.",
                       tolerance_mm, "scan the sides the sweep missed")
    return Verdict(True, f"Volume usable: {surface}, under your {_mm(tolerance_mm)} mm tolerance; {scanned}.",
                   tolerance_mm)


def objective_sentence(m: CalibrationMetrics) -> str:
    """Which objective the fit used, and the one true reason why."""
    name, method = m["objective"], m.get("method", "auto")
    if method != "auto":
        return f"objective {name}, as asked (--method {method})"
    if m.get("phantom_pose") == "solved":
        return (f"objective {name} (every marker fitted to its own wire, the wires located): kept whenever the "
                "phantom pose is solved, as for a robot sweep, where held-out PRE3D measures agreement, not accuracy")
    return f"objective {name}: {m['objective_choice']}"


def _shah_line(shah: tuple[float, float]) -> str:
    return (f"a textbook baseline for comparison: OpenCV's closed-form hand-eye (Shah), run on the same frames' "
            f"registrations at the nominal spacing, fits neither the wires nor the spacing and puts the image "
            f"{shah[0]:.3f} mm / {shah[1]:.3f} deg from this calibration; it is no accuracy figure")


def calibration_lines(calibration: Calibration, shah: tuple[float, float] | None = None,
                      verbose: bool = False) -> list[str]:
    """:func:`calibration_report` as ``probecal calibrate`` prints it."""
    return text_lines(calibration_report(calibration, shah, verbose), "  ")


def calibration_summary(calibration: Calibration) -> list[Block]:
    """The few lines after the verdict: the objective and why, the fit's residuals, the spacing,
    the latency, the held-out hand-eye error and any weakness of the poses."""
    m = calibration.metrics
    if "fre_mm" not in m:
        return []
    sx, sy = calibration.pixel_spacing_mm
    blocks: list[Block] = [objective_sentence(m)]
    if "temporal" in m:
        blocks.append(_latency_line(m["temporal"]))
    pose = ("consistency, the phantom pose solved" if m["phantom_pose"] == "solved"
            else "against the phantom's known pose")
    blocks += [f"FRE {m['fre_mm']:.3f} mm (per-frame registration), marker-to-wire "
               f"{m['calibration_residual_mm']:.3f} mm, PRE3D {m['pre3d_mm']:.3f} ± {m['pre3d_std_mm']:.3f} mm "
               f"({pose})",
               f"pixel spacing {sx:.5f} x {sy:.5f} mm/px"
               + (f", every beam's depth stretched x{calibration.stretch:.4f}" if calibration.stretch else "")]
    cv = m.get("cross_validation")
    if cv and cv.get("identity_translation_mm") is not None:
        blocks.append(f"held-out hand-eye error {_number(cv['identity_translation_mm'])} mm / "
                      f"{_number(cv['identity_rotation_deg'])} deg ({cv['folds']} blocks of frames left out in turn)")
    blocks += [f"weakly determined: {reason}" for reason in m.get("weakly_determined") or []]
    if m["frames_rejected"]:
        blocks.append(f"{m['frames_rejected']} frames left out ({m['frames_rejected_by_fit']} by the fit: markers that "
                      "disagree with the rest)")
    return blocks


def calibration_details(calibration: Calibration, shah: tuple[float, float] | None = None) -> list[Block]:
    """Everything else the calibration measured: the stretch of a fan's beams, where the fit put
    the wires, the arm's errors, the objectives compared, the bound's parts, the error as poses
    are added, the textbook baseline and every frame left out."""
    m = calibration.metrics
    if "fre_mm" not in m:
        return []
    details: list[Block] = []
    if calibration.fan is not None and calibration.stretch is not None:
        k = calibration.stretch
        details.append(f"fan image: every beam's depth below the face stretched x{k:.4f} (sound "
                       f"{abs(k - 1) * 100:.1f} % {'slower' if k < 1 else 'faster'} in the medium than the scanner "
                       f"assumes), the pixels set right before the spacing; the .xml holds the closest affine "
                       f"ImageToProbe over the fan and the fan for PLUS's volume reconstruction")
    shifts = {name: d for name, d in (m.get("wire_shifts_mm") or {}).items() if d is not None}
    if shifts:
        name, far = max(shifts.items(), key=lambda item: item[1])
        details.append(f"wires located by the fit: up to {far:.3f} mm off the definition ({name}); PRE3D and the "
                       "held-out PRE3D score against the definition, every objective alike")
    correction = m.get("arm_correction_mm")
    if correction is not None and calibration.arm is not None:
        details.append(_arm_line(calibration.arm["model"], correction, m.get("arm_undetermined")))
    if m.get("objectives"):
        details.append(_objective_table(m))
    if m.get("corner_error_95_mm") is not None and "corner_error" in m:
        details.append(_corner_line(m))
    if m.get("bound_map") and any(b is not None for row in m["bound_map"]["bound_mm"] for b in row):
        details.append(_bound_map_line(m["bound_map"]))
    if m.get("error_vs_poses"):
        details.append(_curve_table(m["error_vs_poses"]))
    if shah is not None:
        details.append(_shah_line(shah))
    details += [f"frame {index} left out: {reason}" for index, reason in sorted((m.get("rejected_frames") or
                                                                                 {}).items())]
    return details


def calibration_report(calibration: Calibration, shah: tuple[float, float] | None = None,
                       verbose: bool = True) -> list[Block]:
    """The report of a calibration ``probecal calibrate`` made (its metrics): the summary, and with
    ``verbose`` the details; ``shah`` is how far OpenCV's Shah puts the image from it (mm,
    degrees), when compared."""
    if "fre_mm" not in calibration.metrics:
        return ["(a calibration without probecal's figures: a PLUS file or an older one)"]
    return calibration_summary(calibration) + (calibration_details(calibration, shah) if verbose else [])


def _direction(offset: np.ndarray) -> str:
    """The axis an offset mostly points along, e.g. +x."""
    k = int(np.argmax(np.abs(offset)))
    return f"{'+' if offset[k] > 0 else '-'}{'xyz'[k]}"


def _optional(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def wire_check_lines(check: WireCheck, phantom: Phantom) -> list[str]:
    """The verdict, then :func:`wire_check_report`, as ``probecal phantom check`` prints them."""
    return [wire_check_verdict(check).text, *text_lines(wire_check_report(check, phantom), "  ")]


WIRE_COLUMNS = ("wire", "dots", "seen (mm)", "offset", "±", "toward", "verdict", "front", "back", "sag", "spread")


def wire_names(check: WireCheck, wires: list[WireFound]) -> str:
    """Wires by their short label (the live image's and the plot's), e.g. '1D, 3R'."""
    index = {w.name: k for k, w in enumerate(check.wires)}
    return ", ".join(wire_label(index[w.name]) for w in wires)


def wire_check_report(check: WireCheck, phantom: Phantom) -> list[Block]:
    """Every wire of ``phantom`` as the check found it, a row each (:data:`WIRE_COLUMNS`; the wire
    by its short label and its definition's name), then why any wire is left unsure and whether
    the ends and sag were told."""
    rows = []
    for k, (wire, definition) in enumerate(zip(check.wires, phantom.wires)):
        length = np.linalg.norm(definition.back - definition.front)
        seen = "-" if not np.isfinite(wire.seen[0]) else f"{wire.seen[0] * length:.0f}-{wire.seen[1] * length:.0f}"
        front = None if wire.front_mm is None else float(np.linalg.norm(wire.front_mm))
        back = None if wire.back_mm is None else float(np.linalg.norm(wire.back_mm))
        toward = _direction(wire.shift) if np.isfinite(wire.offset_mm) else "-"
        rows.append((f"{wire_label(k)} {wire.name}", str(wire.dots), seen, _optional(wire.offset_mm),
                     _optional(wire.uncertainty_mm), toward, check.verdict(wire), _optional(front), _optional(back),
                     _optional(wire.sag_mm), _optional(wire.scatter_mm)))
    title = (f"{phantom.name}: {len(check.wires)} wires located from {check.frames_used} frames; how far each sits off "
             "its definition in the middle of the stretch seen, as a move of its holes in the walls' plane, with its "
             f"standard error from {check.settings.runs} runs of consecutive frames (mm, phantom frame):")
    notes: list[Block] = []
    if check.unsure():
        notes.append(f"a wire is unsure when its offset lies within a margin of the {_mm(check.tolerance_mm)} mm "
                     f"tolerance (its standard error times Student's t for {check.settings.runs} runs), its dots "
                     f"scatter by more than the tolerance (spread), or too few frames see it ({check.settings.runs} "
                     f"runs of {check.settings.min_dots} need {check.settings.min_frames})")
    if all(w.sag_mm is None for w in check.wires):
        notes.append(f"ends and sag not told: the dots cover less than {MIN_SPAN:.0%} of each wire, or the scan "
                     "cannot tell the wire; a sweep that travels farther along the wires tells them")
    return [title, Table("", WIRE_COLUMNS, tuple(rows)), *notes]


def wire_check_summary(check: WireCheck) -> str:
    """The check's verdict in a few words, for a status line: the wires off, and how many unsure."""
    off, unsure = check.off(), check.unsure()
    text = f"{wire_names(check, off)} off their definition" if off else "no wire off"
    if unsure:
        more = poses_to_tell(check)
        text += f"; {len(unsure)} unsure" + (", more poses would tell some" if more and more.poses else "")
    return text if unsure or off else "every wire within the tolerance"


def wire_check_verdict(check: WireCheck) -> Verdict:
    """The check's answer: the wires off beyond doubt (worst first, with their offsets), else
    whether every wire was told within the tolerance; for the wires left unsure, about how many
    poses in all would tell them (:func:`core.calibration.wirecheck.poses_to_tell`)."""
    tolerance = _mm(check.tolerance_mm)
    off, unsure = check.off(), check.unsure()
    more = poses_to_tell(check)
    unsure_text, next_step = "", ""
    if unsure:
        unsure_text = f"; the scan cannot tell {wire_names(check, unsure)}"
        if more is not None and more.poses is not None:
            untold = [w for w in unsure if w.name in more.untold]
            beyond = "" if not untold else (f" ({wire_names(check, untold)} {'lies' if len(untold) == 1 else 'lie'} "
                                            "too close to the tolerance for any sweep to tell)")
            next_step = f"sweep about {more.poses} poses in all to tell the rest{beyond}"
        else:
            next_step = "no longer sweep would tell them: their offsets lie at the tolerance"
    if off:
        worst = ", ".join(f"{wire_names(check, [w])} {w.offset_mm:.2f} mm" for w in off)
        return Verdict(False, f"Phantom off its definition: {worst}, beyond the {tolerance} mm tolerance"
                              f"{unsure_text}.", check.tolerance_mm, next_step)
    if unsure:
        within = len(check.wires) - len(unsure)
        return Verdict(None, f"Phantom check undecided: no wire off beyond doubt, {within} within {tolerance} mm"
                             f"{unsure_text}.", check.tolerance_mm, next_step)
    return Verdict(True, f"Phantom as defined: every wire within {tolerance} mm of its definition.",
                   check.tolerance_mm)
