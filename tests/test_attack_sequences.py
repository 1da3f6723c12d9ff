"""Hostile PLUS sequence files (issue 13): each is refused with InputError, one line naming the file
(exit 2 through the command line), before memory is taken, and nothing is written."""

from __future__ import annotations

import os
import re
import resource
import subprocess
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest

from probecal.core.errors import InputError
from probecal.core.io.limits import ENV as MEMORY_ENV
from probecal.core.io.plusimport import import_plus
from probecal.core.io.sequence import TrackedSequence, read_sequence, write_sequence
from tests.support.cli import PROBECAL, run_cli
from tests.support.paths import FCAL_VALIDATION
from tests.support.refusals import assert_one_line_error, assert_refused

FORMATS = [("seq.igs.mha", True), ("seq.igs.mha", False), ("seq.seq.nrrd", True), ("seq.seq.nrrd", False)]
FORMAT_IDS = ["mha-zlib", "mha-raw", "nrrd-gzip", "nrrd-raw"]


def small_sequence(n: int = 3, height: int = 4, width: int = 5) -> TrackedSequence:
    """A tiny valid sequence: random frames, ProbeToReference poses 1 mm apart, 10 Hz timestamps."""
    frames = np.random.default_rng(0).integers(0, 256, (n, height, width), dtype=np.uint8)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n)
    return TrackedSequence(frames, {"ProbeToReference": poses}, {"ProbeToReference": np.ones(n, bool)},
                           timestamps=np.arange(n) * 0.1)


def written(folder: Path, name: str = "seq.igs.mha", compress: bool = True,
            seq: TrackedSequence | None = None) -> Path:
    path = folder / name
    write_sequence(path, seq if seq is not None else small_sequence(), compress=compress)
    return path


def header_end(data: bytes) -> int:
    """Bytes of header before the pixels of a sequence with attached pixel data."""
    if data.startswith(b"NRRD"):
        return data.index(b"\n\n") + 2
    return data.index(b"ElementDataFile = LOCAL\n") + len(b"ElementDataFile = LOCAL\n")


def with_field(data: bytes, key: str, value: str | None) -> bytes:
    """``data`` with the header field ``key`` set to ``value`` (None: removed), kept before the
    MetaImage ``ElementDataFile`` line or the NRRD blank line."""
    nrrd = data.startswith(b"NRRD")
    end = data.index(b"\n\n") + 1 if nrrd else data.index(b"ElementDataFile")
    pattern = re.compile(rf"{re.escape(key)}(\s*(?::=|:|=)\s*)")
    lines = data[:end].decode("latin-1").splitlines(keepends=True)
    seps = [m.group(1) for line in lines if (m := pattern.match(line))]
    kept = [line for line in lines if not pattern.match(line)]
    if value is not None:
        sep = seps[0] if seps else (": " if nrrd else " = ")
        kept.append(f"{key}{sep}{value}\n")
    return "".join(kept).encode("latin-1") + data[end:]


def variant(folder: Path, number: int, name: str, data: bytes) -> Path:
    """``data`` in a new file ``NUMBER-name`` (writing fresh files beats truncating one file over
    and over, which some file systems make slow)."""
    path = folder / f"{number}-{name}"
    path.write_bytes(data)
    return path


def refused(path: Path, *fragments: str, names: Path | None = None) -> str:
    """The one-line message read_sequence raises for ``path``: it names the file (``names``, by
    default ``path``) and holds each fragment."""
    message = assert_refused(lambda: read_sequence(path), names or path, *fragments)
    assert message.startswith(f"{names or path}: "), message
    return message


def refused_or_sound(path: Path) -> TrackedSequence | None:
    """Read ``path``: either a one-line InputError naming it, or a self-consistent sequence."""
    try:
        seq = read_sequence(path)
    except InputError as exc:
        assert str(exc).startswith(f"{path}: ") and "\n" not in str(exc), str(exc)
        return None
    n = len(seq)
    assert seq.frames.dtype == np.uint8 and seq.frames.ndim == 3 and n >= 1
    for name, matrices in seq.transforms.items():
        valid = seq.statuses[name]
        assert matrices.shape == (n, 4, 4) and valid.shape == (n,)
        assert np.all(np.isfinite(matrices[valid]))
    assert seq.timestamps is None or (seq.timestamps.shape == (n,) and np.all(np.isfinite(seq.timestamps)))
    return seq


