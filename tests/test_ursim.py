"""The UR controller simulator (core/robot/ursim.py), its wire protocol (core/robot/rtde.py) and the ur_rtde
backend (core/robot/urrobot.py), driven by the REAL ur_rtde 1.6 client.

ur_rtde keeps the GIL while it waits on the network, so it talks to a URSim in a child process
(``URSimProcess``, i.e. ``python -m probecal.app.ursim``); in-process URSims serve our own socket
clients and the backend's connection checks, which fail before ur_rtde is called. ur_rtde uses
fixed ports, so every simulator here has its own loopback address.
"""

import logging
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import rtde_control
import rtde_receive

from probecal.app.ursimprocess import URSimProcess
from probecal.core.acquisition.plan import PoseRanges
from probecal.core.acquisition.rig import Recording, assemble_rig
from probecal.core.geometry.transforms import transform_error
from probecal.core.io.session import load_session
from probecal.core.robot import urrobot as urrobot_module
from probecal.core.robot.armkinematics import kinematics_info, record_of
from probecal.core.robot.contract import HOME_JOINTS, HOME_TOOL_TO_BASE, Robot, RobotError
from probecal.core.robot.primary import (
    KINEMATICS_INFO,
    MAX_PACKAGE_BYTES,
    ROBOT_MESSAGE,
    ROBOT_STATE,
    PrimaryProtocolError,
    frame,
    kinematics_in,
    robot_state,
    version_message,
)
from probecal.core.robot.primary import (
    split_packages as split_primary,
)
from probecal.core.robot.rtde import (
    NOT_FOUND,
    OUTPUT_VARIABLES,
    ControllerVersion,
    PackageType,
    Recipe,
    RTDEProtocolError,
    TextMessage,
    decode_accepted,
    decode_setup_reply,
    encode_input_setup,
    encode_output_setup,
    encode_package,
    encode_protocol_request,
    make_recipe,
    pose_from_ur,
    split_packages,
    ur_from_pose,
)
from probecal.core.robot.ur3 import UR3, ArmModel, MotionLimits, Unreachable, forward_kinematics
from probecal.core.robot.urrobot import (
    PRIMARY_PORT,
    URRobot,
    checked_kinematics,
    probe_controller,
    read_kinematics_info,
)
from probecal.core.robot.ursim import (
    ARM_CALIBRATION_DEG,
    ARM_CALIBRATION_MM,
    CONTROLLER_VERSION,
    DASHBOARD_GREETING,
    DASHBOARD_PORT,
    GARBAGE,
    POLYSCOPE_VERSION,
    RTDE_PORT,
    SCRIPT_PORTS,
    STATE_PORTS,
    URSim,
    arm_calibration,
)
from tests.support.loopback import loopback
from tests.support.waiting import assert_still, wait_until
from tests.test_robot import (
    assert_asynchronous_move_then_wait,
    assert_path_passes_without_stopping,
    shifted,
    stop_once_moving,
    travelled_mm,
)

HOST_IN_PROCESS = loopback(7, 1)
HOST_RTDE_CLIENT = loopback(7, 2)
HOST_URROBOT = loopback(7, 3)
HOST_KILLED = loopback(7, 4)
HOST_WRONG_PROTOCOL = loopback(7, 5)
HOST_GARBAGE = loopback(7, 6)
HOST_SILENT = loopback(7, 7)
HOST_NOTHING = loopback(7, 8)
HOST_STOPPED = loopback(7, 9)
HOST_PRIMARY = loopback(7, 10)
HOST_HOSTILE_PRIMARY = loopback(7, 11)
TIME_SCALE = 0.25
ARM_SEED = 55
TRUTH = ArmModel(UR3, arm_calibration(ARM_SEED))
"""The factory calibration the simulators that ur_rtde drives here compute with."""
def catch_up(receive):
    """Wait until ``receive`` shows the arm still in a state newer than the control stream's
    "done": each ur_rtde interface has its own RTDE connection, and this one may lag."""
    seen = [receive.getTimestamp()]

    def caught_up():
        if receive.getTimestamp() != seen[-1]:
            seen.append(receive.getTimestamp())
        return len(seen) >= 3 and not any(receive.getTargetQd())

    assert wait_until(caught_up)


def dropped(sock):
    """True when the peer closed or reset the connection."""
    try:
        return sock.recv(100) == b""
    except ConnectionResetError:
        return True


