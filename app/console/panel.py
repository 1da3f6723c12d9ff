"""The console's side panel: controls, settings, the live frame, progress and results. Built
once on the server, so every tab shows the same handles."""

from __future__ import annotations

import html
from dataclasses import dataclass
from typing import Literal

import numpy as np
import viser
import viser.uplot as uplot
from viser._gui_handles import GuiProgressBarHandle  # viser 1.1.1 does not export it

from probecal.app.console.draw import SLICE_AXES, colour_bar
from probecal.app.console.scene import LAYERS, REGISTRATION_FULL_SCALE_MM
from probecal.app.report import calibration_lines, wire_check_lines, wire_check_verdict
from probecal.core.acquisition.plan import PoseRanges
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.wirecheck import MIN_FRAMES, WireCheck
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.transforms import transform_error
from probecal.core.robot.ur3 import MotionLimits
from probecal.core.volume.reconstruct import ReconstructionReport

GREEN = "#2f9e44"
RED = "#e03131"
GREY = "#666666"
DEFAULT_POSES = MIN_FRAMES + 8
"""The console's sweep: Check phantom's runs need MIN_FRAMES frames that see each wire, and a
few frames may miss a wire or be refused."""
DEFAULT_FRAMES_PER_PASS = 40
CLI_POSES = 60
CLI_FRAMES_PER_PASS = 120

JPEG_QUALITY = 85
MIN_SPACING_MM, MAX_SPACING_MM = 0.005, 2.0  # what the pixel spacing field takes (scanners: 0.02-0.3 mm/px)
CLOUD_COLORINGS = ("height", "error to CAD")
MOTIONS = {"stop at every pose": "stop", "continuous": "continuous"}
NO_VOLUME = "No volume yet."
NO_PHANTOM_CHECK = "No phantom check yet."


LAYER_HINTS = {
    "robot": "the arm (faded while the calibration is shown)",
    "probe": "the probe's body, from the flange to the image",
    "image plane": "the image where the calibration puts it, the last recorded frame on it",
    "phantom": "the phantom's box where the calibration (else the set-up) puts it",
    "wires": "the phantom's wires",
    "markers": "the dots found, registered to the phantom and coloured by their distance to their wires",
    "cloud": "the reconstructed surface",
    "CAD model": "the test object's CAD model where it sits",
    "volume": "the volume compounded during a scan",
}

CURVE_SERIES = (uplot.Series(label="eq. 4.1 (mm)", stroke="#e03131", width=2),
                uplot.Series(label="PRE3D (mm)", stroke="#1c7ed6", width=2))
CURVE_KEYS: tuple[Literal["identity_translation_mm", "pre3d_mm"], ...] = ("identity_translation_mm", "pre3d_mm")
"""The held-out errors the calibration's error-vs-poses plot draws (``CurvePoint``), one series each."""

STRIP_WIDTH = 330
"""Width (px) of the status column docked on the left of the 3D view."""


@dataclass
class Panel:
    connect: viser.GuiButtonHandle
    start: viser.GuiButtonHandle
    stop: viser.GuiButtonHandle
    resume: viser.GuiCheckboxHandle
    calibrate: viser.GuiButtonHandle
    scan: viser.GuiButtonHandle
    reconstruct: viser.GuiButtonHandle
    save: viser.GuiButtonHandle
    load: viser.GuiButtonHandle
    poses: viser.GuiNumberHandle
    translation: viser.GuiVector3Handle
    rotation: viser.GuiVector3Handle
    speed: viser.GuiSliderHandle
    motion: viser.GuiDropdownHandle
    latency_ms: viser.GuiNumberHandle
    measure_latency: viser.GuiButtonHandle
    spacing: viser.GuiVector2Handle
    frames_per_pass: viser.GuiNumberHandle
    session_path: viser.GuiTextHandle
    status: viser.GuiHtmlHandle
    progress: GuiProgressBarHandle
    counter: viser.GuiMarkdownHandle
    frame: viser.GuiImageHandle
    frame_status: viser.GuiHtmlHandle
    results: viser.GuiHtmlHandle
    report: viser.GuiHtmlHandle
    curve: viser.GuiUplotHandle
    marker_scale: viser.GuiImageHandle
    volume: viser.GuiMarkdownHandle
    cloud_colors: viser.GuiDropdownHandle
    cloud_scale: viser.GuiImageHandle
    view_work: viser.GuiButtonHandle
    view_robot: viser.GuiButtonHandle
    check_phantom: viser.GuiButtonHandle
    phantom_check: viser.GuiHtmlHandle
    phantom_table: viser.GuiHtmlHandle
    layers: dict[str, viser.GuiCheckboxHandle]
    slices: viser.GuiFolderHandle
    window: viser.GuiSliderHandle
    level: viser.GuiSliderHandle
    slice_at: dict[str, viser.GuiSliderHandle]
    slice_images: dict[str, viser.GuiImageHandle]

    def ranges(self) -> PoseRanges:
        (tx, ty, tz), (rx, ry, rz) = self.translation.value, self.rotation.value
        return PoseRanges((float(tx), float(ty), float(tz)), (float(rx), float(ry), float(rz)))

    def limits(self) -> MotionLimits:
        return MotionLimits().scaled(float(self.speed.value))

    def motion_choice(self) -> str:
        """"stop" or "continuous" (``core.acquisition.rig.Recording``)."""
        return MOTIONS[str(self.motion.value)]


