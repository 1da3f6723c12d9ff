"""The console's controller: what its buttons do. It holds the console's state (the rig, the
sessions recorded or loaded, the calibration) and runs each action as a job (``jobs``), calling
``core`` for the work and the view (``view``) for what the tabs show (design §1 step 8, §6 serve).

All state lives on the server, so any number of tabs see the same console. Stop is always live.
When the last tab closes during a sweep, the sweep stops at its next pose and can be resumed (the
dead-man rule), unless the console was started ``unattended``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import trimesh
import viser

from probecal.app.console.gate import Gate
from probecal.app.console.guided import GuidedMode
from probecal.app.console.jobs import JobRunner
from probecal.app.console.panel import (
    BUTTON_HINTS,
    GREEN,
    GREY,
    NO_CALIBRATION_TRACKED,
    NO_SAVE,
    RED,
    VERDICT_COLOURS_BY_USE,
    Panel,
    status_html,
)
from probecal.app.console.view import ConsoleView
from probecal.app.jobs import run_calibration
from probecal.app.report import (
    DEFAULT_TOLERANCE_MM,
    Verdict,
    calibration_verdict,
    reconstruction_verdict,
    self_check_verdict,
    wire_check_summary,
    wire_check_verdict,
)
from probecal.app.tracked import TrackedSpec, tracked_setup
from probecal.core.acquisition.igtl import IgtlPublisher
from probecal.core.acquisition.plan import (
    SELF_CHECK_PASS_MM,
    SELF_CHECK_SPEED_MM_S,
    TEMPORAL_STROKES,
    VOLUME_SPEED_MM_S,
    SweepPlan,
)
from probecal.core.acquisition.rig import Recording, Rig
from probecal.core.acquisition.sweep import (
    ContinuousSweep,
    LiveFrame,
    Sweep,
    SweepOutcome,
    extend_plan,
    resume_state,
)
from probecal.core.calibration.latency import TooFewEchoes, session_latency
from probecal.core.calibration.register import register_frame
from probecal.core.calibration.result import Calibration, calibration_source, load_calibration
from probecal.core.calibration.segment import FrameResult, Segmenter, segment_session, write_segmentation
from probecal.core.calibration.validate import markers_on_wires
from probecal.core.calibration.validity import check_fits
from probecal.core.calibration.wirecheck import WireCheck, check_session, poses_to_tell
from probecal.core.errors import InputError
from probecal.core.geometry.transforms import transform_points
from probecal.core.io.files import inside
from probecal.core.io.jsonio import write_json
from probecal.core.io.session import Session, load_session, read_manifest
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.volume.cad import cad_placement_from_session, session_cad_target
from probecal.core.volume.live import LiveVolume
from probecal.core.volume.reconstruct import REPORT, Reconstruction, reconstruct_session
from probecal.core.volume.saved import load_reconstruction, load_self_check, saved_reconstruction, saved_self_check
from probecal.core.volume.selfcheck import CheckSettings as SelfCheckSettings
from probecal.core.volume.selfcheck import viewed_sweeps, write_self_check

SWEEP_BUTTONS = {"calibration": "Start sweep", "volume": "Scan volume"}
JOBS = frozenset({"Connect", "Start sweep", "Scan volume", "Calibrate", "Check phantom", "Add poses",
                  "Measure latency", "Reconstruct", "Self-check", "Save session", "Load session"})
MOOTED = {"Start sweep": {"Calibrate", "Check phantom", "Save session"}, "Scan volume": {"Reconstruct"},
          "Calibrate": {"Check phantom", "Reconstruct", "Self-check", "Save session"},
          "Measure latency": {"Start sweep"}, "Add poses": {"Calibrate", "Check phantom", "Save session"},
          "Reconstruct": set(), "Check phantom": set(), "Self-check": set(), "Save session": set()}
"""The jobs whose failures a job that runs through makes moot (a new session, a new calibration);
those not named (Connect, Load session) make every failure moot."""
MAX_TEMPORAL_STROKES = 8 * TEMPORAL_STROKES
"""The longest motion Measure latency extends itself to when too few frames show the echo."""
STEP_MARGIN = 0.9
SELF_CHECK_FRAMES = math.ceil(SELF_CHECK_PASS_MM / (STEP_MARGIN * SelfCheckSettings().max_step_mm)) + 1
"""A self-check pass's frames (90): a tenth closer together than the most the check takes."""


def _on_click(button: viser.GuiButtonHandle, action: Callable[[], object]) -> None:
    """Run ``action`` on each click of ``button`` (viser's callbacks return None)."""

    def clicked(_: viser.GuiEvent) -> None:
        action()

    button.on_click(clicked)


