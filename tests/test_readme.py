"""The README's command block is a tutorial that runs: top to bottom, as written, in a fresh
folder (issue 18), with the PLUS data where the setting says it is."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import ROOT


def command_block() -> str:
    """The first ```bash block under "## Command line"."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Command line"):]
    return re.search(r"```bash\n(.*?)```", section, re.DOTALL).group(1)


def test_the_command_block_names_no_placeholder():
    block = command_block()
    assert "..." not in block
    assert "stepper.igs.mha" not in block


@pytest.mark.slow
@pytest.mark.timeout(900)  # about 200 s alone; the suite's other worker may hold the second core
def test_the_readme_command_block_runs_top_to_bottom(plus_data, tmp_path):
    script = tmp_path / "tutorial.sh"
    script.write_text("set -euo pipefail\n" + command_block())
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "PROBECAL_PLUS_DATA": str(Path(plus_data).resolve())}
    result = subprocess.run(["bash", str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=880)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    for made in ("sessions/cal/truth.json", "cal.json", "cal.xml", "fcal.json", "lag.json", "cont.json",
                 "out/vol/report.json", "out/spine/volume.nrrd", "cal.igs.mha", "out/phantom/frame.stl",
                 "sessions/cal/phantom_check.json"):
        assert (tmp_path / made).is_file(), made
    assert "PRE3D" in result.stdout and "image latency" in result.stdout
