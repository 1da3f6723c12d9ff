"""The console's jobs without a browser: a stopped sweep is resumed into its session, or left
behind for a new one when the operator unticks "Resume an unfinished sweep"; the latency is
measured and used; the phantom is checked after a calibration."""

from __future__ import annotations

import re
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from probecal.app import jobs
from probecal.app.console.panel import DEFAULT_POSES, RED, VERDICT_COLOURS
from probecal.app.console.server import launch
from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.wirecheck import CheckSettings
from probecal.core.geometry.phantom import wire_label
from probecal.core.geometry.probe import LinearProbe
from probecal.core.io.session import load_session
from tests.support.waiting import wait_for_frames, wait_for_new_session


@pytest.fixture
def console(tmp_path, request):
    """A connected console on the simulator, its robot 4x faster than real time unless a test
    asks for another ``time_scale`` (wall s per robot s) with ``indirect`` parametrisation."""
    console = launch(port=0, sessions_dir=tmp_path, time_scale=getattr(request, "param", 0.25))
    console.connect()
    console.wait()
    console.panel.poses.value = 8
    yield console
    console.close()


def _stop_after_first_frame(console) -> None:
    before = set(console.sessions_dir.glob("calibration-*"))
    console.start_sweep()
    wait_for_frames(wait_for_new_session(console.sessions_dir, "calibration", before), 1)
    console.stop()
    console.wait()
    assert "Stopped:" in console.panel.status.text and "Start sweep resumes" in console.panel.status.text


def test_start_sweep_resumes_the_stopped_session(console):
    _stop_after_first_frame(console)
    console.start_sweep()
    console.wait()
    assert "Sweep done: 8 frames" in console.panel.status.text
    sessions = list(console.sessions_dir.glob("calibration-*"))
    assert len(sessions) == 1 and len(load_session(sessions[0])) == 8


def test_unticking_resume_starts_a_new_session(console):
    _stop_after_first_frame(console)
    console.panel.resume.value = False
    console.start_sweep()
    console.wait()
    assert "Sweep done: 8 frames" in console.panel.status.text
    sizes = sorted(len(load_session(p)) for p in console.sessions_dir.glob("calibration-*"))
    assert len(sizes) == 2 and sizes[-1] == 8 and sizes[0] < 8


# The simulated scanner images as fast as the CPU lets it: at half real time, a busy machine
# still records enough frames of the continuous motions for the latency and the calibration.
@pytest.mark.parametrize("console", [0.5], indirect=True)
def test_measure_latency_then_a_continuous_sweep_calibrates_with_the_latency_it_measures(console):
    console.measure_latency()
    console.wait()
    status = console.panel.status.text
    assert "Image latency" in status, status
    truth = console.rig.twin.image_latency_s
    assert console.rig.latency_s == pytest.approx(truth, abs=0.003)
    assert console.panel.latency_ms.value == pytest.approx(truth * 1000, abs=3.0)
    temporal = list(console.sessions_dir.glob("temporal-*"))
    assert len(temporal) == 1 and load_session(temporal[0]).has_pose_stream
    # Moving without stopping, the strip counts frames, not the motion's legs.
    assert re.fullmatch(r"Frames recorded: \d+", console.panel.counter.text), console.panel.counter.text
    console.rig.latency_s = 0.0  # forget it: the continuous calibration sweep measures it again
    console.panel.motion.value = "continuous"
    console.start_sweep()
    console.wait()
    assert "Sweep done" in console.panel.status.text, console.panel.status.text
    console.calibrate()
    console.wait()
    assert console.calibration is not None, console.panel.status.text  # why it failed, if it did
    assert console.calibration.image_latency_s == pytest.approx(truth, abs=0.003)
    assert console.rig.latency_s == console.calibration.image_latency_s
    assert "image latency" in console.panel.results.text


