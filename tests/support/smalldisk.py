"""A small disk for a process of its own: a tmpfs of a few kilobytes mounted in a user and mount
namespace that the calling process enters (no root needed where the machine allows user
namespaces), so that a command's writes run out of space.

Enter it in a forked, single-threaded child: the namespaces are the whole process's, and
``unshare`` refuses a process with threads."""

from __future__ import annotations

import contextlib
import ctypes
import os
import traceback
from pathlib import Path

CLONE_NEWNS = 0x00020000
CLONE_NEWUSER = 0x10000000
MS_REC = 0x4000
MS_PRIVATE = 1 << 18


def _check(result: int, what: str) -> None:
    if result != 0:
        code = ctypes.get_errno()
        raise OSError(code, f"{what}: {os.strerror(code)}")


def enter_small_disk(disk: Path, kb: int) -> None:
    """Mount a tmpfs of ``kb`` kilobytes on the folder ``disk``, seen by this process alone."""
    libc = ctypes.CDLL(None, use_errno=True)
    uid, gid = os.getuid(), os.getgid()
    _check(libc.unshare(CLONE_NEWUSER | CLONE_NEWNS), "unshare")
    Path("/proc/self/setgroups").write_text("deny")
    Path("/proc/self/uid_map").write_text(f"0 {uid} 1")
    Path("/proc/self/gid_map").write_text(f"0 {gid} 1")
    _check(libc.mount(b"none", b"/", None, MS_REC | MS_PRIVATE, None), "mount --make-rprivate /")
    _check(libc.mount(b"tmpfs", str(disk).encode(), b"tmpfs", 0, f"size={kb}k".encode()), f"mount {disk}")


def fill(disk: Path) -> None:
    """Write zeros to a file on ``disk`` until it is full."""
    with contextlib.suppress(OSError), open(disk / "fill", "wb") as out:
        while True:
            out.write(bytes(4096))
            out.flush()


def small_disk_refusal() -> str | None:
    """Why this machine allows no small disk (None when it does): tried in a forked child."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read)
        try:
            probe = Path(f"/tmp/probecal-small-disk-{os.getpid()}")
            probe.mkdir()
            enter_small_disk(probe, 16)
            message = b""
        except OSError as exc:
            message = f"user and mount namespaces are not allowed here ({exc.strerror or exc})".encode()
        except BaseException:
            message = traceback.format_exc().encode()
        os.write(write, message)
        os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        said = pipe.read().decode()
    os.waitpid(pid, 0)
    with contextlib.suppress(OSError):
        os.rmdir(f"/tmp/probecal-small-disk-{pid}")
    return said or None