class RTDEClient:
    """A minimal RTDE client on core.robot.rtde, for talking to an in-process URSim."""

    def __init__(self, host):
        self.sock = socket.create_connection((host, RTDE_PORT), timeout=5.0)
        self.buffer = b""

    def close(self):
        self.sock.close()

    def send(self, package_type, payload=b""):
        self.sock.sendall(encode_package(package_type, payload))

    def receive(self, package_type):
        """The payload of the next package of ``package_type`` (others are skipped)."""
        while True:
            packages, self.buffer = split_packages(self.buffer)
            for i, (kind, payload) in enumerate(packages):
                if kind == package_type:
                    rest = b"".join(encode_package(k, p) for k, p in packages[i + 1 :])
                    self.buffer = rest + self.buffer
                    return payload
            chunk = self.sock.recv(65536)
            assert chunk, "the simulator closed the connection"
            self.buffer += chunk

    def request(self, package_type, payload=b""):
        self.send(package_type, payload)
        return self.receive(package_type)

    def setup_outputs(self, names, frequency_hz=500.0):
        """(recipe id, types) the simulator answers to an output recipe."""
        payload = encode_output_setup(frequency_hz, names)
        return decode_setup_reply(self.request(PackageType.CONTROL_PACKAGE_SETUP_OUTPUTS, payload))

    def setup_inputs(self, names):
        """(recipe id, types) the simulator answers to an input recipe."""
        payload = encode_input_setup(names)
        return decode_setup_reply(self.request(PackageType.CONTROL_PACKAGE_SETUP_INPUTS, payload))


def dashboard(host, *commands):
    """The greeting and the reply to each command of the dashboard server at ``host``."""
    with socket.create_connection((host, DASHBOARD_PORT), timeout=5.0) as sock:
        lines = sock.makefile("rb")
        replies = [lines.readline().decode().strip()]
        for command in commands:
            sock.sendall(f"{command}\n".encode())
            replies.append(lines.readline().decode().strip())
    return replies


# -- core/robot/rtde.py ------------------------------------------------------------------------------


def test_recipe_packs_and_unpacks_every_type():
    names = ["timestamp", "actual_q", "robot_mode", "runtime_state", "actual_digital_input_bits",
             "joint_mode", "payload_cog", "output_bit_register_64", "tool_output_mode"]
    recipe = make_recipe(3, names, OUTPUT_VARIABLES)
    assert recipe.valid and recipe.types[:4] == ("DOUBLE", "VECTOR6D", "INT32", "UINT32")
    values = {
        "timestamp": 1.5, "actual_q": tuple(np.arange(6.0)), "robot_mode": -1,
        "runtime_state": 2, "actual_digital_input_bits": 2**40, "joint_mode": (253,) * 6,
        "payload_cog": (0.0, 0.1, 0.2), "output_bit_register_64": True, "tool_output_mode": 7,
    }
    payload = recipe.pack(values)
    assert payload[0] == 3 and len(payload) == 1 + 8 + 48 + 4 + 4 + 8 + 24 + 24 + 1 + 1
    assert recipe.unpack(payload) == values
    with pytest.raises(RTDEProtocolError):
        recipe.unpack(payload[:-1])


def test_unknown_variables_make_an_invalid_recipe():
    recipe = make_recipe(1, ["timestamp", "no_such_variable"], OUTPUT_VARIABLES)
    assert recipe.types == ("DOUBLE", NOT_FOUND) and not recipe.valid
    with pytest.raises(RTDEProtocolError):
        recipe.pack({"timestamp": 0.0, "no_such_variable": 0})


def test_packages_are_framed_and_split_across_reads():
    stream = encode_package(PackageType.CONTROL_PACKAGE_START) + encode_package(
        PackageType.TEXT_MESSAGE, TextMessage("hello", "test", 2).encode()
    )
    packages, rest = split_packages(stream[:-3])
    assert packages == [(PackageType.CONTROL_PACKAGE_START, b"")] and rest == stream[3:-3]
    packages, rest = split_packages(rest + stream[-3:])
    assert rest == b"" and TextMessage.decode(packages[0][1]) == TextMessage("hello", "test", 2)
    with pytest.raises(RTDEProtocolError, match="smaller than"):
        split_packages(GARBAGE)
    version = ControllerVersion(5, 11, 11, 7)
    assert ControllerVersion.decode(version.encode()) == version and str(version) == "5.11.11.7"


