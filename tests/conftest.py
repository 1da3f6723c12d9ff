"""Shared fixtures: paths to the real PLUS data and the probecal entry point."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PLUS = ROOT.parent / "shared" / "data" / "plus"
FCAL_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
FCAL_CALIBRATION = PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha"
FCAL_VALIDATION = PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha"
FCAL_RESULTS = PLUS / "TestImages" / "FreehandCalibration3NWires.results.xml"
VLCUS_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber.xml"
PROBECAL = Path(sys.executable).parent / "probecal"


@pytest.fixture(scope="session")
def plus_data() -> Path:
    if not PLUS.is_dir():
        pytest.skip("the PLUS test data (../shared/data/plus) is not present")
    return PLUS


def run_cli(*args, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run the installed ``probecal`` entry point the way a user would."""
    return subprocess.run(
        [str(PROBECAL), *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300
    )


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """Exit code 2, a single stderr line without a traceback, naming what went wrong."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
