"""Hostile robot controllers: the real ur_rtde client against a URSim whose streamed joints, TCP
pose or timestamps lie (``core.robot.ursim.HostileState``, run by ``support.fuzz_robot``). What
the controller sends is checked as any input is: connecting to one that sends what no arm can is
refused in one line; a sweep it turns on mid-way ends in one line naming it, halts the robot and
keeps what it recorded, which reads back and calibrates. A session's writer takes only what its
reader takes."""

from __future__ import annotations

import math
import subprocess

import numpy as np
import pytest
import rtde_receive

from probecal.app.console.server import launch
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import RefusedRecord, SessionWriter, load_session, read_pose_stream
from probecal.core.robot.armkinematics import kinematics_info
from probecal.core.robot.contract import HOME_TOOL_TO_BASE, RobotError
from probecal.core.robot.primary import KinematicsInfo, robot_state
from probecal.core.robot.ur3 import ArmModel, MotionLimits
from probecal.core.robot.urrobot import URRobot
from probecal.core.robot.ursim import HostileState
from tests.support.cli import PROBECAL, run_cli
from tests.support.fuzz_robot import hostile_controller
from tests.support.loopback import loopback
from tests.support.refusals import PROGRESS_LINE, assert_one_line_error
from tests.support.waiting import wait_for_frames, wait_for_new_session, wait_until
from tests.test_robot import shifted

NAN = math.nan
QUICK = 0.05
"""Wall seconds per robot second of the hostile controllers: twenty times faster than a UR3."""


def _ended_early(result: subprocess.CompletedProcess, host: str, *said: str) -> str:
    """A sweep's end in one line (exit 1), after nothing but progress, naming the controller and
    what it sent; that line."""
    assert "Traceback" not in result.stderr and "Warning" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.strip().splitlines() if not PROGRESS_LINE.fullmatch(line)]
    assert result.returncode == 1 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"probecal: sweep ended early (ur:{host}: the controller"), lines[0]
    for fragment in said:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def _calibrates(session) -> None:
    """The kept session reads back whole, every frame, and calibrates."""
    loaded = load_session(session)
    for i in range(len(loaded)):
        loaded.image(i)
    read_pose_stream(session)
    result = run_cli("calibrate", session)
    assert result.returncode == 0, result.stderr


# -- connecting: refused in one line ---------------------------------------------------------------

CONNECT = {
    "nan joints": (1, HostileState(joints=(NAN,) * 6), "joints (actual_q) [nan, nan, nan, nan, nan, nan]: not 6 "
                                                         "finite numbers"),
    "nan tcp": (2, HostileState(tcp=(0.0, NAN, 0.0, 0.0, 0.0, 0.0)), "a TCP pose (actual_TCP_pose) ["),
    "tcp at 1e10 mm": (3, HostileState(tcp=(1e7, 0.0, 0.0, 0.0, 0.0, 0.0)), "1e+07 m from its base, beyond any arm's "
                                                                           "reach (10 m)"),
    "tcp turned 1e300 rad": (4, HostileState(tcp=(0.0, 0.0, 0.0, 1e300, 0.0, 0.0)), "rotation vector of 1e+300 rad"),
}


@pytest.mark.parametrize("kind", sorted(CONNECT))
def test_connecting_to_a_controller_that_sends_no_arms_state_is_refused_in_one_line(kind, tmp_path):
    n, hostile, said = CONNECT[kind]
    host = loopback(11, n)
    with hostile_controller(host, hostile):
        result = run_cli("sweep", "calibration", tmp_path / "sw", "--robot", f"ur:{host}", "--poses", "3")
    assert_one_line_error(result, f"ur:{host}: the controller sent", said)
    assert "Warning" not in result.stderr
    assert not (tmp_path / "sw").exists()  # nothing half-written


def test_the_console_refuses_to_connect_to_such_a_controller_in_one_line(tmp_path, capfd):
    host = loopback(11, 5)
    with hostile_controller(host, HostileState(joints=(0.0, 0.0, NAN, 0.0, 0.0, 0.0))):
        console = launch(port=0, robot=f"ur:{host}", sessions_dir=tmp_path)
        try:
            console.connect()
            console.wait(60)
            status = console.panel.status.content
            assert f"Connect failed: ur:{host}: the controller sent joints (actual_q)" in status, status
            assert not console.rig.robot.connected
        finally:
            console.close()
    printed = capfd.readouterr()
    assert "Traceback" not in printed.err + printed.out and "Warning" not in printed.err + printed.out


