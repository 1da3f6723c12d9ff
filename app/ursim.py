"""``probecal ursim``: the UR controller simulator (``core.robot.ursim.URSim``) as a program that
runs until SIGINT or SIGTERM, for ur_rtde clients that cannot share a process with it (also
``python -m probecal.app.ursim``; the tests' ``support.ursim_process``)."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading

from probecal.app.oneline import OneLineParser
from probecal.core.robot.ursim import (
    ARM_CALIBRATION_DEG,
    ARM_CALIBRATION_MM,
    CONTROLLER_VERSION,
    DEFAULT_HOST,
    FAULTS,
    URSim,
)


def _amount(text: str) -> float:
    """An option's amount: a finite number, not negative."""
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number of at least 0")
    return value


def main(argv: list[str] | None = None) -> int:
    """Run a URSim until SIGINT or SIGTERM; 2 if it cannot listen."""
    parser = OneLineParser(
        prog="probecal ursim",
        description="Simulated UR3 e-Series controller (dashboard 29999, RTDE 30004, "
        "script ports 30001-30003; 30001 and 30002 stream the kinematics it computes with) "
        "that ur_rtde can drive.",
    )
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to listen on (127.0.0.0/8)")
    parser.add_argument("--time-scale", type=_amount, default=1.0, help="wall s per robot s")
    parser.add_argument("--seed", type=int, default=0, help="repeatability noise seed")
    parser.add_argument("--repeatability-mm", type=_amount, default=0.03, help="RMS reach error")
    parser.add_argument("--arm-calibration-seed", type=int, metavar="SEED",
                        help="compute with a factory calibration drawn from SEED (each DH parameter within "
                        f"±{ARM_CALIBRATION_MM:g} mm or ±{ARM_CALIBRATION_DEG:g}°), not UR's table")
    parser.add_argument("--fault", choices=FAULTS, help="make the RTDE server misbehave")
    args = parser.parse_args(argv)
    try:
        sim = URSim(
            args.host,
            time_scale=args.time_scale,
            seed=args.seed,
            repeatability_mm=args.repeatability_mm,
            arm_calibration_seed=args.arm_calibration_seed,
            fault=args.fault,
            log=lambda text: print(f"URSim: {text}", file=sys.stderr, flush=True),
        ).start()
    except (OSError, ValueError) as exc:
        print(f"ursim: cannot start on {args.host}: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    print(f"URSim {CONTROLLER_VERSION} listening on {args.host}", flush=True)
    while not stop.wait(0.5):
        pass
    sim.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
