"""A calibration's report in words, the same lines for ``probecal calibrate`` and the console:
every figure with its meaning and unit (mm, degrees, mm/px, ms)."""

from __future__ import annotations

from probecal.core.calibration.result import Calibration, CalibrationMetrics, CurvePoint


def _number(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _curve_lines(curve: list[CurvePoint]) -> list[str]:
    lines = ["  error vs poses (held-out frames): poses  eq.4.1 mm  eq.4.1 deg  PRE3D mm"]
    for row in curve:
        t, r, p = row["identity_translation_mm"], row["identity_rotation_deg"], row["pre3d_mm"]
        lines.append(f"  {row['poses']:>37d}  {_number(t):>9}  {_number(r):>10}  {_number(p):>8}")
    return lines


def _objective_lines(m: CalibrationMetrics) -> list[str]:
    """The objectives side by side: PRE3D on held-out blocks of consecutive frames, spacing, rejections."""
    lines = ["  objective     CV PRE3D mm  spacing mm/px       rejected frames"]
    for name, row in m["objectives"].items():
        sx, sy = row["pixel_spacing_mm"]
        chosen = "  <- chosen" if name == m["objective"] else ""
        lines.append(f"  {name:<12}  {_number(row['cv_pre3d_mm']):>11}  {sx:.5f} x {sy:.5f}  "
                     f"{row['frames_rejected']:>15}{chosen}")
    return lines


def _corner_line(m: CalibrationMetrics) -> str:
    parts = m["corner_error"]
    disagree = ", ".join(f"{name} {_number(d, 2)} mm" for name, d in parts["objective_disagreement_mm"].items())
    echo = parts["echo_peak_disagreement_mm"]
    return (f"  image corners +-{_number(m['corner_error_95_mm'], 2)} mm (95 %, tool frame): refits on resampled "
            f"blocks +-{_number(parts['bootstrap_95_mm'], 2)} mm"
            + (f", other objectives {disagree}" if disagree else "")
            + (f", markers at their echoes' peaks {echo:.2f} mm" if echo is not None else ""))


def calibration_lines(calibration: Calibration, shah: tuple[float, float] | None = None) -> list[str]:
    """The report of a calibration ``probecal calibrate`` made (its metrics); ``shah`` is how far
    OpenCV's SHAH puts image_to_tool from it (mm, degrees), when compared."""
    m = calibration.metrics
    if "fre_mm" not in m:
        return ["  (a calibration without probecal's metrics: a PLUS file or an older one)"]
    sx, sy = calibration.pixel_spacing_mm
    lines = []
    if "temporal" in m:
        t = m["temporal"]
        lines.append(f"  image latency {t['image_latency_s'] * 1000:.1f} +- {t['std_error_s'] * 1000:.1f} ms "
                     f"(measured on {t['frames_used']} frames of the up-and-down motion, echo-motion correlation "
                     f"{abs(t['correlation']):.4f}); every frame paired again with it, and later sweeps and "
                     "reconstructions use it")
    lines += [
        f"  frames: {m['frames_used']} used, {m['frames_rejected']} rejected of {m['frames_total']} "
        f"({m['frames_rejected_by_fit']} of them by the fit: markers that disagree with the rest)",
        f"  FRE {m['fre_mm']:.3f} mm (per-frame registration), marker-to-wire {m['calibration_residual_mm']:.3f} mm",
        f"  PRE3D {m['pre3d_mm']:.3f} +- {m['pre3d_std_mm']:.3f} mm (calibration frames, phantom pose "
        f"{m['phantom_pose']})",
        f"  pixel spacing {sx:.5f} x {sy:.5f} mm/px",
    ]
    shifts = {name: d for name, d in (m.get("wire_shifts_mm") or {}).items() if d is not None}
    if shifts:
        name, far = max(shifts.items(), key=lambda item: item[1])
        lines.append(f"  wires located by the fit: up to {far:.3f} mm off the definition ({name}); PRE3D above "
                     f"scores against the definition, {m['objective']}'s CV PRE3D below against the located wires")
    if m.get("objectives"):
        lines += _objective_lines(m) + [f"  choice: {m['objective_choice']}"]
    if m.get("corner_error_95_mm") is not None and "corner_error" in m:
        lines.append(_corner_line(m))
    if m["phantom_pose"] == "solved":
        lines.append("  with the phantom pose solved, PRE3D measures consistency, not accuracy; "
                     "the image-corner bound is the accuracy figure")
    lines += [f"  WEAKLY DETERMINED: {reason}" for reason in m.get("weakly_determined") or []]
    cv = m.get("cross_validation")
    if cv and cv.get("identity_translation_mm") is not None:
        lines.append(f"  cross-validation ({cv['folds']} blocks held out in turn): the thesis's eq. 4.1 identity "
                     f"error {_number(cv['identity_translation_mm'])} mm / {_number(cv['identity_rotation_deg'])} "
                     f"deg, PRE3D {_number(cv['pre3d_mm'])} mm")
    if m.get("error_vs_poses"):
        lines += _curve_lines(m["error_vs_poses"])
    if shah is not None:
        lines.append(f"  for comparison, OpenCV's SHAH (closed-form hand-eye on the per-frame registrations, at the "
                     f"nominal spacing, no wire fit) puts image_to_tool {shah[0]:.3f} mm / {shah[1]:.3f} deg from "
                     "this one")
    rejected = sorted((m.get("rejected_frames") or {}).items())
    lines += [f"  rejected frame {index}: {reason}" for index, reason in rejected[:10]]
    if len(rejected) > 10:
        lines.append(f"  ... and {len(rejected) - 10} more rejected frames")
    return lines