def test_ur_pose_convention_is_metres_and_rotation_vector():
    pose = ur_from_pose(HOME_TOOL_TO_BASE)
    np.testing.assert_allclose(pose[:3], [0.0, -0.3, 0.25], atol=1e-12)
    assert np.linalg.norm(pose[3:]) == pytest.approx(np.pi)
    np.testing.assert_allclose(pose_from_ur(pose), HOME_TOOL_TO_BASE, atol=1e-12)


# -- URSim in process, with our own clients -----------------------------------------------------


@pytest.fixture(scope="module")
def in_process_sim():
    with URSim(HOST_IN_PROCESS, time_scale=0.0) as sim:
        yield sim


def test_rtde_handshake_recipes_and_stream(in_process_sim):
    client = RTDEClient(HOST_IN_PROCESS)
    try:
        assert decode_accepted(
            client.request(PackageType.REQUEST_PROTOCOL_VERSION, encode_protocol_request())
        )
        version = client.request(PackageType.GET_URCONTROL_VERSION)
        assert ControllerVersion.decode(version) == CONTROLLER_VERSION
        assert client.setup_outputs(["nope"]) == (0, [NOT_FOUND])
        assert client.setup_outputs(["timestamp"], frequency_hz=1000.0) == (0, ["DOUBLE"])
        names = ["timestamp", "actual_TCP_pose", "actual_q", "runtime_state", "robot_mode"]
        recipe_id, types = client.setup_outputs(names, frequency_hz=250.0)
        output = Recipe(recipe_id, tuple(names), tuple(types))
        assert recipe_id == 1 and types == ["DOUBLE", "VECTOR6D", "VECTOR6D", "UINT32", "INT32"]
        inputs = ["input_int_register_7", "input_double_register_7"]
        input_id, input_types = client.setup_inputs(inputs)
        assert input_id == 1 and input_types == ["INT32", "DOUBLE"]
        assert decode_accepted(client.request(PackageType.CONTROL_PACKAGE_START))
        states = [output.unpack(client.receive(PackageType.DATA_PACKAGE)) for _ in range(5)]
        stamps = [state["timestamp"] for state in states]
        assert stamps == sorted(stamps) and len(set(stamps)) == 5
        assert states[-1]["runtime_state"] == 1 and states[-1]["robot_mode"] == 7
        np.testing.assert_allclose(states[-1]["actual_q"], HOME_JOINTS, atol=1e-12)
        np.testing.assert_allclose(
            pose_from_ur(states[-1]["actual_TCP_pose"]), HOME_TOOL_TO_BASE, atol=1e-9
        )
        input_recipe = Recipe(input_id, tuple(inputs), tuple(input_types))
        client.send(PackageType.DATA_PACKAGE, input_recipe.pack(dict(zip(inputs, (42, 2.5)))))
        assert wait_until(lambda: in_process_sim.values["input_int_register_7"] == 42)
        assert in_process_sim.values["input_double_register_7"] == 2.5
    finally:
        client.close()


def test_input_registers_held_by_another_client_are_in_use(in_process_sim):
    first, second = RTDEClient(HOST_IN_PROCESS), RTDEClient(HOST_IN_PROCESS)
    try:
        names = ["input_int_register_20"]
        assert first.setup_inputs(names) == (1, ["INT32"])
        assert second.setup_inputs(names) == (0, ["IN_USE"])
        first.close()
        assert wait_until(lambda: second.setup_inputs(names)[0] > 0)
    finally:
        first.close()
        second.close()


def test_dashboard_server_answers_like_polyscope_5(in_process_sim):
    replies = dashboard(
        HOST_IN_PROCESS, "PolyscopeVersion", "get serial number", "is in remote control",
        "robotmode", "safetystatus", "programState", "close safety popup", "make coffee", "quit",
    )
    assert replies == [
        DASHBOARD_GREETING, POLYSCOPE_VERSION, "20215300001", "true", "Robotmode: RUNNING",
        "Safetystatus: NORMAL", "STOPPED <unnamed>", "closing safety popup",
        "could not understand: 'make coffee'", "Disconnected",
    ]


