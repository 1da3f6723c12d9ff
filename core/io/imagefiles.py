"""Folders of ultrasound frames saved as image files (PNG, JPEG, TIFF, BMP, or a scanner's DICOM
export: ``core.io.dicomframes``), as a lab's own scripts write them: listed in natural order,
checked from their headers before any is decoded, and read as 8-bit grey.

Colour frames become grey by luminance (ITU-R BT.601 weights, what OpenCV and VTK's
``vtkImageLuminance`` use). 16-bit frames are scaled to 8 bits by one factor for the whole
recording (its brightest value becomes 255), so that frames stay comparable with each other.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from probecal.core.errors import InputError
from probecal.core.io.dicomframes import DICOM_SUFFIXES, dicom_dataset, dicom_pixels, is_dicom
from probecal.core.io.files import byte_source, read_bytes
from probecal.core.io.limits import checked_bytes

SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", *DICOM_SUFFIXES)
SIXTEEN_BIT_MODES = ("I;16", "I;16B", "I;16L", "I", "I;16N")


@dataclass(frozen=True)
class ImageHeader:
    """What a frame's file header says: size (px) and whether it holds 16-bit values."""

    width: int
    height: int
    sixteen_bit: bool


def natural_key(name: str) -> tuple:
    """Sort key that orders the numbers in a name by value: ``img2`` before ``img10``, ``final
    (2)`` before ``final (10)``."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part.lower())
                 for part in re.split(r"(\d+)", name) if part)


def first_odd_size(headers: Sequence[ImageHeader]) -> int | None:
    """The index of the first frame whose size differs from the first frame's; None when all agree."""
    size = (headers[0].width, headers[0].height)
    return next((k for k, h in enumerate(headers) if (h.width, h.height) != size), None)


def image_files(folder: str | Path) -> list[Path]:
    """The image files (``SUFFIXES``) directly in ``folder``, in natural order of their names;
    InputError naming the folder when it is missing or holds none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "folder of images not found")
    files = [p for p in folder.iterdir() if p.suffix.lower() in SUFFIXES and p.is_file()]
    if not files:
        raise InputError(folder, f"no image files ({', '.join(SUFFIXES)}) in the folder")
    return sorted(files, key=lambda p: natural_key(p.name))


def image_header(path: Path, data: bytes | None = None) -> ImageHeader:
    """The header of one frame's file (or of its encoded ``data``, named by ``path``), read
    without decoding its pixels; InputError naming ``path`` when it is not an image, or when
    decoding it would pass the memory limit."""
    if is_dicom(path):
        ds = dicom_dataset(path, data)
        return ImageHeader(int(ds.Columns), int(ds.Rows), int(ds.BitsAllocated) == 16)
    try:
        with byte_source(path, data) as f, Image.open(f) as image:
            width, height = image.size
            bands, mode = len(image.getbands()), image.mode
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise InputError(path, f"not an image file that can be read ({exc.__class__.__name__})") from None
    sixteen = mode in SIXTEEN_BIT_MODES
    checked_bytes(path, "decoding this image", [height, width, bands], 2 if sixteen else 1)
    return ImageHeader(int(width), int(height), sixteen)


def read_frame(path: Path) -> np.ndarray:
    """One frame's file as a grey array (uint8, or uint16 for a 16-bit file): colour by luminance."""
    return decode_frame(read_bytes(path), path)


def decode_frame(data: bytes, source: Path) -> np.ndarray:
    """An encoded frame (PNG, JPEG, TIFF, BMP bytes, named by ``source``) as a grey array (uint8
    or uint16), its size checked from its header first."""
    if is_dicom(source):
        return dicom_pixels(source, data)
    image_header(source, data)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(source, "the image data cannot be decoded")
    if image.ndim == 3:
        image = gray_from_colour(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(source, f"{image.dtype} pixels: only 8- or 16-bit images are read")
    return image


def gray_from_colour(image: np.ndarray) -> np.ndarray:
    """A BGR or BGRA frame (as OpenCV decodes colour) as grey by luminance (BT.601)."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)


def to_eight_bit(image: np.ndarray, brightest: int) -> np.ndarray:
    """A 16-bit frame scaled to 8 bits with the recording's brightest value at 255."""
    scale = 255.0 / max(int(brightest), 1)
    return np.clip(np.rint(image.astype(np.float32) * scale), 0, 255).astype(np.uint8)


def stored_frame(image: np.ndarray, brightest: int | None, mirror: bool) -> np.ndarray:
    """A frame as a session stores it: 8-bit (a 16-bit one scaled by the recording's
    ``brightest`` value), flipped left to right when ``mirror``."""
    if image.dtype != np.uint8:
        image = to_eight_bit(image, brightest or 0)
    return cv2.flip(image, 1) if mirror else image
