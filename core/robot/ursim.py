"""A UR e-Series controller simulator that the real, unmodified ur_rtde 1.6 client drives.

``URSim`` answers on one host address like a PolyScope 5.11 controller: the dashboard server
(29999), RTDE (30004, protocol 2, 500 Hz) and the script ports (30001..30003). Its arm is a
``SimulatedRobot`` (mm, rad inside; metres and rotation vectors on the wire). It runs the control
script ur_rtde uploads by emulating that script's register protocol: the command id in input int
register 0, arguments in input int register 1 and input double registers 0.., "ready" (1) and
"done with command" (2) in output int register 0, async progress in output int register 2.

ur_rtde's Python bindings keep the GIL while they wait on the network, so a ur_rtde client in
the same process as a URSim deadlocks; give such a client ``URSimProcess`` (the simulator in a
child process, ``python -m core.robot.ursim``). Timestamps are wall-clock seconds since start; with
``time_scale`` < 1 the arm moves faster than a real one by that factor.
"""

from __future__ import annotations

import argparse
import ipaddress
import re
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from enum import IntEnum

import numpy as np

from probecal.core.robot.simulated import RobotError, SimulatedRobot
from probecal.core.robot.rtde import (
    IN_USE,
    INPUT_VARIABLES,
    OUTPUT_VARIABLES,
    PROTOCOL_VERSION,
    ControllerVersion,
    PackageType,
    Recipe,
    RTDEProtocolError,
    TextMessage,
    decode_input_setup,
    decode_output_setup,
    decode_protocol_request,
    default_value,
    encode_accepted,
    encode_package,
    encode_setup_reply,
    make_recipe,
    pose_from_ur,
    pose_to_ur,
    split_packages,
)
from probecal.core.geometry.transforms import invert_transform
from probecal.core.robot.ur3 import MotionLimits, Unreachable, closest_ik, forward_kinematics

DEFAULT_HOST = "127.0.0.2"
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
"""Primary, secondary and real-time interfaces; each accepts URScript (ur_rtde uses 30003)."""
RTDE_PORT = 30004
CONTROLLER_VERSION = ControllerVersion(5, 11, 11, 1052000)
POLYSCOPE_VERSION = f"URSoftware {CONTROLLER_VERSION} (Oct 19 2023)"
SERIAL_NUMBER = "20215300001"
DASHBOARD_GREETING = "Connected: Universal Robots Dashboard Server"
CONTROL_FREQUENCY_HZ = 500.0
"""e-Series controller cycle and the highest RTDE output frequency."""
FAULTS = ("wrong-protocol", "garbage", "silent")
"""RTDE server faults for tests: refuse protocol 2, answer with garbage bytes, or never answer."""
GARBAGE = b"\x00\x01garbage\xde\xad\xbe\xef" * 4
"""What the garbage fault sends: its first two bytes are an impossible package size (1)."""
JOINT_RUNNING = 253
_SOCKET_TIMEOUT_S = 1.0
MAX_LINE_BYTES = 4096  # a dashboard command line
MAX_SCRIPT_BYTES = 1 << 20  # one URScript program (ur_rtde's control script is about 60 kB)
"""Socket operations wake up this often (s); a client that takes no data for as long is dropped."""
_QD_WINDOW_S = 0.03
"""Joints unchanged for this long (s) read as actual_qd = 0 (the arm updates every 10 ms)."""


class RobotMode(IntEnum):
    """The RTDE ``robot_mode`` values URSim goes through."""

    POWER_OFF = 3
    IDLE = 5
    RUNNING = 7


class SafetyMode(IntEnum):
    """The RTDE ``safety_mode`` values URSim goes through."""

    NORMAL = 1
    PROTECTIVE_STOP = 3


class RuntimeState(IntEnum):
    """RTDE ``runtime_state``: PLAYING while the control script runs."""

    STOPPED = 1
    PLAYING = 2


_SAFETY_STATUS_BITS = {SafetyMode.NORMAL: 1 << 0, SafetyMode.PROTECTIVE_STOP: 1 << 2}
_POWER_ON_BIT, _PROGRAM_RUNNING_BIT = 1 << 0, 1 << 1