def leaves_only(folder: Path, *names: str) -> bool:
    """True when ``folder`` holds exactly ``names``, hidden entries included."""
    return sorted(p.name for p in folder.iterdir()) == sorted(names)


@pytest.mark.parametrize("name,compress", FORMATS, ids=FORMAT_IDS)
def test_synthetic_baseline_reads_back(tmp_path, name, compress):
    seq = small_sequence()
    back = read_sequence(written(tmp_path, name, compress, seq))
    assert np.array_equal(back.frames, seq.frames)
    assert np.array_equal(back.transforms["ProbeToReference"], seq.transforms["ProbeToReference"])
    assert back.statuses["ProbeToReference"].all() and np.allclose(back.timestamps, seq.timestamps)


# 1. Pixel data in a detached file: only inside the sequence's own folder.

def detached_nrrd(folder: Path, data_file: str, field: str = "data file") -> Path:
    """A raw NRRD header whose pixels are in ``data_file``."""
    header = written(folder, "whole.seq.nrrd", compress=False).read_bytes()
    header = header[: header_end(header) - 1]
    (folder / "whole.seq.nrrd").unlink()
    path = folder / "seq.seq.nrrd"
    path.write_bytes(with_field(header + b"\n", field, data_file))
    return path


@pytest.mark.parametrize("data_file", ["../../../../etc/passwd", "/etc/passwd", "sub/../../etc/passwd"])
@pytest.mark.parametrize("field", ["data file", "datafile"])
def test_nrrd_data_file_outside_its_folder_is_refused(tmp_path, data_file, field):
    path = detached_nrrd(tmp_path, data_file, field)
    refused(path, "pixel data file", repr(data_file), "only names inside it are allowed")


def test_nrrd_data_file_through_a_link_out_of_its_folder_is_refused(tmp_path):
    (tmp_path / "frames.raw").symlink_to("/etc/passwd")
    refused(detached_nrrd(tmp_path, "frames.raw"), "pixel data file", "leads outside")


@pytest.mark.parametrize("data_file", ["LIST", "slice%03d.raw 1 3 1", "missing.raw", "."])
def test_nrrd_data_file_list_pattern_or_missing_is_refused(tmp_path, data_file):
    refused(detached_nrrd(tmp_path, data_file), "pixel data")


@pytest.mark.parametrize("data_file", ["../frames.raw", "/etc/passwd", "LIST"])
def test_mha_element_data_file_outside_its_folder_is_refused(tmp_path, data_file):
    data = written(tmp_path, compress=False).read_bytes()
    path = tmp_path / "seq.igs.mha"
    path.write_bytes(data[: header_end(data)].replace(b"= LOCAL\n", f"= {data_file}\n".encode()))
    refused(path, "pixel data")


def test_detached_data_inside_the_folder_reads_for_nrrd_and_mha(tmp_path):
    seq = small_sequence()
    (tmp_path / "frames.raw").write_bytes(seq.frames.tobytes())
    assert np.array_equal(read_sequence(detached_nrrd(tmp_path, "frames.raw")).frames, seq.frames)
    data = written(tmp_path, compress=False).read_bytes()
    mha = tmp_path / "seq.igs.mha"
    mha.write_bytes(data[: header_end(data)].replace(b"= LOCAL\n", b"= frames.raw\n"))
    assert np.array_equal(read_sequence(mha).frames, seq.frames)
    (tmp_path / "frames.raw").write_bytes(seq.frames.tobytes()[:-1])
    refused(mha, "truncated pixel data", names=tmp_path.resolve() / "frames.raw")


def test_cli_detached_passwd_exits_2_and_writes_nothing(tmp_path):
    path = detached_nrrd(tmp_path, "../../../../../../etc/passwd")
    result = run_cli("import-plus", path, tmp_path / "out")
    assert_one_line_error(result, "seq.seq.nrrd", "etc/passwd", "only names inside it are allowed")
    assert leaves_only(tmp_path, "seq.seq.nrrd")


