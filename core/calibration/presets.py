"""A calibration made at one depth preset of a probe, derived for another.

Labs calibrate at one preset and scan at another (another start and end depth, width or image
size); PLUS needs a calibration per preset. Where both presets are known (each session's image
size, nominal spacing and first row's depth below the probe's face), the probe's face and axis do
not move, only the pixel map does, so one calibration serves every preset of the probe.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from probecal.core.calibration.result import Calibration
from probecal.core.calibration.validity import check_fits, mismatches, valid_for
from probecal.core.io.session import Session


def derived_for(calibration: Calibration, session: Session) -> Calibration | None:
    """``calibration`` for the setting of ``session``'s images, when both settings are known
    (image size, nominal spacing, first row's depth) and it is rigid times spacing; None
    otherwise. The probe's face and axis stay where they are: the image's axis is its lateral
    centre, its first row ``start_depth_mm`` below the face. The spacing keeps its fitted
    correction of the nominal one (the sound speed, axially), which scales the start depth too."""
    made = calibration.valid_for
    spacing, start = session.nominal_spacing_mm, session.start_depth_mm
    made_spacing = None if made is None else made.get("nominal_spacing_mm")
    made_start = None if made is None else made.get("start_depth_mm")
    if (made is None or calibration.affine is not None or spacing is None or start is None or made_spacing is None
            or made_start is None):
        return None
    (made_sx, made_sy), (sx, sy) = made_spacing, spacing
    kx, ky = calibration.pixel_spacing_mm[0] / made_sx, calibration.pixel_spacing_mm[1] / made_sy
    made_width, width = made["image_size"][0] * made_sx, session.image_size[0] * sx
    shift = np.eye(4)
    shift[:2, 3] = kx * (made_width - width) / 2, ky * (start - made_start)
    return replace(calibration, image_to_tool_rigid=calibration.image_to_tool_rigid @ shift,
                   pixel_spacing_mm=(kx * sx, ky * sy), valid_for=valid_for(session))


def applied(calibration: Calibration, calibration_file: str | Path, session: Session,
            force: bool = False) -> tuple[Calibration, str]:
    """The calibration to apply to ``session`` and what to tell the user: as it is where it was
    made for images like the session's (or does not say); derived for the session's setting
    where both are known (:func:`derived_for`); else as :func:`check_fits` decides."""
    made_for = calibration.valid_for
    differ = [] if made_for is None else mismatches(made_for, session)
    if not differ:
        return calibration, ""
    derived = derived_for(calibration, session)
    if derived is None:
        return calibration, check_fits(made_for, calibration_file, session, force)
    return derived, (f"note: {calibration_file}: made for other images ({'; '.join(differ)}); derived for "
                     f"{session.path}'s (the probe's face and axis kept, the pixel map changed)")
