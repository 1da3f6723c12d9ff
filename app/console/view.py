"""What every tab of the console shows: the side panel (status, progress, the live frame with its
markers, the results) and the 3D scene. It draws what it is given and decides nothing; all
handles are server-wide, so every open tab sees the same."""

from __future__ import annotations

import threading
import time
from collections.abc import Collection
from pathlib import Path

import numpy as np
import trimesh
import viser

from probecal.app.console.draw import (
    Overlay,
    annotate_frame,
    bound_overlay,
    colour_bar,
    slice_outline,
    slice_range_mm,
    volume_slice,
)
from probecal.app.console.panel import (
    BOUND_CAPTION,
    CLOUD_COLORINGS,
    CURVE_KEYS,
    GREEN,
    GREY,
    MM_AXIS,
    NO_CALIBRATION,
    NO_PHANTOM_CHECK,
    NO_SELF_CHECK,
    NO_VOLUME,
    RED,
    Panel,
    build_panel,
    calibration_html,
    counter_html,
    report_html,
    self_check_html,
    status_html,
    strip_status_html,
    surface_html,
    wire_check_html,
    wire_offset_plot,
    wire_table_html,
)
from probecal.app.console.scene import (
    MM,
    REGISTRATION_FULL_SCALE_MM,
    ROBOT_CAMERA,
    ROBOT_LOOK_AT,
    Scene,
    registered_points,
)
from probecal.app.report import Verdict
from probecal.core.acquisition.sweep import LiveFrame
from probecal.core.calibration.register import Registration
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import FrameResult
from probecal.core.calibration.wirecheck import WireCheck
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import image_mm_from_pixels
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.volume.live import LiveVolume
from probecal.core.volume.reconstruct import ERROR_FULL_SCALE_MM, Reconstruction
from probecal.core.volume.saved import SavedSelfCheck
from probecal.core.volume.selfcheck import VIEW_COLORS

OFF_WIRES_DRAWN = 20.0
"""The wires Check phantom finds off are drawn this many times further off than found (tenths of
a millimetre would not show)."""
ROBOT_HZ = 5.0  # the arm's 3D pose costs the browser more than a frame does
CLOUD_COLORS = dict(zip(CLOUD_COLORINGS, ("height_colors", "error_colors")))
"""The reconstruction's colours each of the panel's cloud colourings shows."""
CAMERA_DIRECTION = np.array([0.55, -0.65, 0.52]) / np.linalg.norm([0.55, -0.65, 0.52])
FILL = 0.5
"""The work is framed along ``CAMERA_DIRECTION`` (base frame) from where it fills this much of the
view's height: between the status column and the side panel at 1280 x 800, it is then wide enough
to read and still whole."""
SIDE_PANEL_PX = 400
"""The side panel's width with its margin (px, viser's "large" controls), over the right of the 3D
view: the work is framed in the middle of what it leaves."""
FRAMED_HEIGHT_PX = 800
"""The 3D view's height (px) the side panel's width is reckoned against (1280 x 800): on a taller
view the work sits a little left of the middle of what the panel leaves."""
STEP_LAYERS: dict[str, tuple[set[str], set[str]]] = {
    "calibrating": ({"robot", "probe", "image plane", "phantom", "wires", "markers"}, set()),
    "guiding": ({"phantom", "wires", "guidance"}, set()),
    "guided-calibrated": ({"phantom", "wires", "markers"}, set()),
    "calibrated": ({"robot", "probe", "image plane", "phantom", "wires", "markers"}, {"robot", "probe", "image plane"}),
    "scanning": ({"robot", "probe", "image plane", "CAD model", "volume"}, set()),
    "reconstructed": ({"cloud", "CAD model", "slices"}, set()),
    "self-checked": ({"self-check", "CAD model"}, set()),
}
"""What each step shows (the layers it produced, and what it works with) and fades; the others hidden."""