def build_panel(server: viser.ViserServer, frame_shape: tuple[int, int]) -> Panel:
    """A column docked on the left holds what must stay in sight: the status (the step running,
    its progress, frames recorded and refused, the time left, the last result), Stop and the
    live frame; the side panel on the right holds the work in four steps."""
    gui = server.gui
    gui.configure_theme(control_width="large", dark_mode=False, show_logo=False, brand_color=(40, 90, 230),
                        show_share_button=False)  # and the server refuses the request (server.ConsoleServer)
    strip = gui.add_panel()
    with strip.add_tab("probecal", viser.Icon.ACTIVITY):
        status = gui.add_html(status_html("Not connected: step 1, click Connect.", GREY))
        progress = gui.add_progress_bar(0.0)
        counter = gui.add_markdown("No sweep yet.")
        stop = gui.add_button("Stop", icon=viser.Icon.PLAYER_STOP, color="red",
                              hint="halt the robot at once; what is recorded stays recorded")
        frame = gui.add_image(np.zeros((*frame_shape, 3), np.uint8), label="Live ultrasound", format="jpeg",
                              jpeg_quality=JPEG_QUALITY)
        frame_status = gui.add_html(status_html("No frame yet.", GREY))
    strip.dock_left()
    strip.set_width(STRIP_WIDTH)
    steps = gui.add_tab_group()
    with steps.add_tab("1 Connect"):
        connect = gui.add_button("Connect", icon=viser.Icon.PLUG)
        motion = gui.add_dropdown("Motion", tuple(MOTIONS), initial_value=next(iter(MOTIONS)),
                                  hint="continuous: the robot does not stop; every frame of the stream is recorded "
                                       "and paired by time, and a calibration starts by measuring the image latency")
        speed = gui.add_slider("Speed (× UR default)", min=0.1, max=1.0, step=0.05, initial_value=1.0)
        latency_ms = gui.add_number("Image latency (ms)", 0.0, min=-500.0, max=500.0, step=0.1,
                                    hint="how late the frames are stamped; Measure latency and Calibrate of a "
                                         "continuous sweep set it, sweeps pair frames with it")
        measure_latency = gui.add_button("Measure latency", icon=viser.Icon.CLOCK,
                                         hint="move the probe up and down over the phantom and measure how late the "
                                              "images are")
        spacing = gui.add_vector2("Pixel spacing (mm/px)", (0.1, 0.1), min=(MIN_SPACING_MM,) * 2,
                                  max=(MAX_SPACING_MM,) * 2, step=0.0001,
                                  hint="the scanner's nominal spacing across and down the image (serve --spacing): "
                                       "the live markers use it, sweeps record it and Calibrate starts from it")
    with steps.add_tab("2 Calibrate"):
        start = gui.add_button("Start sweep", icon=viser.Icon.PLAYER_PLAY, color="green")
        calibrate = gui.add_button("Calibrate", icon=viser.Icon.TARGET)
        check_phantom = gui.add_button("Check phantom", icon=viser.Icon.RULER_MEASURE,
                                       hint="after Calibrate: where each wire of the built phantom is, against its "
                                            "definition (probecal phantom check)")
        poses = gui.add_number(f"Poses (CLI: {CLI_POSES})", DEFAULT_POSES, min=6, max=300, step=1,
                               hint=f"the console sweeps {DEFAULT_POSES} by default to be quick (Check phantom needs "
                                    f"{MIN_FRAMES} frames that see each wire); probecal sweep and simulate take "
                                    f"{CLI_POSES}")
        ranges = PoseRanges()
        translation = gui.add_vector3("Translation ± mm", ranges.translation_mm, min=(0, 0, 0), max=(30, 30, 10),
                                      step=0.5)
        rotation = gui.add_vector3("Rotation ± deg", ranges.rotation_deg, min=(0, 0, 0), max=(30, 30, 30), step=0.5)
        resume = gui.add_checkbox("Resume an unfinished sweep", True,
                                  hint="Start sweep and Scan volume continue a stopped or failed sweep's session")
        results = gui.add_html(status_html("No calibration yet: the image plane is drawn at the mount's design pose.",
                                           GREY))
        phantom_check = gui.add_html(status_html(NO_PHANTOM_CHECK, GREY))
        marker_scale = gui.add_image(colour_bar("marker to its wire", 0.0, REGISTRATION_FULL_SCALE_MM, "mm"),
                                     label="Registered markers", format="png")
        curve = gui.add_uplot(tuple(np.zeros(1) for _ in range(len(CURVE_SERIES) + 1)),
                              (uplot.Series(label="poses"), *CURVE_SERIES), title="Held-out error vs poses",
                              axes=(uplot.Axis(label="calibration poses"), uplot.Axis(label="mm")), aspect=1.4,
                              visible=False)
        with gui.add_folder("Full report", expand_by_default=False):
            report = gui.add_html("")
            phantom_table = gui.add_html("")
    with steps.add_tab("3 Scan"):
        scan = gui.add_button("Scan volume", icon=viser.Icon.SCAN)
        reconstruct = gui.add_button("Reconstruct", icon=viser.Icon.CUBE)
        frames_per_pass = gui.add_number(f"Frames per pass (CLI: {CLI_FRAMES_PER_PASS})", DEFAULT_FRAMES_PER_PASS,
                                         min=2, max=240, step=1,
                                         hint=f"the console takes {DEFAULT_FRAMES_PER_PASS} a pass by default to be "
                                              f"quick; probecal sweep and simulate take {CLI_FRAMES_PER_PASS}")
        volume = gui.add_markdown(NO_VOLUME)
        cloud_colors = gui.add_dropdown("Colour cloud by", CLOUD_COLORINGS, initial_value=CLOUD_COLORINGS[0])
        cloud_scale = gui.add_image(colour_bar("height", 0.0, 1.0, "of the range"), label="Cloud colours",
                                    format="png", visible=False)
        with gui.add_folder("Volume slices", expand_by_default=True, visible=False) as slices:
            window = gui.add_slider("Window", min=1, max=255, step=1, initial_value=255)
            level = gui.add_slider("Level", min=0, max=255, step=1, initial_value=128)
            slice_at = {axis: gui.add_slider(f"Slice {axis} (voxel)", min=0, max=1, step=1, initial_value=0)
                        for axis in SLICE_AXES}
            slice_images = {axis: gui.add_image(np.zeros((8, 8), np.uint8), label=f"across {axis}", format="png")
                            for axis in SLICE_AXES}
    with steps.add_tab("4 Session"):
        session_path = gui.add_text("Folder", "")
        save = gui.add_button("Save session", icon=viser.Icon.DEVICE_FLOPPY)
        load = gui.add_button("Load session", icon=viser.Icon.FOLDER_OPEN)
    with steps.add_tab("View"):
        view_work = gui.add_button("Frame the work", icon=viser.Icon.ZOOM_IN,
                                   hint="the camera on the phantom (calibration) or the object (volume)")
        view_robot = gui.add_button("Whole robot", icon=viser.Icon.ZOOM_OUT)
        layers = {layer: gui.add_checkbox(layer[0].upper() + layer[1:], True, hint=LAYER_HINTS[layer])
                  for layer in LAYERS}
    return Panel(connect, start, stop, resume, calibrate, scan, reconstruct, save, load, poses, translation, rotation,
                 speed, motion, latency_ms, measure_latency, spacing, frames_per_pass, session_path, status, progress,
                 counter, frame, frame_status, results, report, curve, marker_scale, volume, cloud_colors,
                 cloud_scale, view_work, view_robot, check_phantom, phantom_check, phantom_table, layers, slices,
                 window, level, slice_at, slice_images)