# 2. Sizes: computed exactly and checked before memory is taken; the body must match them.

def mha_bomb(folder: Path, dims: str, body: bytes, compressed_size: int | None = None) -> Path:
    path = folder / "bomb.igs.mha"
    size = len(body) if compressed_size is None else compressed_size
    path.write_bytes(
        f"ObjectType = Image\nNDims = 3\nBinaryData = True\nCompressedData = True\n"
        f"CompressedDataSize = {size}\nDimSize = {dims}\nElementType = MET_UCHAR\n"
        "Seq_Frame0000_ProbeToReferenceTransform = 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n"
        "ElementDataFile = LOCAL\n".encode() + body)
    return path


def test_huge_dimsize_is_refused_before_memory_is_taken(tmp_path, monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "1000")
    bomb = mha_bomb(tmp_path, "10000 10000 30", zlib.compress(b"abc"))
    assert len(zlib.compress(b"abc")) == 11
    refused(bomb, "the frames and their transforms would need 2.8 GB", "more than the limit of 1000.0 MB")
    overflow = mha_bomb(tmp_path, "4294967296 4294967296 1", zlib.compress(b"abc"))
    refused(overflow, "would need 17179869184.0 GB")


def test_nrrd_with_huge_sizes_is_refused_before_memory_is_taken(tmp_path, monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "1000")
    for compress in (True, False):
        data = written(tmp_path, "seq.seq.nrrd", compress).read_bytes()
        path = tmp_path / "seq.seq.nrrd"
        path.write_bytes(with_field(data, "sizes", "10000 10000 30"))
        refused(path, "would need 2.8 GB")


def test_eleven_byte_body_for_a_large_dimsize_is_refused(tmp_path):
    bomb = mha_bomb(tmp_path, "1000 1000 30", zlib.compress(b"abc"))
    refused(bomb, "compressed pixel data holds 3 of the 30000000 bytes the header declares")


def test_zip_bomb_body_stops_one_byte_past_the_declared_size(tmp_path):
    packer = zlib.compressobj(9)
    body = b"".join(packer.compress(bytes(1 << 20)) for _ in range(64)) + packer.flush()
    bomb = mha_bomb(tmp_path, "100 100 1", body)
    tracemalloc.start()
    try:
        refused(bomb, "holds more than the 10000 bytes")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(body) < 100_000 and peak < 4 << 20  # the 64 MiB it inflates to is never held


@pytest.mark.parametrize("name,compress", FORMATS, ids=FORMAT_IDS)
def test_body_shorter_or_longer_than_declared_is_refused(tmp_path, name, compress):
    data = written(tmp_path, name, compress).read_bytes()
    path = tmp_path / name
    key = "sizes" if name.endswith(".nrrd") else "DimSize"
    path.write_bytes(with_field(data, key, "5 4 4"))
    refused(path, "truncated" if not compress else "holds 60 of the 80 bytes")
    if compress:
        path.write_bytes(with_field(data, key, "5 4 2"))
        refused(path, "holds more than the 40 bytes")


def test_compressed_data_size_past_the_end_of_the_file_is_refused(tmp_path):
    data = written(tmp_path).read_bytes()
    path = tmp_path / "seq.igs.mha"
    path.write_bytes(with_field(data, "CompressedDataSize", str(10**12)))
    refused(path, "truncated pixel data", "of 1000000000000 compressed bytes")


def test_cli_compressed_bomb_under_a_4_gb_address_space_exits_2_and_writes_nothing(tmp_path):
    bomb = mha_bomb(tmp_path, "10000 10000 30", zlib.compress(b"abc"))
    env = {k: v for k, v in os.environ.items() if k != MEMORY_ENV}
    result = subprocess.run(
        [str(PROBECAL), "import-plus", str(bomb), str(tmp_path / "out")], capture_output=True, text=True,
        env=env, timeout=300, check=False,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (4_000_000 * 1024, resource.RLIM_INFINITY)),
    )
    assert_one_line_error(result, "bomb.igs.mha", "would need 2.8 GB")
    assert leaves_only(tmp_path, "bomb.igs.mha")