def test_a_tcp_that_is_not_where_the_joints_put_the_flange_is_refused_but_a_real_arms_slip_is_not():
    """Checked with the arm at rest, against the kinematics the controller states: 50 mm off is a
    TCP that is not the flange; a fifth of a millimetre is within what a real arm's calibration
    moves."""
    lying, honest = loopback(11, 6), loopback(11, 7)
    with hostile_controller(lying, HostileState(tcp=(0.05, 0.0, 0.0, 0.0, 0.0, 0.0))):
        with pytest.raises(RobotError, match=rf"^ur:{lying}: the controller's TCP pose lies 50\.0 mm and 0\.00 deg "
                                             "from where its joints put the flange"):
            URRobot(lying).connect()
    with hostile_controller(honest, HostileState(tcp=(0.0002, 0.0, 0.0, 0.0, 0.0, 0.0))):
        robot = URRobot(honest)
        robot.connect()
        try:
            robot.move_linear(shifted(HOME_TOOL_TO_BASE, dx=20.0), MotionLimits(settle_s=0.0))
            assert robot.connected
        finally:
            robot.disconnect()


KINEMATICS = {
    "nan": (8, robot_state(KinematicsInfo(*np.full((4, 6), np.nan)).encode())),
    "cut short": (15, robot_state(kinematics_info(ArmModel()).encode())[:-40]),
}


@pytest.mark.parametrize("kind", sorted(KINEMATICS))
def test_a_kinematics_info_that_is_nan_or_cut_short_is_set_aside_and_the_arm_still_moves(kind):
    """Already held, and kept so: the controller's stated kinematics are not used, UR's table is."""
    n, state = KINEMATICS[kind]
    host = loopback(11, n)
    with hostile_controller(host, HostileState(robot_state=state)):
        robot = URRobot(host)
        robot.connect()
        try:
            assert robot.kinematics() is None
            robot.move_linear(shifted(HOME_TOOL_TO_BASE, dy=20.0), MotionLimits(settle_s=0.0))
        finally:
            robot.disconnect()


# -- mid-way: the sweep ends at once, the robot halts, what it kept reads back --------------------


def test_a_tcp_of_1e10_mm_mid_sweep_ends_it_and_what_it_kept_calibrates(tmp_path):
    host, out = loopback(11, 9), tmp_path / "sw"
    with hostile_controller(host, HostileState(tcp=(1e7, 0.0, 0.0, 0.0, 0.0, 0.0), after_moves=9), QUICK):
        result = run_cli("sweep", "calibration", out, "--robot", f"ur:{host}", "--poses", "10")
    _ended_early(result, host, "a TCP pose (actual_TCP_pose) 1e+07 m from its base", "frames kept")
    _calibrates(out)


def _calibration_frames(session) -> int:
    """Frames of a continuous calibration sweep's calibration phase recorded so far."""
    records = session / "records.jsonl"
    return records.read_bytes().count(b'"phase": "calibration"') if records.is_file() else 0


