"""A UR e-Series controller simulator that the real, unmodified ur_rtde 1.6 client drives.

``URSim`` answers on one host address like a PolyScope 5.11 controller: the dashboard server
(29999), RTDE (30004, protocol 2, 500 Hz) and the script ports (30001..30003). The primary and
secondary ports (30001, 30002) also send a Version message on connect and then stream RobotState
messages holding KinematicsInfo (``core.robot.primary``, ``STATE_HZ``), as a controller does. Its
arm is a ``SimulatedRobot`` (mm, rad inside; metres and rotation vectors on the wire), computing
with UR's table or with a factory calibration (``arm_calibration``). It runs the control script
ur_rtde uploads (``core.robot.urscript``). This module is the network side: the servers, their
connections and RTDE sessions (``app.ursim`` runs it as a program).

ur_rtde's Python bindings keep the GIL while they wait on the network, so a ur_rtde client in
the same process as a URSim deadlocks: run the simulator in a child process (``app.ursim``; the
tests' ``support.ursim_process``). Timestamps are wall-clock seconds since start; with
``time_scale`` < 1 the arm moves faster than a real one by that factor.
"""

from __future__ import annotations

import ipaddress
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from probecal.core.robot.armkinematics import kinematics_info
from probecal.core.robot.primary import robot_state, version_message
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
    encode_accepted,
    encode_package,
    encode_setup_reply,
    make_recipe,
    split_packages,
)
from probecal.core.robot.simulated import SimulatedRobot
from probecal.core.robot.ur3 import DhDeviation
from probecal.core.robot.urscript import CONTROL_SCRIPT_MARK, Controller, RobotMode, SafetyMode, ScriptParser

