"""Volume scanning: a session's frames and a calibration in, a surface point cloud, a compounded
volume and a report out (design §1 step 7, §6 ``reconstruct``).

One pass over the frames (each read once) feeds both the surface extraction and the compounder.
Everything is in the base frame (PLUS's Reference for imported sessions), mm.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np

from probecal.core.acquisition.coverage import Coverage, sweep_coverage
from probecal.core.acquisition.pairing import paired_at_latency
from probecal.core.calibration.kinematics import through_arm
from probecal.core.calibration.result import Calibration, CalibrationSource, VerdictJSON, calibration_source
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.files import fresh_folder, staged_folder
from probecal.core.io.jsonio import write_json
from probecal.core.io.sequence import oriented_mf, read_sequence
from probecal.core.io.session import Session
from probecal.core.volume.cad import CadTarget
from probecal.core.volume.compound import Compounder, reconstruct_sequence
from probecal.core.volume.grid import Volume, VolumeSettings, output_grid, settings_from_device_set
from probecal.core.volume.pointcloud import (
    base_points_from_pixels,
    clean,
    error_colors,
    refine_cad_placement,
    remove_floor,
    surface_error,
    write_ply,
)
from probecal.core.volume.surface import SurfaceParams, extract_surface
from probecal.core.volume.volumefile import write_volume

Progress = Callable[[int, int], None]
DEFAULT_VOLUME = VolumeSettings(spacing_mm=(0.5, 0.5, 0.5), interpolation="NEAREST_NEIGHBOR",
                                compounding="MEAN", fill_holes=True)
ERROR_FULL_SCALE_MM = 1.0


REPORT = "report.json"
"""The file a reconstruction's report is written to, beside its cloud and volume."""


class VolumeReport(TypedDict):
    """The compounded volume: its shape (nz, ny, nx), origin (centre of voxel 0, mm), voxel size
    (mm) and how it was compounded."""

    shape_zyx: list[int]
    origin_mm: list[float]
    spacing_mm: list[float]
    interpolation: str
    compounding: str
    fill_holes: bool
    fan: dict | None  # the fan the frames were clipped to (pixels; core.geometry.fan.Fan), if any


class _ReconstructionCounts(TypedDict):
    session: str
    frames: int
    frames_with_pose: int
    calibration: CalibrationSource
    surface_points_raw: int
    surface_points: int
    pixel_spacing_mm: list[float]
    image_latency_s: float | None
    volume: VolumeReport
    seconds: float
    coverage: Coverage | None


class ReconstructionReport(_ReconstructionCounts, total=False):
    """``report.json`` of ``probecal reconstruct`` (design §6): what went in and came out, and with a
    CAD target the surface error (mm, design §5) and where the object was taken to sit."""

    surface_mean_mm: float
    surface_p95_mm: float
    cad_to_points_mean_mm: float | None  # None: no CAD face lies under the scanned surface
    cad_to_points_p95_mm: float | None
    object_to_base: np.ndarray
    cad_registered: bool
    verdict: VerdictJSON


@dataclass(frozen=True)
class Reconstruction:
    """The surface points (base frame, mm) with their colours by height and, with a CAD target,
    by their distance to it; the compounded volume (base frame); and the report written beside them."""

    points_base: np.ndarray
    height_colors: np.ndarray
    error_colors: np.ndarray | None
    report: ReconstructionReport
    volume: Volume


def height_colors(points: np.ndarray) -> np.ndarray:
    """Colour points by height (base z), blue low to red high, for viewing the cloud."""
    z = points[:, 2]
    span = max(float(np.ptp(z)), 1e-9)
    return error_colors((z - z.min()) / span, 1.0)


@dataclass(frozen=True)
class FramesSetRight:
    """Resamples a fan image's frames, as the scanner shows them, onto its pixels set right by a
    calibration's stretch (``Calibration.set_right``), where its ``image_to_tool`` maps them exactly."""

    fan: Fan
    stretch: float
    map_x: np.ndarray  # (H, W) float32: the shown pixel each set-right pixel takes its value from
    map_y: np.ndarray

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def clip(self, clip: Fan) -> Fan:
        """A clipping fan of the frames as shown, on the pixels set right: its radii stretched
        from the face as every beam's depth is."""
        face = self.fan.radius_start_px
        return replace(clip, radius_start_px=face + (clip.radius_start_px - face) * self.stretch,
                       radius_stop_px=face + (clip.radius_stop_px - face) * self.stretch)


def frames_set_right(calibration: Calibration, shape: tuple[int, int]) -> FramesSetRight | None:
    """For a fan calibration, what resamples (H, W) = ``shape`` frames onto pixels set right; None for
    any other calibration."""
    if calibration.fan is None or calibration.stretch is None:
        return None
    grid = np.stack(np.meshgrid(np.arange(shape[1], dtype=float), np.arange(shape[0], dtype=float)), axis=-1)
    source = calibration.fan.stretched(grid, 1.0 / calibration.stretch).astype(np.float32)
    return FramesSetRight(calibration.fan, calibration.stretch, source[..., 0].copy(), source[..., 1].copy())