def test_nan_joints_mid_way_in_a_continuous_sweep_end_it_without_a_warning(tmp_path):
    host, out = loopback(11, 10), tmp_path / "sw"
    with hostile_controller(host, HostileState(joints=(0.0, NAN, 0.0, 0.0, 0.0, 0.0), after_moves=None),
                            time_scale=0.5) as controller:
        sweep = subprocess.Popen([str(PROBECAL), "sweep", "calibration", out, "--robot", f"ur:{host}", "--poses", "16",
                                  "--motion", "continuous"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            wait_until(lambda: _calibration_frames(out) >= 15, "15 frames of the calibration phase")
            controller.turn_hostile()
            _, stderr = sweep.communicate(timeout=60)
        finally:
            sweep.kill()
    _ended_early(subprocess.CompletedProcess(sweep.args, sweep.returncode, "", stderr), host,
                 "joints (actual_q) [", ", nan, ", "frames kept", "a continuous sweep is not resumed")
    _calibrates(out)


def _assert_halted(host: str) -> None:
    """The arm of the controller at ``host`` has halted and stays where it is, as a ur_rtde client
    of its own reads it (its positions: the controller lies about its TCP's rotation only)."""
    receive = rtde_receive.RTDEReceiveInterface(host)
    try:
        wait_until(lambda: not any(receive.getTargetQd()), "the arm halted", timeout_s=5.0)
        where, since = receive.getActualTCPPose()[:3], receive.getTimestamp()
        wait_until(lambda: receive.getTimestamp() > since + 0.3, "0.3 s more of the controller's state")
        np.testing.assert_allclose(receive.getActualTCPPose()[:3], where, atol=1e-9)
    finally:
        receive.disconnect()


def test_a_console_sweep_ends_on_the_first_bad_state_and_the_robot_halts(tmp_path, capfd):
    host = loopback(11, 11)
    hostile = HostileState(tcp=(0.0, 0.0, 0.0, NAN, 0.0, 0.0), after_moves=None)
    with hostile_controller(host, hostile, time_scale=0.5) as controller:
        console = launch(port=0, robot=f"ur:{host}", sessions_dir=tmp_path)
        try:
            console.connect()
            console.wait(60)
            console.panel.poses.value = 10
            console.start_sweep()
            path = wait_for_new_session(tmp_path, "calibration", set())
            wait_for_frames(path, 2)
            wait_until(console.rig.robot.is_moving, "the robot moving on to the next pose")
            controller.turn_hostile()
            console.wait(30)
            status = console.panel.status.content
            kept = len(load_session(path))
            assert f"Sweep failed: ur:{host}: the controller sent a TCP pose (actual_TCP_pose) [" in status, status
            assert f"{kept} frames kept" in status and kept >= 2
            _assert_halted(host)
        finally:
            console.close()
    printed = capfd.readouterr()
    assert "Traceback" not in printed.err + printed.out and "Warning" not in printed.err + printed.out


@pytest.mark.parametrize("clock_s, said, n", [
    (-5.0, "the controller's timestamp ran backwards, from ", 12),
    (1e10, "the controller's clock leapt 1e+10 s ahead", 13),
    (NAN, "the controller sent the timestamp nan, not a finite number of seconds", 14),
], ids=["backwards", "leaping ahead", "nan"])
def test_timestamps_that_run_backwards_leap_or_are_no_number_end_the_sweep(tmp_path, clock_s, said, n):
    host, out = loopback(11, n), tmp_path / "sw"
    with hostile_controller(host, HostileState(clock_s=clock_s, after_moves=3), QUICK):
        result = run_cli("sweep", "calibration", out, "--robot", f"ur:{host}", "--poses", "6")
    _ended_early(result, host, said, "2 frames kept")
    assert len(load_session(out)) == 2


# -- one rule for both sides: the writer takes only what the reader takes -------------------------

UNREADABLE = {
    "nan pose": dict(tool_to_base=np.full((4, 4), np.nan)),
    "pose at 1e13 mm": dict(tool_to_base=np.array([[1, 0, 0, 1e13], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])),
    "sheared pose": dict(tool_to_base=np.array([[1, 0.1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])),
    "nan timestamp": dict(tool_to_base=np.eye(4), timestamp=math.nan),
    "infinite pose timestamp": dict(tool_to_base=np.eye(4), pose_timestamp=math.inf),
    "field of its own nan": dict(tool_to_base=np.eye(4), plan_index=0, weight=math.nan),
}


@pytest.mark.parametrize("kind", sorted(UNREADABLE))
def test_the_session_writer_refuses_what_its_reader_would(tmp_path, kind):
    with SessionWriter(tmp_path / "s", Manifest(kind="calibration")) as writer:
        writer.append(np.zeros((4, 4), np.uint8), np.eye(4), timestamp=1.0)
        arguments = dict(UNREADABLE[kind])
        with pytest.raises(RefusedRecord, match="frame 1: .*not written: the session's reader would refuse it"):
            writer.append(np.zeros((4, 4), np.uint8), arguments.pop("tool_to_base"), **arguments)
        writer.append(np.zeros((4, 4), np.uint8), None, timestamp=2.0)
    session = load_session(tmp_path / "s")
    assert [r.pose_valid for r in session.records] == [True, False]
    assert sorted(p.name for p in (tmp_path / "s" / "frames").iterdir()) == ["000000.png", "000001.png"]


def test_the_session_writer_refuses_pose_samples_its_reader_would(tmp_path):
    poses = np.broadcast_to(np.eye(4), (3, 4, 4)).copy()
    with SessionWriter(tmp_path / "s", Manifest(kind="calibration")) as writer:
        writer.append_poses(np.array([1.0, 2.0, 3.0]), poses)
        for times, bad in (([4.0, 3.5, 5.0], poses), ([3.0, 4.0, 5.0], poses), ([4.0, np.nan, 5.0], poses),
                           ([4.0, 5.0, 6.0], poses * [[[1.0]], [[1e13]], [[1.0]]])):
            with pytest.raises(RefusedRecord, match=r"posestream\.jsonl: line [45]\b.*not written"):
                writer.append_poses(np.array(times), bad)
        writer.append_poses(np.array([4.0]), poses[:1])
    times, _ = read_pose_stream(tmp_path / "s")
    assert times.tolist() == [1.0, 2.0, 3.0, 4.0]
