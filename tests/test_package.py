"""probecal installs anywhere (issue 34): a wheel built from the checkout holds every shipped
asset, and installed outside the checkout into a fresh virtual environment its ``probecal``
simulates, calibrates, lists and exports phantoms, reconstructs and serves, run from a folder
outside the checkout.

The fresh environment takes its dependencies from the test's own (a path file naming its
site-packages, which leaves out the checkout's editable install), so that only probecal comes
from the wheel and nothing is downloaded but the build's own setuptools."""

from __future__ import annotations

import os
import site
import subprocess
import sys
import urllib.request
import zipfile
from pathlib import Path

import pytest

from tests.support.waiting import wait_until

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)], check=True,
                   capture_output=True, timeout=600)
    return next(out.glob("probecal-*.whl"))


def test_the_wheel_holds_every_shipped_asset(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = [p.relative_to(ROOT).as_posix() for p in (ROOT / "static").rglob("*")
               if p.is_file() and "__pycache__" not in p.parts]
    assert len(shipped) >= 5
    missing = [name for name in shipped if f"probecal/{name}" not in names]
    assert not missing, missing


@pytest.mark.slow
def test_the_installed_package_works_outside_the_checkout(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(env_dir)], check=True, timeout=300)
    python = env_dir / "bin" / "python"
    packages = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                   check=True, capture_output=True, text=True).stdout.strip())
    (packages / "probecal_test_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True,
                   capture_output=True, timeout=300)
    work = tmp_path / "elsewhere"
    work.mkdir()
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PROBECAL_PLUS_DATA")}

    def probecal(*args: str) -> subprocess.CompletedProcess:
        result = subprocess.run([str(env_dir / "bin" / "probecal"), *args], cwd=work, env=clean, capture_output=True,
                                text=True, timeout=300)
        assert result.returncode == 0, (args, result.stderr)
        return result

    where = subprocess.run([str(python), "-c", "import probecal.core as c; print(c.__file__, c.STATIC_DIR)"],
                           cwd=work, env=clean, check=True, capture_output=True, text=True).stdout
    assert str(ROOT) not in where and str(env_dir) in where, where
    assert "thesis-4layer" in probecal("phantom", "list").stdout
    probecal("phantom", "export", "fcal-2.0", "fcal")
    assert any((work / "fcal").iterdir())
    probecal("simulate", "calibration", "cal", "--poses", "12", "--noise", "realistic")
    probecal("calibrate", "cal", "--out", "cal.json")
    assert (work / "cal.json").is_file() and (work / "cal.xml").is_file()
    probecal("simulate", "volume", "vol", "--frames-per-pass", "20")
    probecal("reconstruct", "vol", "--calibration", "cal.json", "--out", "rec")
    assert (work / "rec" / "volume.nrrd").is_file()
    port = "18731"
    server = subprocess.Popen([str(env_dir / "bin" / "probecal"), "serve", "--port", port, "--sessions", "sessions"],
                              cwd=work, env=clean, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert server.stdout is not None
        assert "probecal console on" in server.stdout.readline()
        page = wait_until(lambda: _get(f"http://127.0.0.1:{port}/"), "the console's page")
        assert b"<html" in page.lower()
    finally:
        server.terminate()
        server.wait(30)


def _get(url: str) -> bytes | None:
    try:
        with urllib.request.urlopen(url, timeout=5) as response:
            return response.read()
    except OSError:
        return None