class Console:
    """The operator console on a viser server, driving a rig (simulated or real)."""

    def __init__(self, server: viser.ViserServer, rig: Rig, sessions_dir: Path, gate: Gate, unattended: bool = False,
                 tracked: TrackedSpec | None = None):
        self.server, self.rig, self.sessions_dir, self.gate = server, rig, Path(sessions_dir), gate
        self.unattended = unattended
        self._tolerance_mm = DEFAULT_TOLERANCE_MM
        self._stop_said = threading.Lock()  # Stop's status and a stopped job's, in the order they happen
        self._unwatched = threading.Event()  # the last page closed during a job, and none has opened since
        twin = rig.twin
        self.stated_spacing_mm: tuple[float, float] | None = None  # a live image source's, once connected
        self.calibration: Calibration | None = None
        self.calibration_file: Path | None = None  # where the calibration was read or saved (None: not saved)
        self.calibration_session: Path | None = None
        self.calibration_from: Path | None = None  # the session the calibration was made from (Save writes there)
        self.volume_session: Path | None = None
        self.segmentation: list[FrameResult] | None = None
        self.phantom_check: WireCheck | None = None  # the last Check phantom's, of the calibration session
        self.interrupted: dict[str, Path] = {}  # kind -> session of a sweep that ended early
        self.publisher: IgtlPublisher | None = None  # OpenIGTLink output to 3D Slicer
        self._sweep: Sweep | ContinuousSweep | None = None
        self.live_volume: LiveVolume | None = None  # compounded during a volume sweep
        self._work: tuple[np.ndarray, float] = (np.zeros(3), 0.0)  # what "Frame the work" frames: centre, size mm
        tracked_set = None if tracked is None else tracked_setup(tracked)
        phantom = twin.phantom if tracked_set is None or tracked_set.phantom is None else tracked_set.phantom
        self.view = ConsoleView(server, phantom, (twin.probe.width_px, twin.probe.height_px),
                                twin.probe.fan if rig.simulated_images and tracked is None else None)
        self.guided = None if tracked is None or tracked_set is None else GuidedMode(tracked, self.view, tracked_set)
        if self.guided is not None:  # a probe moved by hand: the robot's settings and steps are not shown
            p = self.view.panel
            for handle in (p.motion, p.speed, p.measure_latency, p.poses, p.translation, p.rotation, p.resume,
                           p.add_poses, p.scan, p.self_check, p.frames_per_pass):
                handle.visible = False
            self.view.no_calibration = NO_CALIBRATION_TRACKED
            p.results.show(status_html(NO_CALIBRATION_TRACKED, GREY))
        self._spacing_in_use()
        self.view.scene.set_phantom_pose(twin.nominal.phantom_to_base if self.guided is None else np.eye(4))
        self._frame_phantom(frame=False)
        self.jobs = JobRunner(lambda running: self.view.notify("Busy", f"{running} is still running.", error=False),
                              self._failed, self._ran_through, self._stopped)
        self._wire()
        self._enable_buttons()
        server.on_client_connect(self._page_opened)
        server.on_client_disconnect(self._page_closed)

    def _page_opened(self, _: viser.ClientHandle) -> None:
        self._unwatched.clear()
        sweep = self._sweep
        if sweep is not None:
            sweep.hold.clear()

    def _page_closed(self, _: viser.ClientHandle) -> None:
        """The dead-man rule: with no page left open (closed, or silent for a heartbeat:
        ``heartbeat``), a sweep stops at its next pose (a page that opens before then, a reload,
        lets it go on); one without stops has no next pose, and stops at once."""
        if self.unattended or self.server.get_clients() or not self.jobs.busy:
            return
        self._unwatched.set()
        sweep = self._sweep
        if isinstance(sweep, ContinuousSweep):
            sweep.stop()
        elif sweep is not None:
            sweep.hold.set()

    def _wire(self) -> None:
        p = self.panel
        _on_click(p.connect, self.connect)
        _on_click(p.start, self.start_sweep)
        _on_click(p.stop, self.stop)
        _on_click(p.calibrate, self.calibrate)
        _on_click(p.check_phantom, self.check_phantom)
        _on_click(p.add_poses, self.add_poses)
        _on_click(p.scan, self.scan_volume)
        _on_click(p.reconstruct, self.reconstruct)
        _on_click(p.self_check, self.self_check)
        _on_click(p.save, self.save_session)
        _on_click(p.load, self.load_session)
        _on_click(p.measure_latency, self.measure_latency)
        _on_click(p.view_work, lambda: self.view.frame(*self._work))
        _on_click(p.view_robot, self.view.frame_robot)
        p.cloud_colors.on_update(lambda _: self.view.color_cloud())
        for layer, switch in p.layers.items():
            switch.on_update(self._layer_switched(layer))
        for slider in (p.window, p.level, *p.slice_at.values()):
            slider.on_update(lambda _: self.view.show_slices())
        p.latency_ms.on_update(lambda _: self._latency_typed())
        p.tolerance.on_update(lambda _: self._tolerance_set())
        p.spacing.on_update(lambda _: self._spacing_typed())

    def _ran_through(self, job: str, started: float) -> None:
        """A job ran through: its failures shown before, and those it makes moot, go; the buttons
        follow the state it left."""
        self.view.clear_failures({job, *MOOTED.get(job, JOBS)}, started)
        self._enable_buttons()

    def _failed(self, job: str, message: str) -> None:
        self.view.failed(job, message)
        self._enable_buttons()

    def _impossible(self) -> dict[str, str | None]:
        """Why each button's step cannot run now (None: it can), by button."""
        connected = self.rig.robot.connected if self.guided is None else self.guided.connected
        robot = None if connected else "connect the robot first (1 Connect)"
        if self.guided is not None:
            return self._impossible_tracked(robot)
        calibrated = None if self.calibration is not None else "calibrate first (or load a calibrated session)"
        return {
            "start": robot, "scan": robot, "measure_latency": robot,
            "calibrate": None if self.calibration_session is not None else
            "record a calibration sweep (Start sweep) or load a calibration session first",
            "check_phantom": calibrated if calibrated or self.calibration_session is not None else None,
            "add_poses": robot or (None if self._poses_to_add() is not None else
                                   "Check phantom asks for more poses only when it leaves a wire unsure"),
            "reconstruct": calibrated or (None if self.volume_session is not None else
                                          "scan a volume (Scan volume) or load a volume session first"),
            "self_check": robot or calibrated,
            "save": None if self._save_target() is not None else "calibrate first: frames are saved as they are "
                                                                   "recorded",
        }

    def _impossible_tracked(self, unconnected: str | None) -> dict[str, str | None]:
        """As :meth:`_impossible` for a tracked probe: the robot's steps cannot run."""
        robot_only = "a tracked probe is moved by hand: the robot's steps do not run"
        return {"start": unconnected and "connect the tracked probe first (1 Connect)", "scan": robot_only,
                "measure_latency": "the guided acquisition measures it first", "add_poses": robot_only,
                "self_check": robot_only,
                "calibrate": None if self.calibration_session is not None else
                "record a guided acquisition (Start sweep) or load a calibration session first",
                "check_phantom": None if self.calibration is not None and self.calibration_session is not None else
                "calibrate first (or load a calibrated session)",
                "reconstruct": None if self.calibration is not None and self.volume_session is not None else
                "calibrate and load a volume session first",
                "save": None if self._save_target() is not None else "calibrate first"}

    def _enable_buttons(self) -> None:
        """Each step's button disabled while the step is impossible, its hint saying why."""
        for name, reason in self._impossible().items():
            button = getattr(self.panel, name)
            button.disabled = reason is not None
            button.hint = BUTTON_HINTS.get(name) if reason is None else f"Not yet: {reason}."

    def _layer_switched(self, layer: str) -> Callable[[viser.GuiEvent], None]:
        """What the View step's switch of ``layer`` does: show or hide it as the switch says."""

        def switched(event: viser.GuiEvent) -> None:
            self.view.scene.show_layer(layer, bool(self.panel.layers[layer].value))

        return switched

    @property
    def panel(self) -> Panel:
        return self.view.panel

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The volume test object's CAD mesh (object frame, mm)."""
        return self.rig.scanner.mesh

    @property
    def url(self) -> str:
        """Where browsers open the console (with the token, when one is needed)."""
        host = self.server.get_host()
        address = f"http://{f'[{host}]' if ':' in host else host}:{self.server.get_port()}/"
        return address if self.gate.token is None else f"{address}?token={self.gate.token}"

    @property
    def tolerance_mm(self) -> float:
        """The user's tolerance (mm) every verdict is judged against: the last the field held
        within its bounds."""
        return self._tolerance_mm

    def _refuse_field(self, exc: InputError, field: viser.GuiInputHandle, kept: object) -> None:
        """A field set out of its bounds (by a page: the browser's own field keeps within them)
        goes back to the value in use, and every tab is told."""
        self.view.notify("Not taken", f"{exc}; kept {kept}.", error=False)
        field.value = kept  # type: ignore[misc]  # viser 1.1.1's setter

    @property
    def busy(self) -> bool:
        return self.jobs.busy

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the running job (for scripts and tests)."""
        self.jobs.wait(timeout)

    def close(self) -> None:
        """Stop the robot, close the rig and the server."""
        self.stop()
        self.wait(5.0)
        if self.guided is not None:
            self.guided.close()
        self.rig.close()
        if self.publisher is not None:
            self.publisher.close()
        self.server.stop()

    # --- the buttons: each starts a job, and does nothing while another one runs ---------------

    def connect(self) -> bool:
        """Connect the robot and the image source and show where the probe is."""
        return self.jobs.start("Connect", self._connect)

    def start_sweep(self) -> bool:
        return self.jobs.start("Start sweep", lambda: self._sweep_job("calibration"))

    def scan_volume(self) -> bool:
        return self.jobs.start("Scan volume", lambda: self._sweep_job("volume"))

    def calibrate(self) -> bool:
        return self.jobs.start("Calibrate", self._calibrate)

    def check_phantom(self) -> bool:
        return self.jobs.start("Check phantom", self._check_phantom)

    def add_poses(self) -> bool:
        return self.jobs.start("Add poses", self._add_poses)

    def measure_latency(self) -> bool:
        return self.jobs.start("Measure latency", self._measure_latency)

    def reconstruct(self) -> bool:
        return self.jobs.start("Reconstruct", self._reconstruct)

    def self_check(self) -> bool:
        return self.jobs.start("Self-check", self._self_check)

    def save_session(self) -> bool:
        return self.jobs.start("Save session", self._save)

    def load_session(self) -> bool:
        return self.jobs.start("Load session", self._load)

    def stop(self) -> None:
        """Halt the robot at once and end any sweep (which then reports what it kept; one about to
        start does not); recorded frames stay on disk."""
        self.jobs.stop_requested.set()
        sweep = self._sweep
        if sweep is not None:
            sweep.stop()
            return
        if self.guided is not None and self.guided.stop():
            return
        self.rig.robot.stop()
        # "Stopped." only once nothing runs: a job ends at its next step (its progress) and says so
        # then (_stopped); one that has already ended so is not told it is stopping after.
        with self._stop_said:
            running = self.jobs.current
            if running is None:
                self.view.status("Stopped.", RED)
            elif not self.jobs.interrupted.is_set():
                self.view.status(f"Stopping: {running} ends at its next step ...", RED)

    def _stopped(self, job: str) -> None:
        """A job that Stop ended (it raised Interrupted at a step)."""
        with self._stop_said:
            self.view.status(f"Stopped: {job} ended before it finished.", RED)
        self._enable_buttons()

    # --- robot and sweeps ---------------------------------------------------------------------

    def _connect(self) -> None:
        if self.guided is not None:
            self.guided.connect()
            self.view.show_step("guiding")
            self._frame_phantom()
            self.view.status(f"Connected to {self.guided.name}. Next: 2 Calibrate, Start sweep, then follow the "
                             "guidance.", GREEN)
            return
        self.rig.open()
        if not self.rig.simulated_images:
            self.stated_spacing_mm = self.rig.image_format()[1]
            self._spacing_in_use()
        image, pose = self.rig.snapshot()
        self.view.show_step("calibrating")
        self.show(LiveFrame(image, pose, self.rig.robot.joints(), None, 0, 0), "calibration")
        self.view.status(f"Connected to {self.rig.robot_name} and {self.rig.image_name}. "
                         "Next: 2 Calibrate, Start sweep.", GREEN)

    def _require_connected(self) -> None:
        if not self.rig.robot.connected:
            raise InputError(None, "the robot is not connected: click Connect first")

    def _new_session_dir(self, kind: str) -> Path:
        return _free_dir(self.sessions_dir / f"{kind}-{datetime.now():%Y%m%d-%H%M%S}")

    def _resuming(self, kind: str) -> bool:
        """Whether a sweep of this kind continues the unfinished one (the panel's choice)."""
        if not self.panel.resume.value:
            self.interrupted.pop(kind, None)
        return kind in self.interrupted

    def _sweep_job(self, kind: str) -> None:
        """A sweep of ``kind`` (calibration or volume): planned now, or resumed where the last one
        of that kind ended; a tracked probe's guided acquisition."""
        if self.guided is not None:
            self._guided_job()
            return
        self._require_connected()
        plan = None
        if not self._resuming(kind):
            limits = self.panel.limits()
            if kind == "calibration":
                plan = self.rig.calibration_plan(self.panel.pose_count(), self.panel.ranges(), limits,
                                                 progress=self._progress("Planning"))
            else:
                plan = self.rig.volume_plan(self.panel.frames_count(), limits, progress=self._progress("Planning"))
        self.view.show_step("scanning" if kind == "volume" else "calibrating")
        if kind == "volume":  # the new scan's volume, not the last session's
            self.view.clear_volume()
        else:
            self.view.clear_calibration_session()
        if kind == "volume" and self.rig.simulated_images:
            self.view.show_object(self.mesh, self.rig.scanner.object_to_base)
        self.live_volume = None
        if kind == "volume" and plan is not None:
            self.live_volume = LiveVolume(plan.poses, self._image_to_tool(), self._image_size())
        if plan is not None:
            self._frame_plan(plan)
        self._acquire(kind, plan, recorded=self._recorded)

    def _guided_job(self) -> None:
        """A guided acquisition into a new calibration session until the bound is within the
        tolerance, then the calibration of it; Stop ends it keeping every frame recorded."""
        assert self.guided is not None
        path = self._new_session_dir("calibration")
        self.view.clear_calibration_session()
        self.view.status("Guided acquisition: follow the guidance below ...", GREEN)
        outcome = self.guided.run(path, self.tolerance_mm, lambda: self._recording_into(path))
        self.calibration_session, self.segmentation, self.phantom_check = path, None, None
        if outcome.enough:
            self.view.status(f"Enough frames: the bound is within {self.tolerance_mm:g} mm. Calibrating ...", GREEN)
            self._calibrate()
            return
        kept = len(load_session(path))
        if outcome.stopped or self.jobs.stop_requested.is_set():
            self.view.status(f"Stopped: {kept} frames kept in {path}; Calibrate calibrates them.", RED)
        else:
            self.view.status(f"Guided acquisition failed: {outcome.error}. {kept} frames kept in {path}.", RED)
            self.view.notify("Guided acquisition failed", f"{outcome.error} ({kept} frames kept in {path})",
                             job=self.jobs.current)

    def _recording_into(self, path: Path) -> None:
        """The Folder field names the session being recorded, once it exists."""
        self.panel.session_path.value = str(path)  # type: ignore[misc]  # viser 1.1.1 has a setter mypy cannot see

    def _recorded(self, kind: str, path: Path) -> None:
        """The session a sweep of ``kind`` recorded into ``path`` is the one the next steps use."""
        if self.live_volume is not None:
            self.view.show_live_volume(self.live_volume)
        if kind == "calibration":  # a segmentation and a phantom check are of one session
            self.calibration_session, self.segmentation, self.phantom_check = path, None, None
        else:
            self.volume_session = path

    def _measure_latency(self) -> None:
        """Move the probe up and down over the phantom while the stream is recorded (a temporal
        session), measure how late the images are, and pair every later sweep with it. When too
        few frames show the echo (a slow stream), the motion is recorded again, longer, into a new
        session (the first one is kept)."""
        self._require_connected()
        self.view.show_step("calibrating")
        strokes = TEMPORAL_STROKES
        while True:
            path, _ = self._acquire("temporal", self.rig.temporal_plan(strokes), "continuous")
            try:
                estimate = session_latency(load_session(path))
                break
            except TooFewEchoes as exc:  # a slow image stream: the motion again, longer
                if exc.found == 0 or strokes >= MAX_TEMPORAL_STROKES:
                    raise
                strokes = min(MAX_TEMPORAL_STROKES, math.ceil(strokes * max(2.0, 1.5 * exc.needed / exc.found)))
                self.view.status(f"Only {exc.found} frames showed the echo ({exc.needed} needed): moving the probe "
                                 f"up and down again, {strokes} strokes ...", GREEN)
        self._use_latency(estimate.image_latency_s)
        self.view.status(f"Image latency {estimate.image_latency_s * 1000:.1f} ± {estimate.std_error_s * 1000:.1f} ms "
                         f"(echo-motion correlation {abs(estimate.correlation):.4f}, {estimate.frames_used} frames); "
                         "later sweeps pair their frames with it.", GREEN)

    def _latency_typed(self) -> None:
        """The operator's image latency (ms in the panel); the field showing a measured one, to
        0.1 ms, leaves that one as measured."""
        in_use_ms = round(self.rig.latency_s * 1000.0, 1)
        try:
            typed_s = self.panel.latency_s()
        except InputError as exc:
            self._refuse_field(exc, self.panel.latency_ms, in_use_ms)
            return
        if round(typed_s * 1000.0, 1) != in_use_ms:
            self.rig.latency_s = typed_s

    @property
    def nominal_spacing_mm(self) -> tuple[float, float]:
        """The scanner's nominal (sx, sy) mm/px, as sweeps record it (``Rig.image_format``): the
        operator's (Pixel spacing, ``serve --spacing``), else the one a live source states, else
        the twin probe's."""
        return self.rig.spacing_mm or self.stated_spacing_mm or self.rig.twin.probe.nominal_spacing_mm

    def _spacing_typed(self) -> None:
        """The operator's nominal spacing: the live markers are found and registered at it, and
        the next sweep records it (a calibration starts from it)."""
        try:
            sx, sy = self.panel.spacing_mm()
        except InputError as exc:
            self._refuse_field(exc, self.panel.spacing, self.nominal_spacing_mm)
            return
        if (sx, sy) != self.nominal_spacing_mm:
            self.rig.spacing_mm = (sx, sy)
            self._spacing_in_use()

    def _spacing_in_use(self) -> None:
        """The live markers found and registered, and the image plane drawn, at the nominal
        spacing, and the Pixel spacing field showing it."""
        self.segmenter = Segmenter.create(self.rig.twin.phantom, self.nominal_spacing_mm)
        self.view.scene.set_image_mount(self._image_to_tool())
        self.panel.spacing.value = self.nominal_spacing_mm  # type: ignore[misc]  # viser 1.1.1's setter

    def _use_latency(self, latency_s: float) -> None:
        self.rig.latency_s = latency_s
        self.panel.latency_ms.value = round(latency_s * 1000.0, 1)  # type: ignore[misc]  # viser 1.1.1's setter

    def _acquire(self, kind: str, plan: SweepPlan | None, motion: str | None = None,
                 recorded: Callable[[str, Path], None] | None = None) -> tuple[Path, SweepOutcome]:
        """Run a sweep into a session: a new one, or the one an earlier sweep of this kind left
        unfinished (``plan`` None: resumed where it ended); a self-check's (``kind`` "selfcheck")
        is a volume sweep, never resumed. The session keeps whatever was recorded. ``motion`` is
        the panel's unless given. ``recorded(kind, path)`` comes before the status tells how the
        sweep went: once it does, the next step can start. Returns the session and how it went."""
        path = self.interrupted.pop(kind) if plan is None else self._new_session_dir(kind)
        motion = motion or self.panel.motion_choice()
        recorded_as = "volume" if kind == "selfcheck" else kind
        recording = Recording(self.rig, recorded_as, path, plan, self.panel.limits(),
                              lambda f: self.show(f, recorded_as), motion if plan is not None else "stop",
                              SELF_CHECK_SPEED_MM_S if kind == "selfcheck" else VOLUME_SPEED_MM_S)
        self._sweep = recording.sweep
        if self.jobs.stop_requested.is_set():  # Stop came while the sweep was being planned
            recording.sweep.stop()
        if self._unwatched.is_set():  # the last page closed while it was being planned
            recording.sweep.hold.set()
        self.panel.session_path.value = str(path)  # type: ignore[misc]  # viser 1.1.1 has a setter mypy cannot see
        total, done = recording.sweep.total, len(recording.done)
        unit = "frames" if recorded_as == "volume" else "poses"
        verb = f"Resuming ({done} of {total} {unit} done)" if done else f"Sweeping {total} {unit}"
        if isinstance(recording.sweep, ContinuousSweep):
            verb = "Moving without stopping, recording every frame,"
            self.view.counter("Frames recorded: 0", 0.0)  # not the last job's count
        else:
            self.view.counter(f"Frames recorded: {done} / {total}", 100.0 * done / max(total, 1))
        self.view.status(f"{verb} into {path} ...", GREEN)
        started = time.monotonic()
        try:
            outcome = recording.run()
        finally:
            self._sweep = None
            unwatched = self._unwatched.is_set()
            self._unwatched.clear()
        outcome.held = outcome.held or (outcome.stopped and unwatched)  # a sweep without stops is halted, not held
        if recorded is not None:
            recorded(kind, path)
        self._report_sweep(kind, path, outcome, recording.frames, time.monotonic() - started,
                           isinstance(recording.sweep, Sweep) and kind in SWEEP_BUTTONS)
        if not outcome.complete and kind == "temporal":
            raise InputError(path, "the latency motion ended early; Measure latency again")
        return path, outcome

    def _report_sweep(self, kind: str, path: Path, outcome: SweepOutcome, recorded: int, seconds: float,
                      resumable: bool) -> None:
        if outcome.complete:
            after = {"calibration": " Next: Calibrate.", "volume": " Next: Reconstruct.",
                     "selfcheck": " Checking the views ..."}.get(kind, "")
            self.view.status(f"Sweep done: {recorded} frames in {seconds:.1f} s{outcome.notes()}.{after}", GREEN)
            return
        self.view.counter(f"Frames recorded: {recorded}; the sweep ended early", float(self.panel.progress.value))
        if resumable:
            self.interrupted[kind] = path
            resume = f"; {SWEEP_BUTTONS[kind]} resumes the {outcome.remaining} poses left"
        elif kind == "selfcheck":
            resume = "; Self-check records a new sweep"
        else:
            resume = "; a sweep without stops is not resumed: record a new one"
        if outcome.held:
            self.view.status(f"Stopped: no console page was open (serve --unattended lets a sweep run on); "
                             f"{recorded} frames kept in {path}{outcome.notes()}{resume}.", RED)
        elif outcome.stopped:
            self.view.status(f"Stopped: {recorded} frames kept in {path}{outcome.notes()}{resume}.", RED)
        else:
            self.view.status(f"Sweep failed: {outcome.error}. {recorded} frames kept in {path}{outcome.notes()}"
                             f"{resume}.", RED)
            self.view.notify("Sweep failed", f"{outcome.error} ({recorded} frames kept in {path})",
                             job=self.jobs.current)

    # --- what a frame shows -------------------------------------------------------------------

    def _frame_phantom(self, frame: bool = True) -> None:
        """The work is the phantom, where the calibration (else the set-up) puts it."""
        phantom = self.rig.twin.phantom if self.guided is None else self.guided.phantom
        if self.calibration is not None and self.calibration.phantom_to_base is not None:
            phantom_to_base = self.calibration.phantom_to_base
        elif self.guided is not None:  # drawn in its own frame: the guidance is
            phantom_to_base = np.eye(4)
        else:
            phantom_to_base = self.rig.twin.nominal.phantom_to_base
        centre = transform_points(phantom_to_base, phantom.center()[None])[0]
        self._work = (centre, float(np.linalg.norm(np.asarray(phantom.box_max) - phantom.box_min)))
        if frame:
            self.view.frame(*self._work)

    def _frame_plan(self, plan: SweepPlan) -> None:
        """The work is where the plan puts the image: the centres of its images, and their spread."""
        width, height = self._image_size()
        image_to_tool = self._image_to_tool()
        centres = np.array([transform_points(pose @ image_to_tool, np.array([[width / 2, height / 2, 0.0]]))[0]
                            for pose in plan.poses])
        size = float(np.ptp(centres, axis=0).max()) + float(np.linalg.norm(image_to_tool[:3, 1])) * height
        self._work = (centres.mean(axis=0), size)
        self.view.frame(*self._work)

    def _image_to_tool(self) -> np.ndarray:
        """Pixels (as the frames show them) to tool mm: the calibration's, else the mount's design at
        the nominal spacing."""
        if self.calibration is not None:
            return self.calibration.shown_image_to_tool
        return self.rig.twin.nominal.image_to_tool_rigid @ self.rig.twin.probe.scale_matrix(self.nominal_spacing_mm)

    def _image_size(self) -> tuple[int, int]:
        probe = self.rig.twin.probe
        if self.rig.simulated_images:
            return probe.width_px, probe.height_px
        height, width = self.rig.snapshot()[0].shape
        return width, height

    def show(self, frame: LiveFrame, kind: str) -> None:
        """Put a frame on every tab: a calibration frame with the markers found in it and, once
        recorded, registered to the phantom; a recorded volume frame compounded into the live
        volume; and send it to 3D Slicer when publishing."""
        result = self.segmenter(frame.image, frame.index or 0) if kind != "volume" else None
        if result is not None and frame.index is not None:
            self._show_registration(result)
        live = self.live_volume
        if kind == "volume" and frame.index is not None and live is not None:
            live.insert(frame.image, frame.tool_to_base)
            if live.due():
                self.view.show_live_volume(live)
        self.view.show_frame(frame, result)
        if self.publisher is not None:
            self.publisher.publish_frame(frame.image, frame.tool_to_base, time.time())

    def _show_registration(self, result: FrameResult) -> None:
        """The frame's markers registered at the calibrated spacing and phantom pose (the nominal
        ones before a calibration)."""
        if self.calibration is not None and self.calibration.phantom_to_base is not None:
            spacing, phantom_to_base = self.calibration.pixel_spacing_mm, self.calibration.phantom_to_base
        else:
            spacing, phantom_to_base = self.nominal_spacing_mm, self.rig.twin.nominal.phantom_to_base
        registration = (register_frame(self.rig.twin.phantom, result.markers, spacing)
                        if result.found and result.markers is not None else None)
        self.view.show_registration(registration, result.markers, spacing, phantom_to_base)

    def _show_calibration(self, calibration: Calibration, session: Session) -> Verdict:
        """The calibration of ``session`` in the panel and the scene, with its verdict (returned)."""
        if self.publisher is not None:
            self.publisher.publish_calibration(calibration.shown_image_to_tool)
        verdict = calibration_verdict(calibration, self.tolerance_mm)
        self.view.show_calibration(calibration, verdict, session.path, session.truth())
        return verdict

    def _tolerance_set(self) -> None:
        """Every verdict shown judged again at the tolerance now set, the markers coloured to it."""
        try:
            self._tolerance_mm = self.panel.tolerance_mm()
        except InputError as exc:
            self._refuse_field(exc, self.panel.tolerance, self._tolerance_mm)
            return
        if self.calibration is not None and self.calibration_from is not None:
            verdict = calibration_verdict(self.calibration, self.tolerance_mm)
            self.view.show_calibration_verdict(self.calibration, verdict, self.calibration_from,
                                               load_session(self.calibration_from).truth())
        self.view.rescale_markers(self.tolerance_mm)
        shown = self.view.reconstruction
        if shown is not None:
            self.view.show_reconstruction_verdict(reconstruction_verdict(shown[0].report, self.tolerance_mm), shown[1])

    # --- calibration and volume ---------------------------------------------------------------

    def _working(self, what: str) -> Callable[[str], None]:
        """What long work that cannot count its steps is told of each: shown, and where Stop ends it."""
        def step(message: str) -> None:
            self.jobs.check_stop()
            self.view.working(f"{what}: {message} ...")
        return step

    def _progress(self, what: str) -> Callable[[int, int], None]:
        """What long work is told of each step: shown, and where Stop ends the work."""
        def step(done: int, total: int) -> None:
            self.jobs.check_stop()
            self.view.progress(done, total, what)
        return step

    def _calibrate(self) -> None:
        if self.calibration_session is None:
            raise InputError(None, "no calibration session: run Start sweep or Load session first")
        session = load_session(self.calibration_session)
        started = time.monotonic()
        self.view.status(f"Segmenting {len(session)} frames ...", GREEN)
        report = run_calibration(session, frame_progress=self._progress("Segmenting"),
                                 progress=self._working("Calibrating"))
        self.calibration, self.segmentation = report.calibration, report.segmentation
        self.calibration_file, self.phantom_check, self.calibration_from = None, None, session.path
        if report.calibration.image_latency_s is not None:
            self._use_latency(report.calibration.image_latency_s)
        verdict = self._show_calibration(report.calibration, session)
        self.view.show_markers(*markers_on_wires(session, report.calibration, report.segmentation), self.tolerance_mm)
        self.view.show_step("calibrated" if self.guided is None else "guided-calibrated")
        m = report.calibration.metrics
        self.view.counter(f"Calibration: {m['frames_used']} frames used, {m['frames_rejected']} rejected "
                          f"of {m['frames_total']}")
        self._say_what_save_writes()
        self._frame_phantom()  # the status last: once it says done, everything is drawn
        after = "" if verdict.next_step else " Next: 3 Scan, Scan volume."
        self.view.status(f"Calibrated in {time.monotonic() - started:.1f} s. {verdict.text}{after}",
                         GREEN if verdict.usable else RED)

    def _check_phantom(self) -> None:
        """Where each wire of the built phantom is, against its definition, from the calibration
        session and the calibration (``probecal phantom check``)."""
        if self.calibration is None or self.calibration_session is None:
            raise InputError(None, "no calibration: run Calibrate (or load a calibrated session) first")
        session = load_session(self.calibration_session)
        if self.segmentation is None:
            self.view.status(f"Segmenting {len(session)} frames ...", GREEN)
            self.segmentation = segment_session(session, self._progress("Segmenting"))
        self.view.status("Locating every wire of the phantom ...", GREEN)
        check = self.phantom_check = check_session(session, self.calibration, self.segmentation)
        assert session.phantom is not None  # check_session refuses a session without one
        verdict = wire_check_verdict(check)
        self.view.show_phantom_check(check, verdict, session.phantom, session.path)
        self._say_what_save_writes()
        self.view.status(f"Phantom checked from {check.frames_used} frames: {wire_check_summary(check)} (the "
                         "verdict in 2 Calibrate).", VERDICT_COLOURS_BY_USE[verdict.usable])

    def _poses_to_add(self) -> int | None:
        """How many poses the last phantom check asks to add to its calibration session (None:
        none that would tell an unsure wire)."""
        if self.phantom_check is None or self.calibration_session is None:
            return None
        more = poses_to_tell(self.phantom_check)
        if more is None or more.poses is None or more.poses <= self.phantom_check.frames_used:
            return None
        return more.poses - self.phantom_check.frames_used

    def _add_poses(self) -> None:
        """The poses the phantom check asks for, added to the calibration session's sweep and
        recorded, then Calibrate and Check phantom again on all of its frames."""
        self._require_connected()
        path, count = self.calibration_session, self._poses_to_add()
        if path is None or count is None:
            raise InputError(path, "Check phantom asks for no more poses")
        if read_manifest(path).continuous:
            raise InputError(path, "a sweep without stops takes no added poses: record a new one with more poses")
        plan, _ = resume_state(path)
        extend_plan(path, self.rig.calibration_plan(count, self.panel.ranges(), self.panel.limits(),
                                                    draw=len(plan.poses)))
        self.view.show_step("calibrating")
        self.view.clear_calibration_session()
        self.interrupted["calibration"] = path
        self._acquire("calibration", None, recorded=self._recorded)
        if self.calibration_session == path and "calibration" not in self.interrupted:  # every pose recorded
            self._calibrate()
            self._check_phantom()

    def _reconstruct(self) -> None:
        if self.calibration is None:
            raise InputError(None, "no calibration: run Calibrate (or load a calibrated session) first")
        if self.volume_session is None:
            raise InputError(None, "no volume session: run Scan volume or Load session first")
        session = load_session(self.volume_session)
        check_fits(self.calibration.valid_for, self.calibration_session or "the calibration", session)
        if self.calibration_file is None:  # the report names the file it was made with
            self._write_calibration()
        out = _free_dir(session.path / "reconstruction")
        self.view.status(f"Reconstructing {len(session)} frames ...", GREEN)
        tolerance = self.tolerance_mm
        cad = session_cad_target(session, phantom_to_base=self.calibration.phantom_to_base)
        reconstruction = reconstruct_session(session, self.calibration, out, cad=cad,
                                             progress=self._progress("Reconstructing"),
                                             source=calibration_source(self.calibration, self.calibration_file),
                                             stage=self._working("Reconstructing"),
                                             judge=lambda made: reconstruction_verdict(made, tolerance).to_json())
        verdict = self._show_reconstruction(reconstruction, out)
        self.view.counter(f"Reconstruction: {len(session)} frames compounded")
        self.view.status(f"Reconstructed {len(reconstruction.points_base)} surface points. {verdict.text}",
                         GREEN if verdict.usable is not False else RED)

    def _self_check(self) -> None:
        """Sweep the test object from every self-check view into a new session, then check with the
        calibration held that the views' surfaces agree (``probecal selfcheck``), into the
        session's ``selfcheck`` folder."""
        self._require_connected()
        calibration = self.calibration
        if calibration is None:
            raise InputError(None, "no calibration: run Calibrate (or load a calibrated session) first")
        plan = self.rig.self_check_plan(SELF_CHECK_FRAMES, self.panel.limits(), progress=self._progress("Planning"))
        self.view.show_step("scanning")
        self.view.clear_volume()
        if self.rig.simulated_images:
            self.view.show_object(self.mesh, self.rig.scanner.object_to_base)
        self.live_volume = None
        self._frame_plan(plan)
        path, outcome = self._acquire("selfcheck", plan)
        if not outcome.complete:  # its status says why, and what was kept
            return
        session = load_session(path)
        check_fits(calibration.valid_for, self.calibration_session or "the calibration", session)
        if self.calibration_file is None:  # the report names the file it was made with
            self._write_calibration()
        out = _free_dir(path / "selfcheck")
        self.view.working("Self-check: reconstructing and registering the views")
        _, report = write_self_check(viewed_sweeps([(session, calibration)]), out,
                                     source=calibration_source(calibration, self.calibration_file))
        verdict = self._show_self_check(out)
        self.view.counter(f"Self-check: {len(session)} frames from {len(report['views'])} views, in "
                          f"{report['seconds']:.1f} s")
        self.view.status(f"Self-checked {path.name}. {verdict.text}", GREEN if report["trusted"] else RED)

    def _show_self_check(self, out: Path) -> Verdict:
        """The self-check saved in ``out`` shown: each view's surface in its colour and the
        verdict (returned), framed."""
        saved = load_self_check(out)
        verdict = self_check_verdict(saved.report)
        self.view.show_self_check(saved, verdict, out / REPORT)
        self.view.show_step("self-checked")
        points = np.concatenate(saved.views)
        self._work = ((points.min(axis=0) + points.max(axis=0)) / 2, float(np.ptp(points, axis=0).max()))
        self.view.frame(*self._work)
        return verdict

    def _show_reconstruction(self, reconstruction: Reconstruction, out: Path) -> Verdict:
        """A reconstruction of the volume session (in ``out``) shown with its verdict (returned),
        and framed."""
        verdict = reconstruction_verdict(reconstruction.report, self.tolerance_mm)
        self.view.show_reconstruction(reconstruction, verdict, out)
        self.view.show_step("reconstructed")
        points = reconstruction.points_base
        self._work = ((points.min(axis=0) + points.max(axis=0)) / 2, float(np.ptp(points, axis=0).max()))
        self.view.frame(*self._work)
        return verdict

    # --- sessions -----------------------------------------------------------------------------

    def _session_folder(self, text: str) -> Path:
        """The session folder the Folder field names: a name under ``--sessions`` or a path inside
        it; InputError for anything that leads outside."""
        if not text:
            raise InputError(None, f"type a session folder's name (in {self.sessions_dir}) into Folder")
        root = self.sessions_dir.resolve()
        name = Path(text)
        if name.is_absolute():
            resolved = name.resolve()
            if not resolved.is_relative_to(root):
                raise InputError(self.sessions_dir, f"{text!r} is outside the sessions folder; the console opens "
                                                    "only sessions in it")
            name = resolved.relative_to(root)
        return inside(root, name, self.sessions_dir)

    def _save_target(self) -> tuple[Path, list[str]] | None:
        """Where Save writes, and what: the calibration (JSON and PLUS element), its
        segmentation and phantom check, into the calibration session it was made from; None before
        a calibration."""
        if self.calibration is None or self.calibration_from is None:
            return None
        files = ["calibration.json", "calibration.xml"]
        if self.calibration_session == self.calibration_from:  # not a later sweep's
            files += [name for name, made in (("segmentation.json", self.segmentation),
                                              ("phantom_check.json", self.phantom_check)) if made is not None]
        return self.calibration_from, files

    def _say_what_save_writes(self) -> None:
        """Save's note: what it will write, and where, before the user clicks."""
        target = self._save_target()
        if target is None:
            self.panel.save_note.show(status_html(NO_SAVE, GREY))
            return
        folder, files = target
        saved = "" if self.calibration_file is None else " (the calibration is saved; Save writes it again)"
        self.panel.save_note.show(status_html(f"Save writes {', '.join(files)} into the calibration session "
                                              f"{folder.name}{saved}.", GREY))

    def _write_calibration(self) -> list[str]:
        """The calibration, its segmentation and phantom check written into the calibration
        session, as ``probecal calibrate`` and ``probecal phantom check`` write them; the files."""
        target = self._save_target()
        if target is None:
            raise InputError(None, "nothing to save yet: frames are saved as they are recorded; calibrate first")
        folder, files = target
        assert self.calibration is not None  # a target exists only with a calibration
        session = load_session(folder)
        if self.segmentation is not None and "segmentation.json" in files:
            write_segmentation(folder / "segmentation.json", self.segmentation, session)
        if self.phantom_check is not None and "phantom_check.json" in files:
            write_json(folder / "phantom_check.json", {"session": str(folder),
                                                       "calibration": str(folder / "calibration.json"),
                                                       **self.phantom_check.to_json()})
        self.calibration.write(folder / "calibration.json")
        self.calibration_file = folder / "calibration.json"
        self._say_what_save_writes()
        return files

    def _save(self) -> None:
        """Into the calibration session, what its note says (:meth:`_save_target`). Frames are
        saved as they are recorded."""
        files = self._write_calibration()
        self.view.status(f"Saved {', '.join(files)} into the calibration session {self.calibration_from}.", GREEN)
        self.view.notify("Session saved", str(self.calibration_from), error=False)

    def _load(self) -> None:
        """Open a session folder: a calibration session (with its calibration.json, if saved)
        becomes the one Calibrate uses, a volume session (with its last reconstruction, if any) the
        one Reconstruct uses. Every result and layer of the session it replaces goes, and the
        camera frames the loaded session's work."""
        path = self._session_folder(self.panel.session_path.value.strip())
        session = load_session(path)
        if len(session) == 0:
            raise InputError(path, "session has no frames")
        self.view.clear_volume()  # the other session's layers go; a loaded volume shows its own
        self.view.clear_calibration_session()
        self.live_volume = None
        if session.phantom is not None:
            self._load_calibration_session(session)
        else:
            self._load_volume_session(session)
        self._say_what_save_writes()
        self.view.status(f"Loaded {session.manifest.kind or 'session'} session {path} ({len(session)} frames).",
                         GREEN)

    def _load_calibration_session(self, session: Session) -> None:
        """The calibration session's frames and, when saved, its calibration; without one, no
        calibration at all (not the one of the session loaded before)."""
        path = session.path
        saved = inside(path, "calibration.json", path)  # a link out of the session is refused, as on the command line
        calibration = load_calibration(saved) if saved.is_file() else None
        if calibration is not None:
            check_fits(calibration.valid_for, saved, session)
        self.calibration_session, self.segmentation, self.phantom_check = path, None, None
        if calibration is not None:
            self.calibration, self.calibration_file, self.calibration_from = calibration, saved, path
            self._show_calibration(self.calibration, session)
            self.view.counter(f"Calibration: saved in {path.name}")
        else:
            self.calibration, self.calibration_file, self.calibration_from = None, None, None
            self.view.clear_calibration(self._image_to_tool(), self.rig.twin.nominal.phantom_to_base)
        self.view.show_step("calibrated" if calibration is not None else "calibrating")
        pose = session.records[-1].tool_to_base
        self.show(LiveFrame(session.image(len(session) - 1), pose if pose is not None else np.eye(4),
                            self.rig.robot.joints() if self.rig.robot.connected else HOME_JOINTS,
                            None, len(session), len(session)), "calibration")
        self._frame_phantom()

    def _load_volume_session(self, session: Session) -> None:
        """The volume session, its object where it sits and its last reconstruction and
        self-check, if any."""
        folder, checked = saved_reconstruction(session.path), saved_self_check(session.path)
        reconstruction = None if folder is None else load_reconstruction(folder)
        self.volume_session = session.path
        self.view.show_step("scanning")
        placement = cad_placement_from_session(session, None if self.calibration is None
                                               else self.calibration.phantom_to_base)
        if placement is not None:
            self.view.show_object(self.mesh, placement)
            corners = transform_points(placement, self.mesh.bounds)
            self._work = (corners.mean(axis=0), float(np.ptp(corners, axis=0).max()))
            self.view.frame(*self._work)
        self.view.counter(f"Volume session: {len(session)} frames")
        if reconstruction is not None and folder is not None:
            self._show_reconstruction(reconstruction, folder)
        if checked is not None:
            self._show_self_check(checked)


def _free_dir(path: Path) -> Path:
    """``path``, or ``path-2``, ``path-3``, ... whichever does not exist yet."""
    candidate, k = path, 1
    while candidate.exists():
        k += 1
        candidate = path.with_name(f"{path.name}-{k}")
    return candidate
