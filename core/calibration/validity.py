"""What a calibration is valid for, and whether a session's images are of that kind.

A calibration holds for one probe at one scanner setting: the image size (px), the nominal pixel
spacing (mm/px) the scanner reports and so the imaging depth (mm), and the depth of the image's
first row below the probe's face (mm, where known). It records them, with where its images came
from. A session of another setting (another depth preset of the same probe) gets the calibration
derived for its own setting when both settings are known (:func:`derived_for`: the probe's face
and axis stay, the pixel map changes); otherwise a command refuses to apply it, since a
calibration of a 384 x 500 image put on 820 x 616 frames would place every point millimetres
off and still be scored without a word.
"""

from __future__ import annotations

from pathlib import Path
from typing import TypedDict

from probecal.core.errors import InputError, Remedy
from probecal.core.geometry.probe import ConvexProbe
from probecal.core.io.session import Session

SPACING_TOLERANCE = 0.01
"""Nominal spacings this far apart (a fraction) are another scanner setting."""


class ValidFor(TypedDict):
    """The images a calibration was made from: (width, height) px, the nominal (sx, sy) mm/px, the
    depth (mm) and the first row's depth below the probe's face (mm) when known, and their source
    (a scanner, a probe model, a PLUS recording)."""

    image_size: list[int]
    nominal_spacing_mm: list[float] | None
    depth_mm: float | None
    source: str | None
    start_depth_mm: float | None


def image_source(session: Session) -> str | None:
    """Where a session's images came from, in words, when the manifest says."""
    source = session.manifest.source or {}
    probe = session.manifest.probe
    if "simulator" in source and probe is not None:
        if isinstance(probe, ConvexProbe):
            return (f"probecal twin: convex probe of {probe.radius_mm:g} mm radius, {probe.fov_deg:g} deg, "
                    f"{probe.depth_mm:g} mm deep")
        return f"probecal twin: linear probe {probe.n_elements} x {probe.pitch_mm:g} mm, {probe.depth_mm:g} mm deep"
    if source.get("image"):
        return str(source["image"])
    if source.get("sequence"):
        return f"PLUS recording {Path(source.get('config') or source['sequence']).name}"
    return None


def valid_for(session: Session) -> ValidFor:
    """What a calibration from ``session``'s images is valid for."""
    width, height = session.image_size
    spacing = session.nominal_spacing_mm
    return ValidFor(image_size=[width, height], nominal_spacing_mm=None if spacing is None else list(spacing),
                    depth_mm=None if spacing is None else round(height * spacing[1], 3), source=image_source(session),
                    start_depth_mm=session.start_depth_mm)


def mismatches(made_for: ValidFor, session: Session) -> list[str]:
    """How ``session``'s images differ from those a calibration was made for (empty: they fit)."""
    return differences(made_for, session.image_size, session.nominal_spacing_mm)


def differences(made_for: ValidFor, size: tuple[int, int], spacing: tuple[float, float] | None) -> list[str]:
    """How images of ``size`` (width, height px) at nominal ``spacing`` (mm/px, if known) differ
    from those a calibration was made for (empty: they fit)."""
    problems = []
    made_size = tuple(made_for["image_size"])
    if made_size != tuple(size):
        problems.append(f"image size {size[0]} x {size[1]} px, the calibration's {made_size[0]} x {made_size[1]}")
    made_spacing = made_for.get("nominal_spacing_mm")
    if made_spacing is not None and spacing is not None and any(
            abs(a - b) > SPACING_TOLERANCE * b for a, b in zip(spacing, made_spacing)):
        problems.append(f"nominal spacing {spacing[0]:.4g} x {spacing[1]:.4g} mm/px, the calibration's "
                        f"{made_spacing[0]:.4g} x {made_spacing[1]:.4g}")
    return problems


def check_fits(made_for: ValidFor | None, calibration_file: str | Path, session: Session, force: bool = False) -> str:
    """Refuse (InputError naming the calibration file, one line) a calibration made for other
    images than ``session``'s, unless ``force``; then the difference comes back as a warning. A
    calibration that does not say what it was made for (PLUS's, older files) is taken as it is.
    The refusal says which first-row depth, if known, would let the calibration be derived for
    the session's images (``core.calibration.presets``)."""
    if made_for is None:
        return ""
    problems = mismatches(made_for, session)
    if not problems:
        return ""
    made = f" (from {made_for['source']})" if made_for.get("source") else ""
    text = f"made for other images{made} than {session.path}: {'; '.join(problems)}"
    if force:
        return f"warning: {calibration_file}: {text}; applied anyway, as asked"
    unknown = _unknown_start_depths(made_for, session)
    if not unknown:
        raise InputError(calibration_file, text, (Remedy.FORCE,))
    raise InputError(calibration_file, f"{text}; it would be derived for these images were {unknown} first row's "
                                       "depth below the probe's face known", (Remedy.START_DEPTH, Remedy.FORCE))


def _unknown_start_depths(made_for: ValidFor, session: Session) -> str:
    """Whose first-row depth (the calibration's, the session's or both) is all that keeps the
    calibration from being derived for the session's images; empty when that is not so (a
    nominal spacing is unknown too)."""
    if made_for.get("nominal_spacing_mm") is None or session.nominal_spacing_mm is None:
        return ""
    unknown = [whose for whose, depth in (("the calibration's", made_for.get("start_depth_mm")),
                                          (f"{session.path}'s", session.start_depth_mm)) if depth is None]
    return " and ".join(unknown)