def test_many_frames_of_one_pixel_cannot_take_memory_for_transforms(tmp_path, monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "100")
    refused(mha_bomb(tmp_path, "1 1 2000000", zlib.compress(bytes(2_000_000))),
            "the frames and their transforms would need 278.5 MB")


@pytest.mark.parametrize("frames", [2_000_000_000, 10**13])
def test_a_tracker_buffer_of_billions_of_frames_is_refused_before_memory_is_taken(tmp_path, monkeypatch, frames):
    """``DimSize = 0 0 N`` has no pixels and may have no transforms, yet every frame takes a
    timestamp and statuses: a 133-byte file took 2.2 GB, or ended in a traceback (issue 35)."""
    monkeypatch.setenv(MEMORY_ENV, "100")
    path = tmp_path / "tracker.igs.mha"
    path.write_text(f"ObjectType = Image\nNDims = 3\nDimSize = 0 0 {frames}\nElementType = MET_UCHAR\n"
                    "Seq_Frame0000_ImageStatus = OK\nElementDataFile = LOCAL\n")
    tracemalloc.start()
    try:
        assert_refused(lambda: read_sequence(path, images=False), path, "would need", "more than the limit of 100.0 MB")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20


def test_a_header_too_big_for_the_memory_limit_is_refused_while_it_is_read(tmp_path, monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "1")
    data = written(tmp_path, compress=False).read_bytes()
    lines = "".join(f"Seq_Frame0000_Note{i} = {'x' * 40}\n" for i in range(40_000)).encode()
    path = tmp_path / "seq.igs.mha"
    first, rest = data.split(b"\n", 1)
    path.write_bytes(first + b"\n" + lines + rest)
    refused(path, "the header would need")


# 3. A corrupt compressed stream is never imported as pixels.

@pytest.mark.parametrize("name", ["seq.igs.mha", "seq.seq.nrrd"])
def test_every_corrupted_byte_of_a_compressed_body_is_refused_or_harmless(tmp_path, name):
    seq = small_sequence(3, 40, 50)
    seq.frames[:] = np.arange(50, dtype=np.uint8)[None, None, :]
    data = written(tmp_path, name, True, seq).read_bytes()
    start, refusals = header_end(data), 0
    for offset in range(start, len(data)):
        corrupt = bytearray(data)
        corrupt[offset] ^= 0x55
        back = refused_or_sound(variant(tmp_path, offset, name, corrupt))
        refusals += back is None
        assert back is None or np.array_equal(back.frames, seq.frames), offset
    assert refusals >= (len(data) - start) * 0.8


def test_corrupt_stream_message(tmp_path):
    data = bytearray(written(tmp_path, seq=small_sequence(3, 40, 50)).read_bytes())
    data[header_end(data) + 20 : header_end(data) + 30] = b"\xff" * 10
    (tmp_path / "seq.igs.mha").write_bytes(data)
    refused(tmp_path / "seq.igs.mha", "corrupt compressed pixel data")


def test_cli_corrupt_real_recording_exits_2_and_writes_nothing(plus_data, tmp_path):
    data = bytearray(FCAL_VALIDATION.read_bytes())
    middle = (header_end(data) + len(data)) // 2
    data[middle : middle + 64] = bytes(64)
    path = tmp_path / "corrupt.igs.mha"
    path.write_bytes(data)
    result = run_cli("import-plus", path, tmp_path / "out")
    assert_one_line_error(result, "corrupt.igs.mha", "compressed pixel data")
    assert leaves_only(tmp_path, "corrupt.igs.mha")


# 4. Header fields: types, counts, shapes, non-finite numbers, garbage, truncation.

