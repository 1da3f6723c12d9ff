"""PLUS tracked sequence files (``.igs.mha``, ``.seq.nrrd``): frames plus per-frame transforms.

Per frame PLUS stores ``Seq_FrameNNNN_<From>To<To>Transform`` (16 numbers, row-major 4x4, mm),
``..TransformStatus`` (OK | INVALID), ``Seq_FrameNNNN_Timestamp`` (s) and ``..ImageStatus``.
Transform names are kept as PLUS spells them without the ``Transform`` suffix, e.g.
``"ProbeToTracker"``.

Files are written with SimpleITK. They are read here, not by ITK, because a file may be hostile:
the header is parsed strictly, the memory the pixels need is computed exactly and checked against
the limit (core.io.limits) before it is taken, pixel data in a detached file must be inside the
sequence's own folder, and compressed pixels are inflated a block at a time into a buffer of
exactly the declared size, so a body that is corrupt, short or too long is refused.
"""

from __future__ import annotations

import math
import os
import re
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
import SimpleITK as sitk

from probecal.core.errors import InputError
from probecal.core.geometry.transformrepo import TransformRepository
from probecal.core.geometry.transforms import matrix_from_text, text_from_matrix
from probecal.core.io.files import existing_file, inside, library_stderr, open_regular, replace_atomically
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.io.limits import checked_bytes

_FRAME_KEY = re.compile(r"^Seq_Frame([0-9]{1,9})_(.+)$")


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
        """(source_to_target (N,4,4), valid (N,)) stored directly or composed from the stored
        transforms (core.geometry.transformrepo), or None when none joins the two frames.

        PLUS trackers record ``XToTracker`` per tool; ``ProbeToReference`` is then
        ``inv(ReferenceToTracker) @ ProbeToTracker`` (valid where both are).
        """
        found = TransformRepository.build(len(self), self.transforms, self.statuses).find(source, target)
        return None if found is None else (found.matrices, found.valid)


_CHUNK = 1 << 20  # bytes of compressed input read at once; bytes of header between memory checks
_INFLATE_BLOCK = 1 << 24  # most bytes of pixels inflated at once
_MAX_LINE = 1 << 16  # longest header line, bytes
_HEADER_BYTES_PER_BYTE = 32  # memory parsed fields take per header byte: 2 for PLUS files, under 32 at worst
_NUMBER = re.compile(r"[0-9]{1,30}")
_NRRD_MAGIC = re.compile(r"NRRD000[0-9]")
_NRRD_UINT8 = {"uchar", "unsigned char", "uint8", "uint8_t"}
_METAIO_FIELDS = {
    "ObjectType", "ObjectSubType", "NDims", "Comment", "AcquisitionDate", "Name", "ID", "ParentID",
    "Color", "BinaryData", "BinaryDataByteOrderMSB", "ElementByteOrderMSB", "CompressedData",
    "CompressedDataSize", "TransformType", "TransformMatrix", "Rotation", "Orientation", "Offset",
    "Position", "Origin", "CenterOfRotation", "AnatomicalOrientation", "ElementSpacing", "ElementSize",
    "DimSize", "HeaderSize", "Modality", "SequenceID", "ElementMin", "ElementMax",
    "ElementNumberOfChannels", "ElementType", "ElementDataFile", "Kinds",
}


@dataclass
class _Header:
    """What a sequence header promises: sizes (pixels x fastest, then frames), the file holding the
    8-bit pixels and their offset in it (bytes), whether they are zlib/gzip compressed (and the
    compressed size in bytes, when given), the file-wide fields and the per-frame fields
    (name -> frame index -> text)."""

    data_path: Path
    dims: list[int] = field(default_factory=list)
    offset: int = 0
    compressed: bool = False
    compressed_size: int | None = None
    fields: dict[str, str] = field(default_factory=dict)
    per_frame: dict[str, dict[int, str]] = field(default_factory=dict)

    @property
    def tracking_only(self) -> bool:
        """A tracker buffer: frames of transforms and timestamps with no image (``DimSize 0 0 N``)."""
        return len(self.dims) == 3 and self.dims[:2] == [0, 0]


def _shown(text: str) -> str:
    """``text`` quoted for a one-line message, cut to 40 characters."""
    return repr(text if len(text) <= 40 else text[:40] + "...")


