"""The fields a JSON document holds, to compare a file's layout with the one it had."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

GOLDEN = Path(__file__).resolve().parents[1] / "golden"


def key_paths(value: Any, prefix: str = "") -> set[str]:
    """Every key's dotted path in ``value``; a list's items under ``[]``, and keys that are whole
    numbers (frame indices) as ``*``."""
    found: set[str] = set()
    if isinstance(value, dict):
        for key, item in value.items():
            name = "*" if str(key).lstrip("-").isdigit() else str(key)
            path = f"{prefix}.{name}" if prefix else name
            found |= {path} | key_paths(item, path)
    elif isinstance(value, list):
        for item in value:
            found |= key_paths(item, prefix + "[]")
    return found


def golden_keys(name: str) -> set[str]:
    """The key paths kept in ``tests/golden/NAME_keys.json``."""
    return set(json.loads((GOLDEN / f"{name}_keys.json").read_text()))