def md_text(value: object) -> str:
    """``value`` as literal text inside viser markdown, which renders raw HTML: HTML escaped and
    markdown's own marks backslash-escaped (file contents and folder names go through here)."""
    return "".join("\\" + c if c in "\\`*_{}[]()#+-.!|~<>" else c for c in html.escape(str(value), quote=True))


def status_html(text: str, color: str) -> str:
    return f'<div style="color:{color};font-weight:600;padding:2px 0">{html.escape(text)}</div>'


def _matrix_text(matrix: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:9.3f}" for v in row) for row in np.asarray(matrix)) + "\n"


def calibration_html(calibration: Calibration, truth: dict | None) -> str:
    """The calibration's headline: how far the image corners may be off (95 %, its accuracy),
    against the twin's ``truth`` when the session has one; then FRE, PRE3D and the latency in a
    smaller line. Text escaped (a loaded file may hold anything)."""
    m = calibration.metrics
    head, more = [], []
    if m.get("corner_error_95_mm") is not None:
        head.append(f"Image corners within ±{m['corner_error_95_mm']:.2f} mm (95 %)")
    if truth:
        dt, dr = transform_error(calibration.image_to_tool_rigid, np.array(truth["image_to_tool_rigid"]))
        head.append(f"vs truth {dt:.3f} mm / {dr:.3f}°")
    if "fre_mm" in m:
        more.append(f"FRE {m['fre_mm']:.3f} mm · PRE3D {m['pre3d_mm']:.3f} ± {m['pre3d_std_mm']:.3f} mm (consistency)")
    if calibration.image_latency_s is not None:
        more.append(f"image latency {calibration.image_latency_s * 1000:.1f} ms")
    if not head:
        head, more = more[:1], more[1:]
    return (f'<div style="font-weight:700;font-size:15px;padding:2px 0">{html.escape(" · ".join(head))}</div>'
            f'<div style="color:{GREY};padding:0 0 2px 0">{html.escape(" · ".join(more))}</div>')


