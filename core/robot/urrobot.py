"""A UR arm driven through ur_rtde (``rtde_control`` + ``rtde_receive``) as a ``Robot``.

Poses are converted once, here: ours are flange poses ``tool_to_base`` (4x4, mm; the TCP is set
to the flange on connect), ur_rtde's are [x, y, z, rx, ry, rz] in metres and rad. Joints are rad
on both sides. Every error becomes a ``RobotError`` whose one-line message starts "ur:<host>:".

ur_rtde's Python calls keep the GIL while they wait on the network and its constructors have no
timeout, so a worker thread cannot time them out (the whole process freezes with it). Hence
``connect`` first checks with its own sockets and timeouts that the dashboard and RTDE servers
answer like a UR controller, and every move is sent asynchronous and waited for here, watching
the connection, the data stream, the safety state and the control script between short polls.

On connect it also reads the kinematics the controller computes with (its factory calibration)
from the KinematicsInfo its primary interface streams, with its own socket and deadline, and
keeps them only if they agree with the controller's own forward kinematics
(``getForwardKinematics``) at the current joints.

What the controller streams is input like any file's (``core.robot.controllerstate``): a state
whose joints, TCP pose or timestamp is not what an arm can report, or a TCP at rest that is not
where the joints put the flange, faults the robot: a move under way is halted, and every call but
``stop``, ``disconnect`` and ``poses_since`` (which keeps the poses received before) fails with
that reason until the next ``connect``.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import rtde_control
import rtde_receive

from probecal.core.geometry.transforms import transform_error
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.robot.armkinematics import model_of_info, record_of
from probecal.core.robot.contract import HISTORY_S, RobotError
from probecal.core.robot.controllerstate import (
    PoseSample,
    StateError,
    StreamClock,
    checked_sample,
    checked_tcp,
    disagreement,
)
from probecal.core.robot.posestream import ClockSync, PoseBuffer, PoseSamples
from probecal.core.robot.primary import ROBOT_STATE, KinematicsInfo, PrimaryProtocolError, kinematics_in, split_packages
from probecal.core.robot.rtde import (
    ControllerVersion,
    PackageType,
    RTDEProtocolError,
    decode_accepted,
    decode_header,
    encode_package,
    encode_protocol_request,
    ur_from_pose,
)
from probecal.core.robot.trajectory import blended_path
from probecal.core.robot.ur3 import ArmModel, MotionLimits, check_pose, identify_arm, linear_path_joints

T = TypeVar("T")
_log = logging.getLogger(__name__)

DASHBOARD_PORT = 29999
PRIMARY_PORT = 30001
RTDE_PORT = 30004
DASHBOARD_GREETING = b"Connected: Universal Robots Dashboard Server"
CONNECT_TIMEOUT_S = 3.0
STALE_DATA_S = 1.0
"""No new RTDE data for this long (s) means the controller is gone."""
START_TIMEOUT_S = 1.0
"""The controller must report an accepted move as started within this time (s)."""
CATCH_UP_S = 0.5
"""Longest wait (s) for the pose stream to catch up with the control stream's "finished"."""
REACHED_MM = 0.5
REACHED_DEG = 0.1
STOP_DECELERATION_M_S2 = 10.0
_POLL_S = 0.004
STREAM_POLL_S = 0.002
"""How often the pose sampler looks for a new RTDE state (the controller sends one every 2 ms)."""
CONTROLLER_HZ = 500.0
KINEMATICS_TIMEOUT_S = 1.0
"""How long (s) connect waits for a KinematicsInfo (a controller streams RobotState at 10 Hz)."""
KINEMATICS_AGREE_MM = 0.01
KINEMATICS_AGREE_DEG = 1e-4
"""How closely the flange by the stated kinematics must match the controller's own forward
kinematics for probecal to use them."""
RECEIVE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_TCP_pose",
    "target_qd",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "runtime_state",
]
"""What URRobot reads from RTDE (ur_rtde's default recipe streams about 60 variables)."""


