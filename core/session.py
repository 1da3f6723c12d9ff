"""Sessions: a folder that survives a crash.

Layout of ``<session>/``:

- ``manifest.json``: human-readable description (kind, source, image size, probe, known
  ``phantom_to_base``, nominal pixel spacing), written atomically;
- ``phantom.json``: the phantom definition, when there is one;
- ``frames/NNNNNN.png``: lossless frames, each written atomically *before* its record;
- ``records.jsonl``: one JSON line per frame, appended and fsync'ed after the frame is on disk;
- ``truth.json``: ground truth, simulated sessions only (SPEC §2 keys plus per-frame markers);
- ``refused.jsonl``: one JSON line per frame of a live stream that was not recorded, and why.

A process killed at any moment leaves a session that loads, minus at most the frame being
written: an unterminated last line of ``records.jsonl`` is ignored, and an image without a record
is never listed. Poses are ``tool_to_base`` 4x4 in mm; timestamps are in seconds.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

from core.errors import InputError
from core.files import umask, write_atomic
from core.jsonio import read_json, write_json
from core.phantom import Phantom, phantom_from_dict
from core.probe import LinearProbe

FORMAT = "probecal-session/1"
MANIFEST = "manifest.json"
RECORDS = "records.jsonl"
PHANTOM = "phantom.json"
TRUTH = "truth.json"
REFUSED = "refused.jsonl"
FRAMES_DIR = "frames"


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


def _record_from_json(data: dict, path: Path, line_no: int) -> FrameRecord:
    known = {"index", "image", "tool_to_base", "timestamp", "pose_timestamp", "source_index"}
    try:
        pose = data["tool_to_base"]
        if pose is not None:
            pose = np.array(pose, dtype=float)
            if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
                raise ValueError("tool_to_base is not a finite 4x4 matrix")
        return FrameRecord(
            index=int(data["index"]),
            image=str(data["image"]),
            tool_to_base=pose,
            timestamp=data.get("timestamp"),
            pose_timestamp=data.get("pose_timestamp"),
            source_index=data.get("source_index"),
            extra={k: v for k, v in data.items() if k not in known},
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"line {line_no}: bad frame record ({exc})")


class SessionWriter:
    """Creates a session folder (or resumes one) and appends frames crash-safely.

    A new session is assembled in a hidden folder beside ``path`` (manifest, phantom and any
    ``files``, name to bytes) and renamed into place, so a session folder is never visible before
    it loads.
    """

    def __init__(
        self,
        path: str | Path,
        manifest: dict,
        phantom: Phantom | None = None,
        probe: LinearProbe | None = None,
        resume: bool = False,
        files: Mapping[str, bytes] | None = None,
    ):
        self.path = Path(path)
        if resume:
            existing = load_session(self.path)
            self.manifest = existing.manifest
            self._next = len(existing)
        else:
            if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
                raise InputError(self.path, "output folder exists and is not empty")
            self.manifest = {
                "format": FORMAT,
                "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                **manifest,
                "probe": probe.to_dict() if probe is not None else manifest.get("probe"),
                "phantom": PHANTOM if phantom is not None else None,
            }
            self.path.parent.mkdir(parents=True, exist_ok=True)
            staging = Path(tempfile.mkdtemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".creating"))
            try:
                (staging / FRAMES_DIR).mkdir()
                if phantom is not None:
                    write_json(staging / PHANTOM, phantom.to_dict())
                for name, data in (files or {}).items():
                    write_atomic(staging / name, data)
                write_json(staging / MANIFEST, self.manifest)
                staging.chmod(0o777 & ~umask())
                os.replace(staging, self.path)
            except BaseException:
                shutil.rmtree(staging, ignore_errors=True)
                raise
            self._next = 0
        self._records = open(self.path / RECORDS, "ab")

    def __len__(self) -> int:
        return self._next

    def append(
        self,
        image: np.ndarray,
        tool_to_base: np.ndarray | None,
        timestamp: float | None = None,
        pose_timestamp: float | None = None,
        source_index: int | None = None,
        **extra,
    ) -> int:
        """Store one frame (uint8 grayscale) with its pose; returns its index in the session."""
        index = self._next
        name = f"{FRAMES_DIR}/{index:06d}.png"
        ok, png = cv2.imencode(".png", np.ascontiguousarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RuntimeError(f"could not encode frame {index}")
        write_atomic(self.path / name, png.tobytes())
        if tool_to_base is not None and not np.all(np.isfinite(tool_to_base)):
            tool_to_base = None
        record = FrameRecord(index, name, tool_to_base, timestamp, pose_timestamp, source_index, extra)
        self._records.write((json.dumps(record.to_json(), allow_nan=False) + "\n").encode())
        self._records.flush()
        os.fsync(self._records.fileno())
        self._next += 1
        return index

    def update_manifest(self, **changes) -> None:
        self.manifest.update(changes)
        write_json(self.path / MANIFEST, self.manifest)

    def write_truth(self, truth: dict) -> None:
        write_json(self.path / TRUTH, truth)

    def refuse(self, record: dict) -> None:
        """Note a frame that was not recorded, and why: one JSON line in ``refused.jsonl``."""
        with open(self.path / REFUSED, "ab") as log:
            log.write((json.dumps(record, allow_nan=False) + "\n").encode())

    def close(self) -> None:
        if not self._records.closed:
            self._records.close()

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class Session:
    """A loaded session. Images are read lazily with ``image(i)``."""

    path: Path
    manifest: dict
    records: list[FrameRecord]
    phantom: Phantom | None
    probe: LinearProbe | None

    def __len__(self) -> int:
        return len(self.records)

    def image(self, i: int) -> np.ndarray:
        """Frame i as a uint8 (H, W) array. Raises InputError if the file is unreadable."""
        file = self.path / self.records[i].image
        image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
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
    def phantom_to_base(self) -> np.ndarray | None:
        """The known phantom pose (e.g. PLUS PhantomToReference), if the session records one."""
        value = self.manifest.get("phantom_to_base")
        return None if value is None else np.array(value, dtype=float)

    @property
    def pixel_spacing_mm(self) -> tuple[float, float] | None:
        """Nominal (sx, sy) as the scanner reports it, if known."""
        value = self.manifest.get("pixel_spacing_mm")
        return None if value is None else (float(value[0]), float(value[1]))

    def truth(self) -> dict | None:
        file = self.path / TRUTH
        if not file.is_file():
            return None
        return read_json(file)


def load_session(path: str | Path, check_frames: bool = True) -> Session:
    """Load a session folder. Raises InputError naming the file and the problem."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "session folder not found")
    manifest_file = path / MANIFEST
    if not manifest_file.is_file():
        raise InputError(path, f"not a session (no {MANIFEST})")
    manifest = read_json(manifest_file)
    if manifest.get("format") != FORMAT:
        raise InputError(manifest_file, f"unknown session format {manifest.get('format')!r}")
    records_file = path / RECORDS
    records = []
    if records_file.is_file():
        lines = records_file.read_bytes().split(b"\n")
        # The last element is empty after a clean append; anything else there is a torn write.
        for line_no, line in enumerate(lines[:-1], start=1):
            if not line.strip():
                continue
            try:
                data = json.loads(line)
            except json.JSONDecodeError as exc:
                raise InputError(records_file, f"line {line_no}: corrupt record ({exc.msg})")
            records.append(_record_from_json(data, records_file, line_no))
    for i, r in enumerate(records):
        if r.index != i:
            raise InputError(records_file, f"record {i} has index {r.index}: records out of order")
        if check_frames and not (path / r.image).is_file():
            raise InputError(path / r.image, f"frame {i} is missing")
    phantom = None
    if manifest.get("phantom"):
        phantom_file = path / manifest["phantom"]
        if not phantom_file.is_file():
            raise InputError(phantom_file, "phantom definition named in the manifest is missing")
        phantom = phantom_from_dict(read_json(phantom_file), phantom_file)
    probe = LinearProbe.from_dict(manifest["probe"]) if manifest.get("probe") else None
    return Session(path, manifest, records, phantom, probe)
