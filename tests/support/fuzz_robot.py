"""The fuzzing harness's hostile robot controllers: joints, TCP and timestamps that are NaN, huge,
running backwards or inconsistent, and KinematicsInfo packets that lie.

A hostile controller is a URSim whose streamed state lies (``core.robot.ursim.HostileState``), run
in a child process: ur_rtde keeps the GIL while it waits on the network, so it cannot share a
process with the simulator it talks to. A fuzz case forks its controller from the case's own
child, on a loopback address of its own (:func:`case_address`), and records a sweep from it
through the command line, stepwise and continuous, the controller lying from the start or from a
motion on.
"""

from __future__ import annotations

import contextlib
import gc
import math
import multiprocessing
import os
import struct
from collections.abc import Iterator
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from probecal.core.robot.armkinematics import kinematics_info
from probecal.core.robot.primary import KINEMATICS_INFO, MAX_PACKAGE_BYTES, ROBOT_STATE, frame, robot_state
from probecal.core.robot.ur3 import UR3, ArmModel
from probecal.core.robot.ursim import HostileState, URSim, arm_calibration
from tests.support.fuzz import Case, Runner, command_line, read_back

READY_TIMEOUT_S = 30.0
TURN = "turn hostile"


def _serve(host: str, hostile: HostileState, time_scale: float, pipe: Connection) -> None:
    """The child: a hostile URSim on ``host``, turned hostile when the pipe says so, until it is
    killed; what failed to start, sent back."""
    try:
        sim = URSim(host, time_scale=time_scale, hostile=hostile).start()
    except (OSError, ValueError) as exc:
        pipe.send(f"URSim on {host} did not start: {exc}")
        return
    pipe.send("")
    while pipe.recv() == TURN:
        sim.turn_hostile()
        pipe.send("")


class HostileController:
    """A URSim on ``host`` streaming ``hostile`` (``core.robot.ursim.HostileState``), in a child
    process started by ``method`` (``fork`` only from a process without threads: a fuzz case's
    child); ``turn_hostile`` starts its lies at once."""

    def __init__(self, host: str, hostile: HostileState, time_scale: float = 0.05, method: str = "spawn"):
        self.host = host
        context = multiprocessing.get_context(method)
        self._pipe, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(host, hostile, time_scale, child), daemon=True)
        self._process.start()
        child.close()
        try:
            self._answer()
        except BaseException:
            self.stop()
            raise

    def _answer(self) -> None:
        if not self._pipe.poll(READY_TIMEOUT_S):
            raise RuntimeError(f"URSim on {self.host} did not answer within {READY_TIMEOUT_S:g} s")
        problem = self._pipe.recv()
        if problem:
            raise RuntimeError(problem)

    def turn_hostile(self) -> None:
        self._pipe.send(TURN)
        self._answer()

    def stop(self) -> None:
        self._process.kill()
        self._process.join()
        self._pipe.close()


@contextlib.contextmanager
def hostile_controller(host: str, hostile: HostileState, time_scale: float = 0.05,
                       method: str = "spawn") -> Iterator[HostileController]:
    """A :class:`HostileController`, killed on exit."""
    controller = HostileController(host, hostile, time_scale, method)
    try:
        yield controller
    finally:
        controller.stop()


CASE_HOSTS = (250, 255, 16, 256)
"""Where a case's controller listens: 127.A.B.C with A in 250-254 and B in 16-255, apart from the
tests' own addresses (``tests.support.loopback``: 127.16-255.7-12.*) and URSim's default
(127.0.0.2)."""


def case_address(pid: int) -> str:
    """The loopback address of the case whose child has process id ``pid``: cases that run at the
    same time have their own, as their pids differ by less than the addresses there are."""
    first, last, low, high = CASE_HOSTS
    per_first = (high - low) * 254
    k = pid % ((last - first) * per_first)
    return f"127.{first + k // per_first}.{low + k // 254 % (high - low)}.{1 + k % 254}"


