"""Files and folders that appear complete or not at all: written beside their target, then renamed."""

from __future__ import annotations

import errno
import io
import os
import shutil
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

from probecal.core.errors import InputError
from probecal.core.io.limits import checked_bytes

_UMASK = os.umask(0)
os.umask(_UMASK)


def umask() -> int:
    """The process's file-creation mask, as read at start-up."""
    return _UMASK


NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def mount_point(path: Path) -> Path:
    """Where the file system that holds ``path`` (or its nearest existing folder) is mounted."""
    path = Path(os.path.abspath(path))
    while not path.exists():
        path = path.parent
    device = path.stat().st_dev
    while path != path.parent and path.parent.stat().st_dev == device:
        path = path.parent
    return path


def no_space(exc: OSError) -> InputError | None:
    """For an OSError that says the disk (or the user's quota) is full, an InputError that says so
    in one line, naming the device's mount point and the file being written (the error's own);
    None for any other OSError."""
    if exc.errno not in NO_SPACE:
        return None
    if not exc.filename:
        return InputError(None, "no space left on the device")
    writing = Path(os.fsdecode(exc.filename))
    return InputError(None, f"no space left on {mount_point(writing)} writing {writing}")


def _full(path: Path) -> bool:
    """Whether the file system that holds ``path`` has no block left to write."""
    try:
        return os.statvfs(mount_point(path)).f_bavail == 0
    except OSError:
        return False


def _writing(exc: BaseException, path: Path) -> BaseException:
    """A full disk's error as an OSError naming ``path`` as the file being written (a write's own
    names none, a temporary file's a name that is gone; a library's own error, ITK's, is no
    OSError at all, so a disk left with no block is taken as the cause); any other error as it is."""
    if isinstance(exc, OSError) and exc.errno in NO_SPACE or isinstance(exc, Exception) and _full(path):
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return exc


_STDERR = threading.Lock()  # one block at a time moves the process's stderr


@contextmanager
def library_stderr(path: Path) -> Iterator[None]:
    """Hold what a C++ library writing ``path`` prints on the process's stderr (ITK's MetaIO prints
    its errors there, then raises) until the block ends, and print it then, unless the block
    failed for a full disk: :func:`replace_atomically` says that in one line of its own."""
    with _STDERR:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            with tempfile.TemporaryFile() as held:
                os.dup2(held.fileno(), 2)
                try:
                    yield
                except Exception:
                    os.dup2(saved, 2)
                    if not _full(path):
                        _replay(held)
                    raise
                os.dup2(saved, 2)
                _replay(held)
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def _replay(held: BinaryIO) -> None:
    held.seek(0)
    text = held.read()
    if text:
        os.write(2, text)


def replace_atomically(path: str | Path, write: Callable[[Path], object]) -> None:
    """Run ``write(temporary path)`` beside ``path``, sync it, then rename it into place; nothing
    is left of it on any error (a full disk's OSError names ``path``, see :func:`no_space`)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix or ".tmp")
    os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual mode
    os.close(fd)
    try:
        try:
            write(Path(tmp))
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        except BaseException as exc:
            error = _writing(exc, path)  # while the disk is still as full as the write left it
            if error is exc:
                raise
            raise error from None
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


def fresh_folder(path: str | Path, replace: bool = False) -> Path:
    """``path`` for a new output folder: InputError when it is a symbolic link (its target would be
    written or replaced), a file, or, unless ``replace``, a folder that is not empty."""
    path = Path(path)
    if path.is_symlink():
        raise InputError(path, "output folder is a symbolic link; give the folder itself")
    if path.exists() and not path.is_dir():
        raise InputError(path, "is a file; give a folder name")
    if not replace and path.exists() and any(path.iterdir()):
        raise InputError(path, "output folder exists and is not empty")
    return path


@contextmanager
def staged_folder(path: str | Path, staging: str | Path | None = None, what: str = "run",
                  replace: bool = False) -> Iterator[Path]:
    """Build the new folder ``path`` (fresh, see :func:`fresh_folder`) under another name beside it,
    then rename it into place when the block ends; if the block raises (an interrupt too), the
    staging folder goes and ``path`` is untouched (a full disk's OSError names the file being
    written by its name under ``path``). ``replace``: an existing folder at ``path`` is
    swapped out only then, and removed. ``staging`` is that name (refused when anything is there
    already, which is never deleted: a leftover of an interrupted ``what``), else a new hidden one.
    The folder gets the usual mode."""
    path = fresh_folder(path, replace)
    path.parent.mkdir(parents=True, exist_ok=True)
    if staging is None:
        folder = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".writing"))
    else:
        folder = Path(staging)
        if os.path.lexists(folder):
            raise InputError(folder, f"left over from an interrupted {what}; remove it and try again")
        folder.mkdir()
    try:
        folder.chmod(0o777 & ~_UMASK)  # mkdtemp makes 0700
        yield folder
        if replace and path.is_dir():
            old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
            os.replace(path, old)
            os.replace(folder, path)
            shutil.rmtree(old)
        else:
            os.replace(folder, path)  # replaces an empty folder at path
    except BaseException as exc:
        error = _writing(exc, _as_placed(exc, folder, path))  # while the disk is still full
        shutil.rmtree(folder, ignore_errors=True)
        if error is exc:
            raise
        raise error from None


def _as_placed(exc: BaseException, folder: Path, path: Path) -> Path:
    """The file an OSError names, by its name once ``folder`` became ``path`` (else ``path``)."""
    name = getattr(exc, "filename", None)
    if not name:
        return path
    inside_folder = Path(os.path.abspath(os.fsdecode(name)))
    if not inside_folder.is_relative_to(os.path.abspath(folder)):
        return path
    return path / inside_folder.relative_to(os.path.abspath(folder))


NOT_REGULAR = "not a regular file (a FIFO, socket or device); only regular files are read"


def existing_file(path: str | Path) -> Path:
    """``path`` when it names a regular file (after links); InputError naming it otherwise: a FIFO,
    a socket or a device is refused, since opening or reading one may block for ever."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):  # missing, a broken link, a name too long or holding NUL
        raise InputError(path, "file not found") from None
    if stat.S_ISDIR(mode):
        raise InputError(path, "file not found (it is a folder)")
    if not stat.S_ISREG(mode):
        raise InputError(path, NOT_REGULAR)
    return path


def open_regular(path: str | Path) -> io.BufferedReader:
    """A regular file opened for reading, never blocking on the way: its type is checked before it
    is opened (:func:`existing_file`), it is opened with ``O_NONBLOCK`` and checked again on the
    descriptor (in case it was swapped in between). InputError naming it otherwise."""
    path = existing_file(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise InputError(path, NOT_REGULAR)
    return os.fdopen(fd, "rb")


def byte_source(path: str | Path, data: bytes | None = None) -> BinaryIO:
    """A file's encoded ``data`` as a file object, or when None the file ``path`` opened
    (:func:`open_regular`)."""
    return open_regular(path) if data is None else io.BytesIO(data)


def read_bytes(path: str | Path, expansion: int = 1) -> bytes:
    """A regular file's bytes (:func:`open_regular`); InputError naming it when it is missing, not
    a regular file, unreadable, or when ``expansion`` times its size (what parsing it may take,
    ``core.io.limits.PARSED_EXPANSION``) passes the memory limit (:mod:`core.io.limits`)."""
    with open_regular(path) as f:
        try:
            checked_bytes(path, "reading this file" if expansion == 1 else "parsing this file",
                          [os.fstat(f.fileno()).st_size, expansion])
            return f.read()
        except OSError as exc:
            raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