def _header_lines(path: Path, f: BinaryIO) -> Iterator[tuple[int, str]]:
    """(line number, text without its line end) for each complete line of a text header; stops at
    the end of the file or at a last line without a line end. Each MiB of header is checked against
    the memory limit (its fields take at most ``_HEADER_BYTES_PER_BYTE`` bytes per byte)."""
    checked = number = 0
    while True:
        line = f.readline(_MAX_LINE + 1)
        if not line.endswith(b"\n"):
            if len(line) > _MAX_LINE:
                raise InputError(path, f"header line {number + 1} is longer than {_MAX_LINE} bytes")
            return
        number += 1
        if f.tell() - checked >= _CHUNK:
            checked = f.tell()
            checked_bytes(path, "the header", [checked], _HEADER_BYTES_PER_BYTE)
        yield number, line.decode("latin-1").rstrip("\r\n")


def _add_field(path: Path, key: str, value: str, header: _Header) -> None:
    """File a header field as per-frame (``Seq_FrameNNNN_Name``) or file-wide; each only once."""
    if key.startswith("Seq_Frame"):
        m = _FRAME_KEY.match(key)
        if m is None:
            raise InputError(path, f"field {_shown(key)} does not name a frame as Seq_FrameNNNN_Name does")
        table, index = header.per_frame.setdefault(m.group(2), {}), int(m.group(1))
        if index in table:
            raise InputError(path, f"field {_shown(key)} appears twice")
        table[index] = value
    elif key in header.fields:
        raise InputError(path, f"field {_shown(key)} appears twice")
    else:
        header.fields[key] = value


def _whole(path: Path, name: str, text: str | None) -> int:
    """The whole number a header field holds; InputError when it is missing or is not one."""
    if text is None:
        raise InputError(path, f"no {name} in the header")
    if not _NUMBER.fullmatch(text):
        raise InputError(path, f"{name} {_shown(text)} is not a whole number")
    return int(text)


def _dimension(path: Path, name: str, text: str | None) -> int:
    """The number of axes: 2 (one frame) or 3 (frames)."""
    n = _whole(path, name, text)
    if n not in (2, 3):
        raise InputError(path, f"{name} {n}: only sequences of 2D frames ({name} 2 or 3) are supported")
    return n


def _sizes(path: Path, name: str, text: str | None, count: int) -> list[int]:
    """``count`` sizes (pixels, pixels[, frames]) from a header field: all positive, or, in a
    tracker buffer (frames with transforms and no image), ``0 0 frames``."""
    if text is None:
        raise InputError(path, f"no {name} in the header")
    parts = text.split()
    if len(parts) != count or not all(_NUMBER.fullmatch(p) for p in parts):
        raise InputError(path, f"{name} {_shown(text)} must be {count} positive whole numbers")
    sizes = [int(p) for p in parts]
    if 0 in sizes and not (count == 3 and sizes[:2] == [0, 0] and sizes[2] > 0):
        raise InputError(path, f"{name} {_shown(text)} has a zero size: the file holds no image data")
    return sizes


def _data_file(path: Path, name: str) -> Path:
    """The detached pixel data file that ``path``'s header names: one regular file inside the
    sequence's own folder, for MetaImage and NRRD alike."""
    if name == "LIST" or len(name.split()) > 1:
        raise InputError(path, f"pixel data in a list or series of files ({_shown(name)}) is not supported")
    try:
        data = inside(path.parent, name, path)
    except InputError as exc:
        raise InputError(path, f"pixel data file: {exc.problem}") from None
    if not data.is_file():
        raise InputError(path, f"pixel data file {_shown(name)} is missing or not a regular file")
    return data


