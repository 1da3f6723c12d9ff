"""Frames paired with robot poses on a busy machine (issue target: 0 lost, 0 refused).

Two CPU-bound processes hog the cores while a scanner streams frames over OpenIGTLink at 30
frames/s, stamped on this machine's clock and rendered by the twin at the pose the robot had at
that instant (kept as truth). For each robot, the in-process twin and ``probecal ursim`` through
the real ur_rtde client (in its child process):

- a stop-and-go calibration sweep of 60 poses: frames recorded, refused and lost (poses left
  without a frame), and how far each recorded pose is from the planned one;
- a continuous stream of 600 frames while the robot sweeps back and forth at 20 mm/s: frames
  recorded, refused and lost, and how far each paired pose is from the truth (on the frames whose
  truth could be read sharply: a busy machine can take a while to read a pose). The twin's truth
  is exact; through ur_rtde the truth is the newest RTDE state, which arrives late by its delivery
  time on a loaded machine, while the pose stream is stamped by the controller's own clock, so
  there the figure bounds the pairing error from above.

Run: .venv/bin/python benchmarks/bench_pairing.py [--poses 60] [--frames 600] [--hogs 2]
"""

from __future__ import annotations

import argparse
import itertools
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from probecal.app.rigspec import make_rig
from probecal.app.ursimprocess import URSimProcess
from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.imagesource import SourceFrame
from probecal.core.acquisition.pairing import FramePairer
from probecal.core.acquisition.plan import PoseRanges
from probecal.core.acquisition.rig import Recording
from probecal.core.acquisition.sweep import record_stream
from probecal.core.geometry.transforms import make_transform, transform_error
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import SessionWriter, load_session
from probecal.core.robot.contract import RobotError
from probecal.core.robot.ur3 import MotionLimits

HOST = "127.0.0.5"
RATE_HZ = 30.0
SWEEP_MM = 40.0
SWEEP_SPEED = MotionLimits(linear_speed_mm_s=20.0)
TRUTH_READ_S = 0.005
"""A frame's truth counts when reading its pose took at most this long (0.1 mm at 20 mm/s)."""


@contextmanager
def hogs(n: int) -> Iterator[None]:
    """``n`` CPU-bound processes beside the benchmark."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


@contextmanager
def scanner_stream(rig, truth: dict) -> Iterator[IgtlSource]:
    """The twin's scanner imaging at the robot's pose, streamed at RATE_HZ like a PLUS server.

    Each frame is stamped at the middle of the time it took to read the pose it shows;
    ``truth[k]`` is (that pose, how long reading it took, s)."""
    robot = rig.robot

    def frames():
        rng = np.random.default_rng(0)
        for k in itertools.count():
            before = time.time()
            try:
                pose = robot.tool_to_base()
            except RobotError:
                return
            after = time.time()
            truth[k] = pose, after - before
            yield SourceFrame(rig.scanner.calibration_frame(pose, rng)[0], (before + after) / 2, k)

    with IgtlStreamer() as streamer:
        streamer.play(frames(), rate_hz=RATE_HZ)
        with IgtlSource("127.0.0.1", streamer.port, transform_device=None) as source:
            yield source


def stop_and_go(robot_spec: str, poses: int, out: Path) -> str:
    rig = make_rig(robot_spec, "sim", seed=0, time_scale=1.0)
    rig.open()
    try:
        plan = rig.calibration_plan(poses, PoseRanges(), MotionLimits())
        with scanner_stream(rig, {}) as source:
            rig.source = source
            outcome = Recording(rig, "calibration", out, plan, MotionLimits()).run()
            rig.source = None
    finally:
        rig.close()
    session = load_session(out)
    offsets = [np.linalg.norm(r.tool_to_base[:3, 3] - plan.poses[r.extra["plan_index"]][:3, 3])
               for r in session.records]
    lost = len(plan.poses) - outcome.recorded - outcome.skipped
    why = f"; ended early: {outcome.error}" if outcome.error else ""
    return (f"stop-and-go {len(plan.poses)} poses: {outcome.recorded} recorded, {outcome.refused} refused, "
            f"{lost} lost; recorded pose to planned pose max {max(offsets):.3f} mm{why}")


def continuous(robot_spec: str, frames: int, out: Path) -> str:
    rig = make_rig(robot_spec, "sim", seed=0, time_scale=1.0)
    rig.open()
    robot, truth, done = rig.robot, {}, threading.Event()
    start = robot.tool_to_base()
    ends = [start @ make_transform(np.eye(3), [SWEEP_MM, 0.0, 0.0]), start]

    def sweep_back_and_forth():
        for target in itertools.cycle(ends):
            if done.is_set():
                return
            robot.move_linear(target, SWEEP_SPEED)

    mover = threading.Thread(target=sweep_back_and_forth, daemon=True)
    try:
        mover.start()
        with scanner_stream(rig, truth) as source, SessionWriter(out, Manifest(kind="volume")) as writer:
            outcome = record_stream(source, FramePairer(robot), writer, frames)
        done.set()
        mover.join()
    finally:
        done.set()
        rig.close()
    session = load_session(out)
    reads = np.array([truth[r.source_index][1] for r in session.records])
    sharp = [r for r, read in zip(session.records, reads) if read <= TRUTH_READ_S]
    errors = np.array([transform_error(r.tool_to_base, truth[r.source_index][0]) for r in sharp])
    indices = [r.source_index for r in session.records]
    lost = frames - outcome.recorded - outcome.refused
    gaps = sum(b - a - 1 for a, b in zip(indices, indices[1:]))
    why = f"; ended early: {outcome.error}" if outcome.error else ""
    return (f"continuous {frames} frames at {RATE_HZ:g}/s, moving at {SWEEP_SPEED.linear_speed_mm_s:g} mm/s: "
            f"{outcome.recorded} recorded, {outcome.refused} refused, {lost} lost ({gaps} skipped in the sequence)\n"
            f"    paired pose to truth, on the {len(sharp)} frames whose truth was read within "
            f"{TRUTH_READ_S * 1000:g} ms: mean {errors[:, 0].mean():.3f} mm, 95th percentile "
            f"{np.percentile(errors[:, 0], 95):.3f} mm, max {errors[:, 0].max():.3f} mm / {errors[:, 1].max():.3f} deg "
            f"(reading the truth took {np.median(reads) * 1000:.1f} ms median, "
            f"{reads.max() * 1000:.0f} ms at most){why}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--hogs", type=int, default=2, help="CPU-bound processes running beside")
    args = parser.parse_args()
    print(f"{args.hogs} CPU-bound processes beside the benchmark on a {len(__import__('os').sched_getaffinity(0))}"
          f"-core machine", flush=True)
    with tempfile.TemporaryDirectory() as tmp, hogs(args.hogs):
        tmp = Path(tmp)
        print("twin robot (in-process):", flush=True)
        print("  " + stop_and_go("sim", args.poses, tmp / "sim-cal"), flush=True)
        print("  " + continuous("sim", args.frames, tmp / "sim-stream"), flush=True)
        print("probecal ursim + ur_rtde (child process):", flush=True)
        with URSimProcess(HOST, time_scale=1.0):
            print("  " + stop_and_go(f"ur:{HOST}", args.poses, tmp / "ur-cal"), flush=True)
            print("  " + continuous(f"ur:{HOST}", args.frames, tmp / "ur-stream"), flush=True)


if __name__ == "__main__":
    main()
