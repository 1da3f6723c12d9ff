"""Import a robot recording as a lab keeps it: a folder of image files and a table of poses.

Each pose (``core.io.posetable``) goes with one image (``core.io.imagefiles``): by name when the
table has a file column, else the i-th pose with the i-th image in natural order of the names.
The poses become the session's ``tool_to_base`` (the flange in the robot's base frame, mm); the
phantom pose is left to the calibration to solve, as on a robot. The image axes are probecal's
(``core.calibration.labelling.SIMULATED``: the image's left towards the phantom's -x); a lab whose
scanner shows the phantom the other way round mirrors its frames on import. A scanner's DICOM
export that carries its region calibration (``core.io.dicomframes``) gives the nominal spacing and
the start depth where the command line does not, and the frames are cut to that image region (its
first row the one whose depth the scanner states; the probe's axis taken as its lateral centre).

Everything is read and checked before anything is written (the sizes from the files' headers),
and the session is assembled beside ``out_dir`` and renamed into place: a failure leaves nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from probecal.core.errors import InputError, Remedy
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.dicomframes import ScannerRegion, dicom_dataset, is_dicom, scanner_region
from probecal.core.io.files import fresh_folder, inside
from probecal.core.io.imagefiles import (
    ImageHeader,
    first_odd_size,
    image_files,
    image_header,
    read_frame,
    stored_frame,
)
from probecal.core.io.manifest import Manifest
from probecal.core.io.plusimport import tracker_samples
from probecal.core.io.posetable import PoseTable, read_pose_table
from probecal.core.io.session import Session, load_session
from probecal.core.io.staging import imported_session

Progress = Callable[[int, int], None]
KIND = "imported-frames"


@dataclass(frozen=True)
class NominalSpacing:
    """How the nominal pixel spacing is given: (sx, sy) mm/px, or the image's depth and width (mm)
    from which it follows (one of them alone: square pixels)."""

    spacing_mm: tuple[float, float] | None = None
    depth_mm: float | None = None
    width_mm: float | None = None

    def at(self, width_px: int, height_px: int, source: Path,
           stated: tuple[float, float] | None = None) -> tuple[float, float]:
        """(sx, sy) mm/px for an image of that size: as given, else as the files state it
        (``stated``); InputError naming ``source`` when neither says."""
        if self.spacing_mm is not None:
            return self.spacing_mm
        sx = None if self.width_mm is None else self.width_mm / width_px
        sy = None if self.depth_mm is None else self.depth_mm / height_px
        if sx is None and sy is None:
            if stated is not None:
                return stated
            raise InputError(source, "no nominal pixel spacing: give it, or the image's depth and width",
                             (Remedy.SPACING, Remedy.IMAGE_EXTENT))
        return (sx or sy, sy or sx)  # type: ignore[return-value]


def paired_files(folder: Path, table: PoseTable, poses_file: Path) -> list[Path]:
    """The image file of each pose: by the table's names (inside ``folder``), else in natural
    order; InputError naming the table when a name is missing or the counts differ."""
    if table.files is not None:
        paths = [inside(folder, name, poses_file) for name in table.files]
        missing = next((p for p in paths if not p.is_file()), None)
        if missing is not None:
            raise InputError(poses_file, f"names {missing.name!r}, which is not a file in {folder}")
        return paths
    files = image_files(folder)
    if len(files) != len(table):
        raise InputError(poses_file, f"{len(table)} poses for {len(files)} images in {folder} (pair them by name "
                                     "with a 'file' column)")
    return files


def checked_headers(files: list[Path]) -> list[ImageHeader]:
    """Every file's header; InputError naming the first image whose size differs from the first's."""
    headers = [image_header(f) for f in files]
    odd = first_odd_size(headers)
    if odd is not None:
        h, first = headers[odd], headers[0]
        raise InputError(files[odd], f"{h.width}x{h.height} px, where {files[0].name} is {first.width}x{first.height}: "
                                     "every frame must have one size")
    return headers


def scanner_region_of(files: list[Path]) -> ScannerRegion | None:
    """The region calibration that every frame's DICOM file carries (``core.io.dicomframes``);
    None for other files or when none carries one; InputError naming the first file whose region
    differs from the first's (a recording whose depth or zoom changed)."""
    if not all(is_dicom(f) for f in files):
        return None
    regions = [scanner_region(f, dicom_dataset(f)) for f in files]
    odd = next((k for k, r in enumerate(regions) if r != regions[0]), None)
    if odd is not None:
        raise InputError(files[odd], f"its ultrasound region ({_region_text(regions[odd])}) differs from "
                                     f"{files[0].name}'s ({_region_text(regions[0])}): one preset per import")
    return regions[0]


