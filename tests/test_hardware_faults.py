"""Faults on the real robot path (design §7), with the real ur_rtde client and ``probecal ursim``
in a child process: the controller killed mid-sweep, a controller that speaks garbage or the
wrong protocol, and a move outside the workspace that must never be sent."""

from __future__ import annotations

import subprocess
import time

import pytest

from probecal.app.console.server import launch
from probecal.app.ursimprocess import URSimProcess
from probecal.core.io.session import load_session
from probecal.core.robot.contract import HOME_TOOL_TO_BASE
from probecal.core.robot.safety import GuardedRobot, SafetyError, load_workspace
from probecal.core.robot.urrobot import URRobot
from tests.support.cli import PROBECAL, run_cli
from tests.support.loopback import loopback
from tests.support.refusals import assert_one_line_error
from tests.support.waiting import assert_still, wait_for_frames, wait_for_new_session, wait_until


@pytest.mark.slow
def test_controller_killed_mid_sweep_then_resumed_from_the_command_line(tmp_path):
    host, out = loopback(8, 1), tmp_path / "cal"
    controller = URSimProcess(host, time_scale=0.5).start()
    sweep = subprocess.Popen([str(PROBECAL), "sweep", "calibration", str(out), "--robot", f"ur:{host}",
                              "--poses", "12"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_frames(out, 3)
        killed = time.monotonic()
        controller.stop()
        _, stderr = sweep.communicate(timeout=30)
        assert time.monotonic() - killed < 15.0
    finally:
        sweep.kill()
        controller.stop()
    assert sweep.returncode == 1
    message = stderr.strip().splitlines()[-1]
    kept = len(load_session(out))
    assert "connection lost" in message and f"{kept} frames kept in {out}" in message and "--resume" in message
    assert 3 <= kept < 12

    with URSimProcess(host, time_scale=0.0):
        result = run_cli("sweep", "calibration", out, "--resume")  # the robot and seed come from the session
    assert result.returncode == 0, result.stderr
    session = load_session(out)
    assert sorted(r.extra["plan_index"] for r in session.records) == list(range(12))
    assert len(session.truth()["frames"]) == 12
    assert run_cli("calibrate", out).returncode == 0


@pytest.mark.slow
def test_console_says_when_the_controller_drops_and_resumes_the_same_session(tmp_path):
    host = loopback(8, 2)
    controller = URSimProcess(host, time_scale=0.5).start()
    console = launch(port=0, robot=f"ur:{host}", sessions_dir=tmp_path)
    try:
        console.connect()
        console.wait()
        assert f"Connected to the UR controller at {host}" in console.panel.status.text
        console.panel.poses.value = 10
        console.start_sweep()
        path = wait_for_new_session(tmp_path, "calibration", set())
        wait_for_frames(path, 2)
        controller.stop()
        console.wait(30)
        assert not console.busy
        status = console.panel.status.text
        kept = len(load_session(path))
        assert "Sweep failed" in status and "connection lost" in status and f"{kept} frames kept" in status

        with URSimProcess(host, time_scale=0.0):
            console.connect()
            console.wait(30)
            console.start_sweep()
            console.wait(60)
            assert "Sweep done: 10 frames" in console.panel.status.text
        assert console.calibration_session == path and len(load_session(path)) == 10
    finally:
        console.close()
        controller.stop()


@pytest.mark.parametrize("fault", ["garbage", "wrong-protocol", "silent"])
def test_a_controller_speaking_nonsense_is_a_clear_error_not_a_hang(fault, tmp_path):
    host = {"garbage": loopback(8, 3), "wrong-protocol": loopback(8, 4), "silent": loopback(8, 5)}[fault]
    with URSimProcess(host, fault=fault):
        started = time.monotonic()
        result = run_cli("sweep", "calibration", tmp_path / "cal", "--robot", f"ur:{host}")
        assert time.monotonic() - started < 20.0
    assert_one_line_error(result, f"ur:{host}")
    assert not (tmp_path / "cal").exists()  # nothing half-written


def test_a_pose_outside_the_workspace_is_never_sent():
    host = loopback(8, 6)
    with URSimProcess(host, time_scale=0.0) as controller:
        robot = GuardedRobot(URRobot(host), load_workspace())
        robot.connect()
        try:
            before = robot.tool_to_base()
            outside = HOME_TOOL_TO_BASE.copy()
            outside[2, 3] = -50.0
            refused_at = time.time()
            with pytest.raises(SafetyError, match="outside the workspace box"):
                robot.move_linear(outside)
            assert_still(robot, before, refused_at)
        finally:
            robot.disconnect()
        assert "moveL" not in controller.log()


def test_stop_halts_a_ur_sweep_at_once(tmp_path):
    host = loopback(8, 7)
    with URSimProcess(host, time_scale=1.0):
        console = launch(port=0, robot=f"ur:{host}", sessions_dir=tmp_path)
        try:
            console.connect()
            console.wait(30)
            console.panel.poses.value = 20
            console.start_sweep()
            wait_for_frames(wait_for_new_session(tmp_path, "calibration", set()), 1)
            wait_until(console.rig.robot.is_moving, "the robot moving on to the next pose")
            clicked = time.monotonic()
            console.stop()
            console.wait(10)
            assert time.monotonic() - clicked < 5.0  # a hang guard: Stop's speed is bench_console's figure
            assert "Stopped:" in console.panel.status.text
            stopped_at = time.time()
            assert not console.rig.robot.is_moving()
            assert_still(console.rig.robot, console.rig.robot.tool_to_base(), stopped_at)  # it stays where it stopped
        finally:
            console.close()