COMMAND_NAMES = {
    1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK", 6: "forceMode", 7: "forceModeStop",
    8: "zeroFtSensor", 9: "speedJ", 10: "speedL", 11: "servoJ", 12: "servoC",
    13: "setStandardDigitalOut", 14: "setToolDigitalOut", 15: "speedStop", 16: "servoStop",
    17: "setPayload", 18: "teachMode", 19: "endTeachMode", 20: "forceModeSetDamping",
    21: "forceModeSetGainScaling", 22: "setSpeedSlider", 23: "setAnalogOutput", 24: "servoL",
    25: "toolContact", 26: "getStepTime", 27: "getActualJointPositionsHistory",
    28: "getTargetWaypoint", 29: "setTcp", 30: "getInverseKinematics",
    31: "triggerProtectiveStop", 33: "stopL", 34: "stopJ", 35: "setWatchdog",
    36: "isPoseWithinSafetyLimits", 37: "isJointsWithinSafetyLimits", 38: "getJointTorques",
    39: "poseTrans", 40: "getTCPOffset", 41: "jogStart", 42: "jogStop",
    43: "getForwardKinematics", 44: "getForwardKinematics", 45: "movePath",
    46: "getInverseKinematics", 47: "isSteady", 48: "setConfigurableDigitalOut",
    49: "setInputIntRegister", 50: "setInputDoubleRegister", 51: "moveUntilContact",
    52: "freedriveMode", 53: "endFreedriveMode", 54: "getFreedriveStatus",
    55: "setExternalForceTorque", 56: "ftRtdeInputEnable", 57: "enableExternalFtSensor",
    58: "getActualToolFlangePose", 59: "setGravity", 60: "getInverseKinematicsHasSolution",
    61: "getInverseKinematicsHasSolution", 62: "startContactDetection",
    63: "stopContactDetection", 64: "readContactDetection", 65: "setTargetPayload",
    66: "directTorque", 67: "getMassMatrix", 68: "getCoriolisAndCentrifugalTorques",
    69: "getTargetJointAccelerations", 70: "getJacobian", 71: "getJacobianTimeDerivative",
    255: "stopScript",
}
"""ur_rtde 1.6's command ids (RTDE::RobotCommand::Type) and the functions that send them."""

_REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
"""Commands the control script answers with "ready" instead of "done" (servo, speed, ...)."""
_READY, _DONE = 1, 2
_STOP_SCRIPT = 255
_CONTROL_SCRIPT_MARK = "# NODE_CONTROL_LOOP_BEGINS"
_PROGRAM_START = re.compile(r"^(def|sec)\s+(\w+)\s*\(\s*\)\s*:")
_OFFSET = re.compile(r"global reg_offset_(int|float)\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")
"""ur_rtde injects the register offset after the comment, so the number opens the next line."""


class _Controller:
    """The controller's state: the arm, every RTDE variable (registers too), program, safety.

    Not thread-safe by itself: the owner holds one lock around every call and ``values`` access.
    """

    def __init__(self, arm: SimulatedRobot, log: Callable[[str], None]):
        self.arm = arm
        self.log = log
        self.values = {name: default_value(t) for name, t in OUTPUT_VARIABLES.items()}
        self.values.update(
            speed_scaling=1.0,
            target_speed_fraction=1.0,
            actual_main_voltage=48.0,
            actual_robot_voltage=48.0,
            actual_joint_voltage=(48.0,) * 6,
            joint_temperatures=(30.0,) * 6,
            joint_mode=(JOINT_RUNNING,) * 6,
            speed_slider_fraction=1.0,
        )
        self.tcp_to_flange = np.eye(4)
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.script: _ControlScript | None = None
        self.outbox: list[str] = []
        self._t0 = time.monotonic()
        self._q = np.full(6, np.nan)
        self._q_time = self._t0
        self._moving_qd = (0.0,) * 6

    @property
    def program_running(self) -> bool:
        return self.script is not None

    def flange(self) -> np.ndarray:
        """The arm's flange pose ``tool_to_base`` (4x4, mm)."""
        return forward_kinematics(self.arm.joints())

    def flange_from_tcp(self, tcp_to_base: np.ndarray) -> np.ndarray:
        """The flange pose (mm) that puts the TCP at ``tcp_to_base`` (mm)."""
        return tcp_to_base @ invert_transform(self.tcp_to_flange)

    def tcp_from_flange(self, tool_to_base: np.ndarray) -> np.ndarray:
        """The TCP pose (mm) of flange pose ``tool_to_base`` (mm)."""
        return tool_to_base @ self.tcp_to_flange

    def message(self, text: str) -> None:
        """Publish a text message (RTDE 'M' to started clients, and the log)."""
        self.outbox.append(text)
        self.log(text)

    def fault(self, text: str) -> None:
        """A runtime error in the program: report it and stop the program."""
        self.message(f"program stopped: {text}")
        self.end_program()

    def protective_stop(self, text: str) -> None:
        """A fault of the arm: protective stop (unlock it on the dashboard), program stopped."""
        self.safety_mode = SafetyMode.PROTECTIVE_STOP
        self.fault(text)

    def end_program(self) -> None:
        """Stop the running program; the arm halts where it is."""
        self.script = None
        self.arm.stop()

    def start_control_script(self, text: str) -> None:
        """Run ur_rtde's control script, replacing any running program."""
        self.end_program()
        if self.robot_mode != RobotMode.RUNNING or self.safety_mode != SafetyMode.NORMAL:
            self.message(
                f"cannot start rtde_control: robot mode {self.robot_mode.name}, "
                f"safety mode {self.safety_mode.name}"
            )
            return
        offsets = {kind: int(value) for kind, value in _OFFSET.findall(text)}
        self.script = _ControlScript(self, offsets.get("int", 0), offsets.get("float", 0))
        self.message("RTDE Control Script Loaded")

    def step(self) -> None:
        """One controller cycle: the program, then the streamed state."""
        if self.script is not None and not self.script.step():
            self.end_program()
        self._refresh()

    def _refresh(self) -> None:
        """Update the streamed state. The TCP pose is the arm's at this instant (the twin's
        motion is exact in time, as a real controller's state is); the joints follow the arm's
        joint-space ticks. ``target_qd`` is exactly zero once the arm stopped (as on a real
        controller, whose trajectory ended), so the pose in that package is final; while the arm
        moves it holds the last joint speed seen (rad/s)."""
        now = time.monotonic()
        moving = self.arm.is_moving()
        q = self.arm.joints()
        values = self.values
        tcp = tuple(pose_to_ur(self.tcp_from_flange(self.arm.tool_to_base())))
        values.update(actual_TCP_pose=tcp, target_TCP_pose=tcp)
        if not np.array_equal(q, self._q):
            dt = now - self._q_time
            qd = (q - self._q) / dt if np.all(np.isfinite(self._q)) and dt > 0 else np.zeros(6)
            self._q, self._q_time = q, now
            values.update(actual_q=tuple(q), target_q=tuple(q), actual_qd=tuple(qd))
            if np.any(qd):
                self._moving_qd = tuple(qd)
        elif now - self._q_time > _QD_WINDOW_S:
            values["actual_qd"] = (0.0,) * 6
        values["target_qd"] = self._moving_qd if moving else (0.0,) * 6
        powered = self.robot_mode != RobotMode.POWER_OFF
        values.update(
            timestamp=now - self._t0,
            robot_mode=int(self.robot_mode),
            safety_mode=int(self.safety_mode),
            safety_status=int(self.safety_mode),
            safety_status_bits=_SAFETY_STATUS_BITS[self.safety_mode],
            runtime_state=int(RuntimeState.PLAYING if self.script else RuntimeState.STOPPED),
            robot_status_bits=(_POWER_ON_BIT if powered else 0)
            | (_PROGRAM_RUNNING_BIT if self.script else 0),
        )