def _mha_header(path: Path, f: BinaryIO) -> _Header:
    """Parse a MetaImage header: ``key = value`` lines up to ``ElementDataFile``."""
    header = _Header(path)
    for number, line in _header_lines(path, f):
        key, sep, value = (part.strip() for part in line.partition("="))
        if not sep or not key:
            raise InputError(path, f"header line {number} {_shown(line)} is not 'key = value'")
        _add_field(path, key, value, header)
        if key == "ElementDataFile":
            break
    else:
        raise InputError(path, "truncated header: no ElementDataFile line")
    raw = header.fields
    header.dims = _sizes(path, "DimSize", raw.get("DimSize"), _dimension(path, "NDims", raw.get("NDims")))
    if raw.get("ElementType", "MET_UCHAR") != "MET_UCHAR" and not header.tracking_only:
        raise InputError(path, f"pixel type {_shown(raw['ElementType'])} is not 8-bit unsigned (MET_UCHAR)")
    if _whole(path, "ElementNumberOfChannels", raw.get("ElementNumberOfChannels", "1")) != 1:
        raise InputError(path, "only single-channel (grayscale) sequences are supported")
    if raw.get("BinaryData", "True").lower() != "true":
        raise InputError(path, "pixel data as text (BinaryData = False) is not supported")
    if raw.get("HeaderSize", "0") != "0":
        raise InputError(path, "HeaderSize (bytes to skip before the pixels) is not supported")
    compressed = raw.get("CompressedData", "False")
    if compressed.lower() not in ("true", "false"):
        raise InputError(path, f"CompressedData {_shown(compressed)} is neither True nor False")
    header.compressed = compressed.lower() == "true"
    if header.compressed and "CompressedDataSize" in raw:
        header.compressed_size = _whole(path, "CompressedDataSize", raw["CompressedDataSize"]) or None
    if raw["ElementDataFile"].lower() == "local":
        header.offset = f.tell()
    else:
        header.data_path = _data_file(path, raw["ElementDataFile"])
    header.fields = {k: v for k, v in raw.items() if k not in _METAIO_FIELDS}
    return header


def _nrrd_header(path: Path, f: BinaryIO) -> _Header:
    """Parse a NRRD header: ``field: value`` and ``key:=value`` lines up to a blank line, or to the
    end of the file when the pixels are in a detached ``data file``."""
    header = _Header(path)
    nrrd: dict[str, str] = {}
    lines = _header_lines(path, f)
    if not _NRRD_MAGIC.fullmatch(next(lines, (0, ""))[1]):
        raise InputError(path, "not a NRRD file")
    ended = False
    for number, line in lines:
        if not line:
            ended = True
            break
        if line.startswith("#"):
            continue
        key, sep, value = line.partition(":=")
        if sep:
            _add_field(path, key.strip(), value.strip(), header)
            continue
        name, sep, value = line.partition(":")
        name = name.strip().lower().replace(" ", "")
        if not sep or not name:
            raise InputError(path, f"header line {number} {_shown(line)} is not 'field: value' or 'key:=value'")
        if name in nrrd:
            raise InputError(path, f"field {_shown(name)} appears twice")
        nrrd[name] = value.strip()
    if "datafile" in nrrd:
        header.data_path = _data_file(path, nrrd["datafile"])
    elif ended:
        header.offset = f.tell()
    else:
        raise InputError(path, "truncated header: no blank line before the pixel data")
    header.dims = _sizes(path, "sizes", nrrd.get("sizes"), _dimension(path, "dimension", nrrd.get("dimension")))
    if nrrd.get("type") not in _NRRD_UINT8:
        raise InputError(path, f"pixel type {_shown(nrrd.get('type', 'none'))} is not 8-bit unsigned (uchar)")
    encoding = nrrd.get("encoding", "none")
    if encoding not in ("raw", "gzip", "gz"):
        raise InputError(path, f"encoding {_shown(encoding)} is not supported (raw or gzip only)")
    header.compressed = encoding != "raw"
    for skip in ("byte skip", "line skip"):
        if nrrd.get(skip.replace(" ", ""), "0") != "0":
            raise InputError(path, f"{skip} (data to skip before the pixels) is not supported")
    return header


def _inflate(source: Path, f: BinaryIO, available: int, need: int) -> np.ndarray:
    """Decompress the zlib or gzip stream in the next ``available`` bytes of ``f`` into exactly
    ``need`` bytes, a MiB of input at a time; never holds more than ``need`` bytes of output."""
    pixels = np.empty(need, np.uint8)
    out = pixels.data  # a memoryview of the array's bytes
    inflater = zlib.decompressobj(zlib.MAX_WBITS | 32)
    filled, pending = 0, b""
    while not inflater.eof:
        if not pending and available:
            pending = f.read(min(_CHUNK, available))
            available = available - len(pending) if pending else 0
        try:
            block = inflater.decompress(pending, min(_INFLATE_BLOCK, need - filled + 1))
        except zlib.error as exc:
            raise InputError(source, f"corrupt compressed pixel data ({exc})") from None
        pending = inflater.unconsumed_tail
        if filled + len(block) > need:
            raise InputError(source, f"compressed pixel data holds more than the {need} bytes the header declares")
        out[filled : filled + len(block)] = block
        filled += len(block)
        if not block and not pending and not available and not inflater.eof:
            raise InputError(source, f"truncated compressed pixel data: it ends after {filled} of {need} bytes")
    if filled < need:
        raise InputError(source, f"compressed pixel data holds {filled} of the {need} bytes the header declares")
    return pixels


