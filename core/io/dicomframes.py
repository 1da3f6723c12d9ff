"""Ultrasound frames a scanner exports as DICOM files (one frame per file, read with pydicom), and
the scanner's own region calibration that they carry: DICOM's Sequence of Ultrasound Regions
(PS3.3 C.8.5.5), which gives the image region of the frame in pixels, the physical size of its
pixels and the depth of a reference pixel below the probe's face.

The region used is the first one holding a 2D tissue image (RegionSpatialFormat 1, RegionDataType
1) measured in centimetres both ways. Its pixel spacing becomes the session's nominal spacing (mm);
its first row's depth, where the scanner states a reference pixel's depth (ReferencePixelY0 with
ReferencePixelPhysicalValueY), the session's start depth.
"""

from __future__ import annotations

import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np
import pydicom
from PIL import Image
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import get_frame
from pydicom.errors import InvalidDicomError
from pydicom.filereader import _read_file_meta_info, read_preamble
from pydicom.uid import DeflatedExplicitVRLittleEndian, RLELossless

from probecal.core.errors import InputError
from probecal.core.io.files import byte_source
from probecal.core.io.jsonio import MAX_MAGNITUDE, PIXEL_SPACING_MM
from probecal.core.io.limits import checked_bytes
from probecal.core.io.sizes import encoded_size

DICOM_SUFFIXES = (".dcm",)
CENTIMETRES = 3  # PhysicalUnitsXDirection / PhysicalUnitsYDirection
SPATIAL_2D = 1  # RegionSpatialFormat
TISSUE = 1  # RegionDataType