QUICK = 0.05
"""Wall seconds per robot second of a case's controller: twenty times faster than a UR3."""
SWEEP_FROM_CONTROLLER = ("sweep", "calibration", "{in}/sw", "--robot", "ur:{host}", "--poses", "4")
MOTIONS = {"stepwise": (), "continuous": ("--motion", "continuous")}
WHEN = {"at connect": (0, 0.0), "from the 2nd motion": (2, 0.0), "mid 3rd motion": (3, 0.05)}
"""When a controller starts to lie: (the motions its arm has begun, then s of its clock)."""
NAN, INF = math.nan, math.inf
JOINT_LIES = (NAN, INF, -INF, 1e300, -1e10, 200.0, 0.3, 1e-300)
"""Added to one joint: not numbers, past any joint's range, off the TCP (0.3 rad), or nothing."""
TCP_LIES = {"x": (NAN, INF, 1e300, 1e7, 0.05, 1e-7), "rx": (NAN, -INF, 1e300, 7.0, 0.2, 1e-9)}
"""Added to the TCP's x (m) or its rotation vector's x (rad): not numbers, past any arm's reach
(1e7 m: 1e10 mm) or any rotation, off the joints' flange (5 cm, 0.2 rad), or within noise."""
CLOCK_LIES = (-5.0, -0.01, NAN, INF, -INF, 1e10, 1e300, 3.0)
"""Added to the timestamps: running backwards (by 5 s, or by 5 of its 2 ms cycles), not numbers,
leaping ahead, or a step it may take."""


def _kinematics_lies() -> dict[str, bytes]:
    """RobotState messages whose KinematicsInfo lies, by name."""
    truth = kinematics_info(ArmModel(UR3))
    other = kinematics_info(ArmModel(UR3, arm_calibration(7)))
    info = truth.encode()
    return {
        "nan": robot_state(replace(truth, a=truth.a * np.nan).encode()),
        "infinite": robot_state(replace(truth, theta=truth.theta + np.inf).encode()),
        "1e300 mm": robot_state(replace(truth, d=truth.d + 1e300).encode()),
        "another arm's": robot_state(other.encode()),
        "cut short": robot_state(info)[:-40],
        "of another size": robot_state(frame(KINEMATICS_INFO, info[5:-9])),
        "past its message": robot_state(struct.pack(">iB", 400, KINEMATICS_INFO) + info[5:]),
        "in a package past the limit": struct.pack(">iB", MAX_PACKAGE_BYTES + 1, ROBOT_STATE) + bytes(1000),
        "in a package of negative size": struct.pack(">iB", -5, ROBOT_STATE),
    }


def robot_cases() -> list[Case]:
    """A sweep, stepwise and continuous, from each hostile controller: its joints, its TCP, its
    timestamps lying from each moment of :data:`WHEN`, its KinematicsInfo from the start."""
    lies: dict[str, list[HostileState]] = {}
    for k, value in enumerate(JOINT_LIES):
        joints = tuple(value if j == k % 6 else 0.0 for j in range(6))
        lies[f"joints[{k % 6}] + {value!r}"] = [HostileState(joints=joints, after_moves=moves, after_s=after_s)
                                                for moves, after_s in WHEN.values()]
    for axis, values in TCP_LIES.items():
        for value in values:
            tcp = tuple(value if name == axis else 0.0 for name in ("x", "y", "z", "rx", "ry", "rz"))
            lies[f"TCP {axis} + {value!r}"] = [HostileState(tcp=tcp, after_moves=moves, after_s=after_s)
                                               for moves, after_s in WHEN.values()]
    for value in CLOCK_LIES:
        lies[f"timestamp + {value!r}"] = [HostileState(clock_s=value, after_moves=moves, after_s=after_s)
                                          for moves, after_s in WHEN.values()]
    for name, state in _kinematics_lies().items():
        lies[f"KinematicsInfo {name}"] = [HostileState(robot_state=state)]
    cases = []
    for what, states in lies.items():
        for state, when in zip(states, WHEN):
            for motion, extra in MOTIONS.items():
                cases.append(Case(f"robot controller {what}{'' if state.robot_state else ' ' + when}: sweep {motion}",
                                  (*SWEEP_FROM_CONTROLLER, *extra), (), run=from_controller(state)))
    return cases


def from_controller(hostile: HostileState) -> Runner:
    """The command line on ``argv`` with ``{host}`` the address of a controller that lies as
    ``hostile`` says, forked from the case's child. A session the sweep kept (exit 0 or 1) must
    read back whole, its pose stream too; one a refused sweep made is left behind."""
    def run(argv: list[str], folder: Path) -> int:
        from probecal.core.io.session import read_pose_stream

        host = case_address(os.getpid())
        with hostile_controller(host, hostile, QUICK, method="fork"):
            code = command_line([a.replace("{host}", host) for a in argv], folder)
        gc.collect()  # the child ends without finalizers: the robot's ur_rtde log goes with what held it
        session = folder / "sw"
        if session.exists() and code in (0, 1):
            read_pose_stream(session)
            read_back(session)
        return code
    return run