def _measured(value: float) -> float | None:
    """A figure, or None where nothing could be measured (NaN: no CAD face under the scan)."""
    return value if math.isfinite(value) else None


def as_calibrated(session: Session, calibration: Calibration) -> tuple[Session, float | None]:
    """``session`` paired again at the calibration's image latency (:func:`paired_at_latency`;
    the latency it applied, or None) and mapped through the arm the calibration fitted
    (:func:`core.calibration.kinematics.through_arm`)."""
    session, latency = paired_at_latency(session, calibration.image_latency_s)
    return through_arm(session, calibration.arm), latency


def usable_poses(session: Session) -> list[np.ndarray | None]:
    """Every frame's ``tool_to_base`` (mm), None where its pose or its image is not valid."""
    return [r.tool_to_base if r.pose_valid and r.extra.get("image_valid", True) else None for r in session.records]


def frame_surface(image: np.ndarray, tool_to_base: np.ndarray, image_to_tool: np.ndarray,
                  surface: SurfaceParams) -> np.ndarray:
    """(n, 3) base-frame points (mm) of the surface one frame shows (set right, for a fan
    calibration) from its flange pose; ``image_to_tool`` includes the spacing."""
    u, v = extract_surface(image, surface)
    return base_points_from_pixels(u, v, tool_to_base, image_to_tool)


def surface_cloud(raw: np.ndarray, floor_up: tuple[float, float, float] | None) -> np.ndarray:
    """The frames' surface points (base frame, mm) merged (:func:`clean`) and, given the base
    frame's up direction, without the tank floor."""
    points = clean(raw)
    return points if floor_up is None else remove_floor(points, np.asarray(floor_up, dtype=float))


def reconstruct_session(
    session: Session,
    calibration: Calibration,
    out_dir: str | Path,
    settings: VolumeSettings = DEFAULT_VOLUME,
    cad: CadTarget | None = None,
    surface: SurfaceParams = SurfaceParams(),
    floor_up: tuple[float, float, float] | None = (0.0, 0.0, 1.0),
    progress: Progress | None = None,
    source: CalibrationSource | None = None,
    stage: Callable[[str], None] | None = None,
    judge: Callable[[ReconstructionReport], VerdictJSON] | None = None,
) -> Reconstruction:
    """Write ``surface.ply``, ``volume.nrrd`` and ``report.json`` (and ``surface_error.ply`` with a
    CAD target) into ``out_dir``, assembled in a staging folder so a failure leaves nothing, and
    return what they hold.
    ``floor_up`` is the base frame's up direction for removing the tank floor (None: keep it).
    ``progress(done, total)`` hears of the frames, ``stage(what)`` of each step after them.
    ``report.json`` names the calibration: ``source``, else one not saved
    (:func:`core.calibration.result.calibration_source`).
    A session that kept its pose stream is paired again with the calibration's image latency,
    when it has one (the report's ``image_latency_s``; None: the frames' poses as recorded).
    A calibration that fitted the session's arm puts every frame where that arm puts the flange
    (:func:`core.calibration.kinematics.through_arm`), in that arm's base frame: the one the
    calibration's ``phantom_to_base`` is in.
    The frames are clipped to the fan of ``settings``, else to the session's own (a recording of
    a scan-converted fan whose import stated it). A fan calibration's frames are first resampled
    where its stretch sets their pixels right (:class:`FramesSetRight`).
    ``judge(report)`` gives the verdict the report keeps (``verdict``), when given."""
    out_dir = fresh_folder(out_dir)
    if len(session) == 0:
        raise InputError(session.path, "session has no frames")
    if settings.fan is None and session.fan is not None:
        settings = replace(settings, fan=session.fan)
    session, latency = as_calibrated(session, calibration)
    image_to_tool = calibration.image_to_tool
    set_right = frames_set_right(calibration, (session.image_size[1], session.image_size[0]))
    if set_right is not None and settings.fan is not None:
        settings = replace(settings, fan=set_right.clip(settings.fan))
    poses = usable_poses(session)
    if not any(p is not None for p in poses):
        raise InputError(session.path, "no frame has a valid pose")
    image_to_base = [None if p is None else p @ image_to_tool for p in poses]
    started = time.perf_counter()
    first = session.image(next(i for i, p in enumerate(poses) if p is not None))
    grid = output_grid(settings, (first.shape[1], first.shape[0]), image_to_base)
    compounder = Compounder(settings, grid)
    clouds = []
    for i, (tool_to_base, pose) in enumerate(zip(poses, image_to_base)):
        if tool_to_base is not None and pose is not None:
            image = session.image(i) if set_right is None else set_right(session.image(i))
            compounder.insert(image, pose)
            clouds.append(frame_surface(image, tool_to_base, image_to_tool, surface))
        if progress:
            progress(i + 1, len(session))
    raw = np.concatenate(clouds) if clouds else np.empty((0, 3))
    points = surface_cloud(raw, floor_up)
    if len(points) == 0:
        raise InputError(session.path, "no surface found in any frame (nothing brighter than the threshold)")
    if stage:
        stage("filling the volume's holes" if settings.fill_holes else "assembling the volume")
    volume = compounder.result()
    report = ReconstructionReport(
        session=str(session.path),
        frames=len(session),
        frames_with_pose=sum(p is not None for p in poses),
        surface_points_raw=len(raw),
        surface_points=len(points),
        calibration=source or calibration_source(calibration),
        pixel_spacing_mm=list(calibration.pixel_spacing_mm),
        image_latency_s=latency,
        volume=VolumeReport(shape_zyx=list(volume.voxels.shape), origin_mm=list(volume.origin_mm),
                            spacing_mm=list(volume.spacing_mm), interpolation=settings.interpolation,
                            compounding=settings.compounding, fill_holes=settings.fill_holes,
                            fan=None if settings.fan is None else settings.fan.to_json()),
        seconds=0.0,
        coverage=sweep_coverage(session),
    )
    heights, errors = height_colors(points), None
    with staged_folder(out_dir) as staging:
        write_ply(staging / "surface.ply", points, heights)
        write_volume(volume, staging / "volume.nrrd")
        if cad is not None:
            if stage:
                stage("measuring the surface against the CAD model")
            placement = cad.start(points)
            if cad.register:
                placement = refine_cad_placement(points, cad.mesh, placement)
            error = surface_error(points, cad.mesh, placement)
            report |= {"surface_mean_mm": error.points_to_cad_mean, "surface_p95_mm": error.points_to_cad_p95,
                       "cad_to_points_mean_mm": _measured(error.cad_to_points_mean),
                       "cad_to_points_p95_mm": _measured(error.cad_to_points_p95), "object_to_base": placement,
                       "cad_registered": cad.register}
            errors = error_colors(error.point_distances, ERROR_FULL_SCALE_MM)
            write_ply(staging / "surface_error.ply", points, errors)
        report["seconds"] = round(time.perf_counter() - started, 2)
        if judge is not None:
            report["verdict"] = judge(report)
        write_json(staging / REPORT, report)
    return Reconstruction(points, heights, errors, report, volume)