MHA_CASES = [
    ("ElementNumberOfChannels", "x", "ElementNumberOfChannels 'x' is not a whole number"),
    ("ElementNumberOfChannels", "3", "single-channel"),
    ("CompressedDataSize", "abc", "CompressedDataSize 'abc' is not a whole number"),
    ("CompressedDataSize", "-5", "is not a whole number"),
    ("DimSize", "0 4 1", "has a zero size"),
    ("DimSize", "5 0 3", "has a zero size"),
    ("DimSize", "-5 4 3", "must be 3 positive whole numbers"),
    ("DimSize", "5 4", "must be 3 positive whole numbers"),
    ("DimSize", "5 4 3 1", "must be 3 positive whole numbers"),
    ("DimSize", "5.0 4 3", "must be 3 positive whole numbers"),
    ("DimSize", None, "no DimSize"),
    ("NDims", "4", "only sequences of 2D frames"),
    ("NDims", "three", "NDims 'three' is not a whole number"),
    ("NDims", None, "no NDims"),
    ("ElementType", "MET_FLOAT", "not 8-bit unsigned"),
    ("CompressedData", "perhaps", "neither True nor False"),
    ("BinaryData", "False", "as text"),
    ("HeaderSize", "-1", "HeaderSize"),
    ("Seq_Frame0001_Timestamp", "inf", "frame 1 Timestamp 'inf' is not a finite number"),
    ("Seq_Frame0001_Timestamp", "-inf", "is not a finite number"),
    ("Seq_Frame0001_Timestamp", "nan", "is not a finite number"),
    ("Seq_Frame0001_Timestamp", "1e999", "is not a finite number"),
    ("Seq_Frame0001_Timestamp", "soon", "frame 1 Timestamp 'soon' is not a finite number"),
    ("Seq_Frame0001_Timestamp", None, "frame 1 has no Timestamp"),
    ("Seq_Frame0007_ImageStatus", "OK", "frame 7 has a ImageStatus but the file holds 3 frames"),
    ("Seq_Frame99999999999_Timestamp", "1", "does not name a frame"),
    ("Seq_FrameX_Timestamp", "1", "does not name a frame"),
    ("Modality", "x\nno equals sign", "header line"),
    ("UltrasoundImageOrientation", "M" * 70_000, "longer than 65536 bytes"),
]


@pytest.mark.parametrize("compress", [True, False], ids=["zlib", "raw"])
def test_mha_header_field_of_the_wrong_type_or_shape_is_refused(tmp_path, compress):
    original = written(tmp_path, compress=compress).read_bytes()
    for number, (key, value, fragment) in enumerate(MHA_CASES):
        if key == "CompressedDataSize" and not compress:
            continue
        refused(variant(tmp_path, number, "seq.igs.mha", with_field(original, key, value)), fragment)


NRRD_CASES = [
    ("type", "short", "pixel type 'short' is not 8-bit unsigned"),
    ("type", None, "pixel type 'none'"),
    ("dimension", "4", "only sequences of 2D frames"),
    ("dimension", "x", "dimension 'x' is not a whole number"),
    ("sizes", "0 4 1", "has a zero size"),
    ("sizes", "5 4", "must be 3 positive whole numbers"),
    ("sizes", None, "no sizes"),
    ("encoding", "bzip2", "encoding 'bzip2' is not supported"),
    ("encoding", "ascii", "is not supported"),
    ("byte skip", "-1", "byte skip"),
    ("line skip", "2", "line skip"),
    ("Seq_Frame0002_Timestamp", "NaN", "frame 2 Timestamp 'NaN' is not a finite number"),
]


@pytest.mark.parametrize("compress", [True, False], ids=["gzip", "raw"])
def test_nrrd_header_field_of_the_wrong_type_or_shape_is_refused(tmp_path, compress):
    original = written(tmp_path, "seq.seq.nrrd", compress).read_bytes()
    for number, (key, value, fragment) in enumerate(NRRD_CASES):
        refused(variant(tmp_path, number, "seq.seq.nrrd", with_field(original, key, value)), fragment)
    path = tmp_path / "seq.seq.nrrd"
    path.write_bytes(original.replace(b"type: unsigned char\n", b"type: unsigned char\ntype: uchar\n"))
    refused(path, "field 'type' appears twice")


def test_duplicate_and_malformed_mha_lines_are_refused(tmp_path):
    original = written(tmp_path).read_bytes()
    path = tmp_path / "seq.igs.mha"
    path.write_bytes(original.replace(b"NDims = 3\n", b"NDims = 3\nDimSize = 5000 4000 3\n"))
    refused(path, "field 'DimSize' appears twice")
    path.write_bytes(original.replace(b"NDims = 3", b"NDims 3"))
    refused(path, "header line 2 'NDims 3' is not 'key = value'")
    path.write_bytes(original.replace(b"Seq_Frame0001_Timestamp = 0.1",
                                      b"Seq_Frame0001_Timestamp = 0.1\nSeq_Frame0001_Timestamp = 9"))
    refused(path, "field 'Seq_Frame0001_Timestamp' appears twice")