BLEND_MM = 2.0
"""Blend radius of a path's corners (mm), cut to 40 % of the shorter neighbouring segment, as a UR
needs its blends not to overlap."""


def blend_radii_mm(poses: list[np.ndarray]) -> list[float]:
    """The blend radius (mm) at each pose after the first of a path through ``poses``; 0 at the end."""
    lengths = [float(np.linalg.norm(b[:3, 3] - a[:3, 3])) for a, b in zip(poses, poses[1:])]
    return [min(BLEND_MM, 0.4 * min(before, after)) for before, after in zip(lengths, lengths[1:])] + [0.0]


@dataclass
class _Move:
    """One moveL sent to the controller and what became of it.

    The control stream reports the move finished (``reported_at``); the pose stream is a second
    RTDE connection that may lag, so the move counts as finished (``finished_at``) once that
    stream has advanced twice since and shows the trajectory's speed ``target_qd`` at zero.
    """

    target: np.ndarray
    limits: MotionLimits
    previous_operation: int
    sent_at: float
    started: bool = False
    reported_at: float | None = None
    stamp: float = 0.0
    stamp_changes: int = 0
    finished_at: float | None = None
    stopped: bool = False
    fault: str | None = None

    @property
    def active(self) -> bool:
        return self.finished_at is None and self.fault is None