def test_unknown_command_stops_the_control_script_with_a_message(in_process_sim):
    """Drive the control-script register protocol by hand: an unknown id faults, never hangs."""
    program = "def rtde_control():\n    textmsg(1)\n# NODE_CONTROL_LOOP_BEGINS\nend\n"
    with socket.create_connection((HOST_IN_PROCESS, SCRIPT_PORTS[2]), timeout=5.0) as script:
        script.sendall(program.encode())
        assert wait_until(lambda: in_process_sim.program_running)
    assert in_process_sim.values["output_int_register_0"] == 1  # ready for a command
    in_process_sim.write_inputs({"input_int_register_0": 200})
    assert wait_until(lambda: not in_process_sim.program_running)
    assert "command 200 (unknown command) is not supported" in in_process_sim.messages[-1]


def test_a_stop_left_for_the_previous_program_does_not_end_the_next_one(in_process_sim):
    """ur_rtde's moveL with a path stops the script (255), clears the register over RTDE and
    uploads a new script on another socket: a new script that meets the stale 255 (its clear not
    yet applied) keeps running, or ur_rtde would wait for it forever."""
    program = "def rtde_control():\n    textmsg(1)\n# NODE_CONTROL_LOOP_BEGINS\nend\n"
    in_process_sim.write_inputs({"input_int_register_0": 255})
    with socket.create_connection((HOST_IN_PROCESS, SCRIPT_PORTS[2]), timeout=5.0) as script:
        script.sendall(program.encode())
        assert wait_until(lambda: in_process_sim.program_running)
    cycle = in_process_sim.values["timestamp"]
    assert wait_until(lambda: in_process_sim.values["timestamp"] > cycle + 0.05)  # 25 cycles on
    assert in_process_sim.program_running
    in_process_sim.write_inputs({"input_int_register_0": 0})
    cycle = in_process_sim.values["timestamp"]
    assert wait_until(lambda: in_process_sim.values["timestamp"] > cycle + 0.005)  # the script saw the clear
    in_process_sim.write_inputs({"input_int_register_0": 255})
    assert wait_until(lambda: not in_process_sim.program_running)
    assert "Received stop script!" in in_process_sim.messages

def test_stop_closes_every_connection_at_once():
    sim = URSim(HOST_STOPPED, time_scale=0.0).start()
    rtde, dash = RTDEClient(sim.host), socket.create_connection((sim.host, DASHBOARD_PORT), 5.0)
    dash.recv(100)
    sim.stop()
    assert dropped(rtde.sock) and dropped(dash)
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection((sim.host, RTDE_PORT), timeout=5.0)
    rtde.close()
    dash.close()


# -- the primary interface: the kinematics the controller computes with -------------------------


def test_primary_packages_are_framed_and_the_kinematics_found_among_other_sub_packages():
    info, version = kinematics_info(TRUTH), version_message(CONTROLLER_VERSION)
    stream = version + robot_state(frame(0, bytes(42)), info.encode())
    packages, rest = split_primary(stream[:-4])
    assert [kind for kind, _ in packages] == [ROBOT_MESSAGE] and rest == stream[len(version):-4]
    packages, rest = split_primary(rest + stream[-4:])
    assert rest == b"" and [kind for kind, _ in packages] == [ROBOT_STATE]
    found = kinematics_in(packages[0][1])
    for name in ("theta", "a", "d", "alpha"):
        np.testing.assert_allclose(getattr(found, name), getattr(info, name), rtol=1e-15)
    assert kinematics_in(robot_state(frame(0, bytes(42)))) is None


@pytest.fixture(scope="module")
def primary_sim():
    with URSim(HOST_PRIMARY, time_scale=0.0, arm_calibration_seed=ARM_SEED) as sim:
        yield sim


def _first_packages(host, port, count):
    """The first ``count`` packages a primary-interface client at ``port`` receives."""
    with socket.create_connection((host, port), timeout=5.0) as sock:
        buffer, packages = b"", []
        while len(packages) < count:
            chunk = sock.recv(4096)
            assert chunk, "the simulator closed the connection"
            new, buffer = split_primary(buffer + chunk)
            packages += new
    return packages[:count]


