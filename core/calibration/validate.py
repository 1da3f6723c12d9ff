"""Score a calibration on a session it was not computed from (e.g. a PLUS validation sequence).

Reports PRE3D exactly as PLUS does, the markers' distances to their wires under the
calibration, and the thesis's identity-matrix error (eq. 4.1) per frame, all in mm and degrees.
"""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from probecal.core.acquisition.pairing import paired_at_latency
from probecal.core.calibration.frames import observations
from probecal.core.calibration.handeye import marker_offsets, phantom_points_from_pixels
from probecal.core.calibration.metrics import identity_error, pre3d_errors, trimmed_mean_std
from probecal.core.calibration.register import register_frame
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import FrameResult
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import wire_offsets
from probecal.core.geometry.transforms import transform_points
from probecal.core.io.session import Session


class ValidationReport(TypedDict):
    """``probecal validate --out``'s metrics: PRE3D as PLUS computes it (mm; per frame, None where
    a frame has no complete N), the markers' distances to their wires under the calibration (mm)
    and the thesis's eq. 4.1 identity error (mm, degrees), where the phantom pose came from and
    the image latency the frames were paired with (s; None: as recorded)."""

    frames_total: int
    frames_used: int
    frames_left_out: int
    phantom_pose_from: str
    image_latency_s: float | None
    pre3d_mm: float
    pre3d_std_mm: float
    pre3d_per_frame_mm: list[float | None]
    marker_to_wire_mean_mm: float
    marker_to_wire_p95_mm: float
    identity_translation_mm: float | None
    identity_rotation_deg: float | None


def validate_session(session: Session, calibration: Calibration, results: list[FrameResult]) -> ValidationReport:
    """Metrics of ``calibration`` on the segmented ``session``. The phantom pose is the session's
    known one, else the calibration's. A session that kept its pose stream is paired again with
    the calibration's image latency, when it has one (``image_latency_s``; None: as recorded)."""
    if len(session) == 0:
        raise InputError(session.path, "session has no frames")
    phantom = session.phantom
    if phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    phantom_to_base = session.phantom_to_base
    source = "session"
    if phantom_to_base is None:
        phantom_to_base, source = calibration.phantom_to_base, "calibration"
    if phantom_to_base is None:
        raise InputError(session.path, "no phantom pose: the session records none and the calibration has none")
    session, latency = paired_at_latency(session, calibration.image_latency_s)
    obs, left_out = observations(session, results)
    if len(obs) == 0:
        raise InputError(session.path, f"no usable frame among {len(session)}")
    errors = pre3d_errors(phantom, obs.markers_px, obs.tool_to_base, calibration.image_to_tool, phantom_to_base)
    mean, std = trimmed_mean_std(errors)
    offsets = marker_offsets(
        phantom, np.nan_to_num(obs.markers_px), obs.tool_to_base,
        calibration.image_to_tool_rigid, phantom_to_base, calibration.pixel_spacing_mm,
    )
    distances = np.linalg.norm(offsets, axis=2)[np.all(np.isfinite(obs.markers_px), axis=2)]
    identity = []
    for markers, pose in zip(obs.markers_px, obs.tool_to_base):
        reg = register_frame(phantom, markers, calibration.pixel_spacing_mm)
        if reg is not None:
            identity.append(identity_error(calibration.image_to_tool_rigid, phantom_to_base, pose,
                                           reg.image_to_phantom))
    return ValidationReport(
        frames_total=len(session),
        frames_used=len(obs),
        frames_left_out=len(left_out),
        phantom_pose_from=source,
        image_latency_s=latency,
        pre3d_mm=mean,
        pre3d_std_mm=std,
        pre3d_per_frame_mm=[None if not np.all(np.isfinite(e)) else float(np.mean(e)) for e in errors],
        marker_to_wire_mean_mm=float(distances.mean()),
        marker_to_wire_p95_mm=float(np.percentile(distances, 95)),
        identity_translation_mm=float(np.mean([e.translation_mm for e in identity])) if identity else None,
        identity_rotation_deg=float(np.mean([e.rotation_deg for e in identity])) if identity else None,
    )


def markers_on_wires(session: Session, calibration: Calibration,
                     results: list[FrameResult] | None) -> tuple[np.ndarray, np.ndarray]:
    """Every labelled marker of the segmented ``session``'s usable frames where ``calibration``
    puts it, in the base frame ((N, 3) mm), and its distance to its wire ((N,) mm), the phantom
    where the calibration (else the session) puts it; none without a phantom or its pose, or
    without a segmentation."""
    phantom = session.phantom
    phantom_to_base = calibration.phantom_to_base if calibration.phantom_to_base is not None else \
        session.phantom_to_base
    if phantom is None or phantom_to_base is None or results is None or len(session) == 0:
        return np.empty((0, 3)), np.empty(0)
    obs, _ = observations(paired_at_latency(session, calibration.image_latency_s)[0], results)
    if len(obs) == 0:
        return np.empty((0, 3)), np.empty(0)
    markers = calibration.set_right(np.asarray(obs.markers_px, dtype=float))
    points = phantom_points_from_pixels(obs.tool_to_base, calibration.image_to_tool_rigid, phantom_to_base,
                                       calibration.pixel_spacing_mm, markers)
    valid = np.all(np.isfinite(points), axis=2)
    distances = np.linalg.norm(wire_offsets(phantom.lines(), points), axis=2)
    return transform_points(phantom_to_base, points[valid]), distances[valid]
