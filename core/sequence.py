"""PLUS tracked sequence files (``.igs.mha``, ``.seq.nrrd``): frames plus per-frame transforms,
read and written with SimpleITK's MetaImage and NRRD support.

Per frame PLUS stores ``Seq_FrameNNNN_<From>To<To>Transform`` (16 numbers, row-major 4x4, mm),
``..TransformStatus`` (OK | INVALID), ``Seq_FrameNNNN_Timestamp`` (s) and ``..ImageStatus``.
Transform names are kept as PLUS spells them without the ``Transform`` suffix, e.g.
``"ProbeToTracker"``.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from core.errors import InputError
from core.files import replace_atomically
from core.transforms import invert_transform, matrix_from_text, matrix_to_text

_FRAME_KEY = re.compile(r"^Seq_Frame(\d+)_(.+)$")
_STANDARD_KEYS = {
    "ITK_InputFilterName", "ITK_original_direction", "ITK_original_spacing", "Kinds",
    "Modality", "NDims", "ElementNumberOfChannels", "ElementType", "DimSize",
}


@dataclass
class TrackedSequence:
    """Frames (N, H, W) uint8 with per-frame transforms (N, 4, 4), statuses and timestamps."""

    frames: np.ndarray
    transforms: dict[str, np.ndarray] = field(default_factory=dict)
    statuses: dict[str, np.ndarray] = field(default_factory=dict)
    timestamps: np.ndarray | None = None
    image_ok: np.ndarray | None = None
    fields: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def transform(self, source: str, target: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(source_to_target (N,4,4), valid (N,)) stored directly or composed via a common frame.

        PLUS trackers record ``XToTracker`` per tool; ``ProbeToReference`` is then
        ``inv(ReferenceToTracker) @ ProbeToTracker`` (valid where both are).
        """
        name = f"{source}To{target}"
        if name in self.transforms:
            return self.transforms[name], self.statuses[name]
        for key in self.transforms:
            if key.startswith(f"{source}To"):
                via = key[len(source) + 2 :]
                other = f"{target}To{via}"
                if other in self.transforms:
                    target_to_via = self.transforms[other]
                    composed = np.array(
                        [invert_transform(b) @ a for a, b in zip(self.transforms[key], target_to_via)]
                    )
                    return composed, self.statuses[key] & self.statuses[other]
        return None


_ELEMENT_BYTES = {"MET_UCHAR": 1, "MET_CHAR": 1, "MET_USHORT": 2, "MET_SHORT": 2, "MET_FLOAT": 4}


def check_header(path: Path) -> dict[str, str]:
    """Parse the MetaImage text header and check that the pixel data is all there.

    Returns the header fields. Raises InputError for a header that ends early or data that is
    shorter than the header promises (a truncated file).
    """
    fields: dict[str, str] = {}
    size = path.stat().st_size
    with open(path, "rb") as f:
        while True:
            line = f.readline()
            if not line:
                raise InputError(path, "truncated header: no ElementDataFile line")
            key, sep, value = line.decode("latin-1").partition("=")
            if not sep:
                raise InputError(path, f"malformed header line {line[:40]!r}")
            key, value = key.strip(), value.strip()
            if not key.startswith("Seq_Frame"):
                fields[key] = value
            if key == "ElementDataFile":
                data_start = f.tell()
                break
    if fields["ElementDataFile"] != "LOCAL":
        raise InputError(path, "pixel data in a separate file is not supported (ElementDataFile must be LOCAL)")
    try:
        dims = [int(v) for v in fields["DimSize"].split()]
        element = _ELEMENT_BYTES[fields.get("ElementType", "MET_UCHAR")]
    except (KeyError, ValueError):
        raise InputError(path, f"unsupported DimSize {fields.get('DimSize')!r} or ElementType {fields.get('ElementType')!r}")
    if fields.get("CompressedData", "False").lower() == "true":
        expected = int(fields.get("CompressedDataSize", "0") or 0)
    else:
        expected = int(np.prod(dims)) * element * int(fields.get("ElementNumberOfChannels", "1"))
    if expected and size - data_start < expected:
        raise InputError(path, f"truncated pixel data: {size - data_start} of {expected} bytes")
    return fields