def test_primary_and_secondary_send_the_version_then_the_calibrated_kinematics(primary_sim):
    """The factory calibration lies within the documented ±1 mm and ±0.1° of UR's table, and the
    KinematicsInfo states it (absolute DH parameters, metres on the wire)."""
    truth = TRUTH.deviation
    assert np.abs(np.concatenate([truth.d, truth.a])).max() <= ARM_CALIBRATION_MM
    assert np.degrees(np.abs(np.concatenate([truth.theta, truth.alpha]))).max() <= ARM_CALIBRATION_DEG
    for port in STATE_PORTS:
        (version_kind, version), *states = _first_packages(HOST_PRIMARY, port, 3)
        assert version_kind == ROBOT_MESSAGE and version[9] == 3  # a Version message
        assert struct.unpack_from(">BBii", version, 11 + version[10]) == (5, 11, 11, CONTROLLER_VERSION.build)
        assert [kind for kind, _ in states] == [ROBOT_STATE] * 2
        stated = kinematics_in(states[0][1])
        for name, value in zip(("theta", "a", "d", "alpha"), TRUTH.dh()):
            np.testing.assert_allclose(getattr(stated, name), value, rtol=1e-15)


def test_the_primary_interface_still_takes_urscript(primary_sim):
    with socket.create_connection((HOST_PRIMARY, STATE_PORTS[0]), timeout=5.0) as sock:
        sock.sendall(b"textmsg(1)\n")
        assert wait_until(lambda: any("script line ignored" in m for m in primary_sim.messages))


def test_read_kinematics_info_finds_the_calibration(primary_sim):
    info = read_kinematics_info(HOST_PRIMARY)
    for name, value in zip(("theta", "a", "d", "alpha"), TRUTH.dh()):
        np.testing.assert_allclose(getattr(info, name), value, rtol=1e-15)


def _primary_peer(data):
    """A server on the hostile host's primary port that sends ``data`` to one client, then keeps
    the connection open until the client closes it."""
    listener = socket.create_server((HOST_HOSTILE_PRIMARY, PRIMARY_PORT))

    def serve():
        with listener:
            connection, _ = listener.accept()
            with connection:
                connection.sendall(data)
                connection.recv(1)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return thread


HOSTILE_PRIMARY = {
    "oversized package": struct.pack(">iB", MAX_PACKAGE_BYTES + 1, ROBOT_STATE) + bytes(1000),
    "negative size": struct.pack(">iB", -5, ROBOT_STATE),
    "kinematics of another size": robot_state(frame(KINEMATICS_INFO, bytes(219))),
    "sub-package past its message": robot_state(struct.pack(">iB", 400, KINEMATICS_INFO) + bytes(220)),
}


@pytest.mark.parametrize("kind", sorted(HOSTILE_PRIMARY))
def test_a_corrupt_primary_interface_is_refused_without_waiting(kind):
    """Refused as soon as the package's header or size is read: well before the deadline, at
    which the reader would have returned None."""
    peer = _primary_peer(version_message(CONTROLLER_VERSION) + HOSTILE_PRIMARY[kind])
    with pytest.raises(PrimaryProtocolError):
        read_kinematics_info(HOST_HOSTILE_PRIMARY, timeout_s=30.0)
    peer.join()


def test_a_primary_interface_without_kinematics_gives_none_by_the_deadline():
    peer = _primary_peer(version_message(CONTROLLER_VERSION) + robot_state(frame(0, bytes(42))))
    assert read_kinematics_info(HOST_HOSTILE_PRIMARY, timeout_s=0.3) is None
    peer.join()


# -- the real ur_rtde client against python -m probecal.app.ursim -------------------------------------


@pytest.fixture(scope="module")
def ur_rtde_sim():
    with URSimProcess(HOST_RTDE_CLIENT, time_scale=TIME_SCALE, arm_calibration_seed=ARM_SEED) as sim:
        receive = rtde_receive.RTDEReceiveInterface(HOST_RTDE_CLIENT)
        control = rtde_control.RTDEControlInterface(HOST_RTDE_CLIENT)
        yield sim, receive, control
        del control, receive


def test_receive_interface_streams_the_default_recipe(ur_rtde_sim):
    _, receive, control = ur_rtde_sim
    first = receive.getTimestamp()
    assert wait_until(lambda: receive.getTimestamp() > first)
    q, pose = receive.getActualQ(), receive.getActualTCPPose()
    np.testing.assert_allclose(pose_from_ur(pose), TRUTH.forward(q), atol=1e-6)  # its calibrated kinematics
    assert receive.getRobotMode() == 7 and receive.getSafetyMode() == 1
    assert receive.getRuntimeState() == 2 and control.isProgramRunning()  # the control script
    assert receive.getSpeedScaling() == 1.0 and not receive.isProtectiveStopped()
    assert receive.getJointMode() == [253] * 6


