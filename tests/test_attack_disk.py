"""A full disk: every command that writes says so in one line (exit 2), naming the device and the
file, and leaves nothing half-written. The disk is a small tmpfs mounted in a mount namespace of
the command's own (``unshare``), so no root is needed where user namespaces are allowed."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import cv2
import pytest

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.io.session import load_session
from tests.support.cli import PROBECAL
from tests.support.refusals import assert_one_line_error

DISK_KB = 64
# Mount a tmpfs on $DISK, run the command, then list what is on the disk and any hidden file
# (a temporary one left behind) in it.
SCRIPT = ('mount -t tmpfs -o size={kb}k tmpfs "$DISK" && {prepare} "$@"; code=$?; echo --left-- >&2; '
          'ls -A "$DISK" >&2; echo --hidden-- >&2; find "$DISK" -mindepth 2 -name ".*" >&2; exit $code')


def _unshare() -> str | None:
    """The unshare tool, when this machine lets it mount a tmpfs in a namespace of its own."""
    tool = shutil.which("unshare")
    if tool is None:
        return None
    probe = subprocess.run([tool, "--user", "--map-root-user", "--mount", "sh", "-c",
                            "mount -t tmpfs -o size=64k tmpfs /mnt"], capture_output=True)
    return tool if probe.returncode == 0 else None


UNSHARE = _unshare()
pytestmark = pytest.mark.skipif(UNSHARE is None, reason="this machine allows no tmpfs in a mount namespace "
                                                        "(unshare --user --mount), so no small disk to fill")


def on_full_disk(disk: Path, args: list, fill: bool = False, copy: Path | None = None, kb: int = DISK_KB) -> tuple:
    """Run ``probecal ARGS`` with a tmpfs of ``kb`` on ``disk`` (``copy`` copied onto it first, and
    the rest of it filled when ``fill``); the result, what is on the disk (names at its top) and
    any hidden file below them."""
    disk.mkdir(exist_ok=True)
    prepare = (f'cp -r "{copy}" "$DISK"/ && ' if copy else "") \
        + ('{ cat /dev/zero > "$DISK/fill" 2>/dev/null; true; } && ' if fill else "")
    command = [UNSHARE, "--user", "--map-root-user", "--mount", "sh", "-c",
               SCRIPT.format(kb=kb, prepare=prepare), "sh", str(PROBECAL), *map(str, args)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "DISK": str(disk)})
    error, _, rest = result.stderr.partition("--left--\n")
    left, _, hidden = rest.partition("--hidden--\n")
    return subprocess.CompletedProcess(result.args, result.returncode, result.stdout, error), left.split(), \
        hidden.split()


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("twin") / "cal"
    simulate_calibration(folder, n_poses=12, seed=3, noise="realistic")
    return folder


def test_a_simulation_onto_a_full_disk_says_so_and_leaves_nothing(tmp_path):
    disk = tmp_path / "disk"
    result, left, _ = on_full_disk(disk, ["simulate", "calibration", disk / "cal", "--poses", "12"])
    assert_one_line_error(result, f"no space left on {disk} writing {disk / 'cal'}")
    assert left == []


def test_an_export_onto_a_full_disk_says_so_and_leaves_nothing(tmp_path, session):
    disk = tmp_path / "disk"
    result, left, _ = on_full_disk(disk, ["export-plus", session, disk / "out.igs.mha"])
    assert_one_line_error(result, f"no space left on {disk} writing {disk / 'out.igs.mha'}")
    assert left == []


def test_a_calibration_on_a_full_disk_says_so_and_keeps_the_session(tmp_path, session):
    disk = tmp_path / "disk"
    result, left, hidden = on_full_disk(disk, ["calibrate", disk / "cal"], fill=True, copy=session, kb=1024)
    assert_one_line_error(result, f"no space left on {disk} writing {disk / 'cal'}")
    assert sorted(left) == ["cal", "fill"] and hidden == []


def test_an_import_onto_a_full_disk_says_so_and_leaves_nothing(tmp_path, session):
    twin = load_session(session)
    images = tmp_path / "images"
    images.mkdir()
    for i in range(len(twin)):
        cv2.imwrite(str(images / f"img{i + 1}.png"), twin.image(i))
    table = tmp_path / "poses.csv"
    table.write_text("".join(",".join(repr(float(v)) for v in pose.ravel()) + "\n" for pose in twin.poses()))
    disk = tmp_path / "disk"
    result, left, _ = on_full_disk(disk, ["import-frames", images, "--poses", table, disk / "out", "--spacing", "0.1"])
    assert_one_line_error(result, f"no space left on {disk} writing {disk / 'out'}")
    assert left == []


def test_a_sweep_that_fills_the_disk_ends_early_saying_so_and_keeps_its_frames(tmp_path):
    """The disk fills mid-sweep: the sweep ends early in one line that says so as every command
    does, and the session folder with the frames recorded before it stays (the fuzzing harness
    reads such a session back whole, on the disk it fills)."""
    disk = tmp_path / "disk"
    result, left, hidden = on_full_disk(disk, ["sweep", "calibration", disk / "sw", "--poses", "3",
                                               "--time-scale", "0"], copy=None, kb=64)
    assert result.returncode == 1, result.stderr
    line, = result.stderr.strip().splitlines()[-1:]
    assert line.startswith(f"probecal: sweep ended early (no space left on {disk} writing {disk / 'sw'}"), line
    assert "Traceback" not in result.stderr and left == ["sw"] and hidden == []