@pytest.mark.parametrize("console", [1.0], indirect=True)
def test_the_volume_grows_live_in_the_console_during_a_continuous_volume_sweep(console):
    """In real time: the scanner's frames come at its rate while the robot moves, and at 4x a busy
    machine's renderer kept only 17 of them (31 idle)."""
    console.panel.motion.value = "continuous"
    console.scan_volume()
    console.wait()
    assert "Sweep done" in console.panel.status.text, console.panel.status.text
    live = console.live_volume
    recorded = len(load_session(console.volume_session))
    assert live is not None and live.frames == recorded > 20
    points, gray = live.points()
    assert len(points) > 1000 and gray.min() >= 128
    assert f"Live volume: {recorded} frames compounded" in console.panel.volume.text
    # The bright voxels lie on the test object, where the twin put it.
    object_to_base = console.rig.scanner.object_to_base
    lo, hi = console.mesh.bounds
    inside = np.all((points - object_to_base[:3, 3]) @ object_to_base[:3, :3] >= lo - 3.0, axis=1)
    assert inside.mean() > 0.9


def test_check_phantom_needs_a_calibration_then_tells_every_wire(console):
    console.check_phantom()
    console.wait()
    assert "no calibration: run Calibrate" in console.panel.status.text
    console.panel.poses.value = DEFAULT_POSES  # the console's own default can decide
    console.start_sweep()
    console.wait()
    console.calibrate()
    console.wait()
    console.check_phantom()
    console.wait()
    status = console.panel.status.text
    assert "Phantom checked from " in status, status
    table = console.panel.phantom_table.text
    for wire in console.rig.twin.phantom.wires:
        assert wire.name in table
    assert f"standard error from {CheckSettings().runs} runs" in table and "verdict" in table
    tables = console.panel.phantom_table.content
    assert tables.count("<table") == 2 and "<pre" not in tables  # tables that fit the panel, not a printout
    # The offsets plotted with their standard errors, each wire's bar in its verdict's colour.
    plot, check = console.panel.offsets, console.phantom_check
    assert plot.visible and len(plot.series) == len(plot.data) == 3 + len(check.wires)
    for k, (wire, bar) in enumerate(zip(check.wires, plot.data[3:])):
        ends = bar[~np.isnan(bar)]
        assert np.allclose(ends, [max(wire.offset_mm - wire.uncertainty_mm, 0.0), wire.offset_mm + wire.uncertainty_mm])
        assert np.all(plot.data[0][~np.isnan(bar)] == k)
        assert plot.series[3 + k]["stroke"] == VERDICT_COLOURS[check.verdict(wire)]
    verdict = console.panel.phantom_check.text  # in words, where the user looks, wires by the plot's labels
    assert "standard error from" not in verdict and console.calibration_session.name in verdict
    labels = [series["label"] for series in plot.series[3:]]
    assert labels == [wire_label(k) for k in range(len(check.wires))]
    named = re.findall(r"\b[1-4][LDR]\b", verdict)
    assert named and set(named) <= set(labels), verdict
    assert (RED in console.panel.status.content) == bool(check.off())  # a wire off is red in the status too
    off = [wire for wire in console.phantom_check.wires if console.phantom_check.verdict(wire) == "off"]
    scene = console.view.scene  # the wires found off, drawn off their definition
    assert scene.wires_off.visible == bool(off) and (not off or len(scene.wires_off.points) == len(off))
    # Every wire is seen in each of the runs, so the check can tell: some wires at least.
    check = console.phantom_check
    # (a busy machine may lose a frame of the sweep to timing; the check needs min_frames of them)
    assert check is not None and check.settings.min_frames <= check.frames_used <= DEFAULT_POSES
    assert all(wire.runs == check.settings.runs for wire in check.wires), [(w.name, w.runs) for w in check.wires]
    assert len(check.unsure()) < len(check.wires), status
    assert f"{len(check.unsure())} unsure" in status or not check.unsure(), status
    assert not check.unsure() or "poses in all to tell the rest" in verdict or "no longer sweep" in verdict, verdict


def test_add_poses_sweeps_what_the_check_asks_for_into_the_session_and_checks_again(console):
    """Eight poses leave the check undecided: it names the poses that would tell, Add poses
    sweeps them into the same session, calibrates and checks again on every frame."""
    console.start_sweep()
    console.wait()
    session = console.calibration_session
    assert console.panel.add_poses.disabled  # nothing asked for yet
    for job in (console.calibrate, console.check_phantom):
        job()
        console.wait()
    verdict = console.panel.phantom_check.text
    asked = int(re.search(r"sweep about (\d+) poses in all", verdict).group(1))
    assert asked > 8 and not console.panel.add_poses.disabled, verdict
    console.add_poses()
    console.wait()
    recorded = len(load_session(session))  # a pose the arm cannot reach is skipped, a frame may be refused
    assert console.calibration_session == session and asked - 3 <= recorded <= asked, (recorded, asked)
    assert console.phantom_check.frames_used > 8 and "Phantom check" in console.panel.status.text
    manifest = load_session(session).manifest
    assert manifest.plan["poses"] == asked