def reconstruct_plus(
    sequence_file: str | Path, config_file: str | Path, progress: Progress | None = None
) -> Volume:
    """Reconstruct a PLUS ``.igs.mha`` with a device-set XML's ``<VolumeReconstruction>`` settings,
    PLUS-style: the volume frame is the config's ReferenceCoordinateFrame ("Reference" by
    default), ``image_to_reference = ToolToReference @ ImageToTool`` with ImageToTool (e.g.
    Image->Probe, includes the pixel spacing) from the config's CoordinateDefinitions and
    ToolToReference per frame from the sequence (composed from ...ToTracker if needed). Frames
    with an invalid transform or image status are skipped. Raises InputError naming the file."""
    sequence_file, config_file = Path(sequence_file), Path(config_file)
    config = read_device_set(config_file)
    settings, attributes = settings_from_device_set(config), config.volume_reconstruction
    if settings is None or attributes is None:  # both None exactly when the element is missing
        raise InputError(config_file, "no <VolumeReconstruction> element")
    image = attributes.get("ImageCoordinateFrame", "Image")
    reference = attributes.get("ReferenceCoordinateFrame", "Reference")
    seq = read_sequence(sequence_file)
    image_to_reference = None
    for (source, tool), image_to_tool in config.transforms.items():
        found = seq.transform(tool, reference) if source == image else None
        if found is not None:
            tool_to_reference, valid = found
            image_to_reference = [m @ image_to_tool if ok else None for m, ok in zip(tool_to_reference, valid)]
            break
    if image_to_reference is None:
        raise InputError(
            config_file,
            f"no {image}->tool transform whose tool->{reference} pose is in {sequence_file.name} "
            f"(sequence transforms: {', '.join(sorted(seq.transforms)) or 'none'})",
        )
    if seq.image_ok is not None:
        image_to_reference = [m if ok else None for m, ok in zip(image_to_reference, seq.image_ok)]
    try:
        # PLUS turns frames to MF before it pastes them: its clip rectangle, fan and ImageToProbe are in MF pixels.
        frames = oriented_mf(seq.frames, seq.fields.get("UltrasoundImageOrientation", "MF"))
        return reconstruct_sequence(iter(frames), image_to_reference, settings, progress)
    except ValueError as exc:
        raise InputError(sequence_file, str(exc))
