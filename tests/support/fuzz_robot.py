"""The fuzzing harness's hostile robot controllers: joints, TCP and timestamps that are NaN, huge,
running backwards or inconsistent, and KinematicsInfo packets that lie.

A hostile controller is a URSim whose streamed state lies (``core.robot.ursim.HostileState``), run
in a child process: ur_rtde keeps the GIL while it waits on the network, so it cannot share a
process with the simulator it talks to.
"""

from __future__ import annotations

import contextlib
import multiprocessing
from collections.abc import Iterator
from multiprocessing.connection import Connection

from probecal.core.robot.ursim import HostileState, URSim
from tests.support.fuzz import Case

READY_TIMEOUT_S = 30.0


def _serve(host: str, hostile: HostileState, time_scale: float, ready: Connection) -> None:
    """The child: a hostile URSim on ``host`` until it is killed; what failed, sent back."""
    try:
        URSim(host, time_scale=time_scale, hostile=hostile).start()
    except (OSError, ValueError) as exc:
        ready.send(f"URSim on {host} did not start: {exc}")
        return
    ready.send("")
    ready.recv()  # until the parent closes its end or kills this process


@contextlib.contextmanager
def hostile_controller(host: str, hostile: HostileState, time_scale: float = 0.05,
                       method: str = "spawn") -> Iterator[None]:
    """A URSim on ``host`` that streams ``hostile``, in a child process started by ``method``
    (``fork`` only from a process without threads: a fuzz case's child), killed on exit."""
    context = multiprocessing.get_context(method)
    parent, child = context.Pipe()
    process = context.Process(target=_serve, args=(host, hostile, time_scale, child), daemon=True)
    process.start()
    child.close()
    try:
        if not parent.poll(READY_TIMEOUT_S):
            raise RuntimeError(f"URSim on {host} did not start within {READY_TIMEOUT_S:g} s")
        problem = parent.recv()
        if problem:
            raise RuntimeError(problem)
        yield
    finally:
        process.kill()
        process.join()
        parent.close()


def robot_cases() -> list[Case]:
    return []
