"""Volume files that 3D Slicer and PLUS open in place: ``.nrrd`` (pynrrd) and ``.mha`` (SimpleITK),
axis-aligned uint8 voxels with their origin and spacing in mm."""

from __future__ import annotations

from pathlib import Path

import nrrd
import numpy as np
import SimpleITK as sitk

from probecal.core.errors import InputError
from probecal.core.io.files import existing_file, library_stderr, open_regular, replace_atomically
from probecal.core.io.limits import checked_bytes
from probecal.core.volume.grid import Volume


def write_volume(volume: Volume, path: str | Path) -> None:
    """Write ``.mha`` (SimpleITK) or ``.nrrd`` (pynrrd), atomically, so 3D Slicer opens it in place.

    ``origin_mm`` is the centre of voxel (0, 0, 0) in the volume (base / reference) frame, in mm,
    with an identity direction. Like PLUS, the volume-frame axes are written as the file's patient
    axes: ``.mha`` gets Offset = origin, TransformMatrix = identity (MetaImage is LPS), and ``.nrrd``
    gets ``space: left-posterior-superior``, ``space origin`` = origin, ``space directions`` =
    diag(spacing). Both open identically: a point at volume (x, y, z) mm appears in Slicer at LPS
    (x, y, z), i.e. RAS (-x, -y, z), the same place as PLUS's own ``.mha`` output.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    voxels = np.ascontiguousarray(volume.voxels, dtype=np.uint8)
    origin = [float(v) for v in volume.origin_mm]
    spacing = [float(v) for v in volume.spacing_mm]
    if suffix == ".mha":
        def write(tmp: Path) -> None:
            image = sitk.GetImageFromArray(voxels)
            image.SetOrigin(origin)
            image.SetSpacing(spacing)
            with library_stderr(tmp):
                sitk.WriteImage(image, str(tmp), useCompression=True)
    elif suffix == ".nrrd":
        header = {
            "type": "uint8",
            "dimension": 3,
            "space": "left-posterior-superior",
            "space directions": np.diag(spacing),
            "space origin": np.array(origin),
            "kinds": ["domain", "domain", "domain"],
            "encoding": "gzip",
        }

        def write(tmp: Path) -> None:
            nrrd.write(str(tmp), voxels, header, index_order="C")
    else:
        raise ValueError(f"{path}: volumes are written as .nrrd or .mha")
    replace_atomically(path, write)


def read_volume(path: str | Path) -> Volume:
    """Read a ``.mha``/``.nrrd`` volume written by ``write_volume`` or PLUS (axis-aligned, uint8).
    Raises InputError for a missing file or a rotated or non-uint8 volume."""
    path = existing_file(path)
    try:
        if path.suffix.lower() == ".nrrd":
            with open_regular(path) as f:
                declared = nrrd.read_header(f)
            checked_bytes(path, "the volume", [int(v) for v in np.ravel(declared.get("sizes", []))])
            data, header = nrrd.read(str(path), index_order="C")
            directions = np.asarray(header.get("space directions", np.eye(3)), float)
            origin = tuple(float(v) for v in header.get("space origin", (0.0, 0.0, 0.0)))
            if header.get("space", "left-posterior-superior") != "left-posterior-superior":
                raise InputError(path, f"unsupported space {header['space']!r} (expected left-posterior-superior)")
        else:
            image = sitk.ReadImage(str(path))
            data = sitk.GetArrayFromImage(image)
            directions = np.array(image.GetDirection()).reshape(3, 3) * np.array(image.GetSpacing())
            origin = tuple(image.GetOrigin())
    except (RuntimeError, ValueError, nrrd.NRRDError) as exc:
        raise InputError(path, f"unreadable volume ({exc})")
    spacing = np.diag(directions)
    if data.ndim != 3 or data.dtype != np.uint8:
        raise InputError(path, f"expected a 3D uint8 volume, got {data.dtype} {data.shape}")
    if not np.allclose(directions, np.diag(spacing)) or min(spacing) <= 0:
        raise InputError(path, "only axis-aligned volumes (identity direction) are supported")
    (ox, oy, oz), (sx, sy, sz) = origin, spacing.tolist()
    return Volume(data, (ox, oy, oz), (sx, sy, sz))
