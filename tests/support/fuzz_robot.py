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


def robot_cases() -> list[Case]:
    return []