class _ControlScript:
    """ur_rtde's ``rtde_control`` script, emulated one controller cycle (``step``) at a time.

    Follows the script's main loop: realtime commands process and signal ready; any other
    non-zero command id runs once and signals done when finished (a blocking move keeps the loop
    waiting); command 0 clears and signals ready; 255 ends the script. A command URSim does not
    implement is a runtime error: a text message, and the program stops.
    """

    def __init__(self, controller: _Controller, int_offset: int, float_offset: int):
        self.controller = controller
        self.int_offset = int_offset
        self.float_offset = float_offset
        self.executing = False
        self.blocking = False
        self.async_move = False
        self.write_count = 0
        self.operation_id = 0
        self._async_progress(-1)
        self._write_int(0, _READY)

    def step(self) -> bool:
        """One cycle; False once the script has ended."""
        arm = self.controller.arm
        if self.blocking:
            if arm.is_moving():
                return True
            self.blocking = False
            if self._motion_failed():
                return False
            self._write_int(0, _DONE)
        if self.async_move and not arm.is_moving():
            self.async_move = False
            self._async_progress(-1)
            if self._motion_failed():
                return False
        cmd = self._read_int(0)
        if cmd in _REALTIME_COMMANDS:
            return self._unsupported(cmd)
        if cmd == 0:
            self.executing = False
            self._write_int(0, _READY)
            return True
        keep_running = self.executing or self._process(cmd)
        self.executing = True
        return keep_running

    def _process(self, cmd: int) -> bool:
        handler = _HANDLERS.get(cmd)
        if handler is None:
            return self._unsupported(cmd)
        try:
            handler(self)
        except (Unreachable, RobotError, ValueError) as exc:
            self.controller.fault(f"{COMMAND_NAMES[cmd]} failed: {exc}")
            return False
        if cmd == _STOP_SCRIPT:
            self.controller.message("Received stop script!")
            return False
        if not self.blocking:
            self._write_int(0, _DONE)
        return True

    def _unsupported(self, cmd: int) -> bool:
        name = COMMAND_NAMES.get(cmd, "unknown command")
        self.controller.fault(f"command {cmd} ({name}) is not supported by URSim")
        return False

    def _motion_failed(self) -> bool:
        """True (and a protective stop) when the move that just ended faulted."""
        try:
            self.controller.arm.wait(timeout=1.0)
        except RobotError as exc:
            self.controller.protective_stop(str(exc))
            return True
        return False

    def _read_int(self, index: int) -> int:
        return self.controller.values[f"input_int_register_{index + self.int_offset}"]

    def _read_float(self, index: int) -> float:
        return self.controller.values[f"input_double_register_{index + self.float_offset}"]

    def _read_floats(self, index: int, count: int = 6) -> np.ndarray:
        return np.array([self._read_float(index + i) for i in range(count)])

    def _write_int(self, index: int, value: int) -> None:
        self.controller.values[f"output_int_register_{index + self.int_offset}"] = value

    def _write_floats(self, index: int, values) -> None:
        for i, value in enumerate(values):
            name = f"output_double_register_{index + i + self.float_offset}"
            self.controller.values[name] = float(value)

    def _async_progress(self, value: int) -> None:
        """The script's write_async_progress_register: op id, change count, running, progress."""
        self.write_count = self.write_count + 1 if self.write_count < 127 else 0
        if value == 0:
            self.operation_id = self.operation_id + 1 if self.operation_id < 127 else 0
        register = self.write_count * 65536 + self.operation_id * 16777216
        if value >= 0:
            register += min(value, 32767) + 32768
        self._write_int(2, register)

    def _stop_async_move(self) -> None:
        if self.async_move:
            self.controller.arm.stop()
            self.async_move = False
            self._async_progress(-1)

    def _start_move(self, start: Callable[[], None]) -> None:
        """Start a move as the script's move thread (async) or with the main loop waiting."""
        self._stop_async_move()
        start()
        if self._read_int(1) == 1:
            self.async_move = True
            self._async_progress(0)
        else:
            self.blocking = True

    def _joint_move(self, q: np.ndarray) -> None:
        speed, accel = self._read_float(6), self._read_float(7)
        self._start_move(lambda: self.controller.arm.move_joints(q, speed, accel))

    def _linear_move(self, tcp_to_base: np.ndarray) -> None:
        limits = MotionLimits(
            linear_speed_mm_s=self._read_float(6) * 1000.0,
            linear_accel_mm_s2=self._read_float(7) * 1000.0,
            settle_s=0.0,
        )
        flange = self.controller.flange_from_tcp(tcp_to_base)
        self._start_move(lambda: self.controller.arm.move_linear(flange, limits, asynchronous=True))

    def move_j(self) -> None:
        self._joint_move(self._read_floats(0))

    def move_j_ik(self) -> None:
        flange = self.controller.flange_from_tcp(pose_from_ur(self._read_floats(0)))
        self._joint_move(closest_ik(flange, self.controller.arm.joints()))

    def move_l(self) -> None:
        self._linear_move(pose_from_ur(self._read_floats(0)))

    def move_l_fk(self) -> None:
        self._linear_move(self.controller.tcp_from_flange(forward_kinematics(self._read_floats(0))))

    def stop(self) -> None:
        """stopL / stopJ: end the move thread, then halt (URSim halts at once)."""
        self._stop_async_move()
        self.controller.arm.stop()
        if self._read_int(1) == 1:
            self._async_progress(0)
            self._async_progress(-1)

    def set_payload(self) -> None:
        self.controller.values["payload"] = self._read_float(0)
        self.controller.values["payload_cog"] = tuple(self._read_floats(1, 3))

    def set_tcp(self) -> None:
        self.controller.tcp_to_flange = pose_from_ur(self._read_floats(0))

    def get_tcp_offset(self) -> None:
        self._write_floats(0, pose_to_ur(self.controller.tcp_to_flange))

    def forward_kinematics(self) -> None:
        self._write_floats(0, pose_to_ur(self.controller.tcp_from_flange(self.controller.flange())))

    def forward_kinematics_args(self) -> None:
        tcp_to_flange = pose_from_ur(self._read_floats(6))
        self._write_floats(0, pose_to_ur(forward_kinematics(self._read_floats(0)) @ tcp_to_flange))

    def inverse_kinematics(self) -> None:
        flange = self.controller.flange_from_tcp(pose_from_ur(self._read_floats(0)))
        self._write_floats(0, closest_ik(flange, self.controller.arm.joints()))

    def inverse_kinematics_args(self) -> None:
        flange = self.controller.flange_from_tcp(pose_from_ur(self._read_floats(0)))
        self._write_floats(0, closest_ik(flange, self._read_floats(6)))

    def is_steady(self) -> None:
        self._write_int(1, int(not self.controller.arm.is_moving()))

    def end(self) -> None:
        self._stop_async_move()