DEFAULT_HOST = "127.0.0.2"
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
"""Primary, secondary and real-time interfaces; each accepts URScript (ur_rtde uses 30003)."""
STATE_PORTS = SCRIPT_PORTS[:2]
"""The interfaces that stream RobotState (with KinematicsInfo) to every client."""
STATE_HZ = 10.0
ARM_CALIBRATION_MM = 1.0
ARM_CALIBRATION_DEG = 0.1
"""How far (±, uniform per DH parameter) a simulated factory calibration moves UR's table."""
RTDE_PORT = 30004
CONTROLLER_VERSION = ControllerVersion(5, 11, 11, 1052000)
POLYSCOPE_BUILD_DATE = "Oct 19 2023"
POLYSCOPE_VERSION = f"URSoftware {CONTROLLER_VERSION} ({POLYSCOPE_BUILD_DATE})"
SERIAL_NUMBER = "20215300001"
DASHBOARD_GREETING = "Connected: Universal Robots Dashboard Server"
CONTROL_FREQUENCY_HZ = 500.0
"""e-Series controller cycle and the highest RTDE output frequency."""
FAULTS = ("wrong-protocol", "garbage", "silent")
"""RTDE server faults for tests: refuse protocol 2, answer with garbage bytes, or never answer."""
GARBAGE = b"\x00\x01garbage\xde\xad\xbe\xef" * 4
"""What the garbage fault sends: its first two bytes are an impossible package size (1)."""
_SOCKET_TIMEOUT_S = 1.0
"""Socket operations wake up this often (s); a client that takes no data for as long is dropped."""
MAX_LINE_BYTES = 4096  # a dashboard command line


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

    def wait_closed(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the connection to close; whether it has."""
        return self._closed.wait(timeout_s)

    def recv(self) -> bytes:
        """The next bytes from the client; b"" once it closed or the connection was dropped."""
        while not self.closed:
            try:
                return self.sock.recv(65536)
            except TimeoutError:
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

    def data_package(self, cycle: int, values: dict[str, object]) -> bytes | None:
        """The data package of ``values`` due in controller cycle ``cycle``, if any (caller holds
        the lock)."""
        if not self.started or self.output is None or cycle % self.every_cycles:
            return None
        return encode_package(PackageType.DATA_PACKAGE, self.output.pack(values))


@dataclass(frozen=True)
class HostileState:
    """What a hostile controller streams in place of its arm's true state, for tests: ``joints``
    (rad) added to the actual_q and ``tcp`` (UR's [x, y, z, rx, ry, rz], metres and rad) to the
    actual_TCP_pose its RTDE server streams, and ``clock_s`` (s) to its timestamp, once its arm has
    begun ``after_moves`` motions (0: from the start; None: once told, :meth:`URSim.turn_hostile`)
    and ``after_s`` more seconds have passed on its clock; ``robot_state``, when given, is the
    RobotState message its primary and secondary ports stream in place of the one stating its
    kinematics."""

    joints: tuple[float, ...] = (0.0,) * 6
    tcp: tuple[float, ...] = (0.0,) * 6
    clock_s: float = 0.0
    after_moves: int | None = 0
    after_s: float = 0.0
    robot_state: bytes | None = None


class _Liar:
    """Applies a :class:`HostileState` to the state a URSim streams, counting its arm's motions."""

    def __init__(self, hostile: HostileState):
        self.hostile = hostile
        self.moves = 0
        self.moving = False
        self.from_s: float | None = hostile.after_s if hostile.after_moves == 0 else None

    def streamed(self, values: dict[str, object], moving: bool) -> dict[str, object]:
        """``values`` as the hostile controller streams them in this cycle (``moving``: its arm is)."""
        hostile, now = self.hostile, float(np.asarray(values["timestamp"]))
        if moving and not self.moving:
            self.moves += 1
            if self.moves == hostile.after_moves:
                self.from_s = now + hostile.after_s
        self.moving = moving
        if self.from_s is None or now < self.from_s:
            return values
        return {**values, "actual_q": tuple(np.asarray(values["actual_q"], dtype=float) + hostile.joints),
                "actual_TCP_pose": tuple(np.asarray(values["actual_TCP_pose"], dtype=float) + hostile.tcp),
                "timestamp": now + hostile.clock_s}


def arm_calibration(seed: int) -> DhDeviation:
    """The factory calibration a URSim with ``arm_calibration_seed`` ``seed`` computes with: DH
    deviations from the UR3's table within ±``ARM_CALIBRATION_MM`` and ±``ARM_CALIBRATION_DEG``."""
    return DhDeviation.draw(np.random.default_rng(seed), ARM_CALIBRATION_MM, ARM_CALIBRATION_DEG)


class URSim:
    """A simulated UR3 e-Series controller on ``host`` (fixed UR ports, see module docstring).

    ``time_scale``, ``seed`` and ``repeatability_mm`` are the arm's (``SimulatedRobot``); with an
    ``arm_calibration_seed`` its controller computes with the calibration :func:`arm_calibration`
    draws from it, else with UR's table. ``fault`` makes the RTDE server misbehave for tests (one
    of ``FAULTS``), and ``hostile`` makes the state it streams lie (:class:`HostileState`). ``log``
    receives every text message the controller publishes. A URSim starts once; after ``stop`` make
    a new one (the address can be reused at once).
    """

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        *,
        time_scale: float = 1.0,
        seed: int = 0,
        repeatability_mm: float = 0.03,
        arm_calibration_seed: int | None = None,
        fault: str | None = None,
        hostile: HostileState | None = None,
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
        calibration = None if arm_calibration_seed is None else arm_calibration(arm_calibration_seed)
        arm = SimulatedRobot(seed=seed, time_scale=time_scale, repeatability_mm=repeatability_mm,
                             controller_calibration=calibration)
        arm.connect()
        self._robot_state = robot_state(kinematics_info(arm.model).encode())
        if hostile is not None and hostile.robot_state is not None:
            self._robot_state = hostile.robot_state
        self._liar = None if hostile is None else _Liar(hostile)
        self._controller = Controller(arm, self._record)
        self._listeners: list[socket.socket] = []
        self._connections: set[_Connection] = set()
        self._sessions: set[_RTDESession] = set()
        self._claims: dict[str, _RTDESession] = {}
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()

    def __enter__(self) -> URSim:
        return self.start()

    def __exit__(self, *exc: object) -> None:
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

    def turn_hostile(self) -> None:
        """Stream the lies of its :class:`HostileState` from now on (its ``after_s`` later)."""
        if self._liar is None:
            raise ValueError("this URSim has no HostileState to turn to")
        with self._lock:
            now = float(np.asarray(self._controller.values["timestamp"]))
            self._liar.from_s = now + self._liar.hostile.after_s

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
            *((port, self._serve_state) for port in STATE_PORTS),
            *((port, self._serve_script) for port in SCRIPT_PORTS if port not in STATE_PORTS),
            (RTDE_PORT, self._serve_rtde),
        ]

    def _spawn(self, target: Callable[..., object], *args: object) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _accept(self, listener: socket.socket, handler: Callable[[_Connection], None]) -> None:
        while not self._stopping.is_set():
            try:
                sock, _ = listener.accept()
            except TimeoutError:
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
                values = self._controller.values
                if self._liar is not None:
                    values = self._liar.streamed(values, self._controller.arm.is_moving())
                outbox, self._controller.outbox = self._controller.outbox, []
                texts = [
                    encode_package(PackageType.TEXT_MESSAGE, TextMessage(text).encode())
                    for text in outbox
                ]
                outgoing = []
                for session in self._sessions:
                    package = session.data_package(cycle, values)
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

    def _serve_state(self, connection: _Connection) -> None:
        """A primary or secondary client: the Version message, RobotState at ``STATE_HZ`` from
        a thread of its own (a client that does not take it is dropped), URScript as any
        script port takes it."""
        threading.Thread(target=self._stream_state, args=(connection,), daemon=True).start()
        self._serve_script(connection)

    def _stream_state(self, connection: _Connection) -> None:
        sent = connection.send(version_message(CONTROLLER_VERSION, build_date=POLYSCOPE_BUILD_DATE))
        while sent and connection.send(self._robot_state):
            sent = not connection.wait_closed(1.0 / STATE_HZ)

    def _serve_script(self, connection: _Connection) -> None:
        parser = ScriptParser()
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
        elif CONTROL_SCRIPT_MARK in text:
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


def _is_loopback_address(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False

