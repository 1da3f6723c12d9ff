"""ur_rtde in a child process, so that a controller that dies mid-command cannot freeze us.

ur_rtde's Python calls keep the GIL while they wait on the network, and a command whose answer
never comes blocks for minutes: in-process, the console, its Stop button and the sweep would all
freeze with it. Here a child process owns the :class:`core.robot.urrobot.URRobot`; every call goes over a
pipe with a deadline, and a child that misses one is killed (which also drops its connection to
the controller) and the call fails with a RobotError naming the host. ur_rtde's own chatter on
stdout and stderr goes to the child's log, not to our terminal. The robot's pose stream is sampled
in the child, where the controller's data arrives, and fetched from it in batches
(``poses_since``), so a busy parent process loses no pose.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
import threading
import time
import weakref
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from probecal.core.robot.contract import RobotError
from probecal.core.robot.posestream import PoseSamples
from probecal.core.robot.ur3 import ArmModel, MotionLimits

CALL_TIMEOUT_S = 5.0
PATH_POSE_TIMEOUT_S = 0.5
"""What each waypoint adds to a path's call: ur_rtde hands a path to the controller one waypoint
at a time, each a round trip, which on a busy machine took a 12-pose sweep past ``CALL_TIMEOUT_S``."""
CONNECT_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 2.0
WAIT_POLL_S = 0.005
"""How often ``wait`` asks the child whether the move is over; the pipe is free in between."""


def _serve(connection: Connection, host: str, connect_timeout_s: float, log_path: str) -> None:
    """The child: run URRobot calls from the pipe until it closes."""
    log = os.open(log_path, os.O_WRONLY | os.O_APPEND)
    os.dup2(log, 1)
    os.dup2(log, 2)
    from probecal.core.robot.urrobot import URRobot

    robot = URRobot(host, connect_timeout_s)
    while True:
        try:
            name, args = connection.recv()
        except EOFError:
            break
        try:
            result = robot.connected if name == "connected" else getattr(robot, name)(*args)
            connection.send(("ok", result))
        except Exception as exc:  # every failure goes back to the caller, whatever its type
            connection.send(("error", exc))
    robot.disconnect()


class URRobotProcess:
    """A ``Robot`` for a UR controller at ``host``, with ur_rtde running in a child process."""

    def __init__(self, host: str, call_timeout_s: float = CALL_TIMEOUT_S, connect_timeout_s: float = 3.0):
        self.host = host
        self._call_timeout_s = call_timeout_s
        self._connect_timeout_s = connect_timeout_s
        self._lock = threading.Lock()
        self._process: multiprocessing.process.BaseProcess | None = None
        self._pipe: Connection | None = None
        handle, self._log_path = tempfile.mkstemp(prefix="ur_rtde-", suffix=".log")
        os.close(handle)
        weakref.finalize(self, os.unlink, self._log_path)
        self._connected = False

    @property
    def connected(self) -> bool:
        """Connected, and the child's link to the controller is still up."""
        if not (self._connected and self._process is not None and self._process.is_alive()):
            return False
        try:
            return bool(self._call("connected"))
        except RobotError:
            return False

    def log(self) -> str:
        """What ur_rtde printed in the child."""
        with open(self._log_path, errors="replace") as log:
            return log.read()

    def connect(self) -> None:
        if self.connected:
            return
        self._end_child()
        context = multiprocessing.get_context("spawn")
        self._pipe, child_end = context.Pipe()
        self._process = context.Process(target=_serve, name=f"ur_rtde {self.host}", daemon=True,
                                        args=(child_end, self.host, self._connect_timeout_s, self._log_path))
        self._process.start()
        child_end.close()
        self._call("connect", timeout_s=CONNECT_TIMEOUT_S)
        self._connected = True

    def disconnect(self) -> None:
        if self.connected:
            try:
                self._call("disconnect", timeout_s=CALL_TIMEOUT_S)
            except RobotError:
                pass
        self._end_child()

    def tool_to_base(self) -> np.ndarray:
        return self._call("tool_to_base")

    def joints(self) -> np.ndarray:
        return self._call("joints")

    def kinematics(self) -> ArmModel | None:
        return self._call("kinematics")

    def poses_since(self, after: float) -> PoseSamples:
        """The pose stream the child sampled where the controller's data arrives, in one batch."""
        return self._call("poses_since", after)

    def move_linear(self, target_tool_to_base: np.ndarray, limits: MotionLimits | None = None,
                    asynchronous: bool = False) -> None:
        self._call("move_linear", target_tool_to_base, limits, True)
        if not asynchronous:
            self.wait()

    def move_path(self, poses: list[np.ndarray], limits: MotionLimits | None = None,
                  asynchronous: bool = False) -> None:
        self._call("move_path", poses, limits, True,
                   timeout_s=self._call_timeout_s + PATH_POSE_TIMEOUT_S * len(poses))
        if not asynchronous:
            self.wait()

    def is_moving(self) -> bool:
        return self._call("is_moving")

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the current move by short questions to the child, never holding the pipe
        while the move runs, so the pose stream and Stop stay live for other threads."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self._call("is_moving"):
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(WAIT_POLL_S)
        return self._call("wait", 0.0)  # raises the move's fault, if it had one

    def stop(self) -> None:
        """stopL; if the child cannot take the command at once, it is killed, which drops the
        connection (the controller then ends the control script). Never raises."""
        if self._pipe is None:
            return
        if not self._lock.acquire(timeout=STOP_TIMEOUT_S):
            self._end_child()
            return
        try:
            self._exchange("stop", (), STOP_TIMEOUT_S)
        except RobotError:
            self._end_child()
        finally:
            self._lock.release()

    def _call(self, name: str, *args: object, timeout_s: float | None = None) -> Any:
        with self._lock:
            return self._exchange(name, args, timeout_s or self._call_timeout_s)

    def _exchange(self, name: str, args: tuple, timeout_s: float) -> Any:
        """One call to the child (the lock held); a dead or silent child is a RobotError."""
        pipe = self._pipe
        if pipe is None:
            raise RobotError(f"ur:{self.host}: robot not connected")
        try:
            pipe.send((name, args))
            if not pipe.poll(timeout_s):
                self._end_child()
                raise RobotError(f"ur:{self.host}: connection lost: the controller stopped answering "
                                 f"({name} took over {timeout_s:g} s)")
            status, value = pipe.recv()
        except (EOFError, OSError):
            self._end_child()
            raise RobotError(f"ur:{self.host}: connection lost ({name})")
        if status == "error":
            if name == "connect":
                self._connected = False
            raise value
        return value

    def _end_child(self) -> None:
        self._connected = False
        process, pipe = self._process, self._pipe
        self._process = self._pipe = None
        if pipe is not None:
            pipe.close()
        if process is not None:
            process.join(1.0)
            if process.is_alive():
                process.kill()
                process.join(5.0)