_HANDLERS: dict[int, Callable[[_ControlScript], None]] = {
    1: _ControlScript.move_j,
    2: _ControlScript.move_j_ik,
    3: _ControlScript.move_l,
    4: _ControlScript.move_l_fk,
    17: _ControlScript.set_payload,
    29: _ControlScript.set_tcp,
    30: _ControlScript.inverse_kinematics_args,
    33: _ControlScript.stop,
    34: _ControlScript.stop,
    40: _ControlScript.get_tcp_offset,
    43: _ControlScript.forward_kinematics,
    44: _ControlScript.forward_kinematics_args,
    46: _ControlScript.inverse_kinematics,
    47: _ControlScript.is_steady,
    _STOP_SCRIPT: _ControlScript.end,
}
"""The commands URSim implements, by id."""


class _ScriptParser:
    """Splits URScript text sent to a script port into programs (def/sec ... end) and lines."""

    def __init__(self) -> None:
        self._pending = ""
        self._program: list[str] | None = None

    def feed(self, text: str) -> list[tuple[str, str]]:
        """(program name or "", text) of each program or loose line completed by ``text``.
        ValueError once a program or a line passes MAX_SCRIPT_BYTES."""
        self._pending += text
        *lines, self._pending = self._pending.split("\n")
        held = len(self._pending) + sum(len(line) + 1 for line in self._program or [])
        if held + sum(len(line) for line in lines) > MAX_SCRIPT_BYTES:
            raise ValueError(f"a script of more than {MAX_SCRIPT_BYTES} bytes")
        done = []
        for line in lines:
            if self._program is not None:
                self._program.append(line)
                if line.rstrip() == "end":
                    name = _PROGRAM_START.match(self._program[0]).group(2)
                    done.append((name, "\n".join(self._program)))
                    self._program = None
            elif _PROGRAM_START.match(line):
                self._program = [line]
            elif line.strip():
                done.append(("", line))
        return done


