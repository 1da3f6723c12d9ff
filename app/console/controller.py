"""The browser console (viser): a thin layer over core that drives the robot and scanner,
records sessions, calibrates and reconstructs, and shows it all live (SPEC §1 step 8, §6 serve).

All state lives on the server and every GUI and scene handle is global, so any number of tabs
see the same console. Long work runs in one background job at a time; Stop is always live.
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import socket
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import trimesh
import viser

from probecal.app.console.draw import annotate_frame, plot_curve
from probecal.app.console.gate import Gate, checked_token, gated, host_names, new_token
from probecal.app.console.panel import GREEN, GREY, RED, Panel, build_panel, calibration_md, status_html, surface_md
from probecal.app.console.scene import Scene, registered_points
from probecal.core.acquisition.igtl import IgtlPublisher
from probecal.core.acquisition.imagesource import ImageSourceError
from probecal.core.acquisition.plan import SweepPlan
from probecal.core.acquisition.rig import Recording, Rig, make_rig
from probecal.core.acquisition.sweep import LiveFrame, Sweep, SweepOutcome
from probecal.core.calibration.register import markers_to_image_mm, register_frame
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.calibration.segment import FrameResult, Segmenter, results_to_json, segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.errors import InputError
from probecal.core.io.files import inside
from probecal.core.io.jsonio import write_json
from probecal.core.io.session import MANIFEST, Session, load_session
from probecal.core.robot.contract import HOME_JOINTS, RobotError
from probecal.core.robot.safety import Workspace
from probecal.core.twin.testobject import TEST_OBJECT_FILE
from probecal.core.volume.pointcloud import read_mesh
from probecal.core.volume.reconstruct import CadTarget, cad_placement_from_session, reconstruct_session

ROBOT_HZ = 5.0  # the arm's 3D pose costs the browser more than a frame does


class Console:
    """The operator console on a viser server, driving a rig (simulated or real)."""

    def __init__(self, server: viser.ViserServer, rig: Rig, sessions_dir: Path, gate: Gate):
        self.server, self.rig, self.sessions_dir, self.gate = server, rig, Path(sessions_dir), gate
        twin = rig.twin
        self.segmenter = Segmenter.create(twin.phantom, twin.probe.nominal_spacing_mm)
        self.calibration: Calibration | None = None
        self.calibration_session: Path | None = None
        self.volume_session: Path | None = None
        self.segmentation: list[FrameResult] | None = None
        self.cloud_colors: dict[str, np.ndarray] = {}
        self.frames_shown = 0
        self._robot_shown_at = 0.0
        self._job: threading.Thread | None = None
        self._sweep: Sweep | None = None
        self._stop_requested = threading.Event()  # Stop since the running job started
        self.interrupted: dict[str, Path] = {}  # kind -> session of a sweep that ended early
        self._lock = threading.Lock()
        self.publisher: IgtlPublisher | None = None  # OpenIGTLink output to 3D Slicer
        self.scene = Scene(server, twin.phantom, (twin.probe.width_px, twin.probe.height_px))
        self.scene.set_image_mount(twin.nominal.image_to_tool_rigid @ twin.probe.scale_matrix(twin.probe.nominal_spacing_mm))
        self.scene.set_phantom_pose(twin.nominal.phantom_to_base)
        self.scene.set_robot(HOME_JOINTS)
        self.panel: Panel = build_panel(server, (twin.probe.height_px, twin.probe.width_px))
        self._wire()

    # --- wiring -------------------------------------------------------------------------------

    def _wire(self) -> None:
        p = self.panel
        p.connect.on_click(lambda _: self.connect())
        p.start.on_click(lambda _: self.start_sweep())
        p.stop.on_click(lambda _: self.stop())
        p.calibrate.on_click(lambda _: self.calibrate())
        p.scan.on_click(lambda _: self.scan_volume())
        p.reconstruct.on_click(lambda _: self.reconstruct())
        p.save.on_click(lambda _: self._start_job("Save session", self._save))
        p.load.on_click(lambda _: self._start_job("Load session", self._load))
        p.cloud_colors.on_update(lambda _: self._color_cloud())

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

    def close(self) -> None:
        """Stop the robot, close the rig and the server."""
        self.stop()
        self.wait(5.0)
        self.rig.close()
        if self.publisher is not None:
            self.publisher.close()
        self.server.stop()

    # --- feedback -----------------------------------------------------------------------------

    def status(self, text: str, color: str = GREY) -> None:
        self.panel.status.content = status_html(text, color)

    def notify(self, title: str, body: str, error: bool = True) -> None:
        """A notification in every open tab (red for failures)."""
        for client in self.server.get_clients().values():
            client.add_notification(title, body, color="red" if error else "blue",
                                    auto_close_seconds=None if error else 4.0)

    def progress(self, done: int, total: int, what: str, note: str = "") -> None:
        self.panel.progress.value = 100.0 * min(done, total) / max(total, 1)
        self.panel.counter.content = f"{what}: {done} / {total}{note}"

    # --- jobs ---------------------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        return self._job is not None and self._job.is_alive()

    def _start_job(self, name: str, work: Callable[[], None]) -> bool:
        """Run ``work`` in the background unless a job is running (then do nothing)."""
        with self._lock:
            if self.busy:
                self.notify("Busy", f"{self._job.name} is still running.", error=False)
                return False
            self._stop_requested.clear()
            self._job = threading.Thread(target=self._run, args=(name, work), name=name, daemon=True)
            self._job.start()
            return True

    def _run(self, name: str, work: Callable[[], None]) -> None:
        try:
            work()
        except (InputError, RobotError, ImageSourceError, ValueError, OSError) as exc:
            self.status(f"{name} failed: {exc}", RED)
            self.notify(f"{name} failed", str(exc))
        except Exception as exc:  # the console must survive anything a job throws
            self.status(f"{name} failed: {type(exc).__name__}: {exc}", RED)
            self.notify(f"{name} failed", f"{type(exc).__name__}: {exc}")

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the running job (for scripts and tests)."""
        job = self._job
        if job is not None:
            job.join(timeout)

    # --- robot --------------------------------------------------------------------------------

    def connect(self) -> None:
        """Connect the robot and the image source and show where the probe is."""
        self._start_job("Connect", self._connect)

    def _connect(self) -> None:
        self.rig.open()
        image, pose = self.rig.snapshot()
        self.show(LiveFrame(image, pose, self.rig.robot.joints(), None, 0, 0), "calibration")
        self.status(f"Connected to {self.rig.robot_name} and {self.rig.image_name}.", GREEN)

    def stop(self) -> None:
        """Halt the robot at once and end any sweep (which then reports what it kept; one about to
        start does not); recorded frames stay on disk."""
        self._stop_requested.set()
        sweep = self._sweep
        if sweep is not None:
            sweep.stop()
            return
        self.rig.robot.stop()
        self.status("Stopped.", RED)

    def _require_connected(self) -> None:
        if not self.rig.robot.connected:
            raise InputError(None, "the robot is not connected: click Connect first")

    def start_sweep(self) -> bool:
        return self._start_job("Start sweep", self._calibration_sweep)

    def scan_volume(self) -> bool:
        return self._start_job("Scan volume", self._volume_sweep)

    def calibrate(self) -> bool:
        return self._start_job("Calibrate", self._calibrate)

    def reconstruct(self) -> bool:
        return self._start_job("Reconstruct", self._reconstruct)

    def _new_session_dir(self, kind: str) -> Path:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        path = self.sessions_dir / f"{kind}-{stamp}"
        k = 1
        while path.exists():
            k += 1
            path = self.sessions_dir / f"{kind}-{stamp}-{k}"
        return path

    def _acquire(self, kind: str, plan: SweepPlan | None) -> Path:
        """Run a sweep into a session: a new one, or the one an earlier sweep of this kind left
        unfinished (``plan`` None: resumed where it ended). The session keeps whatever was recorded."""
        path = self.interrupted.pop(kind) if plan is None else self._new_session_dir(kind)
        recording = Recording(self.rig, kind, path, plan, self.panel.limits(), lambda f: self.show(f, kind))
        self._sweep = recording.sweep
        if self._stop_requested.is_set():  # Stop came while the sweep was being planned
            recording.sweep.stop()
        self.panel.session_path.value = str(path)
        total, done = recording.sweep.total, len(recording.done)
        self.progress(done, total, "Frames recorded")  # not the last job's count
        verb = f"Resuming ({done} of {total} poses done)" if done else f"Sweeping {total} poses"
        self.status(f"{verb} into {path} ...", GREEN)
        started = time.monotonic()
        try:
            outcome = recording.run()
        finally:
            self._sweep = None
        self._report_sweep(kind, path, outcome, recording.frames, time.monotonic() - started)
        return path

    def _report_sweep(self, kind: str, path: Path, outcome: SweepOutcome, recorded: int, seconds: float) -> None:
        if outcome.complete:
            self.status(f"Sweep done: {recorded} frames in {seconds:.1f} s{outcome.notes()}.", GREEN)
            return
        self.interrupted[kind] = path
        button = "Start sweep" if kind == "calibration" else "Scan volume"
        resume = f"; {button} resumes the {outcome.remaining} poses left"
        if outcome.stopped:
            self.status(f"Stopped: {recorded} frames kept in {path}{outcome.notes()}{resume}.", RED)
        else:
            self.status(f"Sweep failed: {outcome.error}. {recorded} frames kept in {path}{outcome.notes()}{resume}.",
                        RED)
            self.notify("Sweep failed", f"{outcome.error} ({recorded} frames kept in {path})")

    def _resuming(self, kind: str) -> bool:
        """Whether a sweep of this kind continues the unfinished one (the panel's choice)."""
        if not self.panel.resume.value:
            self.interrupted.pop(kind, None)
        return kind in self.interrupted

    def _calibration_sweep(self) -> None:
        self._require_connected()
        plan = None
        if not self._resuming("calibration"):
            plan = self.rig.calibration_plan(int(self.panel.poses.value), self.panel.ranges(), self.panel.limits())
        self.calibration_session = self._acquire("calibration", plan)

    def _volume_sweep(self) -> None:
        self._require_connected()
        plan = None
        if not self._resuming("volume"):
            plan = self.rig.volume_plan(int(self.panel.frames_per_pass.value), self.panel.limits())
        if self.rig.simulated_images:
            self.scene.set_object(self.mesh, self.rig.scanner.object_to_base)
        self.volume_session = self._acquire("volume", plan)

    # --- display ------------------------------------------------------------------------------

    def show(self, frame: LiveFrame, kind: str) -> None:
        """Put a frame on every tab: the arm, the image with its markers, the registration."""
        if kind == "calibration":
            result = self.segmenter(frame.image, frame.index or 0)
            annotated = annotate_frame(frame.image, result.markers, result.candidates)
            if frame.index is not None:
                self._show_registration(result)
            if result.found:
                found = int(np.all(np.isfinite(result.markers), axis=1).sum())
                text, color = f"{found} markers found and labelled", GREEN
            else:
                text, color = f"Pattern not found: {result.reason}", RED
        else:
            annotated = annotate_frame(frame.image, None, np.empty((0, 2)))
            text, color = "Volume sweep frame", GREEN
        now = time.monotonic()
        with self.server.atomic():
            if frame.index is not None or now - self._robot_shown_at >= 1.0 / ROBOT_HZ:
                self.scene.set_robot(frame.joints)
                self._robot_shown_at = now
            self.panel.frame.image = annotated
            # Unchanged text is not re-sent: every re-render costs the browser time.
            html_status = status_html(text, color)
            if self.panel.frame_status.content != html_status:
                self.panel.frame_status.content = html_status
            if frame.total and frame.index is not None:
                refused = f" · {frame.refused} refused (reasons in the report)" if frame.refused else ""
                self.progress(frame.done, frame.total, "Frames recorded", refused)
        if frame.index is not None:
            self.scene.set_plane_texture(frame.image)
        if self.publisher is not None:
            self.publisher.publish_frame(frame.image, frame.tool_to_base, time.time())
        self.frames_shown += 1

    def _spacing_and_phantom_pose(self) -> tuple[tuple[float, float], np.ndarray]:
        if self.calibration is not None and self.calibration.phantom_to_base is not None:
            return self.calibration.pixel_spacing_mm, self.calibration.phantom_to_base
        return self.rig.twin.probe.nominal_spacing_mm, self.rig.twin.nominal.phantom_to_base

    def _show_registration(self, result: FrameResult) -> None:
        """The frame's markers registered to the phantom, in the base frame, coloured by their
        distance to their wire."""
        registration = None
        spacing, phantom_to_base = self._spacing_and_phantom_pose()
        if result.found:
            registration = register_frame(self.rig.twin.phantom, result.markers, spacing)
        if registration is None:
            self.scene.set_registration(np.empty((0, 3)), np.empty(0))
            return
        points = markers_to_image_mm(result.markers[registration.wire_indices], spacing)
        self.scene.set_registration(registered_points(phantom_to_base, registration.image_to_phantom, points),
                                    registration.residuals_mm)

    def _show_calibration(self, calibration: Calibration, session: Session) -> None:
        if self.publisher is not None:
            self.publisher.publish_calibration(calibration.image_to_tool)
        self.panel.results.content = calibration_md(calibration, session.truth())
        curve = calibration.metrics.get("error_vs_poses") or []
        self.panel.curve.image = plot_curve(curve)
        self.panel.curve.visible = bool(curve)
        self.scene.set_image_mount(calibration.image_to_tool)
        if calibration.phantom_to_base is not None:
            self.scene.set_phantom_pose(calibration.phantom_to_base)

    # --- calibration and volume -----------------------------------------------------------------

    def _calibrate(self) -> None:
        if self.calibration_session is None:
            raise InputError(None, "no calibration session: run Start sweep or Load session first")
        session = load_session(self.calibration_session)
        started = time.monotonic()
        self.status(f"Segmenting {len(session)} frames ...", GREEN)
        results = segment_session(session, progress=lambda d, t: self.progress(d, t, "Segmenting"))
        self.panel.progress.value = 100.0
        report = calibrate_session(session, results, progress=lambda msg: self.status(msg.capitalize() + " ...", GREEN))
        self.calibration, self.segmentation = report.calibration, results
        self._show_calibration(report.calibration, session)
        last = len(session) - 1
        self._show_registration(results[last])
        self.status(f"Calibrated from {len(report.frames_used)} frames in {time.monotonic() - started:.1f} s.", GREEN)

    def _reconstruct(self) -> None:
        if self.calibration is None:
            raise InputError(None, "no calibration: run Calibrate (or load a calibrated session) first")
        if self.volume_session is None:
            raise InputError(None, "no volume session: run Scan volume or Load session first")
        session = load_session(self.volume_session)
        out = self._free_dir(session.path / "reconstruction")
        cad = None
        mesh_file = inside(session.path, session.manifest.get("cad_mesh", TEST_OBJECT_FILE.name), session.path / MANIFEST)
        placement = cad_placement_from_session(session)
        if mesh_file.is_file() and placement is not None:
            cad = CadTarget(read_mesh(mesh_file), placement, False)
        self.status(f"Reconstructing {len(session)} frames ...", GREEN)
        report = reconstruct_session(session, self.calibration, out, cad=cad,
                                     progress=lambda d, t: self.progress(d, t, "Reconstructing"))
        cloud = trimesh.load(out / "surface.ply")
        points = np.asarray(cloud.vertices)
        self.cloud_colors = {"height": np.asarray(cloud.colors)[:, :3]}
        if (out / "surface_error.ply").is_file():
            self.cloud_colors["error to CAD"] = np.asarray(trimesh.load(out / "surface_error.ply").colors)[:, :3]
        self.scene.set_cloud(points, self.cloud_colors["height"])
        self._color_cloud()
        self.panel.volume.content = surface_md(report, str(out))
        self.status(f"Reconstructed {len(points)} surface points.", GREEN)

    def _color_cloud(self) -> None:
        """Colour the reconstruction as the panel asks (height, or the distance to the CAD model)."""
        colors = self.cloud_colors.get(self.panel.cloud_colors.value)
        if colors is not None:
            self.scene.set_cloud_colors(colors)
        elif self.cloud_colors:
            self.notify("No CAD comparison", "this reconstruction has no CAD model to measure against", error=False)

    @staticmethod
    def _free_dir(path: Path) -> Path:
        candidate, k = path, 1
        while candidate.exists():
            k += 1
            candidate = path.with_name(f"{path.name}-{k}")
        return candidate

    # --- sessions ------------------------------------------------------------------------------

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
                raise InputError(self.sessions_dir, f"{text!r} is outside the sessions folder; the console opens only sessions in it")
            name = resolved.relative_to(root)
        return inside(root, name, self.sessions_dir)

    def _save(self) -> None:
        """Write the calibration (JSON and PLUS element) and the segmentation into the session,
        as ``probecal segment`` and ``probecal calibrate`` would."""
        if self.calibration is None or self.calibration_session is None:
            raise InputError(None, "nothing to save yet: frames are saved as they are recorded; calibrate first")
        session = load_session(self.calibration_session)
        if self.segmentation is not None:
            write_json(session.path / "segmentation.json", results_to_json(self.segmentation, session))
        xml = self.calibration.write(session.path / "calibration.json")
        self.status(f"Saved {session.path / 'calibration.json'} and {xml.name}.", GREEN)
        self.notify("Session saved", str(session.path), error=False)

    def _load(self) -> None:
        """Open a session folder: a calibration session (with its calibration.json, if saved)
        becomes the one Calibrate uses, a volume session the one Reconstruct uses."""
        path = self._session_folder(self.panel.session_path.value.strip())
        session = load_session(path)
        if len(session) == 0:
            raise InputError(path, "session has no frames")
        if session.phantom is not None:
            self.calibration_session = path
            if (path / "calibration.json").is_file():
                self.calibration = load_calibration(path / "calibration.json")
                self._show_calibration(self.calibration, session)
            pose = session.records[-1].tool_to_base
            self.show(LiveFrame(session.image(len(session) - 1), pose if pose is not None else np.eye(4),
                            self.rig.robot.joints() if self.rig.robot.connected else HOME_JOINTS,
                            None, len(session), len(session)), "calibration")
        else:
            self.volume_session = path
            placement = cad_placement_from_session(session)
            if placement is not None:
                self.scene.set_object(self.mesh, placement)
        self.status(f"Loaded {session.manifest.get('kind', 'session')} session {path} ({len(session)} frames).", GREEN)


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
    except (OSError, ValueError):
        return False