def _region_text(region: ScannerRegion | None) -> str:
    if region is None:
        return "none"
    sx, sy = region.spacing_mm
    return f"{list(region.box_px)} px at {sx:g} x {sy:g} mm/px"


def import_frames(
    images_dir: str | Path,
    poses_file: str | Path,
    out_dir: str | Path,
    phantom: Phantom,
    spacing: NominalSpacing,
    units: str | None = None,
    direction: str = "flange-to-base",
    mirror: bool = False,
    progress: Progress | None = None,
    start_depth_mm: float | None = None,
) -> tuple[Session, PoseTable]:
    """Turn a folder of frames and a pose table into a session in ``out_dir`` (see the module
    docstring); ``mirror`` flips every frame left to right. Returns the session and the table as
    read (its layout, units and direction, for the import's summary). ``start_depth_mm``: how far
    below the probe's face the first row lies, if known (``core.calibration.validity``)."""
    images_dir, poses_file, out = Path(images_dir), Path(poses_file), fresh_folder(out_dir)
    if not images_dir.is_dir():
        raise InputError(images_dir, "folder of images not found")
    images_dir = images_dir.resolve()
    table = read_pose_table(poses_file, units, direction)
    files = paired_files(images_dir, table, poses_file)
    headers = checked_headers(files)
    region = scanner_region_of(files)
    width, height = (headers[0].width, headers[0].height) if region is None else region.size_px
    sx, sy = spacing.at(width, height, images_dir, None if region is None else region.spacing_mm)
    if start_depth_mm is None and region is not None:
        start_depth_mm = region.start_depth_mm

    def frame(f: Path) -> np.ndarray:
        """A frame as read, cut to the scanner's image region where its files give one."""
        image = read_frame(f)
        return image if region is None else region.cropped(image)

    brightest = None
    if any(h.sixteen_bit for h in headers):
        brightest = 0
        for i, f in enumerate(files):
            brightest = max(brightest, int(frame(f).max()))
            if progress:
                progress(i + 1, 2 * len(files))
    manifest = Manifest(
        kind=KIND,
        source={"images": str(images_dir), "poses": str(poses_file.resolve()), "layout": table.layout,
                "units": table.units, "direction": table.direction, "mirrored": mirror},
        image_size=(width, height),
        pixel_spacing_mm=(sx, sy),
        start_depth_mm=start_depth_mm,
        scanner_region=None if region is None else region.to_json(),
    )
    done = len(files) if brightest is not None else 0
    with imported_session(out, poses_file, manifest, phantom) as writer:
        for i, f in enumerate(files):
            image = stored_frame(frame(f), brightest, mirror)
            t = None if table.times_s is None else float(table.times_s[i])
            writer.append(image, table.flange_to_base[i], timestamp=t, pose_timestamp=t, source_index=i,
                          file=f.relative_to(images_dir).as_posix())
            if progress:
                progress(done + i + 1, done + len(files))
        if table.times_s is not None:
            writer.append_poses(*tracker_samples(table.times_s, table.flange_to_base, np.ones(len(table), bool)))
    return load_session(out), table
