"""Sessions: a folder that survives a crash.

Layout of ``<session>/``:

- ``manifest.json``: human-readable description (kind, source, image size, probe, known
  ``phantom_to_base``, nominal pixel spacing), written atomically;
- ``phantom.json``: the phantom definition, when there is one;
- ``frames/NNNNNN.png``: lossless frames, each written atomically *before* its record;
- ``records.jsonl``: one JSON line per frame, appended and fsync'ed after the frame is on disk;
- ``truth.json``: ground truth, simulated sessions only (design §2 keys plus per-frame markers);
- ``refused.jsonl``: one JSON line per frame of a live stream that was not recorded, and why;
- ``posestream.jsonl``: the robot's pose stream while the frames were taken, when it was kept
  (continuous sweeps): one line per sample, ``[t, the top three rows of tool_to_base]``, appended
  and fsync'ed in batches, so that frames can be paired again with another latency.

A process killed at any moment leaves a session that loads, minus at most the frame being
written: an unterminated last line of ``records.jsonl`` is ignored, and an image without a record
is never listed. The writer checks every record and pose sample as the reader will, with the
reader's own checks, so that what a session holds always reads back. Poses are ``tool_to_base``
4x4 in mm; timestamps are in seconds.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Probe
from probecal.core.geometry.transforms import RIGID_TOLERANCE
from probecal.core.io.files import inside, read_bytes, staged_folder, write_atomic
from probecal.core.io.jsonio import (
    describe,
    expect_bool,
    expect_integer,
    expect_line_length,
    expect_matrix,
    expect_name_inside,
    expect_number,
    expect_numbers,
    expect_object,
    expect_spacing,
    json_lines,
    optional,
    parse_json,
    read_json,
    required,
    write_json,
)
from probecal.core.io.limits import PARSED_EXPANSION, checked_bytes
from probecal.core.io.manifest import Manifest
from probecal.core.io.phantomfile import dict_from_phantom, phantom_from_dict

MANIFEST = "manifest.json"
RECORDS = "records.jsonl"
PHANTOM = "phantom.json"
TRUTH = "truth.json"
REFUSED = "refused.jsonl"
MAX_REFUSALS_LOGGED = 10_000
"""The most refused frames ``refused.jsonl`` lists (a line each, at most about 1 kB)."""
REFUSAL_CHARS = 500
"""The most of a refusal's text (its reason) ``refused.jsonl`` keeps."""
POSE_STREAM = "posestream.jsonl"
FRAMES_DIR = "frames"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Frames are stored losslessly with zlib's fastest level and PNG's "up" row filter: about the size of
# libpng's adaptive filtering, written three to four times and read about twice as fast (a 3 Mpx
# frame: 25 -> 7 ms to write, 11 -> 7 ms to read), which is most of segmenting a fine scanner's frame.
PNG_SETTINGS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]


@dataclass(frozen=True)
class FrameRecord:
    """One recorded frame: its image file and the flange pose (``tool_to_base``, mm) paired with it.

    ``tool_to_base`` is None when the pose was not valid. ``source_index`` is the frame's index in
    the file it was imported from (None for recorded sessions).
    """

    index: int
    image: str
    tool_to_base: np.ndarray | None
    timestamp: float | None = None
    pose_timestamp: float | None = None
    source_index: int | None = None
    extra: dict = field(default_factory=dict)

    @property
    def pose_valid(self) -> bool:
        return self.tool_to_base is not None

    def to_json(self) -> dict:
        out = {
            "index": self.index,
            "image": self.image,
            "tool_to_base": None if self.tool_to_base is None else self.tool_to_base.tolist(),
            "timestamp": self.timestamp,
            "pose_timestamp": self.pose_timestamp,
        }
        if self.source_index is not None:
            out["source_index"] = self.source_index
        out.update(self.extra)
        return out


_RECORD_KEYS = {"index", "image", "tool_to_base", "timestamp", "pose_timestamp", "source_index"}


class RefusedRecord(InputError):
    """A frame's record or a pose sample that a session's writer does not write, because its reader
    would refuse it; the message names the file and the problem."""


