"""How soon the console notices a page gone during a sweep (the dead-man rule), and how soon the
robot then stands still: for a page closed cleanly, a close frame followed by silence, a page that
stops reading, and one whose network freezes, each a raw page that started a stop-and-go sweep on
the simulator; ``--browser`` adds Chromium tabs closed and frozen. Prints, per way of going, the
median and worst time from the page's last word to the sweep held and to the robot still, against
the heartbeat's bound. The trials are ``tests/support/deadman_timing.py`` (they drive the test
suite's raw page and freezing relay).

Run: .venv/bin/python benchmarks/bench_deadman.py [--trials 5] [--browser]
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    run = subprocess.run([sys.executable, "-m", "tests.support.deadman_timing", *sys.argv[1:]], cwd=ROOT, check=False)
    sys.exit(run.returncode)


if __name__ == "__main__":
    main()