def test_blocking_move_l_reaches_the_target(ur_rtde_sim):
    _, receive, control = ur_rtde_sim
    start = pose_from_ur(receive.getActualTCPPose())
    target = shifted(start, dx=30.0, dz=-20.0, rot_deg=(0.0, 5.0, 10.0))
    assert control.moveL(ur_from_pose(target), 0.2, 1.0)
    catch_up(receive)
    dt, dr = transform_error(pose_from_ur(receive.getActualTCPPose()), target)
    assert dt < 0.1 and dr < 0.02
    assert control.getAsyncOperationProgress() < 0


def test_asynchronous_move_l_then_stop_l_halts_early(ur_rtde_sim):
    _, receive, control = ur_rtde_sim
    start = pose_from_ur(receive.getActualTCPPose())
    target = shifted(start, dx=-150.0)
    assert control.moveL(ur_from_pose(target), 0.1, 0.5, True)
    assert control.getAsyncOperationProgress() >= 0  # running

    def travelled():
        return np.linalg.norm(pose_from_ur(receive.getActualTCPPose())[:3, 3] - start[:3, 3])

    assert wait_until(lambda: travelled() > 5.0)
    control.stopL(2.0)
    assert control.getAsyncOperationProgress() < 0
    catch_up(receive)
    halted = receive.getActualTCPPose()
    catch_up(receive)  # more states from the controller: it stays there
    assert receive.getActualTCPPose() == halted
    assert 5.0 < travelled() < 140.0


def test_move_j_reaches_the_joints_and_is_steady(ur_rtde_sim):
    _, receive, control = ur_rtde_sim
    q = np.array(receive.getActualQ()) + [0.3, -0.1, 0.1, 0.0, 0.0, 0.2]
    assert control.moveJ(list(q), 1.0, 2.0)
    catch_up(receive)
    np.testing.assert_allclose(receive.getActualQ(), q, atol=1e-9)
    assert control.isSteady()
    np.testing.assert_allclose(pose_from_ur(control.getForwardKinematics()), TRUTH.forward(q), atol=1e-6)
    assert transform_error(TRUTH.forward(q), forward_kinematics(q))[0] > 0.1  # not the table's


def test_unsupported_command_stops_the_script_until_it_is_reuploaded(ur_rtde_sim):
    sim, receive, control = ur_rtde_sim
    control.speedL([0.01, 0, 0, 0, 0, 0], 0.5, 0.1)
    assert wait_until(lambda: not control.isProgramRunning())
    assert not control.moveL(receive.getActualTCPPose(), 0.1, 0.5)  # refused, not hung
    assert "command 10 (speedL) is not supported by URSim" in sim.log()
    assert control.reuploadScript()
    assert wait_until(control.isProgramRunning)
    assert control.moveJ(list(HOME_JOINTS), 1.0, 2.0)
    catch_up(receive)
    np.testing.assert_allclose(receive.getActualQ(), HOME_JOINTS, atol=1e-9)


# -- URRobot behaves like SimulatedRobot ---------------------------------------------------------


@pytest.fixture(scope="module")
def urrobot():
    with URSimProcess(HOST_URROBOT, time_scale=TIME_SCALE, arm_calibration_seed=ARM_SEED):
        robot = URRobot(HOST_URROBOT)
        robot.connect()
        yield robot
        robot.disconnect()


@pytest.fixture
def robot(urrobot):
    """The connected URRobot, back at home and idle."""
    urrobot.stop()
    urrobot.move_linear(HOME_TOOL_TO_BASE, MotionLimits(linear_speed_mm_s=400.0, settle_s=0.0))
    return urrobot


def test_urrobot_implements_the_protocol_and_is_safe_when_not_connected():
    robot = URRobot(HOST_NOTHING)
    assert isinstance(robot, Robot) and not robot.connected
    robot.stop()
    assert not robot.is_moving() and robot.wait(0.0)
    with pytest.raises(RobotError, match=f"ur:{HOST_NOTHING}: robot not connected"):
        robot.move_linear(HOME_TOOL_TO_BASE)
    with pytest.raises(RobotError, match="not connected"):
        robot.tool_to_base()