@contextmanager
def _captured_stderr():
    """Collect what C++ libraries (ITK's MetaIO) print on file descriptor 2."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        lines: list[str] = []
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines.extend(ln.strip() for ln in sink.read().decode(errors="replace").splitlines() if ln.strip())


def read_sequence(path: str | Path) -> TrackedSequence:
    """Read a PLUS ``.igs.mha`` (compressed or not) or ``.seq.nrrd``. Raises InputError on any
    bad input."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    with open(path, "rb") as f:
        head = f.read(64)
    nrrd = path.name.lower().endswith(".nrrd")
    if nrrd and not head.startswith(b"NRRD"):
        raise InputError(path, "not a NRRD file")
    if not nrrd:
        if not head.startswith(b"ObjectType") and b"NDims" not in head:
            raise InputError(path, "not a MetaImage (.mha) file")
        check_header(path)
    with _captured_stderr() as messages:
        try:
            reader = sitk.ImageFileReader()
            reader.SetFileName(str(path))
            reader.SetImageIO("NrrdImageIO" if nrrd else "MetaImageIO")
            image = reader.Execute()
        except RuntimeError:
            image = None
    if image is None:
        detail = messages[0] if messages else "ITK could not read it"
        raise InputError(path, f"unreadable image data ({detail})")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(path, "only single-channel (grayscale) sequences are supported")
    frames = sitk.GetArrayFromImage(image)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.dtype != np.uint8:
        raise InputError(path, f"pixel type {frames.dtype} is not 8-bit unsigned")
    n = frames.shape[0]
    per_frame: dict[str, dict[int, str]] = {}
    fields = {}
    for key in reader.GetMetaDataKeys():
        m = _FRAME_KEY.match(key)
        if m:
            per_frame.setdefault(m.group(2), {})[int(m.group(1))] = reader.GetMetaData(key).strip()
        elif key not in _STANDARD_KEYS and not key.startswith("NRRD_"):
            fields[key] = reader.GetMetaData(key).strip()
    seq = TrackedSequence(frames=frames, fields=fields)
    for name, values in per_frame.items():
        if name.endswith("Transform"):
            matrices = np.full((n, 4, 4), np.nan)
            for i, text in values.items():
                if i >= n:
                    raise InputError(path, f"frame {i} has a {name} but the file holds {n} frames")
                try:
                    matrices[i] = matrix_from_text(text)
                except ValueError as exc:
                    raise InputError(path, f"frame {i} {name}: {exc}")
            status_values = per_frame.get(name + "Status", {})
            status = np.array([status_values.get(i, "OK").upper() == "OK" for i in range(n)])
            status &= np.all(np.isfinite(matrices.reshape(n, -1)), axis=1)
            seq.transforms[name[: -len("Transform")]] = matrices
            seq.statuses[name[: -len("Transform")]] = status
    if "Timestamp" in per_frame:
        try:
            seq.timestamps = np.array(
                [float(per_frame["Timestamp"].get(i, "nan")) for i in range(n)]
            )
        except ValueError as exc:
            raise InputError(path, f"bad frame timestamp ({exc})")
    if "ImageStatus" in per_frame:
        seq.image_ok = np.array([per_frame["ImageStatus"].get(i, "OK").upper() == "OK" for i in range(n)])
    return seq


def write_sequence(path: str | Path, seq: TrackedSequence, compress: bool = True) -> None:
    """Write a PLUS-compatible ``.igs.mha`` or ``.seq.nrrd`` (by the file name); the file appears
    complete or not at all."""
    path = Path(path)
    n = len(seq)
    image = sitk.GetImageFromArray(np.ascontiguousarray(seq.frames, dtype=np.uint8), isVector=False)
    meta = {"UltrasoundImageOrientation": "MFA", **seq.fields}
    for i in range(n):
        prefix = f"Seq_Frame{i:04d}_"
        for name, matrices in seq.transforms.items():
            status = seq.statuses.get(name, np.ones(n, bool))[i]
            matrix = matrices[i] if np.all(np.isfinite(matrices[i])) else np.eye(4)
            meta[f"{prefix}{name}Transform"] = matrix_to_text(matrix)
            meta[f"{prefix}{name}TransformStatus"] = "OK" if status else "INVALID"
        if seq.timestamps is not None:
            meta[f"{prefix}Timestamp"] = repr(float(seq.timestamps[i]))
        ok = True if seq.image_ok is None else bool(seq.image_ok[i])
        meta[f"{prefix}ImageStatus"] = "OK" if ok else "INVALID"
    for key, value in meta.items():
        image.SetMetaData(key, value)

    def write(tmp: Path) -> None:
        writer = sitk.ImageFileWriter()
        writer.SetFileName(str(tmp))
        writer.SetUseCompression(compress)
        writer.Execute(image)

    replace_atomically(path, write)