class _Connection:
    """An accepted client socket that any thread may send on or close (at most once)."""

    def __init__(self, sock: socket.socket, on_close: Callable[[_Connection], None]):
        sock.settimeout(_SOCKET_TIMEOUT_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock = sock
        self._on_close = on_close
        self._send_lock = threading.Lock()
        self._closed = threading.Event()

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def send(self, data: bytes) -> bool:
        """Send all of ``data``; a client that does not take it in time is dropped."""
        with self._send_lock:
            if self.closed:
                return False
            try:
                self.sock.sendall(data)
                return True
            except OSError:
                pass
        self.close()
        return False

    def recv(self) -> bytes:
        """The next bytes from the client; b"" once it closed or the connection was dropped."""
        while not self.closed:
            try:
                return self.sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return b""
        return b""

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._on_close(self)


class _RTDESession:
    """One RTDE client: its recipes, and whether its output recipe is being streamed."""

    def __init__(self, sim: URSim, connection: _Connection):
        self.sim = sim
        self.connection = connection
        self.output: Recipe | None = None
        self.inputs: dict[int, Recipe] = {}
        self.claimed: set[str] = set()
        self.input_requests = 0
        self.started = False
        self.every_cycles = 1
        self.refused = False

    def serve(self) -> None:
        """Reader loop: answer requests and apply input data until the client goes."""
        fault = self.sim.fault
        if fault == "garbage":
            self.connection.send(GARBAGE)
        buffer = b""
        while data := self.connection.recv():
            if fault == "garbage":
                self.connection.send(GARBAGE)
                continue
            if fault == "silent" or self.refused:
                continue
            try:
                packages, buffer = split_packages(buffer + data)
                for package_type, payload in packages:
                    self._handle(package_type, payload)
            except RTDEProtocolError as exc:
                self.sim.log(f"RTDE client dropped: {exc}")
                break
        self.connection.close()

    def _reply(self, package_type: PackageType, payload: bytes) -> None:
        self.connection.send(encode_package(package_type, payload))

    def _handle(self, package_type: int, payload: bytes) -> None:
        if package_type == PackageType.REQUEST_PROTOCOL_VERSION:
            accepted = self.sim.fault != "wrong-protocol" and (
                decode_protocol_request(payload) == PROTOCOL_VERSION
            )
            self.refused = not accepted
            self._reply(PackageType.REQUEST_PROTOCOL_VERSION, encode_accepted(accepted))
        elif package_type == PackageType.GET_URCONTROL_VERSION:
            self._reply(PackageType.GET_URCONTROL_VERSION, CONTROLLER_VERSION.encode())
        elif package_type == PackageType.CONTROL_PACKAGE_SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif package_type == PackageType.CONTROL_PACKAGE_SETUP_INPUTS:
            self._setup_inputs(payload)
        elif package_type == PackageType.CONTROL_PACKAGE_START:
            accepted = self.output is not None or bool(self.inputs)
            self._reply(PackageType.CONTROL_PACKAGE_START, encode_accepted(accepted))
            self.started = accepted
        elif package_type == PackageType.CONTROL_PACKAGE_PAUSE:
            self.started = False
            self._reply(PackageType.CONTROL_PACKAGE_PAUSE, encode_accepted(True))
        elif package_type == PackageType.DATA_PACKAGE:
            self._apply_inputs(payload)
        elif package_type != PackageType.TEXT_MESSAGE:
            self._text(f"unknown RTDE package type {package_type}")

    def _text(self, text: str) -> None:
        self._reply(PackageType.TEXT_MESSAGE, TextMessage(text, level=1).encode())

    def _setup_outputs(self, payload: bytes) -> None:
        """A new output recipe (id 1) at up to 500 Hz; id 0 and the types when refused."""
        frequency, names = decode_output_setup(payload)
        recipe = make_recipe(1, names, OUTPUT_VARIABLES)
        accepted = not self.started and recipe.valid and 0.0 < frequency <= CONTROL_FREQUENCY_HZ
        if accepted:
            self.output = recipe
            self.every_cycles = max(1, round(CONTROL_FREQUENCY_HZ / frequency))
        reply = encode_setup_reply(recipe.recipe_id if accepted else 0, recipe.types)
        self._reply(PackageType.CONTROL_PACKAGE_SETUP_OUTPUTS, reply)

    def _setup_inputs(self, payload: bytes) -> None:
        """Input recipes are numbered by request (as ur_rtde assumes); id 0 when refused."""
        self.input_requests += 1
        recipe = self.sim.claim_inputs(self, decode_input_setup(payload), self.input_requests)
        if recipe.valid:
            self.inputs[recipe.recipe_id] = recipe
        reply = encode_setup_reply(recipe.recipe_id if recipe.valid else 0, recipe.types)
        self._reply(PackageType.CONTROL_PACKAGE_SETUP_INPUTS, reply)

    def _apply_inputs(self, payload: bytes) -> None:
        recipe = self.inputs.get(payload[0]) if payload else None
        if recipe is None:
            self._text(f"data package for unknown input recipe {payload[:1].hex()}")
            return
        self.sim.write_inputs(recipe.unpack(payload))

    def data_package(self, cycle: int) -> bytes | None:
        """The data package due in controller cycle ``cycle``, if any (caller holds the lock)."""
        if not self.started or self.output is None or cycle % self.every_cycles:
            return None
        return encode_package(PackageType.DATA_PACKAGE, self.output.pack(self.sim.values))


class URSim:
    """A simulated UR3 e-Series controller on ``host`` (fixed UR ports, see module docstring).

    ``time_scale``, ``seed`` and ``repeatability_mm`` are the arm's (``SimulatedRobot``);
    ``fault`` makes the RTDE server misbehave for tests (one of ``FAULTS``). ``log`` receives
    every text message the controller publishes. A URSim starts once; after ``stop`` make a new
    one (the address can be reused at once).
    """

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        *,
        time_scale: float = 1.0,
        seed: int = 0,
        repeatability_mm: float = 0.03,
        fault: str | None = None,
        log: Callable[[str], None] | None = None,
    ):
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"fault must be one of {FAULTS}, got {fault!r}")
        if not _is_loopback_address(host):
            raise ValueError(f"{host!r} is not a loopback address (127.0.0.0/8): URSim has no access control")
        self.host = host
        self.fault = fault
        self._log = log
        self._messages: list[str] = []
        self._lock = threading.Lock()
        arm = SimulatedRobot(seed=seed, time_scale=time_scale, repeatability_mm=repeatability_mm)
        arm.connect()
        self._controller = _Controller(arm, self._record)
        self._listeners: list[socket.socket] = []
        self._connections: set[_Connection] = set()
        self._sessions: set[_RTDESession] = set()
        self._claims: dict[str, _RTDESession] = {}
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()

    def __enter__(self) -> URSim:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def robot(self) -> SimulatedRobot:
        """The simulated arm (flange poses in mm, joints in rad)."""
        return self._controller.arm

    @property
    def values(self) -> dict[str, object]:
        """Every RTDE variable by name, as streamed (hold no reference across cycles)."""
        return self._controller.values

    @property
    def messages(self) -> list[str]:
        """The text messages the controller published so far."""
        with self._lock:
            return list(self._messages)

    @property
    def program_running(self) -> bool:
        with self._lock:
            return self._controller.program_running

    def log(self, text: str) -> None:
        """Record a line in the controller's log (``log`` callback), not sent to clients."""
        if self._log is not None:
            self._log(text)

    def start(self) -> URSim:
        """Listen on every port and start the controller; raises OSError if a port is taken."""
        try:
            for port, handler in self._ports():
                listener = socket.create_server((self.host, port), reuse_port=False)
                listener.settimeout(_SOCKET_TIMEOUT_S)
                self._listeners.append(listener)
                self._spawn(self._accept, listener, handler)
        except OSError:
            self.stop()
            raise
        self._spawn(self._run_controller)
        return self

    def stop(self) -> None:
        """Close every socket at once (clients see the connection drop) and halt the arm."""
        self._stopping.set()
        for listener in self._listeners:
            try:
                listener.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            listener.close()
        with self._lock:
            connections = list(self._connections)
        for connection in connections:
            connection.close()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join()
        self._threads.clear()
        self._listeners.clear()
        self._controller.arm.stop()

    def claim_inputs(self, session: _RTDESession, names: list[str], recipe_id: int) -> Recipe:
        """An input recipe for ``session``; variables another client holds are ``IN_USE``."""
        with self._lock:
            recipe = make_recipe(recipe_id, names, INPUT_VARIABLES)
            types = tuple(
                IN_USE if self._claims.get(name, session) is not session else data_type
                for name, data_type in zip(recipe.names, recipe.types)
            )
            recipe = Recipe(recipe_id, recipe.names, types)
            if recipe.valid:
                self._claims.update({name: session for name in names})
                session.claimed.update(names)
            return recipe

    def write_inputs(self, values: dict[str, object]) -> None:
        with self._lock:
            self._controller.values.update(values)

    def _record(self, text: str) -> None:
        self._messages.append(text)
        self.log(text)

    def _ports(self) -> list[tuple[int, Callable[[_Connection], None]]]:
        return [
            (DASHBOARD_PORT, self._serve_dashboard),
            *((port, self._serve_script) for port in SCRIPT_PORTS),
            (RTDE_PORT, self._serve_rtde),
        ]

    def _spawn(self, target: Callable, *args) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _accept(self, listener: socket.socket, handler: Callable[[_Connection], None]) -> None:
        while not self._stopping.is_set():
            try:
                sock, _ = listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            connection = _Connection(sock, self._forget)
            with self._lock:
                self._connections.add(connection)
            if self._stopping.is_set():
                connection.close()
                return
            threading.Thread(target=handler, args=(connection,), daemon=True).start()

    def _forget(self, connection: _Connection) -> None:
        with self._lock:
            self._connections.discard(connection)
            for session in [s for s in self._sessions if s.connection is connection]:
                self._sessions.discard(session)
                for name in session.claimed:
                    self._claims.pop(name, None)

    def _run_controller(self) -> None:
        """The controller cycle at 500 Hz: program, state, then each client's data package."""
        period = 1.0 / CONTROL_FREQUENCY_HZ
        next_time = time.monotonic()
        cycle = 0
        while not self._stopping.is_set():
            with self._lock:
                self._controller.step()
                outbox, self._controller.outbox = self._controller.outbox, []
                texts = [
                    encode_package(PackageType.TEXT_MESSAGE, TextMessage(text).encode())
                    for text in outbox
                ]
                outgoing = []
                for session in self._sessions:
                    package = session.data_package(cycle)
                    if session.started and texts:
                        outgoing.append((session.connection, b"".join(texts)))
                    if package is not None:
                        outgoing.append((session.connection, package))
            for connection, data in outgoing:
                connection.send(data)
            cycle += 1
            next_time += period
            delay = next_time - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:
                next_time = time.monotonic()

    def _serve_rtde(self, connection: _Connection) -> None:
        session = _RTDESession(self, connection)
        with self._lock:
            if connection.closed:
                return
            self._sessions.add(session)
        session.serve()

    def _serve_script(self, connection: _Connection) -> None:
        parser = _ScriptParser()
        while data := connection.recv():
            try:
                completed = parser.feed(data.decode(errors="replace"))
            except ValueError as exc:
                self.log(f"script client dropped: {exc}")
                break
            for name, text in completed:
                with self._lock:
                    self._run_script(name, text)
        connection.close()

    def _run_script(self, name: str, text: str) -> None:
        controller = self._controller
        if not name:
            controller.message(f"script line ignored (URSim runs only programs): {text.strip()}")
        elif _CONTROL_SCRIPT_MARK in text:
            controller.start_control_script(text)
        elif text.startswith("sec"):
            controller.message(f"secondary program {name} ignored: URSim does not run it")
        else:
            controller.fault(f"program {name} not run: URSim runs only ur_rtde's control script")

    def _serve_dashboard(self, connection: _Connection) -> None:
        connection.send(f"{DASHBOARD_GREETING}\n".encode())
        pending = b""
        while data := connection.recv():
            *lines, pending = (pending + data).split(b"\n")
            if len(pending) > MAX_LINE_BYTES or any(len(line) > MAX_LINE_BYTES for line in lines):
                connection.send(f"line longer than {MAX_LINE_BYTES} bytes; closing\n".encode())
                break
            for line in lines:
                command = line.decode(errors="replace").strip()
                with self._lock:
                    reply = self._dashboard(command)
                connection.send(f"{reply}\n".encode())
                if command.lower() == "quit":
                    connection.close()
                    return
        connection.close()

    def _dashboard(self, command: str) -> str:
        """The dashboard server's reply to one command line (caller holds the lock)."""
        controller = self._controller
        word = command.lower()
        state = "PLAYING" if controller.program_running else "STOPPED"
        program = "rtde_control" if controller.program_running else "<unnamed>"
        if word == "stop":
            controller.end_program()
        elif word == "power off":
            controller.end_program()
            controller.robot_mode = RobotMode.POWER_OFF
        elif word == "power on" and controller.robot_mode == RobotMode.POWER_OFF:
            controller.robot_mode = RobotMode.IDLE
        elif word == "brake release":
            controller.robot_mode = RobotMode.RUNNING
        elif word in ("unlock protective stop", "restart safety"):
            controller.safety_mode = SafetyMode.NORMAL
        replies = {
            "polyscopeversion": POLYSCOPE_VERSION,
            "get serial number": SERIAL_NUMBER,
            "get robot model": "UR3",
            "is in remote control": "true",
            "robotmode": f"Robotmode: {controller.robot_mode.name}",
            "safetymode": f"Safetymode: {controller.safety_mode.name}",
            "safetystatus": f"Safetystatus: {controller.safety_mode.name}",
            "programstate": f"{state} {program}",
            "running": f"Program running: {str(controller.program_running).lower()}",
            "stop": "Stopped",
            "play": "Failed to execute: play",
            "pause": "Failed to execute: pause",
            "power on": "Powering on",
            "power off": "Powering off",
            "brake release": "Brake releasing",
            "unlock protective stop": "Protective stop releasing",
            "restart safety": "Restarting safety",
            "close safety popup": "closing safety popup",
            "close popup": "closing popup",
            "get loaded program": "No program loaded",
            "isprogramsaved": "false <unnamed>",
            "shutdown": "Shutting down",
            "quit": "Disconnected",
        }
        if word in replies:
            return replies[word]
        verb, _, argument = command.partition(" ")
        prefixed = {
            "load": f"File not found: {argument}",
            "popup": "showing popup",
            "addtolog": "Added log message",
        }
        return prefixed.get(verb.lower(), f"could not understand: '{command}'")


