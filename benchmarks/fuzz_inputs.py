"""The long run of the fuzzing harness (issue 35): hostile inputs to every reader and every
subcommand (``tests/support/fuzz.py`` says which and how), each under ``PROBECAL_MAX_MEMORY_MB``
and a time limit; prints the cases tried and their outcomes, the most memory any took, and every
failure. Then how much memory parsing a text file may take, in times its size (what
``core.io.limits.PARSED_EXPANSION`` bounds).

Run: .venv/bin/python benchmarks/fuzz_inputs.py [--cases 2000] [--seed 0] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tracemalloc
import xml.etree.ElementTree as ET
from pathlib import Path

from probecal.core.io.jsonio import parse_json
from probecal.core.io.limits import PARSED_EXPANSION

ROOT = Path(__file__).resolve().parent.parent

TEXTS = {
    "JSON [[],...]": ("json", "[" + ",".join(["[]"] * 200_000) + "]"),
    'JSON [{"":[]},...]': ("json", "[" + ",".join(['{"":[]}'] * 100_000) + "]"),
    'JSON [{"":0},...]': ("json", "[" + ",".join(['{"":0}'] * 100_000) + "]"),
    "JSON [[[]],...]": ("json", "[" + ",".join(["[[]]"] * 100_000) + "]"),
    "XML <a/>...": ("xml", "<r>" + "<a/>" * 200_000 + "</r>"),
    "XML <a b=''/>...": ("xml", "<r>" + "<a b=''/>" * 100_000 + "</r>"),
    "XML <a><b/></a>...": ("xml", "<r>" + "<a><b/></a>" * 100_000 + "</r>"),
}


def expansion(kind: str, text: str) -> float:
    """Peak memory parsing ``text`` takes (as probecal parses it), in times its size."""
    data = text.encode()
    tracemalloc.start()
    value = parse_json(data, "bench") if kind == "json" else ET.fromstring(data)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    del value
    return peak / len(data)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--cases", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    report = ROOT / "out" / "fuzz_report.json"
    report.parent.mkdir(exist_ok=True)
    run = subprocess.run([sys.executable, "-m", "tests.support.fuzz", "--cases", str(args.cases), "--seed",
                          str(args.seed), "--workers", str(args.workers), "--report", str(report)],
                         cwd=ROOT, check=False)
    outcomes = json.loads(report.read_text())["outcomes"]
    slow = sorted(outcomes, key=lambda o: -o["seconds"])[:3]
    print("slowest: " + "; ".join(f"{o['case']} {o['seconds']:.1f} s ({o['kind']})" for o in slow))
    print(f"parsing, peak memory in times the file's size (PARSED_EXPANSION = {PARSED_EXPANSION}):")
    for name, (kind, text) in TEXTS.items():
        print(f"  {name:24s} {expansion(kind, text):5.1f}")
    sys.exit(run.returncode)


if __name__ == "__main__":
    main()