def test_urrobot_reads_pose_joints_and_timestamp_of_one_state(robot):
    first = robot.pose_sample()
    tool_to_base, joints, timestamp_s = robot.pose_sample()
    assert robot.connected and robot.controller_version == CONTROLLER_VERSION
    assert timestamp_s >= first.timestamp_s > 0.0
    np.testing.assert_allclose(TRUTH.forward(joints), tool_to_base, atol=1e-6)
    assert transform_error(tool_to_base, HOME_TOOL_TO_BASE)[0] < 0.1


def test_urrobot_reads_the_controllers_calibrated_kinematics(robot):
    """Read from the primary interface on connect, checked against ur_rtde's getForwardKinematics:
    the simulator's factory calibration, to the last bits metres and mm leave."""
    model = robot.kinematics()
    assert model is not None and model.table is UR3
    for name in ("theta", "d", "a", "alpha"):
        np.testing.assert_allclose(getattr(model.deviation, name), getattr(TRUTH.deviation, name), atol=1e-12)


def test_a_session_recorded_through_ur_rtde_records_the_controllers_kinematics(robot, tmp_path):
    rig = assemble_rig(robot, "URSim", None)
    plan = rig.calibration_plan(2, PoseRanges(), MotionLimits())
    outcome = Recording(rig, "calibration", tmp_path / "cal", plan, MotionLimits()).run()
    assert outcome.complete
    manifest = load_session(tmp_path / "cal").manifest
    assert manifest.arm == "UR3" and manifest.arm_kinematics.model == "UR3"
    truth = record_of(TRUTH)
    for name in ("theta_deg", "d_mm", "a_mm", "alpha_deg"):
        np.testing.assert_allclose(getattr(manifest.arm_kinematics, name), getattr(truth, name), atol=1e-12)


def test_stated_kinematics_are_taken_only_where_they_match_the_controllers_own_forward_kinematics():
    q = HOME_JOINTS + 0.2
    info = kinematics_info(TRUTH)
    model, problem = checked_kinematics(info, q, TRUTH.forward(q))
    assert problem == "" and model.table is UR3
    np.testing.assert_allclose(model.deviation.d, TRUTH.deviation.d, atol=1e-12)
    other = ArmModel(UR3, arm_calibration(ARM_SEED + 1))
    assert "from its own forward kinematics" in checked_kinematics(info, q, other.forward(q))[1]
    assert checked_kinematics(replace(info, a=info.a * 1.5), q, TRUTH.forward(q)) == (
        None, "its KinematicsInfo describes no arm probecal knows")
    # The table with joints 2 and 3 moved 2000 km along their parallel axes: the same flange, but
    # past what a session records.
    table = kinematics_info(ArmModel())
    far = replace(table, d=table.d + [0.0, 2e9, -2e9, 0.0, 0.0, 0.0])
    assert "beyond what a session records" in checked_kinematics(far, q, forward_kinematics(q))[1]


def test_urrobot_takes_the_table_where_the_controller_states_no_kinematics(robot, monkeypatch, caplog):
    monkeypatch.setattr(urrobot_module, "read_kinematics_info", lambda host: None)
    robot.disconnect()
    with caplog.at_level(logging.WARNING, logger=urrobot_module.__name__):
        robot.connect()
    assert robot.kinematics() is None
    assert "sent no KinematicsInfo within 1 s; taking UR's table" in caplog.text
    monkeypatch.undo()
    robot.disconnect()
    robot.connect()
    assert robot.kinematics() is not None


def test_urrobot_blocking_move_reaches_the_target(robot):
    target = shifted(HOME_TOOL_TO_BASE, dx=30.0, dy=-20.0, rot_deg=(0.0, 5.0, 10.0))
    robot.move_linear(target)
    assert not robot.is_moving()
    dt, dr = transform_error(robot.tool_to_base(), target)
    assert dt < 0.1 and dr < 0.02


def test_urrobot_asynchronous_move_then_wait(robot):
    assert_asynchronous_move_then_wait(robot, 10.0)


def test_urrobot_drives_a_path_without_stopping_through_ur_rtdes_move_path(robot):
    assert_path_passes_without_stopping(robot, 20.0)


def test_urrobot_stop_halts_an_asynchronous_move_early(robot):
    start = robot.tool_to_base()
    robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=150.0), asynchronous=True)
    assert wait_until(lambda: travelled_mm(robot, start) > 5.0)
    assert robot.is_moving()
    robot.stop()
    assert not robot.is_moving() and robot.wait(0.0)
    halted = robot.tool_to_base()
    assert_still(robot, halted, time.time())
    assert 5.0 < travelled_mm(robot, start) < 140.0
    assert abs(halted[1, 3] - start[1, 3]) < 0.1 and abs(halted[2, 3] - start[2, 3]) < 0.1


