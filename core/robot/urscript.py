"""The controller inside URSim: its state (every RTDE variable, robot and safety modes, the arm)
and the control script ur_rtde uploads, emulated one controller cycle at a time, with the parser
that splits URScript sent to a script port into programs.

The script's register protocol: the command id in input int register 0, arguments in input int
register 1 and input double registers 0.., "ready" (1) and "done with command" (2) in output int
register 0, async progress in output int register 2. Poses are mm inside, metres and rotation
vectors in the registers."""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterable
from enum import IntEnum

import numpy as np

from probecal.core.geometry.transforms import invert_transform
from probecal.core.robot.contract import RobotError
from probecal.core.robot.rtde import OUTPUT_VARIABLES, default_value, pose_from_ur, ur_from_pose
from probecal.core.robot.simulated import SimulatedRobot
from probecal.core.robot.ur3 import MotionLimits, Unreachable

JOINT_RUNNING = 253
MAX_SCRIPT_BYTES = 1 << 20  # one URScript program (ur_rtde's control script is about 60 kB)
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
CONTROL_SCRIPT_MARK = "# NODE_CONTROL_LOOP_BEGINS"
_PROGRAM_START = re.compile(r"^(def|sec)\s+(\w+)\s*\(\s*\)\s*:")
_OFFSET = re.compile(r"global reg_offset_(int|float)\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")
"""ur_rtde injects the register offset after the comment, so the number opens the next line."""
_NUMBER = r"[-+0-9.eE]+"
_PATH_MOVE = re.compile(rf"^\s*movel\(p\[((?:{_NUMBER},){{5}}{_NUMBER})\],a=({_NUMBER}),v=({_NUMBER}),r=({_NUMBER})\)",
                        re.MULTILINE)
"""A moveL of the path ur_rtde injects into the control script's ``exec_move_path`` (moveL with a
path): ``movel(p[x,y,z,rx,ry,rz],a=...,v=...,r=...)``, metres, rad, m/s, m/s^2."""


class Controller:
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
        self.script: ControlScript | None = None
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
        return self.arm.model.forward(self.arm.joints())

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
        self.script = ControlScript(self, offsets.get("int", 0), offsets.get("float", 0), _injected_path(text))
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
        tcp = tuple(ur_from_pose(self.tcp_from_flange(self.arm.tool_to_base())))
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


class ControlScript:
    """ur_rtde's ``rtde_control`` script, emulated one controller cycle (``step``) at a time.

    Follows the script's main loop: realtime commands process and signal ready; any other
    non-zero command id runs once and signals done when finished (a blocking move keeps the loop
    waiting); command 0 clears and signals ready; 255 ends the script. A command URSim does not
    implement is a runtime error: a text message, and the program stops.

    The command that was in the register when the script loaded belongs to the program before
    it and is not run. ur_rtde stops the old program (255), clears the register over RTDE, then
    uploads the new one on the script port: a real controller spends a good part of a second
    compiling it, so the clear has always landed first; here the two sockets are served by
    different threads, and a new script that met the stale 255 would end at once and leave
    ur_rtde waiting for it forever.
    """

    def __init__(self, controller: Controller, int_offset: int, float_offset: int,
                 path: list[tuple[np.ndarray, MotionLimits]] | None = None):
        self.controller = controller
        self.path = path or []  # the moveL path injected into this copy of the script (TCP poses, mm)
        self.int_offset = int_offset
        self.float_offset = float_offset
        self.executing = False
        self.blocking = False
        self.async_move = False
        self.write_count = 0
        self.operation_id = 0
        self.stale_command: int | None = self._read_int(0)
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
        if cmd == self.stale_command:
            cmd = 0
        else:
            self.stale_command = None
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

    def _write_floats(self, index: int, values: Iterable[float]) -> None:
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
        self._joint_move(self.controller.arm.model.closest_ik(flange, self.controller.arm.joints()))

    def move_l(self) -> None:
        self._linear_move(pose_from_ur(self._read_floats(0)))

    def move_l_fk(self) -> None:
        self._linear_move(self.controller.tcp_from_flange(self.controller.arm.model.forward(self._read_floats(0))))

    def move_path(self) -> None:
        """movePath: the injected moveL path, through its poses without stopping at the first
        one's speed and acceleration (URSim rounds the corners by its acceleration-limited blends,
        ``core.robot.trajectory``, not by the blend radii)."""
        if not self.path:
            raise ValueError("no path was injected into the control script")
        flanges = [self.controller.flange_from_tcp(tcp) for tcp, _ in self.path]
        limits = self.path[0][1]
        self._start_move(lambda: self.controller.arm.move_path(flanges, limits, asynchronous=True))

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
        self._write_floats(0, ur_from_pose(self.controller.tcp_to_flange))

    def forward_kinematics(self) -> None:
        self._write_floats(0, ur_from_pose(self.controller.tcp_from_flange(self.controller.flange())))

    def forward_kinematics_args(self) -> None:
        tcp_to_flange = pose_from_ur(self._read_floats(6))
        self._write_floats(0, ur_from_pose(self.controller.arm.model.forward(self._read_floats(0)) @ tcp_to_flange))

    def inverse_kinematics(self) -> None:
        flange = self.controller.flange_from_tcp(pose_from_ur(self._read_floats(0)))
        self._write_floats(0, self.controller.arm.model.closest_ik(flange, self.controller.arm.joints()))

    def inverse_kinematics_args(self) -> None:
        flange = self.controller.flange_from_tcp(pose_from_ur(self._read_floats(0)))
        self._write_floats(0, self.controller.arm.model.closest_ik(flange, self._read_floats(6)))

    def is_steady(self) -> None:
        self._write_int(1, int(not self.controller.arm.is_moving()))

    def end(self) -> None:
        self._stop_async_move()


_HANDLERS: dict[int, Callable[[ControlScript], None]] = {
    1: ControlScript.move_j,
    2: ControlScript.move_j_ik,
    3: ControlScript.move_l,
    4: ControlScript.move_l_fk,
    17: ControlScript.set_payload,
    29: ControlScript.set_tcp,
    30: ControlScript.inverse_kinematics_args,
    33: ControlScript.stop,
    34: ControlScript.stop,
    40: ControlScript.get_tcp_offset,
    43: ControlScript.forward_kinematics,
    45: ControlScript.move_path,
    44: ControlScript.forward_kinematics_args,
    46: ControlScript.inverse_kinematics,
    47: ControlScript.is_steady,
    _STOP_SCRIPT: ControlScript.end,
}
"""The commands URSim implements, by id."""


def _injected_path(text: str) -> list[tuple[np.ndarray, MotionLimits]]:
    """The moveL path ur_rtde injected into a control script: TCP poses (mm) and their limits."""
    path = []
    for pose, accel, speed, _blend in _PATH_MOVE.findall(text):
        limits = MotionLimits(linear_speed_mm_s=float(speed) * 1000.0, linear_accel_mm_s2=float(accel) * 1000.0,
                              settle_s=0.0)
        path.append((pose_from_ur(np.array([float(v) for v in pose.split(",")])), limits))
    return path


class ScriptParser:
    """Splits URScript text sent to a script port into programs (def/sec ... end) and lines."""

    def __init__(self) -> None:
        self._pending = ""
        self._program: list[str] | None = None
        self._program_name = ""

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
                    done.append((self._program_name, "\n".join(self._program)))
                    self._program = None
            elif start := _PROGRAM_START.match(line):
                self._program, self._program_name = [line], start.group(2)
            elif line.strip():
                done.append(("", line))
        return done