def _pre(text: str) -> str:
    """Monospaced text whose lines keep their columns (scrolling sideways rather than wrapping)."""
    return (f'<pre style="font-size:10px;line-height:1.25;white-space:pre;overflow-x:auto;margin:4px 0">'
            f'{html.escape(text)}</pre>')


def report_html(calibration: Calibration) -> str:
    """The report as ``probecal calibrate`` prints it and the matrices, for the Full report folder."""
    body = "\n".join(calibration_lines(calibration))
    body += "\n\nimage_to_tool_rigid (mm)\n" + _matrix_text(calibration.image_to_tool_rigid)
    if calibration.phantom_to_base is not None:
        body += "\nphantom_to_base (mm)\n" + _matrix_text(calibration.phantom_to_base)
    return _pre(body)


def wire_check_html(check: WireCheck) -> str:
    """The phantom check's verdict in words, where the user looks; text escaped."""
    return f'<div style="font-weight:700;padding:2px 0">{html.escape(" ".join(wire_check_verdict(check)[:1]))}</div>'


def wire_table_html(check: WireCheck, phantom: Phantom) -> str:
    """Every wire as ``probecal phantom check`` prints it, for the Full report folder."""
    return _pre("\n".join(wire_check_lines(check, phantom)))


def surface_md(report: ReconstructionReport, out_dir: str) -> str:
    text = f"{report['surface_points']} surface points from {report['frames']} frames  \n"
    if "surface_mean_mm" in report:
        text += (f"**Surface error mean {report['surface_mean_mm']:.3f} mm**, 95th percentile "
                 f"{report['surface_p95_mm']:.3f} mm (CAD to points {report['cad_to_points_mean_mm']:.3f} mm)  \n")
    return text + f"written to {md_text(out_dir)}"