@dataclass(frozen=True)
class ScannerRegion:
    """A scanner's region calibration of its frames: the image region (px, DICOM's
    RegionLocationMinX0, MinY0, MaxX1, MaxY1, inclusive), its pixel spacing (sx, sy) mm/px and the
    depth (mm) of the region's first row below the probe's face, when the scanner states it."""

    box_px: tuple[int, int, int, int]
    spacing_mm: tuple[float, float]
    start_depth_mm: float | None

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height) of the region."""
        x0, y0, x1, y1 = self.box_px
        return x1 - x0 + 1, y1 - y0 + 1

    def cropped(self, image: np.ndarray) -> np.ndarray:
        """The region of a frame."""
        x0, y0, x1, y1 = self.box_px
        return image[y0 : y1 + 1, x0 : x1 + 1]

    def to_json(self) -> dict:
        return {"region_px": list(self.box_px), "pixel_spacing_mm": list(self.spacing_mm),
                "start_depth_mm": self.start_depth_mm}


def is_dicom(path: Path) -> bool:
    return path.suffix.lower() in DICOM_SUFFIXES


def dicom_dataset(path: Path, data: bytes | None = None, with_pixels: bool = False) -> Dataset:
    """The DICOM data set of one file (or of its bytes ``data``, named by ``path``), its size
    checked from the header before any pixel is decoded; InputError naming ``path`` when it is not
    a DICOM image, holds more than one frame, or decoding it would pass the memory limit."""
    try:
        with byte_source(path, data) as f, warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # pydicom's notes on odd values: its errors count
            _check_inflated_size(path, f)
            ds = pydicom.dcmread(f, stop_before_pixels=not with_pixels)
        rows, columns = int(ds.Rows), int(ds.Columns)
        samples, bits = int(ds.get("SamplesPerPixel", 1)), int(ds.BitsAllocated)
        stated = ds.get("NumberOfFrames")
        frames = 1 if stated is None or stated == "" else int(stated)
    except (InvalidDicomError, AttributeError, TypeError, ValueError, EOFError, OSError, zlib.error) as exc:
        raise InputError(path, f"not a DICOM image that can be read ({exc.__class__.__name__})") from None
    if frames != 1:
        raise InputError(path, f"{frames} frames in one DICOM file: export one frame per file")
    if bits not in (8, 16):
        raise InputError(path, f"{bits}-bit pixels: only 8- or 16-bit images are read")
    checked_bytes(path, "decoding this image", [rows, columns, samples], bits // 8)
    return ds


INFLATE_STEP = 1 << 20
"""Bytes a deflated DICOM body is inflated by at a time, to count its size: none of it is kept."""


def _check_inflated_size(path: Path, f: BinaryIO) -> None:
    """InputError naming ``path`` when a DICOM file in the deflated transfer syntax would inflate
    past the memory limit: pydicom inflates the whole body at once before any header can be
    checked, so it is inflated here first in bounded steps and counted. ``f`` is left at its start."""
    try:
        read_preamble(f, False)
        meta = _read_file_meta_info(f)
    except (InvalidDicomError, AttributeError, TypeError, ValueError, EOFError, OSError):
        meta = FileMetaDataset()  # not a DICOM file, or not a Part 10 one: dcmread says which
    if meta.get("TransferSyntaxUID") == DeflatedExplicitVRLittleEndian:
        inflater, total = zlib.decompressobj(-zlib.MAX_WBITS), 0
        while chunk := f.read(INFLATE_STEP):
            while chunk:
                total += len(inflater.decompress(chunk, INFLATE_STEP))
                checked_bytes(path, "inflating this deflated DICOM file", [total])
                chunk = inflater.unconsumed_tail
    f.seek(0)


def _check_encoded_frame(path: Path, ds: Dataset) -> None:
    """InputError naming ``path`` unless a compressed frame's own header (JPEG, JPEG-LS, JPEG 2000)
    gives the size its Rows and Columns say: a decoder allocates what the frame says, not what
    was checked. RLE decodes into the size Rows and Columns give."""
    syntax = ds.file_meta.get("TransferSyntaxUID")
    if syntax is None or not syntax.is_compressed or syntax == RLELossless:
        return
    try:
        frame = get_frame(ds.PixelData, 0, number_of_frames=1)
    except (ValueError, TypeError, AttributeError, KeyError, EOFError) as exc:
        raise InputError(path, f"the DICOM pixel data's fragments cannot be read ({exc})") from None
    size = encoded_size(frame)
    if size is None:
        raise InputError(path, f"pixel data in {syntax.name} whose size cannot be read from its header")
    if size != (int(ds.Columns), int(ds.Rows)):
        raise InputError(path, f"the {syntax.name} frame is {size[0]}x{size[1]} px, but Columns and Rows say "
                               f"{int(ds.Columns)}x{int(ds.Rows)}")


def dicom_pixels(path: Path, data: bytes) -> np.ndarray:
    """One DICOM frame's pixels as a grey array (uint8 or uint16): colour by luminance, MONOCHROME1
    inverted."""
    ds = dicom_dataset(path, data, with_pixels=True)
    _check_encoded_frame(path, ds)
    try:
        with warnings.catch_warnings():  # the size is checked against probecal's own limit, not Pillow's
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            warnings.simplefilter("ignore", UserWarning)  # pydicom's notes on odd values
            image = np.asarray(ds.pixel_array)
    except (AttributeError, ValueError, NotImplementedError, RuntimeError, OSError,
            Image.DecompressionBombError) as exc:
        raise InputError(path, f"the DICOM pixel data cannot be decoded ({exc})") from None
    if image.ndim == 3:  # pydicom gives colour as RGB
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    if image.dtype.kind == "i":
        image = np.clip(image, 0, None)
    image = image.astype(np.uint16 if int(ds.BitsAllocated) == 16 else np.uint8)
    if str(ds.get("PhotometricInterpretation", "")) == "MONOCHROME1":
        image = np.iinfo(image.dtype).max - image
    return image


def scanner_region(path: Path, ds: Dataset) -> ScannerRegion | None:
    """The frame's region calibration (see the module docstring); None when it has none that
    gives a 2D tissue image's spacing in centimetres; InputError naming ``path`` when the region
    lies outside the frame or its spacing is not positive."""
    for region in ds.get("SequenceOfUltrasoundRegions", []):
        if (int(region.get("RegionSpatialFormat", 0)) != SPATIAL_2D or int(region.get("RegionDataType", 0)) != TISSUE
                or int(region.get("PhysicalUnitsXDirection", 0)) != CENTIMETRES
                or int(region.get("PhysicalUnitsYDirection", 0)) != CENTIMETRES):
            continue
        box = tuple(int(region.get(name, -1)) for name in
                    ("RegionLocationMinX0", "RegionLocationMinY0", "RegionLocationMaxX1", "RegionLocationMaxY1"))
        x0, y0, x1, y1 = box
        if not (0 <= x0 < x1 < int(ds.Columns) and 0 <= y0 < y1 < int(ds.Rows)):
            raise InputError(path, f"the ultrasound region {list(box)} px lies outside the "
                                   f"{int(ds.Columns)}x{int(ds.Rows)} frame")
        sx, sy = (10.0 * abs(float(region.get(name, 0.0))) for name in ("PhysicalDeltaX", "PhysicalDeltaY"))
        low, high = PIXEL_SPACING_MM
        if not (low <= sx <= high and low <= sy <= high):
            raise InputError(path, f"the ultrasound region's PhysicalDeltaX/Y ({sx:g} x {sy:g} mm) is not a pixel "
                                   f"size within [{low:g}, {high:g}] mm")
        start = None
        if "ReferencePixelY0" in region and "ReferencePixelPhysicalValueY" in region:
            depth = 10.0 * float(region.ReferencePixelPhysicalValueY) - int(region.ReferencePixelY0) * sy
            if not abs(depth) <= MAX_MAGNITUDE:
                raise InputError(path, f"the ultrasound region's reference pixel depth ({depth:g} mm) is not a finite "
                                       f"depth (at most {MAX_MAGNITUDE:g} mm)")
            start = depth if depth >= 0.0 else None
        return ScannerRegion((x0, y0, x1, y1), (sx, sy), start)
    return None
