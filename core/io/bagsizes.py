"""What a bag's compressed storage inflates to, counted before rosbags inflates any of it.

rosbags inflates a ROS 1 chunk (LZ4 or BZ2), an MCAP chunk (LZ4 or zstd) or a zstd-compressed ROS 2
message whole, in memory, and a zstd-compressed ROS 2 storage file whole, to a temporary file; a
few MB can hold hundreds of MB of zeros. So every compressed block is inflated here first in
bounded steps, counted and dropped, and a block that declares (or makes) more than the memory
limit is refused with an InputError naming the bag.
"""

from __future__ import annotations

import bz2
import sqlite3
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO, Protocol

import lz4.frame  # type: ignore[import-untyped]
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError

from probecal.core.errors import InputError
from probecal.core.io.files import open_regular, read_bytes
from probecal.core.io.limits import PARSED_EXPANSION, checked_bytes

try:
    from compression import zstd  # type: ignore[import-not-found]  # Python 3.14
except ImportError:
    from backports import zstd  # as rosbags does

STEP = 1 << 20
"""Bytes read, and inflated, at a time."""
ROS1_MAGIC = b"#ROSBAG V2.0\n"
ROS1_CHUNK = 0x05
MCAP_MAGIC = b"\x89MCAP0\r\n"
MCAP_CHUNK, MCAP_FOOTER = 0x06, 0x02


class Decompressor(Protocol):
    @property
    def eof(self) -> bool: ...

    @property
    def needs_input(self) -> bool: ...

    def decompress(self, data: bytes, max_length: int = -1) -> bytes: ...


DECOMPRESSORS: dict[str, Callable[[], Decompressor]] = {
    "bz2": bz2.BZ2Decompressor,
    "lz4": lz4.frame.LZ4FrameDecompressor,
    "zstd": zstd.ZstdDecompressor,
}


def check_bag_sizes(path: Path) -> None:
    """InputError naming the bag at ``path`` (a ROS 1 file or a ROS 2 folder) when any compressed
    block of it declares or inflates to more than the memory limit; a bag it cannot make sense
    of is left to rosbags, which says why."""
    if path.is_dir():
        _check_ros2(path)
        return
    with open_regular(path) as f:
        if f.read(len(ROS1_MAGIC)) == ROS1_MAGIC:
            _check_ros1(path, f)


def _inflated(path: Path, what: str, compression: str, pieces: Iterator[bytes]) -> None:
    """Inflate the compressed ``pieces`` in bounded steps, counting what they make against the
    memory limit (InputError naming ``path`` and ``what`` past it)."""
    if compression not in DECOMPRESSORS:
        return  # none, or one rosbags refuses itself
    decompressor, total = DECOMPRESSORS[compression](), 0
    for piece in pieces:
        data = piece
        while True:
            try:
                total += len(decompressor.decompress(data, STEP))
            except (OSError, RuntimeError, ValueError, EOFError, zstd.ZstdError) as exc:
                raise InputError(path, f"{what} does not inflate ({exc})") from None
            checked_bytes(path, f"inflating {what}", [total])
            if decompressor.eof:
                return
            if decompressor.needs_input:
                break
            data = b""


def _pieces(f: BinaryIO, size: int) -> Iterator[bytes]:
    """The next ``size`` bytes of ``f`` in pieces of at most STEP."""
    while size > 0:
        piece = f.read(min(size, STEP))
        if not piece:
            return
        size -= len(piece)
        yield piece


def _ros1_fields(header: bytes) -> dict[str, bytes]:
    fields, at = {}, 0
    while at + 4 <= len(header):
        (length,) = struct.unpack_from("<I", header, at)
        name, _, value = header[at + 4 : at + 4 + length].partition(b"=")
        fields[name.decode("latin-1")] = value
        at += 4 + length
    return fields


def _check_ros1(path: Path, f: BinaryIO) -> None:
    """Every chunk record of a ROS 1 bag: its declared size (``size``), then what it inflates to."""
    while len(prefix := f.read(4)) == 4:
        (header_length,) = struct.unpack("<I", prefix)
        fields = _ros1_fields(f.read(min(header_length, STEP)))
        f.seek(max(header_length - STEP, 0), 1)
        size_bytes = f.read(4)
        if len(size_bytes) < 4:
            return
        (data_length,) = struct.unpack("<I", size_bytes)
        if fields.get("op") == bytes([ROS1_CHUNK]):
            declared = fields.get("size", b"")
            if len(declared) == 4:
                checked_bytes(path, "a chunk of the bag", [struct.unpack("<I", declared)[0]])
            compression = fields.get("compression", b"none").decode("latin-1")
            _inflated(path, "a chunk of the bag", compression, _pieces(f, data_length))
        else:
            f.seek(data_length, 1)


def _check_mcap(path: Path, f: BinaryIO) -> None:
    """Every chunk record of an MCAP file: its declared uncompressed size, then what it inflates to."""
    if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
        return
    while len(head := f.read(9)) == 9:
        opcode, length = struct.unpack("<BQ", head)
        if opcode == MCAP_FOOTER:
            return
        if opcode != MCAP_CHUNK:
            f.seek(length, 1)
            continue
        fixed = f.read(8 + 8 + 8 + 4 + 4)
        if len(fixed) < 32:
            return
        _, _, uncompressed, _, name_length = struct.unpack("<QQQII", fixed)
        checked_bytes(path, "a chunk of the bag", [uncompressed])
        compression = f.read(min(name_length, 16)).decode("latin-1")
        f.seek(max(name_length - 16, 0), 1)
        records_length = f.read(8)
        if len(records_length) < 8:
            return
        (records,) = struct.unpack("<Q", records_length)
        end = f.tell() + records
        _inflated(path, "a chunk of the bag", compression, _pieces(f, records))
        f.seek(end)


def _ros2_metadata(path: Path) -> dict:
    """The bag's metadata.yaml, as far as it can be read (an empty one otherwise: rosbags says why)."""
    metadata = path / "metadata.yaml"
    try:
        data = YAML(typ="safe").load(read_bytes(metadata, PARSED_EXPANSION))
    except (InputError, YAMLError, UnicodeDecodeError, ValueError):
        return {}
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    return info if isinstance(info, dict) else {}


def _check_ros2(path: Path) -> None:
    """A ROS 2 bag's storage files: a zstd-compressed file, inflated whole by rosbags, or each
    zstd-compressed message; and every MCAP chunk."""
    info = _ros2_metadata(path)
    mode = str(info.get("compression_mode") or "").lower()
    files = [path / Path(str(name)).name for name in info.get("relative_file_paths") or []]
    for file in files:
        if not file.is_file():
            continue
        if mode == "file":
            with open_regular(file) as f:
                _inflated(path, f"{file.name}", "zstd", _pieces(f, file.stat().st_size))
            continue
        if file.suffix == ".mcap":
            with open_regular(file) as f:
                _check_mcap(path, f)
        elif mode == "message" and file.suffix == ".db3":
            _check_db3_messages(path, file)


def _check_db3_messages(path: Path, file: Path) -> None:
    """Each zstd-compressed message of a ROS 2 SQLite storage file."""
    try:
        with sqlite3.connect(f"file:{file}?mode=ro", uri=True) as db:
            for (data,) in db.execute("SELECT data FROM messages"):
                _inflated(path, "a message of the bag", "zstd", iter([bytes(data)]))
    except sqlite3.Error:
        return  # not a storage file rosbags can read either: it says why