def _gated_server(host: str, port: int, gate: Gate) -> viser.ViserServer:
    """A viser server on ``host:port`` (0: a free port) whose every request passes ``gate``.
    InputError if ``port`` is taken (viser would silently move to the next one)."""
    gate.port = port or _free_port(host)
    with gated(gate), contextlib.redirect_stdout(io.StringIO()):  # viser's banner would print a tokenless address
        server = viser.ViserServer(host=host, port=gate.port, label="probecal", verbose=False)
    if server.get_port() != gate.port:
        if port:
            server.stop()
            raise InputError(None, f"port {port} on {host} is in use (another console?); choose another with --port")
        gate.port = server.get_port()  # the free port was taken meanwhile; requests so far were refused
    return server


def launch(host: str = "127.0.0.1", port: int = 8080, robot: str = "sim", image: str = "sim",
           sessions_dir: str | Path = "sessions", time_scale: float = 0.25, seed: int = 0,
           token: str | None = None, workspace: Workspace | None = None, publish: int | None = None,
           latency_s: float = 0.0) -> Console:
    """Start the console without blocking (port 0 picks a free port). ``time_scale`` is wall
    seconds per robot second for the simulated robot (0.25: four times faster than real).
    ``publish`` is an OpenIGTLink port on loopback on which 3D Slicer receives the calibration
    (ImageToProbe) and every frame shown, placed by ProbeToReference.

    The console moves a robot, so it answers only its own page (``app.console.gate``); off loopback it
    needs a ``token`` (one is made when none is given) that browsers present once in the printed
    address and then in a cookie."""
    exposed = not _is_loopback(host)
    if token is None and exposed:
        token = new_token()
    gate = Gate(host_names(host), None if token is None else checked_token(token, "the command line"))
    server = _gated_server(host, port, gate)
    try:
        rig = make_rig(robot, image, seed, time_scale, workspace, latency_s)
    except BaseException:
        server.stop()
        raise
    console = Console(server, rig, Path(sessions_dir), gate)
    if publish is not None:
        console.publisher = IgtlPublisher(publish, "127.0.0.1")
    return console


def serve(host: str = "127.0.0.1", port: int = 8080, robot: str = "sim", image: str = "sim",
          sessions_dir: str | Path = "sessions", time_scale: float = 0.25, token: str | None = None,
          workspace: Workspace | None = None, publish: int | None = None, latency_s: float = 0.0) -> None:
    """Start the console and block until interrupted."""
    console = launch(host, port, robot, image, sessions_dir, time_scale, token=token, workspace=workspace,
                     publish=publish, latency_s=latency_s)
    print(f"probecal console on {console.url} (Ctrl+C to stop)", flush=True)
    if console.publisher is not None:
        print(f"OpenIGTLink for 3D Slicer on port {console.publisher.port}: ImageToProbe, Image, ProbeToReference",
              flush=True)
    try:
        while True:
            time.sleep(1.0)
    finally:
        console.close()