class URSimProcess:
    """URSim in a child process (``python -m core.robot.ursim``), for clients such as ur_rtde that
    cannot share a process with it. ``stop`` kills it (SIGKILL): every socket drops at once."""

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        *,
        time_scale: float = 1.0,
        seed: int = 0,
        repeatability_mm: float = 0.03,
        fault: str | None = None,
        ready_timeout_s: float = 30.0,
    ):
        self.host = host
        self._args = ["--host", host, "--time-scale", repr(time_scale), "--seed", str(seed)]
        self._args += ["--repeatability-mm", repr(repeatability_mm)]
        self._args += ["--fault", fault] if fault else []
        self._ready_timeout_s = ready_timeout_s
        self._process: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()

    def __enter__(self) -> URSimProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def start(self) -> URSimProcess:
        """Start the child and wait until it listens; RuntimeError if it does not."""
        self._process = subprocess.Popen(
            [sys.executable, "-m", "probecal.core.robot.ursim", *self._args],
            stdout=subprocess.PIPE,
            stderr=self._log,
            stdin=subprocess.DEVNULL,
        )
        with selectors.DefaultSelector() as selector:
            selector.register(self._process.stdout, selectors.EVENT_READ)
            ready = selector.select(self._ready_timeout_s)
        line = self._process.stdout.readline().decode() if ready else ""
        if not line.startswith("URSim"):
            self.stop()
            raise RuntimeError(f"URSim on {self.host} did not start: {self.log().strip()[-500:]}")
        return self

    def stop(self) -> None:
        """Kill the child at once (SIGKILL) and reap it."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
        if self._process is not None:
            self._process.wait()
            self._process.stdout.close()

    def log(self) -> str:
        """Everything the child wrote to stderr: its text messages and errors."""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")


def _is_loopback_address(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def main(argv: list[str] | None = None) -> int:
    """``probecal ursim``: run a URSim until SIGINT or SIGTERM; 2 if it cannot listen."""
    parser = argparse.ArgumentParser(
        prog="probecal ursim",
        description="Simulated UR3 e-Series controller (dashboard 29999, RTDE 30004, "
        "script ports 30001-30003) that ur_rtde can drive.",
    )
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to listen on (127.0.0.0/8)")
    parser.add_argument("--time-scale", type=float, default=1.0, help="wall s per robot s")
    parser.add_argument("--seed", type=int, default=0, help="repeatability noise seed")
    parser.add_argument("--repeatability-mm", type=float, default=0.03, help="RMS reach error")
    parser.add_argument("--fault", choices=FAULTS, help="make the RTDE server misbehave")
    args = parser.parse_args(argv)
    try:
        sim = URSim(
            args.host,
            time_scale=args.time_scale,
            seed=args.seed,
            repeatability_mm=args.repeatability_mm,
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
