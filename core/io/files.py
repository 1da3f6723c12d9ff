"""Files that appear complete or not at all: written beside their target, then renamed."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from probecal.core.errors import InputError

_UMASK = os.umask(0)
os.umask(_UMASK)


def umask() -> int:
    """The process's file-creation mask, as read at start-up."""
    return _UMASK


def replace_atomically(path: str | Path, write: Callable[[Path], None]) -> None:
    """Run ``write(temporary path)`` beside ``path``, sync it, then rename it into place."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix or ".tmp")
    os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual mode
    os.close(fd)
    try:
        write(Path(tmp))
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write bytes (or text, as UTF-8) so that readers see the old content or the new, never half."""
    payload = data.encode() if isinstance(data, str) else data
    replace_atomically(path, lambda tmp: tmp.write_bytes(payload))


def inside(root: str | Path, name: str | Path, owner: str | Path) -> Path:
    """``root / name`` for a ``name`` that a file (``owner``) refers to, refused with InputError
    naming ``owner`` unless it stays inside ``root``: no absolute path, no ``..``, no symlink
    that leads out."""
    text = str(name)
    if not text or "\x00" in text:
        raise InputError(owner, f"empty or invalid file name {text!r}")
    relative = Path(text)
    if relative.is_absolute() or ".." in relative.parts:
        raise InputError(owner, f"{text!r} points outside {root}; only names inside it are allowed")
    base = Path(root).resolve()
    target = (base / relative).resolve()
    if not target.is_relative_to(base):
        raise InputError(owner, f"{text!r} leads outside {root} (through a link)")
    return base / relative