def _frame_shape(header: _Header) -> list[int]:
    """(frames, height, width) of the pixels a header declares."""
    return header.dims[::-1] if len(header.dims) == 3 else [1, *header.dims[::-1]]


FRAME_BYTES = 16
"""What every frame takes besides its pixels and transforms (bytes): its timestamp and statuses.
A tracker buffer has no pixels, and its frame count alone must not take the memory."""


def _check_memory(path: Path, header: _Header) -> None:
    """Refuse, before any of it is taken, a header whose frames (N x H x W bytes), transforms
    (N 4x4 float64 and a status per transform name) and timestamps would together pass the
    memory limit."""
    n, height, width = _frame_shape(header)
    transforms = sum(name.endswith("Transform") for name in header.per_frame)
    per_frame = height * width + transforms * (16 * 8 + 1) + FRAME_BYTES
    checked_bytes(path, "the frames and their transforms", [n, per_frame])


def _read_pixels(header: _Header) -> np.ndarray:
    """Frames (N, H, W) uint8 from the file that holds the pixels; the data must hold exactly what
    the header declares."""
    shape = _frame_shape(header)
    if header.tracking_only:
        return np.zeros(shape, np.uint8)
    source, need = header.data_path, math.prod(shape)
    with open_regular(source) as f:
        available = max(os.fstat(f.fileno()).st_size - header.offset, 0)
        f.seek(header.offset)
        if not header.compressed:
            if available < need:
                raise InputError(source, f"truncated pixel data: {available} of {need} bytes")
            pixels = np.empty(need, np.uint8)
            if f.readinto(pixels.data) != need:
                raise InputError(source, "truncated pixel data: the file shrank while it was read")
            return pixels.reshape(shape)
        size = header.compressed_size
        if size is not None and size > available:
            raise InputError(source, f"truncated pixel data: {available} of {size} compressed bytes")
        return _inflate(source, f, available if size is None else size, need).reshape(shape)


def _matrix(text: str) -> np.ndarray | None:
    """A 4x4 from PLUS's 16 numbers, or None when the text is not 16 finite numbers: like PLUS,
    treat such a transform as missing, so the frame has no valid pose."""
    try:
        matrix = matrix_from_text(text)
    except ValueError:
        return None
    return matrix if np.all(np.isfinite(matrix)) else None


def _timestamps(path: Path, values: dict[int, str], n: int) -> np.ndarray:
    """Every frame's timestamp (s); InputError for a frame without one or with one that is not a
    finite number a session can hold (within ±``MAX_MAGNITUDE``)."""
    if len(values) < n:
        missing = next(i for i in range(n) if i not in values)
        raise InputError(path, f"frame {missing} has no Timestamp")
    out = np.empty(n)
    for i, text in values.items():
        try:
            out[i] = float(text)
        except ValueError:
            out[i] = np.nan
        if not abs(out[i]) <= MAX_MAGNITUDE:
            raise InputError(path, f"frame {i} Timestamp {_shown(text)} is not a finite number "
                                   f"(at most {MAX_MAGNITUDE:g} s in size)")
    return out


def _statuses_ok(values: dict[int, str], n: int) -> np.ndarray:
    """(n,) True where a frame's status is OK or not given."""
    ok = np.ones(n, bool)
    for i, text in values.items():
        ok[i] = text.upper() == "OK"
    return ok