def test_urrobot_stop_interrupts_a_blocking_move_with_an_error(robot):
    stopper = stop_once_moving(robot)
    with pytest.raises(RobotError, match="stopped before reaching the target"):
        robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=150.0))
    stopper.join()
    assert not robot.is_moving()


@pytest.mark.parametrize(
    "target",
    [
        shifted(HOME_TOOL_TO_BASE, dy=-1000.0),  # 1 m away
        shifted(HOME_TOOL_TO_BASE, dy=600.0),  # reachable, but the line crosses the base axis
        np.full((4, 4), np.nan),
    ],
)
def test_urrobot_refuses_unreachable_targets_without_sending(robot, target, monkeypatch):
    sent = []
    monkeypatch.setattr(robot, "_command", lambda what, *args: sent.append(what))
    before = robot.joints()
    with pytest.raises(Unreachable):
        robot.move_linear(target)
    assert sent == [] and not robot.is_moving()
    np.testing.assert_allclose(robot.joints(), before, atol=1e-12)


def test_urrobot_reports_a_program_stopped_from_the_dashboard(robot):
    robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=150.0), asynchronous=True)
    assert dashboard(HOST_URROBOT, "stop")[1] == "Stopped"
    with pytest.raises(RobotError, match="control script not running during moveL"):
        robot.wait(timeout=10.0)
    assert not robot.is_moving()
    with pytest.raises(RobotError, match="refused moveL .control script not running"):
        robot.move_linear(HOME_TOOL_TO_BASE)
    robot.disconnect()
    robot.connect()
    assert robot.connected


def test_urrobot_disconnect_and_reconnect(robot):
    pose = robot.tool_to_base()
    robot.disconnect()
    assert not robot.connected
    robot.stop()
    with pytest.raises(RobotError, match="not connected"):
        robot.joints()
    robot.connect()
    assert robot.connected
    assert transform_error(robot.tool_to_base(), pose)[0] < 1e-6


# -- failures: a clear RobotError, never a hang -------------------------------------------------


def test_killing_the_simulator_mid_move_raises_robot_error():
    sim = URSimProcess(HOST_KILLED, time_scale=1.0).start()
    robot = URRobot(HOST_KILLED)
    try:
        robot.connect()
        robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=150.0), asynchronous=True)
        assert wait_until(robot.is_moving)
        sim.stop()  # mid-move, with no ur_rtde command waiting on the controller
        with pytest.raises(RobotError, match=f"ur:{HOST_KILLED}: connection lost during moveL"):
            robot.wait()
        assert not robot.connected
        robot.stop()
        with pytest.raises(RobotError, match="refused the connection"):
            robot.connect()
    finally:
        sim.stop()
        robot.disconnect()


@pytest.mark.parametrize(
    "fault, host, message",
    [
        ("wrong-protocol", HOST_WRONG_PROTOCOL, "refused RTDE protocol version 2"),
        ("garbage", HOST_GARBAGE, "RTDE server .port 30004. sent an invalid reply"),
        ("silent", HOST_SILENT, "no answer from the RTDE server .port 30004. within 0.5 s"),
    ],
    ids=["wrong-protocol", "garbage", "silent"],  # not the hosts: each parallel worker has its own
)
def test_misbehaving_rtde_server_fails_connect_clearly(fault, host, message):
    with URSim(host, fault=fault):
        robot = URRobot(host, connect_timeout_s=0.5)
        with pytest.raises(RobotError, match=f"^ur:{host}: .*{message}") as error:
            robot.connect()
        assert "\n" not in str(error.value) and not robot.connected


def test_no_controller_fails_connect_clearly():
    with pytest.raises(RobotError, match=f"ur:{HOST_NOTHING}: the dashboard server .* refused"):
        probe_controller(HOST_NOTHING, timeout_s=0.5)


def test_main_refuses_an_address_in_use_with_one_line():
    with URSim(HOST_SILENT, time_scale=0.0):
        result = subprocess.run(
            [sys.executable, "-m", "probecal.app.ursim", "--host", HOST_SILENT],
            capture_output=True, text=True, timeout=60,
        )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [result.stderr.strip()]
    assert f"cannot start on {HOST_SILENT}" in result.stderr