def _recv_exact(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        if not chunk:
            raise ConnectionResetError("the server closed the connection")
        data += chunk
    return data


def _rtde_request(sock: socket.socket, package_type: PackageType, payload: bytes = b"") -> bytes:
    """Send one RTDE request and return the payload of its reply (which must be of that type)."""
    sock.sendall(encode_package(package_type, payload))
    size, reply_type = decode_header(_recv_exact(sock, 3))
    if reply_type != package_type:
        raise RTDEProtocolError(
            f"reply of type {reply_type:#04x} to a {chr(package_type)!r} request"
        )
    return _recv_exact(sock, size - 3)


def probe_controller(host: str, timeout_s: float = CONNECT_TIMEOUT_S) -> ControllerVersion:
    """Check that a UR controller answers on ``host``, each step within ``timeout_s``.

    Reads the dashboard server's greeting, negotiates RTDE protocol version 2 and asks the
    controller version; raises RobotError naming the host and what failed.
    """
    stage = f"dashboard server (port {DASHBOARD_PORT})"
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
            greeting = sock.makefile("rb").readline()
        if not greeting.startswith(DASHBOARD_GREETING):
            raise RobotError(f"ur:{host}: unexpected {stage} greeting {greeting[:60]!r}")
        stage = f"RTDE server (port {RTDE_PORT})"
        with socket.create_connection((host, RTDE_PORT), timeout=timeout_s) as sock:
            if not decode_accepted(
                _rtde_request(sock, PackageType.REQUEST_PROTOCOL_VERSION, encode_protocol_request())
            ):
                raise RobotError(f"ur:{host}: the {stage} refused RTDE protocol version 2")
            return ControllerVersion.decode(_rtde_request(sock, PackageType.GET_URCONTROL_VERSION))
    except TimeoutError as exc:
        raise RobotError(f"ur:{host}: no answer from the {stage} within {timeout_s:g} s") from exc
    except ConnectionRefusedError as exc:
        raise RobotError(f"ur:{host}: the {stage} refused the connection") from exc
    except RTDEProtocolError as exc:
        raise RobotError(f"ur:{host}: the {stage} sent an invalid reply: {exc}") from exc
    except OSError as exc:
        raise RobotError(f"ur:{host}: cannot talk to the {stage}: {exc}") from exc


def read_kinematics_info(host: str, timeout_s: float = KINEMATICS_TIMEOUT_S) -> KinematicsInfo | None:
    """The KinematicsInfo of the first RobotState that the primary interface (port 30001) of
    ``host`` sends within ``timeout_s``; None when none comes. Other packages are skipped; a
    package whose size is out of bounds, or a KinematicsInfo of another size, raises
    PrimaryProtocolError, and a port that cannot be reached OSError."""
    deadline = time.monotonic() + timeout_s
    buffer = b""
    with socket.create_connection((host, PRIMARY_PORT), timeout=timeout_s) as sock:
        while (left := deadline - time.monotonic()) > 0:
            sock.settimeout(left)
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                return None
            if not chunk:
                return None
            packages, buffer = split_packages(buffer + chunk)
            for kind, payload in packages:
                if kind == ROBOT_STATE and (info := kinematics_in(payload)) is not None:
                    return info
    return None


def checked_kinematics(info: KinematicsInfo, joints: np.ndarray,
                       stated_tool_to_base: np.ndarray) -> tuple[ArmModel | None, str]:
    """The model of the KinematicsInfo a controller stated, if at ``joints`` (rad) it puts the
    flange where the controller's own forward kinematics does (``stated_tool_to_base``, mm) within
    ``KINEMATICS_AGREE_MM`` and ``KINEMATICS_AGREE_DEG``; else None and why not. Parameters that
    are not finite numbers within ``MAX_MAGNITUDE`` are refused before any arithmetic."""
    values = np.concatenate([info.theta, info.a, info.d, info.alpha])
    if not (np.all(np.isfinite(values)) and np.abs(values).max() <= MAX_MAGNITUDE):
        return None, f"its KinematicsInfo holds parameters that are not finite numbers within {MAX_MAGNITUDE:g}"
    model = model_of_info(info, joints)
    if model is None:
        return None, "its KinematicsInfo describes no arm probecal knows"
    try:
        record_of(model)
    except ValueError as exc:
        return None, f"its KinematicsInfo is beyond what a session records ({exc})"
    dt, dr = transform_error(model.forward(joints), stated_tool_to_base)
    if not (dt <= KINEMATICS_AGREE_MM and dr <= KINEMATICS_AGREE_DEG):
        return None, f"its KinematicsInfo puts the flange {dt:.3f} mm and {dr:.4f} deg from its own forward kinematics"
    return model, ""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class URRobot:
    """A UR arm at ``host`` through ur_rtde, implementing ``core.robot.simulated.Robot``.

    Move limits: ``MotionLimits``' linear speed and acceleration (mm/s, mm/s^2) become moveL's
    m/s and m/s^2 (moveL has no separate rotational limits); ``settle_s`` is waited here after
    the controller reports the move finished.
    """

    def __init__(self, host: str, connect_timeout_s: float = CONNECT_TIMEOUT_S):
        self.host = host
        self._timeout_s = connect_timeout_s
        self._control: rtde_control.RTDEControlInterface | None = None
        self._receive: rtde_receive.RTDEReceiveInterface | None = None
        self._move: _Move | None = None
        self._command_lock = threading.RLock()
        self._last_timestamp = 0.0
        self._last_data_at = 0.0
        self._history = PoseBuffer(capacity=int(HISTORY_S * CONTROLLER_HZ))
        self._clock = ClockSync()
        self._sampling = threading.Event()
        self._sampler: threading.Thread | None = None
        self.controller_version: ControllerVersion | None = None
        """The URControl version the controller reported on the last connect."""
        self._kinematics: ArmModel | None = None
        self._arm: ArmModel | None = None  # what its TCP at rest is checked against (None: an arm not known)
        self._fault: str | None = None  # why what the controller streams is not trusted (None: it is)

    @property
    def connected(self) -> bool:
        return self._control is not None and self._fault is None and self._connection_problem() is None

    def connect(self) -> None:
        """Connect, upload ur_rtde's control script and set the TCP to the flange."""
        if self.connected:
            return
        self._release()
        self.controller_version = probe_controller(self.host, self._timeout_s)
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(
                self.host, variables=RECEIVE_VARIABLES
            )
            self._control = rtde_control.RTDEControlInterface(self.host)
        except (RuntimeError, ValueError) as exc:
            self._release()
            raise RobotError(f"ur:{self.host}: connect failed: {_first_line(exc)}") from exc
        try:
            self._wait_for_data()
            self.pose_sample()
            if not self._command("setTcp", self._control.setTcp, [0.0] * 6):
                raise RobotError(f"ur:{self.host}: the controller refused setTcp")
            self._wait_for_data(self._rtde_receive.getTimestamp())  # the TCP now the flange
            self._kinematics = self._read_kinematics()
            self._arm = self._kinematics or self._identified_arm()
            self.pose_sample()  # at rest: its TCP where its joints put the flange
        except RobotError:
            self._release()
            raise
        self._history = PoseBuffer(capacity=int(HISTORY_S * CONTROLLER_HZ))  # a new controller clock
        self._clock = ClockSync()
        self._sampling.set()
        self._sampler = threading.Thread(target=self._sample_stream, args=(self._receive,), name="rtde-poses",
                                         daemon=True)
        self._sampler.start()

    def disconnect(self) -> None:
        """Stop any motion, end the control script and close the connection."""
        self.stop()
        if self._control is not None and self._connection_problem() is None:
            try:
                self._control.stopScript()
            except RuntimeError:
                pass
        self._release()

    def tool_to_base(self) -> np.ndarray:
        """The measured flange pose (4x4, mm)."""
        return self.pose_sample().tool_to_base

    def joints(self) -> np.ndarray:
        """The measured joint angles (6,), rad."""
        return self.pose_sample().joints

    def kinematics(self) -> ArmModel | None:
        """The kinematics the controller computes flange poses with, as read on connect; None
        when it stated none that probecal could use (the reason is logged)."""
        self._require_connected()
        return self._kinematics

    def _identified_arm(self) -> ArmModel | None:
        """The table of the arm whose joints and flange pose the controller reports, where it
        states no kinematics (:func:`core.robot.ur3.identify_arm`); None for an arm not known."""
        sample = self.pose_sample()
        table = identify_arm(sample.joints, sample.tool_to_base)
        return None if table is None else ArmModel(table)

    def _read_kinematics(self) -> ArmModel | None:
        """The controller's kinematics (:meth:`_stated_kinematics`); None, logged, where it
        states none that probecal can use."""
        model, problem = self._stated_kinematics()
        if model is None:
            _log.warning("ur:%s: %s; taking UR's table for its kinematics", self.host, problem)
        return model

    def _stated_kinematics(self) -> tuple[ArmModel | None, str]:
        """The controller's KinematicsInfo as a model, checked against its ``getForwardKinematics``
        at the current joints (:func:`checked_kinematics`); else None and why not."""
        try:
            info = read_kinematics_info(self.host)
        except (OSError, PrimaryProtocolError) as exc:
            return None, f"the primary interface (port {PRIMARY_PORT}) failed: {exc}"
        if info is None:
            return None, (f"the primary interface (port {PRIMARY_PORT}) sent no KinematicsInfo within "
                          f"{KINEMATICS_TIMEOUT_S:g} s")
        q = self.joints()
        stated = self._command("getForwardKinematics", self._rtde_control.getForwardKinematics)  # the TCP is the flange
        if not np.array_equal(self.joints(), q):
            return None, "the arm moved while its kinematics were checked"
        try:
            flange = checked_tcp(stated, "a flange pose (getForwardKinematics)")
        except StateError as exc:
            return None, str(exc)
        return checked_kinematics(info, q, flange)

    def pose_sample(self) -> PoseSample:
        """Flange pose, joints and the controller timestamp (s) of one and the same RTDE state,
        checked (:func:`core.robot.controllerstate.checked_sample`; with the arm at rest, its TCP
        against its joints too); RobotError, and the robot faulted, when they are not an arm's."""
        receive = self._require_connected()
        while True:
            timestamp = receive.getTimestamp()
            pose, q, speeds = receive.getActualTCPPose(), receive.getActualQ(), receive.getTargetQd()
            again = receive.getTimestamp()
            if again == timestamp or not (np.isfinite(timestamp) and np.isfinite(again)):
                break
        try:
            sample = checked_sample(pose, q, timestamp)
        except StateError as exc:
            raise self._faulted(str(exc)) from None
        move = self._move
        at_rest = (move is None or not move.active) and not any(speeds)
        problem = None if self._arm is None or not at_rest else disagreement(sample, self._arm)
        if problem is not None:
            raise self._faulted(problem)
        return sample

    def _faulted(self, problem: str) -> RobotError:
        """The robot faulted by what its controller sent (``problem``): the error to raise."""
        self._fault = self._fault or f"ur:{self.host}: {problem}"
        return RobotError(self._fault)

    def poses_since(self, after: float) -> PoseSamples:
        """Every RTDE state the sampler saw after ``after`` (s, this machine's clock), stamped by
        the controller's ``timestamp`` mapped to this machine's clock; after a fault, those it
        took before."""
        self._require_link()
        offset = self._clock.offset
        return PoseSamples.empty() if offset is None else self._history.since(after, offset)

    def _sample_stream(self, receive: rtde_receive.RTDEReceiveInterface) -> None:
        """Sampler thread: each new RTDE state's flange pose into the history, under the
        controller's timestamp; the host time it was seen at tunes the clock mapping. A state
        that is no arm's (:func:`checked_sample`, :class:`StreamClock`) faults the robot and
        ends the sampling: the history keeps what came before it."""
        last, clock = None, StreamClock()
        while self._sampling.is_set():
            time.sleep(STREAM_POLL_S)
            try:
                if not receive.isConnected():
                    return
                timestamp = receive.getTimestamp()
                if timestamp == last:
                    continue
                pose, q = receive.getActualTCPPose(), receive.getActualQ()
                if receive.getTimestamp() != timestamp and np.isfinite(timestamp):
                    continue  # a newer state came in while reading: take that one next time
            except RuntimeError:
                return
            seen = time.time()
            try:
                sample = checked_sample(pose, q, timestamp)
                clock.check(sample.timestamp_s, seen)
            except StateError as exc:
                self._faulted(str(exc))
                return
            self._clock.observe(sample.timestamp_s, seen)
            self._history.add(sample.tool_to_base, sample.timestamp_s)
            last = timestamp

    def move_linear(
        self,
        target_tool_to_base: np.ndarray,
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """moveL to a flange pose; the straight path is checked (Unreachable) before sending."""
        limits = limits if limits is not None else MotionLimits()
        self._require_idle()
        target = check_pose(target_tool_to_base)
        linear_path_joints(self.joints(), target)
        self._send("moveL", target, limits, asynchronous, ur_from_pose(target),
                   limits.linear_speed_mm_s / 1000.0, limits.linear_accel_mm_s2 / 1000.0, True)

    def move_path(
        self,
        poses: list[np.ndarray],
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """ur_rtde's moveL through a path with blend radii (:func:`blend_radii_mm`); the path the
        twin's model predicts (``core.robot.trajectory``) is checked (Unreachable) before sending."""
        limits = limits if limits is not None else MotionLimits()
        self._require_idle()
        path = blended_path([self.tool_to_base(), *poses], limits)
        path.joints_along(self.joints())
        speed, accel = limits.linear_speed_mm_s / 1000.0, limits.linear_accel_mm_s2 / 1000.0
        radii = blend_radii_mm([self.tool_to_base(), *poses])
        entries = [[*ur_from_pose(pose), speed, accel, r / 1000.0] for pose, r in zip(poses, radii)]
        self._send("moveL path", check_pose(poses[-1]), limits, asynchronous, entries, True)

    def _require_idle(self) -> None:
        self._require_connected()
        if self.is_moving():
            raise RobotError(f"ur:{self.host}: robot is already moving")

    def _send(self, what: str, target: np.ndarray, limits: MotionLimits, asynchronous: bool, *args: object) -> None:
        """Send ur_rtde's moveL with ``args`` (a pose or a path) and follow it to ``target``."""
        with self._command_lock:
            operation = self._rtde_control.getAsyncOperationProgressEx().operationId()
            move = _Move(target, limits, operation, time.monotonic())
            self._move = move
            try:
                accepted = self._command(what, self._rtde_control.moveL, *args)
            except RobotError as exc:
                move.fault = str(exc)
                raise
        if not accepted:
            reason = self._state_problem() or "not ready for a command"
            move.fault = f"ur:{self.host}: the controller refused {what} ({reason})"
            raise RobotError(move.fault)
        if asynchronous:
            return
        self.wait()
        if move.stopped or not self._reached(move.target):
            raise RobotError(f"ur:{self.host}: move stopped before reaching the target")

    def is_moving(self) -> bool:
        """True from moveL until the controller finished it and ``settle_s`` passed."""
        move = self._move
        if move is None or move.fault is not None:
            return False
        if move.finished_at is None:
            self._update(move)
        if move.fault is not None:
            return False
        if move.finished_at is None:
            return True
        settle_s = 0.0 if move.stopped else move.limits.settle_s
        return time.monotonic() < move.finished_at + settle_s

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the current move; False on timeout. Raises RobotError if the move faulted."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.is_moving():
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(_POLL_S)
        move = self._move
        if move is not None and move.fault is not None:
            raise RobotError(move.fault)
        return True

    def stop(self) -> None:
        """stopL at once and wait until the arm is still; safe when idle, not connected or
        after the connection was lost."""
        move = self._move
        if move is not None and move.active:
            move.stopped = True
        if self._control is None or self._connection_problem() is not None:
            return
        try:
            with self._command_lock:
                self._control.stopL(STOP_DECELERATION_M_S2)
        except RuntimeError:
            return
        if move is None or not move.active:
            return
        if move.reported_at is None:
            self._report_finished(move)
        while self.is_moving():
            time.sleep(_POLL_S)

    def _require_connected(self) -> rtde_receive.RTDEReceiveInterface:
        """The receive interface of a connected robot that is not faulted; RobotError otherwise."""
        receive = self._require_link()
        if self._fault is not None:
            raise RobotError(self._fault)
        return receive

    def _require_link(self) -> rtde_receive.RTDEReceiveInterface:
        """The receive interface of a connected robot, faulted or not; RobotError otherwise."""
        if self._control is None:
            raise RobotError(f"ur:{self.host}: robot not connected")
        problem = self._connection_problem()
        if problem is not None:
            raise RobotError(f"ur:{self.host}: {problem}")
        return self._rtde_receive

    @property
    def _rtde_control(self) -> rtde_control.RTDEControlInterface:
        """The control interface; RobotError when not connected."""
        if self._control is None:
            raise RobotError(f"ur:{self.host}: robot not connected")
        return self._control

    @property
    def _rtde_receive(self) -> rtde_receive.RTDEReceiveInterface:
        """The receive interface; RobotError when not connected."""
        if self._receive is None:
            raise RobotError(f"ur:{self.host}: robot not connected")
        return self._receive

    def _command(self, what: str, function: Callable[..., T], *args: object) -> T:
        """Call one ur_rtde command, with its errors as RobotError; none to a faulted robot."""
        if self._fault is not None:
            raise RobotError(self._fault)
        problem = self._connection_problem()
        if problem is not None:
            raise RobotError(f"ur:{self.host}: {problem} before {what}")
        try:
            with self._command_lock:
                return function(*args)
        except (RuntimeError, ValueError) as exc:
            raise RobotError(f"ur:{self.host}: {what} failed: {_first_line(exc)}") from exc

    def _update(self, move: _Move) -> None:
        """Follow the controller's report on ``move``: started, finished (its end state checked,
        :meth:`pose_sample`) or a fault; a move of a robot faulted by what its controller sent is
        halted."""
        if self._fault is not None:
            move.fault = self._fault
            self.stop()
            return
        problem = self._connection_problem() or self._state_problem()
        if problem is not None:
            move.fault = f"ur:{self.host}: {problem} during moveL"
            return
        if move.reported_at is None:
            status = self._rtde_control.getAsyncOperationProgressEx()
            running = status.isAsyncOperationRunning()
            operation = status.operationId()
            move.started = move.started or running or operation != move.previous_operation
            if move.started and not running:
                self._report_finished(move)
            elif not move.started and time.monotonic() - move.sent_at > START_TIMEOUT_S:
                move.fault = f"ur:{self.host}: the controller did not start moveL"
            return
        stamp = self._rtde_receive.getTimestamp()
        if stamp != move.stamp:
            move.stamp, move.stamp_changes = stamp, move.stamp_changes + 1
        caught_up = move.stamp_changes >= 2 and not any(self._rtde_receive.getTargetQd())
        if caught_up or time.monotonic() - move.reported_at > CATCH_UP_S:
            move.finished_at = time.monotonic()
            try:
                self.pose_sample()  # the arm at rest: its TCP where its joints put the flange
            except RobotError as exc:
                move.fault = str(exc)

    def _report_finished(self, move: _Move) -> None:
        """The control stream says ``move`` is over; now let the pose stream catch up."""
        move.reported_at = time.monotonic()
        move.stamp, move.stamp_changes = self._rtde_receive.getTimestamp(), 0

    def _connection_problem(self) -> str | None:
        """Why the connection is unusable, or None (also notices a stalled data stream)."""
        if not (self._rtde_control.isConnected() and self._rtde_receive.isConnected()):
            return "connection lost"
        now = time.monotonic()
        timestamp = self._rtde_receive.getTimestamp()
        if timestamp != self._last_timestamp:
            self._last_timestamp, self._last_data_at = timestamp, now
        elif now - self._last_data_at > STALE_DATA_S:
            return f"no data from the controller for {STALE_DATA_S:g} s"
        return None

    def _state_problem(self) -> str | None:
        """Why the controller cannot move, or None."""
        if self._rtde_receive.isEmergencyStopped():
            return "emergency stop"
        if self._rtde_receive.isProtectiveStopped():
            return "protective stop"
        if not self._rtde_control.isProgramRunning():
            return "control script not running"
        return None

    def _wait_for_data(self, stamp: float = 0.0) -> None:
        """Wait until the receive stream (a connection of its own, which may lag the control
        stream) has moved on twice from the state stamped ``stamp`` (s)."""
        deadline = time.monotonic() + self._timeout_s
        seen = [stamp]
        while len(seen) < 3:
            if time.monotonic() > deadline:
                raise RobotError(f"ur:{self.host}: no RTDE data within {self._timeout_s:g} s")
            time.sleep(_POLL_S)
            if (timestamp := self._rtde_receive.getTimestamp()) != seen[-1]:
                seen.append(timestamp)
        self._last_timestamp, self._last_data_at = self._rtde_receive.getTimestamp(), time.monotonic()

    def _reached(self, target: np.ndarray) -> bool:
        dt, dr = transform_error(self.tool_to_base(), target)
        return dt < REACHED_MM and dr < REACHED_DEG

    def _release(self) -> None:
        """Stop the sampler and drop the ur_rtde objects; their destructors close the connections
        (0.5 s each)."""
        self._sampling.clear()
        if self._sampler is not None:
            self._sampler.join()
            self._sampler = None
        self._move = None
        self._kinematics = self._arm = self._fault = None
        self._control = None
        self._receive = None