def _record_from_json(data: Any, root: Path, source: Path, where: str) -> FrameRecord:
    """A record of ``records.jsonl`` (``where`` names it: its line, or the frame being written)
    checked field by field; its image must lie inside ``root``."""
    at = f"{where}: "
    record = expect_object(data, source, where)
    image = required(record, "image", expect_name_inside, source, at, root=root)
    for key in ("plan_index", "sweep", "view"):
        optional(record, key, expect_integer, source, at, minimum=0)
    if "image_valid" in record:
        expect_bool(record["image_valid"], source, at + "image_valid")
    return FrameRecord(
        index=required(record, "index", expect_integer, source, at, minimum=0),
        image=image,
        tool_to_base=optional(record, "tool_to_base", expect_matrix, source, at, rigid=True),
        timestamp=optional(record, "timestamp", expect_number, source, at),
        pose_timestamp=optional(record, "pose_timestamp", expect_number, source, at),
        source_index=optional(record, "source_index", expect_integer, source, at, minimum=0),
        extra={k: v for k, v in record.items() if k not in _RECORD_KEYS},
    )


def read_manifest(path: str | Path) -> Manifest:
    """The checked manifest of the session folder ``path`` (see :meth:`Manifest.from_json`)."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "session folder not found")
    manifest_file = inside(path, MANIFEST, path)
    if not os.path.lexists(manifest_file):
        raise InputError(path, f"not a session (no {MANIFEST})")
    return Manifest.from_json(read_json(manifest_file), path, manifest_file)


class SessionWriter:
    """Creates a session folder (or resumes one, whose own manifest is kept: ``manifest`` is then
    not used) and appends frames crash-safely.

    A new session is assembled in a hidden folder beside ``path`` (manifest, phantom and any
    ``files``, name to bytes) and renamed into place, so a session folder is never visible before
    it loads.
    """

    def __init__(
        self,
        path: str | Path,
        manifest: Manifest,
        phantom: Phantom | None = None,
        probe: Probe | None = None,
        resume: bool = False,
        files: Mapping[str, bytes] | None = None,
    ):
        self.path = Path(path)
        if resume:
            existing = load_session(self.path)
            self.manifest = existing.manifest
            self._next = len(existing)
        else:
            self.manifest = replace(manifest, created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                                    probe=probe if probe is not None else manifest.probe,
                                    phantom=PHANTOM if phantom is not None else None)
            with staged_folder(self.path) as staging:
                (staging / FRAMES_DIR).mkdir()
                if phantom is not None:
                    write_json(staging / PHANTOM, dict_from_phantom(phantom))
                for name, data in (files or {}).items():
                    write_atomic(staging / name, data)
                write_json(staging / MANIFEST, self.manifest.to_json())
            self._next = 0
        self._records = open(self.path / RECORDS, "ab")
        self._refused = 0
        stream = read_pose_stream(self.path) if resume else None
        self._pose_lines = 0 if stream is None else len(stream[0])  # pose samples kept
        self._last_pose_s = -np.inf if stream is None else float(stream[0][-1])

    def __len__(self) -> int:
        return self._next

    def append(
        self,
        image: np.ndarray,
        tool_to_base: np.ndarray | None,
        timestamp: float | None = None,
        pose_timestamp: float | None = None,
        source_index: int | None = None,
        **extra: object,
    ) -> int:
        """Store one frame (uint8 grayscale) with its pose (None: no valid pose); returns its
        index in the session. RefusedRecord, and nothing written, when the session's reader would
        refuse the record (a pose that is not a finite rigid transform within ``MAX_MAGNITUDE``, a
        timestamp that is not a finite number, ...)."""
        index = self._next
        name = f"{FRAMES_DIR}/{index:06d}.png"
        line = self._checked_line(FrameRecord(index, name, tool_to_base, timestamp, pose_timestamp, source_index,
                                              extra))
        ok, png = cv2.imencode(".png", np.ascontiguousarray(image), PNG_SETTINGS)
        if not ok:
            raise RuntimeError(f"could not encode frame {index}")
        write_atomic(self.path / name, png.tobytes())
        self._records.write(line)
        self._records.flush()
        os.fsync(self._records.fileno())
        self._next += 1
        return index

    def _checked_line(self, record: FrameRecord) -> bytes:
        """``record``'s line of ``records.jsonl``, checked by the reader's own checks; RefusedRecord
        naming the frame and the problem when they would refuse it."""
        file = self.path / RECORDS
        text = json.dumps(record.to_json(), allow_nan=True)
        try:
            expect_line_length(file, record.index + 1, len(text.encode()), "records", MAX_RECORD_LINE)
            _record_from_json(json.loads(text), self.path, file, f"frame {record.index}")
            parse_json(text, file, f"frame {record.index}: not a record")  # what the fields leave: numbers of its own
        except InputError as exc:
            raise RefusedRecord(file, f"{exc.problem} (not written: the session's reader would refuse it)") from None
        return (text + "\n").encode()

    def append_poses(self, timestamps: np.ndarray, tool_to_base: np.ndarray) -> None:
        """Append pose-stream samples ((n,) s, later than those already kept; (n, 4, 4) mm) to
        ``posestream.jsonl`` and sync them to disk. RefusedRecord, and none written, when the
        session's reader would refuse one (:func:`read_pose_stream`)."""
        if len(timestamps) == 0:
            return
        file = self.path / POSE_STREAM
        rows = np.column_stack([timestamps, np.asarray(tool_to_base)[:, :3, :].reshape(len(timestamps), 12)])
        lines = [json.dumps(row, allow_nan=True) for row in rows.tolist()]
        try:
            for k, line in enumerate(lines):
                expect_line_length(file, self._pose_lines + k + 1, len(line), "pose samples", MAX_SAMPLE_LINE)
            times, _ = _stream_samples([_stream_row(json.loads(line), file, self._pose_lines + k + 1)
                                        for k, line in enumerate(lines)], file, self._pose_lines + 1, self._last_pose_s)
        except InputError as exc:
            raise RefusedRecord(file, f"{exc.problem} (not written: the session's reader would refuse it)") from None
        text = "".join(line + "\n" for line in lines)
        with open(file, "ab") as stream:
            stream.write(text.encode())
            stream.flush()
            os.fsync(stream.fileno())
        self._pose_lines += len(lines)
        self._last_pose_s = float(times[-1])

    def update_manifest(self, **changes: Any) -> None:
        """Change fields of the manifest (:class:`Manifest`'s) and rewrite it."""
        self.manifest = replace(self.manifest, **changes)
        write_json(self.path / MANIFEST, self.manifest.to_json())

    def write_truth(self, truth: dict) -> None:
        write_json(self.path / TRUTH, truth)

    def refuse(self, record: dict) -> None:
        """Note a frame that was not recorded, and why: one JSON line in ``refused.jsonl``, its
        texts cut to :data:`REFUSAL_CHARS`; past :data:`MAX_REFUSALS_LOGGED` lines only counted
        (the sweep's own count says how many in all), so a source refused at every frame cannot
        fill the disk."""
        self._refused += 1
        if self._refused > MAX_REFUSALS_LOGGED:
            return
        cut = {key: value[:REFUSAL_CHARS] if isinstance(value, str) else value for key, value in record.items()}
        with open(self.path / REFUSED, "ab") as log:
            log.write((json.dumps(cut, allow_nan=False) + "\n").encode())

    def close(self) -> None:
        if not self._records.closed:
            self._records.close()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class Session:
    """A loaded session. Images are read lazily with ``image(i)``."""

    path: Path
    manifest: Manifest
    records: list[FrameRecord]
    phantom: Phantom | None

    def __len__(self) -> int:
        return len(self.records)

    def image(self, i: int) -> np.ndarray:
        """Frame i as a uint8 (H, W) array. Raises InputError if the file is unreadable."""
        file = self.path / self.records[i].image
        data = read_bytes(file)
        _check_png(data, file, i)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InputError(file, f"frame {i}: image is missing or unreadable")
        return image

    def poses(self) -> np.ndarray:
        """(N, 4, 4) tool_to_base for every frame, NaN where the pose is not valid."""
        out = np.full((len(self.records), 4, 4), np.nan)
        for i, r in enumerate(self.records):
            if r.tool_to_base is not None:
                out[i] = r.tool_to_base
        return out

    @property
    def probe(self) -> Probe | None:
        """The probe that imaged the frames, where the session states it."""
        return self.manifest.probe

    @property
    def fan(self) -> Fan | None:
        """The fan of a scan-converted recording's frames (pixels), where its import stated one."""
        return self.manifest.fan

    @property
    def phantom_to_base(self) -> np.ndarray | None:
        """The known phantom pose (mm; e.g. PLUS PhantomToReference), if the session records one."""
        value = self.manifest.phantom_to_base
        return None if value is None else np.array(value, dtype=float)

    @property
    def pixel_spacing_mm(self) -> tuple[float, float] | None:
        """Nominal (sx, sy) mm/px as the scanner reports it, if known."""
        value = self.manifest.pixel_spacing_mm
        return None if value is None else (float(value[0]), float(value[1]))

    @property
    def nominal_spacing_mm(self) -> tuple[float, float] | None:
        """The scanner's nominal (sx, sy) mm/px, else a PLUS recording's approximate spacing hint;
        None when neither is known."""
        if self.pixel_spacing_mm is not None:
            return self.pixel_spacing_mm
        hint = (self.manifest.segmentation_hints or {}).get("ApproximateSpacingMmPerPixel")
        return None if not hint else (float(hint), float(hint))

    @property
    def start_depth_mm(self) -> float | None:
        """How far below the probe's face the frames' first row lies (nominal mm), if known."""
        value = self.manifest.start_depth_mm
        return None if value is None else float(value)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) px of the frames: the manifest's, else the first frame's."""
        if self.manifest.image_size is not None:
            return self.manifest.image_size
        height, width = self.image(0).shape[:2]
        return width, height

    def truth(self) -> dict | None:
        """``truth.json`` (simulated sessions), checked (:func:`read_truth`); None if there is none."""
        return read_truth(self.path)

    @property
    def has_pose_stream(self) -> bool:
        """Whether the session kept its robot's pose stream (continuous sweeps)."""
        return (self.path / POSE_STREAM).is_file()

    def pose_stream(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The kept pose stream: timestamps (M,) s, increasing, and ``tool_to_base`` (M, 4, 4) mm;
        None when the session kept none."""
        return read_pose_stream(self.path)


_STREAM_ROW = 13  # t and the top three rows of a 4x4
SAMPLE_BYTES = 1024
"""What reading one pose sample may take (bytes): its numbers parsed, their array (200), the
sample as a row and as a pose (232), the rigidity check's products (216)."""
MAX_SAMPLE_LINE = 4096
"""A pose sample's longest line (bytes): 13 numbers take about 300."""


def read_pose_stream(folder: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """``posestream.jsonl`` of the session folder, every line checked (13 finite numbers, times
    increasing, a rigid pose); an unterminated last line (a write cut short) is ignored. None
    when there is none; InputError naming the file and the line otherwise."""
    file = inside(folder, POSE_STREAM, folder)
    if not file.is_file():
        return None
    samples = [_stream_row(parse_json(line, file, f"line {number}: corrupt pose sample"), file, number)
               for number, line in json_lines(file, "pose samples", SAMPLE_BYTES, MAX_SAMPLE_LINE)]
    return _stream_samples(samples, file, 1)


def _stream_row(value: Any, file: Path, line: int) -> np.ndarray:
    """One pose sample of ``posestream.jsonl`` (its ``line``): 13 finite numbers within
    ``MAX_MAGNITUDE``; InputError naming the file and the line otherwise."""
    return expect_numbers(value, file, f"line {line}", count=_STREAM_ROW)


def _stream_samples(samples: list[np.ndarray], file: Path, first: int,
                    after: float = -np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Pose samples (:func:`_stream_row`, the first on line ``first``) as timestamps (M,) s and
    poses (M, 4, 4) mm: InputError naming the file and the line unless the times increase, from
    after ``after`` (s), and every pose is rigid."""
    rows = np.array(samples).reshape(len(samples), _STREAM_ROW)
    times = rows[:, 0]
    backwards = np.flatnonzero(np.diff(np.concatenate([[after], times])) <= 0)
    if len(backwards):
        at = int(backwards[0])
        raise InputError(file, f"line {first + at}: timestamp {times[at]!r} is not after the line before it")
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :] = rows[:, 1:].reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    rotations = poses[:, :3, :3]
    skewed = np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    not_rigid = np.flatnonzero((skewed > RIGID_TOLERANCE) | (np.abs(np.linalg.det(rotations) - 1) > RIGID_TOLERANCE))
    if len(not_rigid):
        raise InputError(file, f"line {first + not_rigid[0]}: the pose is not a rigid transform")
    return times, poses


def read_truth(folder: str | Path) -> dict | None:
    """The session folder's ``truth.json`` (simulated sessions), its transforms checked; None if
    there is none."""
    file = inside(folder, TRUTH, folder)
    if not file.is_file():
        return None
    truth = read_json(file)
    optional(truth, "image_to_tool", expect_matrix, file)
    for key in ("image_to_tool_rigid", "phantom_to_base", "object_to_base"):
        optional(truth, key, expect_matrix, file, rigid=True)
    optional(truth, "pixel_spacing_mm", expect_spacing, file)
    return truth


def _check_png(data: bytes, file: Path, i: int) -> None:
    """Refuse frame ``i`` (``data``, read from ``file``) unless it is a sound PNG, before libpng sees
    it (libpng complains on stderr): its signature, every chunk whole with its CRC right, an IHDR
    first whose fields are valid, and a size within the memory limit."""
    if not data.startswith(PNG_SIGNATURE):
        raise InputError(file, f"frame {i}: not a PNG image")
    view, at, chunks = memoryview(data), len(PNG_SIGNATURE), 0
    while at < len(data):
        length, kind = struct.unpack(">I4s", view[at:at + 8]) if at + 8 <= len(data) else (0, b"")
        end = at + 12 + length
        if not kind or end > len(data):
            raise InputError(file, f"frame {i}: the PNG file is cut short")
        if chunks == 0:
            _check_ihdr(kind, bytes(view[at + 8:end - 4]), file, i)
        if zlib.crc32(view[at + 4:end - 4]) != int.from_bytes(view[end - 4:end], "big"):
            raise InputError(file, f"frame {i}: the PNG chunk {kind.decode('latin-1')!r} is corrupt (CRC)")
        at, chunks = end, chunks + 1
        if kind == b"IEND":
            break


_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}  # colour type: bits


def _check_ihdr(kind: bytes, body: bytes, file: Path, i: int) -> None:
    """A PNG's first chunk, which must be a valid IHDR whose image fits the memory limit."""
    if kind != b"IHDR" or len(body) != 13:
        raise InputError(file, f"frame {i}: the PNG file does not start with its IHDR header")
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", body)
    if not (0 < width < 2**31 and 0 < height < 2**31) or depth not in _PNG_DEPTHS.get(colour, ()) \
            or compression or filtering or interlace > 1:
        raise InputError(file, f"frame {i}: the PNG header is invalid ({width} x {height} px, bit depth {depth}, "
                               f"colour type {colour})")
    checked_bytes(file, f"frame {i} ({width} x {height} px)", (height, width, 4, 2 if depth == 16 else 1))


RECORD_BYTES = 2048
"""What one record takes once read (bytes): measured 1.2 kB at its peak for a sweep's record with
a pose and timestamps; fields of its own (``extra``) are counted apart, at PARSED_EXPANSION."""
MAX_RECORD_LINE = 1 << 16
"""A record's longest line (bytes): a sweep's take about 420."""


def _read_records(root: Path) -> list[FrameRecord]:
    """The records of the session folder ``root``: complete lines of ``records.jsonl``, each
    checked; an unterminated last line (a write cut short) is ignored."""
    records_file = inside(root, RECORDS, root)
    if not os.path.lexists(records_file):
        return []
    records = []
    kept = 0  # what the records' own fields hold beyond RECORD_BYTES (bytes, at most)
    for line_no, line in json_lines(records_file, "records", RECORD_BYTES, MAX_RECORD_LINE):
        if line.strip():
            data = parse_json(line, records_file, f"line {line_no}: corrupt record")
            records.append(_record_from_json(data, root, records_file, f"line {line_no}"))
            if records[-1].extra:
                kept += len(line) * PARSED_EXPANSION
                checked_bytes(records_file, f"the records' own fields up to line {line_no}", [kept])
    for i, r in enumerate(records):
        if r.index != i:
            raise InputError(records_file, f"record {i} has index {describe(r.index)}: records out of order")
    return records


def load_session(path: str | Path, check_frames: bool = True) -> Session:
    """Load a session folder. Raises InputError naming the file and the problem; every file the
    session names must lie inside its folder."""
    path = Path(path)
    manifest = read_manifest(path)
    records = _read_records(path)
    if check_frames:
        for i, r in enumerate(records):
            if not (path / r.image).is_file():
                raise InputError(path / r.image, f"frame {i} is missing")
    phantom = None
    if manifest.phantom is not None:
        phantom_file = path / manifest.phantom
        if not os.path.lexists(phantom_file):
            raise InputError(phantom_file, "phantom definition named in the manifest is missing")
        phantom = phantom_from_dict(read_json(phantom_file), phantom_file)
    return Session(path, manifest, records, phantom)


def load_recorded_session(path: str | Path) -> Session:
    """A session to work on (:func:`load_session`): InputError naming its records when it holds no
    frames."""
    session = load_session(path)
    if not session.records:
        raise InputError(session.path / RECORDS, "holds no frames")
    return session
