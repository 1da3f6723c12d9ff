"""JSON files that people read: numeric lists on one line, written atomically."""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np

_NUMBER_LIST = re.compile(r"\[\s*(-?[\d.eE+-]+(?:,\s*-?[\d.eE+-]+)*)\s*\]")


def _default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def to_json_text(obj) -> str:
    """Indented JSON with innermost numeric lists kept on one line."""
    text = json.dumps(obj, indent=2, default=_default, allow_nan=False)
    return _NUMBER_LIST.sub(lambda m: "[" + ", ".join(s.strip() for s in m.group(1).split(",")) + "]", text) + "\n"


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write a file so that readers see either the old content or the new, never half of it."""
    path = Path(path)
    payload = data.encode() if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: str | Path, obj) -> None:
    """Atomically write ``obj`` as readable JSON."""
    write_atomic(path, to_json_text(obj))
