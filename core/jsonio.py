"""JSON files that people read: numeric lists on one line, written atomically."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.files import write_atomic

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


def read_json(path: str | Path) -> dict:
    """A JSON file's content; InputError naming the file when it is missing or not valid JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "file not found")
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({exc})")


def write_json(path: str | Path, obj) -> None:
    """Atomically write ``obj`` as readable JSON."""
    write_atomic(path, to_json_text(obj))