def _tracked_sequence(path: Path, frames: np.ndarray, header: _Header) -> TrackedSequence:
    """Frames plus the per-frame transforms, statuses and timestamps the header holds."""
    n = len(frames)
    for name, values in header.per_frame.items():
        if max(values) >= n:
            raise InputError(path, f"frame {max(values)} has a {name} but the file holds {n} frames")
    seq = TrackedSequence(frames=frames, fields=header.fields)
    for name, values in header.per_frame.items():
        if not name.endswith("Transform"):
            continue
        matrices = np.full((n, 4, 4), np.nan)
        usable = np.zeros(n, bool)
        for i, text in values.items():
            matrix = _matrix(text)
            if matrix is not None:
                matrices[i], usable[i] = matrix, True
        seq.transforms[name.removesuffix("Transform")] = matrices
        seq.statuses[name.removesuffix("Transform")] = usable & _statuses_ok(
            header.per_frame.get(name + "Status", {}), n)
    if "Timestamp" in header.per_frame:
        seq.timestamps = _timestamps(path, header.per_frame["Timestamp"], n)
    if "ImageStatus" in header.per_frame:
        seq.image_ok = _statuses_ok(header.per_frame["ImageStatus"], n)
    return seq


def read_sequence(path: str | Path, images: bool = True) -> TrackedSequence:
    """Read a PLUS ``.igs.mha`` (raw or compressed) or ``.seq.nrrd`` (raw or gzip). Raises
    InputError naming the file on any bad input; the memory the pixels and transforms need is
    checked against the limit (core.io.limits) before it is taken. A tracker buffer (``DimSize =
    0 0 N``: transforms and timestamps, no image) is read as (N, 0, 0) frames when ``images`` is
    False, and refused otherwise."""
    path = existing_file(path)
    nrrd = path.name.lower().endswith(".nrrd")
    with open_regular(path) as f:
        head = f.read(64)
        if not head:
            raise InputError(path, "empty file")
        if not nrrd and not head.startswith(b"ObjectType") and b"NDims" not in head:
            raise InputError(path, "not a MetaImage (.mha) file")
        f.seek(0)
        header = _nrrd_header(path, f) if nrrd else _mha_header(path, f)
    if images and header.tracking_only:
        raise InputError(path, "a tracker buffer (DimSize 0 0 N): it holds poses but no images")
    _check_memory(path, header)
    return _tracked_sequence(path, _read_pixels(header), header)


def oriented_mf(frames: np.ndarray, orientation: str) -> np.ndarray:
    """Frames (N, H, W) of a file stored in PLUS's ``UltrasoundImageOrientation`` as PLUS holds
    them in memory, ``MF``: the marked side at column 0 and the transducer at row 0. ``U..``
    files are mirrored left to right, ``.N`` files upside down (PLUS's own segmentation of an
    ``MN`` recording, and its clip rectangle, are in the flipped rows). A view, not a copy."""
    code = (orientation or "MF").upper()
    columns = slice(None, None, -1) if code.startswith("U") else slice(None)
    rows = slice(None, None, -1) if code[1:2] == "N" else slice(None)
    return frames[:, rows, columns]


SEQUENCE_SUFFIXES = (".mha", ".nrrd")


def sequence_file_name(path: str | Path) -> Path:
    """``path`` if its name ends in a format :func:`write_sequence` writes in one file (MetaImage
    ``.mha``, NRRD ``.nrrd``); InputError naming it otherwise."""
    path = Path(path)
    if path.suffix.lower() not in SEQUENCE_SUFFIXES:
        raise InputError(path, "a PLUS sequence is written as .igs.mha or .seq.nrrd: give a name ending in "
                               f"{' or '.join(SEQUENCE_SUFFIXES)}")
    return path


def write_sequence(path: str | Path, seq: TrackedSequence, compress: bool = True) -> None:
    """Write a PLUS-compatible ``.igs.mha`` or ``.seq.nrrd`` (by the file name,
    :func:`sequence_file_name`); the file appears complete or not at all."""
    path = sequence_file_name(path)
    n = len(seq)
    image = sitk.GetImageFromArray(np.ascontiguousarray(seq.frames, dtype=np.uint8), isVector=False)
    meta = {"UltrasoundImageOrientation": "MFA", **seq.fields}
    for i in range(n):
        prefix = f"Seq_Frame{i:04d}_"
        for name, matrices in seq.transforms.items():
            status = seq.statuses.get(name, np.ones(n, bool))[i]
            matrix = matrices[i] if np.all(np.isfinite(matrices[i])) else np.eye(4)
            meta[f"{prefix}{name}Transform"] = text_from_matrix(matrix)
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
        with library_stderr(tmp):
            writer.Execute(image)

    replace_atomically(path, write)