@pytest.mark.parametrize("text", ["nan " * 16, "inf " + "0 " * 15, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0", "one two", ""])
def test_unusable_transform_marks_that_frame_invalid_and_is_skipped_on_import(tmp_path, text):
    data = written(tmp_path).read_bytes()
    path = tmp_path / "seq.igs.mha"
    path.write_bytes(with_field(data, "Seq_Frame0001_ProbeToReferenceTransform", text))
    seq = read_sequence(path)
    assert seq.statuses["ProbeToReference"].tolist() == [True, False, True]
    session = import_plus(path, None, tmp_path / "out")
    assert [r.pose_valid for r in session.records] == [True, False, True]
    assert np.allclose(session.records[2].tool_to_base[0, 3], 2.0)


@pytest.mark.parametrize("name", ["seq.igs.mha", "seq.seq.nrrd"])
def test_empty_and_garbage_files_are_refused(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"")
    refused(path, "empty file")
    rng = np.random.default_rng(1)
    for number in range(40):
        garbage = rng.integers(0, 256, int(rng.integers(1, 3000)), dtype=np.uint8).tobytes()
        magic = [b"", b"ObjectType = Image\n", b"NRRD0004\n"][number % 3]
        refused(variant(tmp_path, number, name, magic + garbage))


@pytest.mark.parametrize("name,compress", FORMATS, ids=FORMAT_IDS)
def test_truncated_at_every_offset_is_refused(tmp_path, name, compress):
    data = written(tmp_path, name, compress, small_sequence(2, 3, 4)).read_bytes()
    for cut in range(len(data)):
        refused(variant(tmp_path, cut, name, data[:cut]))
    assert len(read_sequence(tmp_path / name)) == 2


@pytest.mark.parametrize("name,compress", FORMATS, ids=FORMAT_IDS)
def test_random_byte_mutations_are_refused_or_read_consistently(tmp_path, name, compress):
    data = written(tmp_path, name, compress).read_bytes()
    rng = np.random.default_rng(2)
    for number in range(150):
        mutated = bytearray(data)
        for offset in rng.integers(0, len(data), int(rng.integers(1, 4))):
            mutated[offset] = int(rng.integers(0, 256))
        refused_or_sound(variant(tmp_path, number, name, mutated))


HOSTILE_VALUES = ["", "x", "-1", "0", "1e3", "nan", "inf", "3.5", "9" * 40, "1 2 3 4 5 6", "\x00\xff",
                  "LOCAL LOCAL", "../x", "/dev/zero"]


@pytest.mark.parametrize("name,compress", FORMATS, ids=FORMAT_IDS)
def test_hostile_values_in_every_field_are_refused_or_read_consistently(tmp_path, name, compress):
    nrrd = name.endswith(".nrrd")
    fields = (["type", "dimension", "sizes", "encoding", "data file", "byte skip", "line skip", "endian"] if nrrd
              else ["NDims", "DimSize", "ElementType", "ElementNumberOfChannels", "CompressedData",
                    "CompressedDataSize", "BinaryData", "HeaderSize"])
    fields += ["Seq_Frame0001_Timestamp", "Seq_Frame0001_ProbeToReferenceTransform",
               "Seq_Frame0001_ProbeToReferenceTransformStatus", "Seq_Frame0001_ImageStatus"]
    data = written(tmp_path, name, compress).read_bytes()
    cases = [(key, value) for key in fields for value in HOSTILE_VALUES]
    for number, (key, value) in enumerate(cases):
        refused_or_sound(variant(tmp_path, number, name, with_field(data, key, value)))
    assert leaves_only(tmp_path, name, *(f"{number}-{name}" for number in range(len(cases))))


def test_real_recording_truncated_anywhere_is_refused(plus_data, tmp_path):
    data = FCAL_VALIDATION.read_bytes()
    end = header_end(data)
    for cut in (1, 9, 500, 5000, end - 30, end - 1, end, end + 1, end + 2, (end + len(data)) // 2, len(data) - 1):
        refused(variant(tmp_path, cut, "cut.igs.mha", data[:cut]))


def test_real_recording_with_hostile_header_fields_is_refused(plus_data, tmp_path):
    data = FCAL_VALIDATION.read_bytes()
    for number, (key, value, fragment) in enumerate([
            ("DimSize", "820 616 95", "holds 47481280 of the 47986400 bytes"),
            ("DimSize", "820 616", "must be 3 positive"),
            ("CompressedDataSize", "abc", "not a whole number"),
            ("Seq_Frame0050_Timestamp", "inf", "frame 50 Timestamp 'inf'"),
            ("ElementDataFile", "../../../../etc/passwd", "only names inside it are allowed")]):
        edited = (with_field(data, key, value) if key != "ElementDataFile"
                  else data[: header_end(data)].replace(b"= LOCAL", f"= {value}".encode()))
        refused(variant(tmp_path, number, "edited.igs.mha", edited), fragment)


# 5. The import's staging folder: a leftover is refused, never deleted.

def test_leftover_staging_folder_is_refused_not_deleted(tmp_path):
    seq_file = written(tmp_path)
    leftover = tmp_path / ".out.importing"
    leftover.mkdir()
    (leftover / "keep.txt").write_text("someone's")
    with pytest.raises(InputError) as caught:
        import_plus(seq_file, None, tmp_path / "out")
    assert str(caught.value) == f"{leftover}: left over from an interrupted import; remove it and try again"
    assert (leftover / "keep.txt").read_text() == "someone's" and not (tmp_path / "out").exists()
    leftover.rename(tmp_path / "elsewhere")
    leftover.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(InputError):
        import_plus(seq_file, None, tmp_path / "out")
    assert (tmp_path / "elsewhere" / "keep.txt").is_file()


def test_cli_leftover_staging_folder_exits_2_and_is_kept(tmp_path):
    seq_file = written(tmp_path)
    (tmp_path / ".out.importing").mkdir()
    result = run_cli("import-plus", seq_file, tmp_path / "out")
    assert_one_line_error(result, ".out.importing", "remove it and try again")
    assert leaves_only(tmp_path, "seq.igs.mha", ".out.importing")


def test_import_failure_leaves_nothing_and_output_file_is_not_a_folder(tmp_path):
    data = written(tmp_path).read_bytes()
    bad = tmp_path / "bad.igs.mha"
    bad.write_bytes(with_field(data, "Seq_Frame0002_Timestamp", "nan"))
    with pytest.raises(InputError, match="frame 2 Timestamp 'nan'"):
        import_plus(bad, None, tmp_path / "out")
    assert leaves_only(tmp_path, "seq.igs.mha", "bad.igs.mha")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is a file; give a folder name"):
        import_plus(tmp_path / "seq.igs.mha", None, tmp_path / "file")
    session = import_plus(tmp_path / "seq.igs.mha", None, tmp_path / "good")
    assert len(session) == 3 and leaves_only(tmp_path, "seq.igs.mha", "bad.igs.mha", "file", "good")


@pytest.mark.parametrize(("key", "value", "fragment"), [
    ("Seq_Frame0000_Timestamp", "1e300", "at most 1e+12 s in size"),
    ("Seq_Frame0000_Timestamp", "99999999999999999999", "at most 1e+12 s in size"),
    ("Seq_Frame0000_ProbeToReferenceTransform", "2 0 0 1 0 2 0 1 0 0 2 1 0 0 0 1",
     "does not make a session that reads back: frame 0: tool_to_base is not a rigid transform"),
], ids=["timestamp-1e300", "timestamp-20-digits", "scaled-pose"])
def test_an_import_that_a_session_cannot_hold_is_refused_and_leaves_nothing(tmp_path, key, value, fragment):
    """A sequence that reads but whose session would not load back (found by the fuzzing harness:
    the session was put in place, then refused)."""
    bad = tmp_path / "bad.igs.mha"
    bad.write_bytes(with_field(written(tmp_path).read_bytes(), key, value))
    assert_refused(lambda: import_plus(bad, None, tmp_path / "out"), bad, fragment)
    assert leaves_only(tmp_path, "seq.igs.mha", "bad.igs.mha")
