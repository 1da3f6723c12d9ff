"""A short run of the fuzzing harness (``tests/support/fuzz.py``, issue 35): hostile inputs to every
reader and subcommand end well (exit 0) or refused in one line (exit 2); none ends in a traceback,
hangs, leaves anything behind or takes memory past the limit. ``benchmarks/fuzz_inputs.py`` runs
the long one. Its corpus holds PLUS buffers and a device set, so it needs the real PLUS data."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

from tests.support.fuzz import FAILURES

ROOT = Path(__file__).resolve().parent.parent
CASES = 80


def test_a_short_fuzz_run_ends_every_hostile_input_well_or_in_one_line(plus_data, tmp_path):
    report = tmp_path / "fuzz.json"
    result = subprocess.run([sys.executable, "-m", "tests.support.fuzz", "--cases", str(CASES), "--seed", "11",
                             "--workers", "1", "--report", str(report)],
                            cwd=ROOT, capture_output=True, text=True, timeout=1200, check=False)
    assert report.is_file(), result.stdout + result.stderr
    data = json.loads(report.read_text())
    assert [o for o in data["valid"] if o["kind"] != "ok"] == []  # the corpus itself runs through
    assert [o for o in data["outcomes"] if o["kind"] in FAILURES] == [], result.stdout
    kinds = Counter(o["kind"] for o in data["outcomes"])
    assert len(data["outcomes"]) == CASES and kinds["refused"] > CASES // 4, kinds
