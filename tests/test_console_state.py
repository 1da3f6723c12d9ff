"""The console's state stays true (issue 34, part 4), without a browser: no error before the user
acted, Save writes into the folder the Folder field names, a reconstruction records the
calibration that made it, loading a session clears the other session's layers, and Measure
latency records its motion again, longer, when a slow stream shows too few echoes."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import replace

import numpy as np
import pytest

from probecal.app.console.draw import SLICE_AXES, slice_index
from probecal.app.console.panel import NO_CALIBRATION, NO_PHANTOM_CHECK, NO_VOLUME, RED
from probecal.app.console.scene import MM
from probecal.app.console.server import launch
from probecal.core.calibration.latency import TooFewEchoes, session_latency
from probecal.core.io.session import MANIFEST, load_session
from tests.test_attack_meshes_and_volumes import FIFO_NAMING_MESHES


@pytest.fixture
def console(tmp_path):
    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.25)
    yield console
    console.close()


def _run(console, job) -> str:
    job()
    console.wait()
    return console.panel.status.text


def _calibrated_and_scanned(console):
    """A console that swept 8 poses, calibrated them and scanned a small volume."""
    _run(console, console.connect)
    console.panel.poses.value = 8
    console.panel.frames_per_pass.value = 4
    _run(console, console.start_sweep)
    assert "Calibrated" in _run(console, console.calibrate), console.panel.status.text
    assert "Sweep done" in _run(console, console.scan_volume), console.panel.status.text
    return console.calibration_session, console.volume_session


def test_connect_shows_the_probe_without_an_error_before_the_user_acted(console):
    """Right after Connect the probe looks at no phantom: the live frame says so, not in red."""
    assert "Connected" in _run(console, console.connect)
    shown = console.panel.frame_status.text
    assert "No wire pattern in view" in shown and RED not in shown and "not found" not in shown


def test_save_says_what_it_writes_into_the_calibration_session_and_a_volume_names_its_calibration(console):
    calibration_session, volume_session = _calibrated_and_scanned(console)
    note = console.panel.save_note.text
    assert f"Save writes calibration.json, calibration.xml, segmentation.json into the calibration session " \
           f"{calibration_session.name}" in note, note
    assert not (calibration_session / "calibration.json").exists()  # said, not yet written

    # Reconstructed before a Save: the calibration is written into its session first, and the
    # report names that file with the hash of its bytes, never null.
    assert "Reconstructed" in _run(console, console.reconstruct), console.panel.status.text
    saved = calibration_session / "calibration.json"
    report = json.loads(next(volume_session.glob("reconstruction*/report.json")).read_text())
    assert report["calibration"] == {"file": str(saved.resolve()), "derived": False,
                                     "sha256": hashlib.sha256(saved.read_bytes()).hexdigest()}
    assert report["verdict"]["text"] in console.panel.volume.text

    console.panel.session_path.value = str(volume_session)  # the Folder field is Load's, not Save's
    status = _run(console, console.save_session)
    assert f"into the calibration session {calibration_session}" in status, status
    assert (calibration_session / "segmentation.json").is_file() and not (volume_session / "calibration.json").exists()
    assert json.loads(saved.read_text())["image_to_tool_rigid"] == console.calibration.image_to_tool_rigid.tolist()


def test_loading_a_session_replaces_every_result_of_the_one_before(console):
    calibration_session, volume_session = _calibrated_and_scanned(console)
    status = _run(console, console.check_phantom)  # 8 frames: the check says what it lacks
    assert "unsure, more poses would tell some" in status, status
    assert "poses in all to tell the rest" in console.panel.phantom_check.text
    _run(console, console.reconstruct)
    scene, panel = console.view.scene, console.panel
    assert scene.cloud is not None and scene.object is not None
    shown = panel.volume.text

    # A volume session with a reconstruction on disk shows it, its verdict and its slices.
    _run(console, console.scan_volume)
    assert console.volume_session != volume_session and "Live volume" in panel.volume.text
    assert scene.cloud is None and not panel.slices.visible  # the new scan's, not the last reconstruction
    panel.session_path.value = str(volume_session)
    assert "Loaded volume session" in _run(console, console.load_session), panel.status.text
    assert scene.object is not None and scene.cloud is not None and panel.slices.visible
    assert panel.volume.text == shown and volume_session.name in shown

    # An uncalibrated calibration session: nothing of the calibration before remains.
    uncalibrated = console.sessions_dir / "uncalibrated"
    shutil.copytree(calibration_session, uncalibrated, ignore=shutil.ignore_patterns("calibration.*", "segm*"))
    panel.session_path.value = uncalibrated.name
    assert "Loaded calibration session" in _run(console, console.load_session), panel.status.text
    assert console.calibration is None and NO_CALIBRATION in panel.results.text
    assert panel.report.text == ""
    assert not panel.curve.visible and "Reconstruction" not in panel.counter.text
    assert scene.cloud is None and scene.object is None and scene.live is None
    assert NO_VOLUME in panel.volume.text and not panel.cloud_scale.visible
    assert NO_PHANTOM_CHECK in panel.phantom_check.text and not panel.offsets.visible
    assert "Nothing to save yet" in panel.save_note.text
    assert "Reconstruct failed" in _run(console, console.reconstruct)  # no calibration: nothing to use

    # Its calibrated twin: the calibration and its verdict, naming the session.
    panel.session_path.value = calibration_session.name
    _run(console, console.load_session)
    assert console.calibration is not None and calibration_session.name in panel.results.text
    assert "Calibration usable" in panel.results.text or "Not usable" in panel.results.text


def test_the_reconstructed_volume_shows_in_three_slices_with_window_and_level(console):
    _calibrated_and_scanned(console)
    _run(console, console.reconstruct)
    panel = console.panel
    assert panel.slices.visible
    wide = {axis: panel.slice_images[axis].image for axis in SLICE_AXES}
    assert all(image.max() > 0 for image in wide.values())  # each slice cuts through the object's echoes
    volume = console.view._reconstruction.volume
    x0, sx = volume.origin_mm[0], volume.spacing_mm[0]
    assert panel.slice_at["x"].min == pytest.approx(x0, abs=0.05) and panel.slice_at["x"].step == pytest.approx(sx)
    assert panel.slice_at["x"].max == pytest.approx(x0 + (volume.voxels.shape[2] - 1) * sx, abs=0.05)  # mm, base
    outlines = console.view.scene.slices.points / MM  # each slice's plane in the 3D view, where it cuts
    assert outlines.shape == (12, 2, 3) and np.allclose(outlines[8:, :, 0], panel.slice_at["x"].value, atol=1e-3)
    assert slice_index(volume, "x", panel.slice_at["x"].min) == 0
    panel.slice_at["x"].value = (panel.slice_at["x"].min + panel.slice_at["x"].value) / 2  # the slider moves the cut
    assert not np.array_equal(panel.slice_images["x"].image, wide["x"])
    assert np.allclose(console.view.scene.slices.points[8:, :, 0] / MM, panel.slice_at["x"].value, atol=1e-3)
    panel.window.value = 16
    panel.level.value = int(wide["z"].max()) - 8  # a narrow window at the top: only the brightest echoes stay bright
    narrow = panel.slice_images["z"].image
    assert 0 < (narrow > 0).sum() < (wide["z"] > 0).sum()
    _run(console, console.load_session)  # the folder field names the volume session: loading it reads them back
    assert panel.slices.visible and console.view.scene.slices is not None


def test_measure_latency_records_the_motion_again_longer_when_a_slow_stream_shows_too_few_echoes(console):
    """A stream of 3 frames a second shows too few echoes during the default motion: the console
    moves the probe again, for longer, into a new session, keeps the first, and measures."""
    grabber = console.rig.grabber
    console.rig.grabber = lambda kind: replace(grabber(kind), frame_rate_hz=3.0)
    _run(console, console.connect)
    status = _run(console, console.measure_latency)
    assert "Image latency" in status, status
    sessions = sorted(console.sessions_dir.glob("temporal-*"), key=lambda p: len(load_session(p)))
    assert len(sessions) >= 2
    with pytest.raises(TooFewEchoes):
        session_latency(load_session(sessions[0]))
    assert len(load_session(sessions[-1])) > len(load_session(sessions[0]))


def test_steps_that_cannot_count_their_progress_show_a_moving_bar_not_a_full_one(console, monkeypatch):
    """Calibrate and Reconstruct cannot count their work: while they run the bar is striped and
    moving and the counter names the stage (Reconstruct's bar sat at 100 % for 3.4 s, issue 34);
    once they end it stands still."""
    seen: list[tuple[str, bool]] = []
    working = console.view.working

    def recording(text: str) -> None:
        working(text)
        seen.append((text, console.panel.progress.animated))

    monkeypatch.setattr(console.view, "working", recording)
    _calibrated_and_scanned(console)
    _run(console, console.reconstruct)
    for step in ("Calibrating: ", "Reconstructing: "):
        stages = [animated for text, animated in seen if text.startswith(step)]
        assert stages and all(stages), seen
    assert not console.panel.progress.animated and "surface to CAD" in console.panel.volume.text


def test_a_session_naming_a_mesh_that_names_a_fifo_is_refused_and_the_console_stays_free(console):
    """A glTF whose buffer was a FIFO wedged Reconstruct, and every job after it was "Busy:
    Reconstruct is still running" (issue 35): the mesh is refused and the console works on."""
    _, volume = _calibrated_and_scanned(console)
    os.mkfifo(volume / "fifo")
    (volume / "m.gltf").write_bytes(FIFO_NAMING_MESHES["gltf"])
    manifest = json.loads((volume / MANIFEST).read_text())
    (volume / MANIFEST).write_text(json.dumps({**manifest, "cad_mesh": "m.gltf"}))
    status = _run(console, console.reconstruct)
    assert "not a regular file" in status and "fifo" in status, status
    assert "Busy" not in _run(console, console.connect), console.panel.status.text