class ConsoleView:
    """The panel and the scene of one console, for a phantom and an image size (width, height) px."""

    def __init__(self, server: viser.ViserServer, phantom: Phantom, image_size_px: tuple[int, int],
                 fan: Fan | None = None):
        self.server = server
        width, height = image_size_px
        self.fan = fan  # a fan image's: the frames and the image plane show it
        self.scene = Scene(server, phantom, image_size_px, fan)
        self.scene.set_robot(HOME_JOINTS)
        self.panel: Panel = build_panel(server, (height, width))
        self.frames_shown = 0
        self.no_calibration = NO_CALIBRATION  # what the results say before a calibration
        self._robot_shown_at = 0.0
        self._reconstruction: Reconstruction | None = None
        self._reconstruction_dir: Path | None = None
        self._markers: tuple[np.ndarray, np.ndarray] = (np.empty((0, 3)), np.empty(0))  # calibrated, with distances
        self._progress_what, self._progress_from = "", (0, 0.0)
        self._failures: list[tuple[str, float, viser.NotificationHandle]] = []  # job, shown at, handle
        self._failures_lock = threading.Lock()
        self._marker_full_scale = REGISTRATION_FULL_SCALE_MM  # the panel's marker colour bar starts at it
        self._image_size_px = image_size_px
        self.bound_overlay: Overlay | None = None  # the calibration's bound map, over every frame
        self._last_frame: tuple[np.ndarray, FrameResult | None] | None = None  # drawn again when the map changes

    # --- feedback -----------------------------------------------------------------------------

    def status(self, text: str, color: str = GREY) -> None:
        """The status line, in a box of fixed height so that Stop below it never moves (a longer
        text scrolls inside it)."""
        self.panel.status.show(strip_status_html(text, color))

    def notify(self, title: str, body: str, error: bool = True, job: str | None = None) -> None:
        """A notification in every open tab: blue, closing by itself; or red, for a failure of
        ``job``, staying until :meth:`clear_failures` removes it."""
        for client in self.server.get_clients().values():
            handle = client.add_notification(title, body, color="red" if error else "blue",
                                             auto_close_seconds=None if error else 4.0)
            if error and job is not None:
                with self._failures_lock:
                    self._failures.append((job, time.monotonic(), handle))

    def clear_failures(self, jobs: Collection[str], before: float) -> None:
        """Remove the failure notifications of ``jobs`` shown before ``before`` (time.monotonic):
        what they told of is gone."""
        with self._failures_lock:
            gone = [(j, t, h) for j, t, h in self._failures if j in jobs and t < before]
            self._failures = [f for f in self._failures if f not in gone]
        for _, _, handle in gone:
            handle.remove()

    def progress(self, done: int, total: int, what: str) -> None:
        """The strip's progress bar and counter line, with the time left at the rate so far."""
        now = time.monotonic()
        if what != self._progress_what or done <= self._progress_from[0]:
            self._progress_what, self._progress_from = what, (done, now)
        first, since = self._progress_from
        left = ""
        if first < done < total and now - since > 1.0:
            left = f" · about {(total - done) * (now - since) / (done - first):.0f} s left"
        self.counter(f"{what}: {done} / {total}{left}", 100.0 * min(done, total) / max(total, 1))

    def counter(self, text: str, percent: float = 100.0) -> None:
        """The strip's counter line and bar (by default full: a job done)."""
        self.panel.progress.value = percent  # type: ignore[misc]  # viser 1.1.1 has a setter mypy cannot see
        self.panel.progress.animated = False
        self.panel.counter.show(counter_html(text))

    def working(self, text: str) -> None:
        """A step that cannot count its progress: the bar striped and moving, the counter naming it."""
        self.panel.progress.value = 100.0  # type: ignore[misc]  # viser 1.1.1 has a setter mypy cannot see
        self.panel.progress.animated = True
        self.panel.counter.show(counter_html(text))

    def _sweep_progress(self, frame: LiveFrame) -> None:
        """The strip's bar and counter during a sweep: poses (frames, moving without stopping)
        recorded and refused, and the time its plan has left at the pace so far."""
        refused = f" · {frame.refused} refused (reasons in the report)" if frame.refused else ""
        left = "" if frame.left_s is None or frame.left_s < 1.0 else f" · about {frame.left_s:.0f} s left"
        if frame.fraction is None:
            percent, count = 100.0 * min(frame.done, frame.total) / max(frame.total, 1), f"{frame.done} / {frame.total}"
        else:
            percent, count = 100.0 * frame.fraction, str(frame.done)
        self.counter(f"{frame.progress_label}: {count}{refused}{left}", percent)

    def failed(self, job: str, message: str) -> None:
        self.status(f"{job} failed: {message}", RED)
        self.notify(f"{job} failed", message, job=job)

    # --- frames -------------------------------------------------------------------------------

    def _annotated(self, image: np.ndarray, result: FrameResult | None) -> np.ndarray:
        """The frame under the bound map (once calibrated) with the markers ``result`` found."""
        if result is None:
            return annotate_frame(image, None, np.empty((0, 2)), fan=self.fan, overlay=self.bound_overlay)
        return annotate_frame(image, result.markers, result.candidates, fan=self.fan, overlay=self.bound_overlay)

    def show_frame(self, frame: LiveFrame, result: FrameResult | None) -> None:
        """A frame on every tab: the arm at its joints, the image with the markers ``result``
        found (None: a volume frame, nothing to find) and, for a recorded frame, the progress."""
        self._last_frame = (frame.image, result)
        annotated = self._annotated(frame.image, result)
        if result is None:
            text, color = "Volume sweep frame", GREEN
        elif result.found:
            assert result.markers is not None  # the segmenter gives markers with every frame it found
            found = int(np.all(np.isfinite(result.markers), axis=1).sum())
            text, color = f"{found} markers found and labelled", GREEN
        elif frame.index is None:  # a look through the probe, not a frame the user asked for
            text, color = f"No wire pattern in view: {result.reason}", GREY
        else:
            text, color = f"Pattern not found: {result.reason}", RED
        now = time.monotonic()
        with self.server.atomic():
            if frame.index is not None or now - self._robot_shown_at >= 1.0 / ROBOT_HZ:
                self.scene.set_robot(frame.joints)
                self._robot_shown_at = now
            self.panel.frame.image = annotated
            self.panel.frame_status.show(status_html(text, color))
            if frame.index is not None and (frame.total or frame.fraction is not None):
                self._sweep_progress(frame)
        if frame.index is not None:
            self.scene.set_plane_texture(frame.image)
        self.frames_shown += 1

    def show_registration(self, registration: Registration | None, markers_px: np.ndarray | None,
                          spacing_mm: tuple[float, float], phantom_to_base: np.ndarray) -> None:
        """A frame's markers registered to the phantom, in the base frame, coloured by their
        distance to their wire (nothing for None)."""
        if registration is None or markers_px is None:
            self.scene.set_registration(np.empty((0, 3)), np.empty(0))
            return
        points = image_mm_from_pixels(markers_px[registration.wire_indices], spacing_mm)
        self.scene.set_registration(registered_points(phantom_to_base, registration.image_to_phantom, points),
                                    registration.residuals_mm)
        self._marker_scale(REGISTRATION_FULL_SCALE_MM)

    def _marker_scale(self, full_scale_mm: float) -> None:
        """The markers' colour bar, from 0 to ``full_scale_mm`` (redrawn only when it changes)."""
        if full_scale_mm != self._marker_full_scale:
            self._marker_full_scale = full_scale_mm
            self.panel.marker_scale.image = colour_bar("marker to its wire", 0.0, full_scale_mm, "mm")

    # --- results ------------------------------------------------------------------------------

    def show_calibration(self, calibration: Calibration, verdict: Verdict, session: Path, truth: dict | None) -> None:
        """The verdict and results of ``session``'s calibration in the panel (against the twin's
        ``truth`` when given), the held-out error curve, and the image plane and phantom where the
        calibration puts them."""
        self.show_calibration_verdict(calibration, verdict, session, truth)
        self.panel.report.show(report_html(calibration))
        curve = calibration.metrics.get("error_vs_poses") or []
        if curve:
            values = [[np.nan if (value := point.get(key)) is None else float(value) for point in curve]
                      for key in CURVE_KEYS]
            self.panel.curve.data = (np.array([float(point["poses"]) for point in curve]),
                                     *(np.array(v) for v in values))
        self.panel.curve.visible = bool(curve)
        self._show_bound_map(calibration)
        self.scene.set_image_mount(calibration.shown_image_to_tool)
        if calibration.phantom_to_base is not None:
            self.scene.set_phantom_pose(calibration.phantom_to_base)

    def _show_bound_map(self, calibration: Calibration) -> None:
        """The calibration's bound map over the live frame, its legend under the frame (nothing
        for a calibration without one: made without validation, or by PLUS)."""
        bound_map = calibration.metrics.get("bound_map")
        self._lay_bound_map(None if bound_map is None else bound_overlay(bound_map, self._image_size_px, self.fan))

    def _lay_bound_map(self, overlay: Overlay | None) -> None:
        """``overlay`` (None: none) over the last frame shown and every later one, and its legend."""
        self.bound_overlay = overlay
        if overlay is not None:
            self.panel.bound_scale.image = colour_bar(BOUND_CAPTION, overlay.low, overlay.high, "mm")
        self.panel.bound_scale.visible = overlay is not None
        if self._last_frame is not None:
            self.panel.frame.image = self._annotated(*self._last_frame)

    def show_calibration_verdict(self, calibration: Calibration, verdict: Verdict, session: Path,
                                 truth: dict | None) -> None:
        """The calibration's headline: its verdict (at the tolerance now set) and figures."""
        self.panel.results.show(calibration_html(calibration, verdict, session, truth))

    def clear_calibration(self, image_to_tool: np.ndarray, phantom_to_base: np.ndarray) -> None:
        """No calibration: no results, report or curve, the image plane at the mount's design
        (``image_to_tool``) and the phantom where the set-up puts it."""
        self.panel.results.show(status_html(self.no_calibration, GREY))
        self.panel.report.show("")
        self.panel.curve.visible = False
        self._lay_bound_map(None)
        self.scene.set_image_mount(image_to_tool)
        self.scene.set_phantom_pose(phantom_to_base)
        self.counter("No calibration yet.", 0.0)

    def show_phantom_check(self, check: WireCheck, verdict: Verdict, phantom: Phantom, session: Path) -> None:
        """The phantom check's verdict in the Calibrate step, every wire in its Full report as
        ``probecal phantom check`` prints it, and the wires it finds off drawn where it finds them."""
        self.panel.phantom_check.show(wire_check_html(verdict, session))
        self.panel.phantom_table.show(wire_table_html(check, phantom))
        data, series, wire_axis, scales = wire_offset_plot(check)
        with self.server.atomic():
            plot = self.panel.offsets
            plot.series, plot.data, plot.scales = series, data, scales
            plot.axes = (wire_axis, MM_AXIS)
            plot.visible = True
        off = [k for k, wire in enumerate(check.wires) if check.verdict(wire) == "off"]
        self.scene.set_wires_off(phantom.moved(OFF_WIRES_DRAWN * np.nan_to_num(check.shifts_mm)).lines()[off])

    def show_live_volume(self, live: LiveVolume) -> None:
        """The volume compounded so far during a volume sweep."""
        points, gray = live.points()
        self.scene.set_live_volume(points, gray)
        self.panel.volume.show(status_html(f"Live volume: {live.frames} frames compounded, {len(points)} bright "
                                           "voxels shown (0.5 mm, nearest neighbour, no hole filling)", GREY))

    def show_reconstruction(self, reconstruction: Reconstruction, verdict: Verdict, out_dir: Path) -> None:
        """A reconstruction in ``out_dir`` (of its session): its verdict and figures, the cloud and
        the slices."""
        self._reconstruction, self._reconstruction_dir = reconstruction, out_dir
        self.scene.set_cloud(reconstruction.points_base, reconstruction.height_colors)
        self.color_cloud()
        self.show_reconstruction_verdict(verdict, out_dir)
        volume = reconstruction.volume
        for k, (axis, slider) in enumerate(self.panel.slice_at.items()):
            low, high, step = slice_range_mm(volume, axis)
            filled = np.flatnonzero(np.any(volume.voxels > 0, axis=tuple(a for a in range(3) if a != k)))
            middle = int(np.median(filled)) if len(filled) else volume.voxels.shape[k] // 2
            with self.server.atomic():  # to 0.1 mm, as the slider shows them: the nearest voxel is cut
                slider.min, slider.max, slider.step = round(low, 1), round(high, 1), step
                slider.value = round(low + middle * step, 1)  # type: ignore[misc]  # viser 1.1.1's setter
        self.panel.slices.visible = True
        self.show_slices()

    def show_self_check(self, saved: SavedSelfCheck, verdict: Verdict, report_file: Path) -> None:
        """A self-check (its report in ``report_file``): each view's surface (base mm) in its
        colour, in place of any earlier self-check's, and its verdict and worst pass."""
        self.scene.set_views([(points, VIEW_COLORS[k % len(VIEW_COLORS)]) for k, points in enumerate(saved.views)])
        self.panel.self_check_result.show(self_check_html(verdict, saved.report, report_file))

    @property
    def reconstruction(self) -> tuple[Reconstruction, Path] | None:
        """The reconstruction shown and its folder; None when none is."""
        if self._reconstruction is None or self._reconstruction_dir is None:
            return None
        return self._reconstruction, self._reconstruction_dir

    def show_reconstruction_verdict(self, verdict: Verdict, out_dir: Path) -> None:
        """The reconstruction's headline: its verdict (at the tolerance now set) and figures."""
        if self._reconstruction is not None:
            self.panel.volume.show(surface_html(self._reconstruction.report, verdict, out_dir))

    def show_slices(self) -> None:
        """The three slices through the reconstruction's volume where the sliders cut it, windowed."""
        if self._reconstruction is None:
            return
        volume = self._reconstruction.volume
        cuts = {axis: float(self.panel.slice_at[axis].value) for axis in self.panel.slice_images}
        for axis, image in self.panel.slice_images.items():
            image.image = volume_slice(volume, axis, cuts[axis], float(self.panel.window.value),
                                       float(self.panel.level.value))
        self.scene.set_slices(np.concatenate([slice_outline(volume, axis, at) for axis, at in cuts.items()]))

    def color_cloud(self) -> None:
        """Colour the reconstruction as the panel asks (height, or the distance to the CAD model),
        with its colour scale."""
        if self._reconstruction is None:
            return
        coloring = str(self.panel.cloud_colors.value)
        colors = getattr(self._reconstruction, CLOUD_COLORS[coloring])
        if colors is None:
            self.notify("No CAD comparison", "this reconstruction has no CAD model to measure against", error=False)
            return
        self.scene.set_cloud_colors(colors)
        if coloring == "height":
            z = self._reconstruction.points_base[:, 2]
            scale = colour_bar("height above the base, z", float(z.min()), float(z.max()), "mm")
        else:
            scale = colour_bar("distance to the CAD surface", 0.0, ERROR_FULL_SCALE_MM, "mm")
        self.panel.cloud_scale.image = scale
        self.panel.cloud_scale.visible = True

    def frame(self, centre_base_mm: np.ndarray, size_mm: float) -> None:
        """Every tab's camera (and that of tabs opened later) on ``centre_base_mm``, from where
        ``size_mm`` fills :data:`FILL` of the view's height: the phantom while calibrating, the
        object while scanning."""
        look_at = np.asarray(centre_base_mm, float) * MM
        view_height_m = max(size_mm, 50.0) * MM / FILL
        distance = view_height_m / (2.0 * np.tan(self.server.initial_camera.fov / 2.0))
        right = np.cross(-CAMERA_DIRECTION, [0.0, 0.0, 1.0])
        aside = right * view_height_m * SIDE_PANEL_PX / 2.0 / FRAMED_HEIGHT_PX / np.linalg.norm(right)
        self._camera(look_at + aside, look_at + aside + CAMERA_DIRECTION * distance)

    def show_step(self, step: str) -> None:
        """Show the layers of ``step`` (:data:`STEP_LAYERS`), in the View step's switches too, and
        hide the others."""
        shown, faded = STEP_LAYERS[step]
        for layer, switch in self.panel.layers.items():
            switch.value = layer in shown  # type: ignore[misc]  # viser 1.1.1's setter; its callback shows the layer
        self.scene.fade(faded)

    def show_markers(self, points_base_mm: np.ndarray, distances_mm: np.ndarray, tolerance_mm: float) -> None:
        """Markers in the base frame coloured by their distance to their wires (every frame's, once
        calibrated), on a fixed scale: red at the tolerance and beyond, so a good calibration
        shows blue and green markers."""
        self._markers = (points_base_mm, distances_mm)
        self.scene.set_registration(points_base_mm, distances_mm, tolerance_mm)
        self._marker_scale(tolerance_mm)

    def rescale_markers(self, tolerance_mm: float) -> None:
        """The calibrated markers shown again on the scale of a new tolerance."""
        if len(self._markers[1]):
            self.show_markers(*self._markers, tolerance_mm)

    def frame_robot(self) -> None:
        """Every tab's camera back on the whole robot."""
        self._camera(np.array(ROBOT_LOOK_AT), np.array(ROBOT_CAMERA))

    def _camera(self, look_at: np.ndarray, position: np.ndarray) -> None:
        self.server.initial_camera.look_at = tuple(look_at)
        self.server.initial_camera.position = tuple(position)
        for client in self.server.get_clients().values():
            with client.atomic():  # viser moves look_at with the position: the position goes first
                client.camera.position = position
                client.camera.look_at = look_at

    def clear_volume(self) -> None:
        """Nothing of a volume session left: its object, live volume, cloud and results, and a
        self-check's."""
        self._reconstruction, self._reconstruction_dir = None, None
        self.panel.slices.visible = False
        self.scene.clear_volume()
        self.panel.volume.show(status_html(NO_VOLUME, GREY))
        self.panel.self_check_result.show(status_html(NO_SELF_CHECK, GREY))
        self.panel.cloud_scale.visible = False

    def clear_calibration_session(self) -> None:
        """Nothing of a calibration session's frames left: the registered markers and the phantom check."""
        self._markers = (np.empty((0, 3)), np.empty(0))
        self.scene.set_registration(np.empty((0, 3)), np.empty(0))
        self.panel.phantom_check.show(status_html(NO_PHANTOM_CHECK, GREY))
        self.panel.phantom_table.show("")
        self.panel.offsets.visible = False
        self.scene.set_wires_off(np.empty((0, 2, 3)))

    def show_object(self, mesh: trimesh.Trimesh, object_to_base: np.ndarray) -> None:
        self.scene.set_object(mesh, object_to_base)
