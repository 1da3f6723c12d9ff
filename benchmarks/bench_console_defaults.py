"""The console at its own defaults on the simulator (issue 34, part 4), without a browser: does
Measure latency measure every time (extending its motion when a run shows too few echoes), how
close the first time-left estimate of each sweep comes to the time it took, what Reconstruct's
strip says after its frames, and whether Check phantom can decide at the default poses.

Run: .venv/bin/python benchmarks/bench_console_defaults.py [--latency-runs 16] [--seed 0]
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

from probecal.app.console.server import launch

LEFT = re.compile(r"about (\d+) s left")


def watch(console, job) -> tuple[float, float | None, list[str]]:
    """Run a console job at its defaults; the wall time it took, the first time-left estimate the
    strip showed (s) and every different counter line it showed."""
    started = time.monotonic()
    job()
    first, lines = None, []
    while console.busy:
        line = console.panel.counter.text
        if not lines or lines[-1] != line:
            lines.append(line)
        if first is None and (match := LEFT.search(line)):
            first = float(match.group(1)) + (time.monotonic() - started)  # the whole sweep, as first told
        time.sleep(0.01)
    console.wait()
    return time.monotonic() - started, first, lines


def latency(runs: int, seed: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        console = launch(port=0, sessions_dir=Path(tmp), seed=seed)
        try:
            console.connect()
            console.wait()
            measured, extended, errors = 0, 0, []
            for _ in range(runs):
                before = set(Path(tmp).glob("temporal-*"))
                console.measure_latency()
                console.wait()
                made = set(Path(tmp).glob("temporal-*")) - before
                if "Image latency" in console.panel.status.text:
                    measured += 1
                    errors.append(abs(console.rig.latency_s - console.rig.twin.image_latency_s) * 1000)
                extended += len(made) > 1
            print(f"Measure latency at the console's defaults: measured in {measured} of {runs} runs "
                  f"({extended} extended their motion), error {max(errors, default=float('nan')):.2f} ms at most")
        finally:
            console.close()


def sweeps(seed: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        console = launch(port=0, sessions_dir=Path(tmp), seed=seed)
        try:
            console.connect()
            console.wait()
            for name, job in (("Start sweep", console.start_sweep), ("Scan volume", console.scan_volume)):
                took, first, _ = watch(console, job)
                told = "none shown" if first is None else f"{first:.1f} s"
                print(f"{name} at the defaults: took {took:.1f} s; the first estimate of the whole sweep, {told}")
            console.calibrate()
            console.wait()
            took, _, lines = watch(console, console.reconstruct)
            steps = [line for line in lines if not re.match(r"Reconstructing: \d+ / \d+", line)]
            print(f"Reconstruct: {took:.1f} s; after its frames the strip said: {' | '.join(steps)}")
            console.check_phantom()
            console.wait()
            check = console.phantom_check
            if check is None:
                print(f"Check phantom: {console.panel.status.text}")
                return
            verdicts = [check.verdict(w) for w in check.wires]
            print(f"Check phantom at the default {check.frames_used} frames: "
                  + ", ".join(f"{verdicts.count(v)} {v}" for v in ("off", "within", "unsure"))
                  + f"; every wire seen in all {max(w.runs for w in check.wires)} runs: "
                  + str(all(w.runs == max(x.runs for x in check.wires) for w in check.wires)))
        finally:
            console.close()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--latency-runs", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    latency(args.latency_runs, args.seed)
    sweeps(args.seed)


if __name__ == "__main__":
    sys.exit(main())