def test_the_pixel_spacing_field_sets_the_nominal_spacing_of_the_live_markers_and_the_sweeps(console):
    """An operator with a scanner that resamples its frames types its nominal spacing, lateral
    then axial (as ``serve --spacing SX SY``): the live markers are found at it, the sweep records
    it and Calibrate starts from it."""
    assert console.panel.spacing.value == pytest.approx(console.rig.twin.probe.nominal_spacing_mm)
    assert console.rig.spacing_mm is None  # the twin probe's, until the operator types one
    typed = (0.095, 0.105)
    console.panel.spacing.value = typed
    assert console.rig.spacing_mm == typed and console.segmenter.spacing_mm == typed
    before = set(console.sessions_dir.glob("calibration-*"))
    console.panel.poses.value = 12
    console.start_sweep()
    console.wait()
    session = load_session(wait_for_new_session(console.sessions_dir, "calibration", before))
    assert session.nominal_spacing_mm == pytest.approx(typed)
    console.calibrate()
    console.wait()
    assert console.calibration is not None, console.panel.status.text
    assert console.calibration.metrics["initial_pixel_spacing_mm"] == pytest.approx(typed)
    # The twin's true spacing is 0.1 x ~0.097 (water at its temperature): the fit finds it again.
    assert console.calibration.pixel_spacing_mm == pytest.approx(console.rig.twin.pixel_spacing_mm, abs=0.002)


def test_a_live_source_that_states_its_spacing_shows_it_in_the_pixel_spacing_field(tmp_path):
    """A source that states its frames' spacing (a replayed session here, an IGTL IMAGE message's
    spacing on a real rig): once connected, the field shows it and the live markers use it."""
    recorded = simulate_calibration(tmp_path / "recorded", n_poses=3, seed=0,
                                    probe=replace(LinearProbe(), width_px=400, height_px=600))
    stated = recorded.pixel_spacing_mm
    assert stated is not None and stated != LinearProbe().nominal_spacing_mm
    console = launch(port=0, sessions_dir=tmp_path / "sessions", image=f"replay:{recorded.path}")
    try:
        console.connect()
        console.wait()
        assert "Connected" in console.panel.status.text, console.panel.status.text
        assert console.panel.spacing.value == pytest.approx(stated)
        assert console.segmenter.spacing_mm == pytest.approx(stated) and console.rig.spacing_mm is None
    finally:
        console.close()


def test_calibrate_runs_its_fits_in_worker_processes_and_stop_ends_it_there(console, monkeypatch):
    """The console's Calibrate is the command line's (``app.jobs.run_calibration``): its fits run
    in worker processes, and Stop still ends it at its next step, the workers dropping the rest;
    the next Calibrate runs whole."""
    pools: list[ProcessPoolExecutor] = []

    class CountedPool(ProcessPoolExecutor):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            pools.append(self)

    monkeypatch.setattr(jobs, "ProcessPoolExecutor", CountedPool)
    console.panel.poses.value = 12
    console.start_sweep()
    console.wait()
    working, steps = console.view.working, []

    def stop_while_fitting(text: str) -> None:
        steps.append(text)
        if "fitting" in text and not console.jobs.stop_requested.is_set():
            console.stop()  # the operator presses Stop once the fits are under way
        working(text)

    monkeypatch.setattr(console.view, "working", stop_while_fitting)
    console.calibrate()
    console.wait()
    assert "Stopped: Calibrate ended before it finished." in console.panel.status.text, steps
    assert console.calibration is None and len(pools) == 1
    assert sum("fitting" in step for step in steps) == 1  # the step after Stop ended it
    monkeypatch.setattr(console.view, "working", working)
    console.calibrate()
    console.wait()
    assert console.calibration is not None, console.panel.status.text
    assert "Calibrated in" in console.panel.status.text and len(pools) == 2
