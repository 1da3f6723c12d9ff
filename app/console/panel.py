"""The console's side panel: controls, settings, the live frame, progress and results. Built
once on the server, so every tab shows the same handles."""

from __future__ import annotations

import html
from dataclasses import dataclass

import numpy as np
import viser
from viser._gui_handles import GuiProgressBarHandle  # viser 1.1.1 does not export it

from probecal.core.acquisition.plan import PoseRanges
from probecal.core.calibration.result import Calibration
from probecal.core.geometry.transforms import transform_error
from probecal.core.robot.ur3 import MotionLimits
from probecal.core.volume.reconstruct import ReconstructionReport

GREEN = "#2f9e44"
RED = "#e03131"
GREY = "#666666"
DEFAULT_POSES = 30
DEFAULT_FRAMES_PER_PASS = 40
JPEG_QUALITY = 85
CLOUD_COLORINGS = ("height", "error to CAD")
MOTIONS = {"stop at every pose": "stop", "continuous": "continuous"}


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
    frames_per_pass: viser.GuiNumberHandle
    session_path: viser.GuiTextHandle
    status: viser.GuiHtmlHandle
    progress: GuiProgressBarHandle
    counter: viser.GuiMarkdownHandle
    frame: viser.GuiImageHandle
    frame_status: viser.GuiHtmlHandle
    results: viser.GuiMarkdownHandle
    curve: viser.GuiImageHandle
    volume: viser.GuiMarkdownHandle
    cloud_colors: viser.GuiDropdownHandle

    def ranges(self) -> PoseRanges:
        (tx, ty, tz), (rx, ry, rz) = self.translation.value, self.rotation.value
        return PoseRanges((float(tx), float(ty), float(tz)), (float(rx), float(ry), float(rz)))

    def limits(self) -> MotionLimits:
        return MotionLimits().scaled(float(self.speed.value))

    def motion_choice(self) -> str:
        """"stop" or "continuous" (``core.acquisition.rig.Recording``)."""
        return MOTIONS[str(self.motion.value)]


def build_panel(server: viser.ViserServer, frame_shape: tuple[int, int]) -> Panel:
    gui = server.gui
    gui.configure_theme(control_width="large", dark_mode=False, show_logo=False, brand_color=(40, 90, 230))
    gui.add_markdown("**probecal** · robot-guided ultrasound calibration")
    status = gui.add_html(status_html("Not connected: click Connect.", GREY))
    with gui.add_folder("Acquisition"):
        connect = gui.add_button("Connect", icon=viser.Icon.PLUG)
        start = gui.add_button("Start sweep", icon=viser.Icon.PLAYER_PLAY, color="green")
        stop = gui.add_button("Stop", icon=viser.Icon.PLAYER_STOP, color="red")
        resume = gui.add_checkbox("Resume an unfinished sweep", True,
                                  hint="Start sweep and Scan volume continue a stopped or failed sweep's session")
        poses = gui.add_number("Poses", DEFAULT_POSES, min=6, max=300, step=1)
        ranges = PoseRanges()
        translation = gui.add_vector3("Translation ± mm", ranges.translation_mm, min=(0, 0, 0), max=(30, 30, 10),
                                      step=0.5)
        rotation = gui.add_vector3("Rotation ± deg", ranges.rotation_deg, min=(0, 0, 0), max=(30, 30, 30), step=0.5)
        speed = gui.add_slider("Speed (× UR default)", min=0.1, max=1.0, step=0.05, initial_value=1.0)
        motion = gui.add_dropdown("Motion", tuple(MOTIONS), initial_value=next(iter(MOTIONS)),
                                  hint="continuous: the robot does not stop; every frame of the stream is recorded "
                                       "and paired by time, and a calibration starts by measuring the image latency")
        latency_ms = gui.add_number("Image latency (ms)", 0.0, min=-500.0, max=500.0, step=0.1,
                                    hint="how late the frames are stamped; Measure latency and Calibrate of a "
                                         "continuous sweep set it, sweeps pair frames with it")
        measure_latency = gui.add_button("Measure latency", icon=viser.Icon.CLOCK,
                                         hint="move the probe up and down over the phantom and measure how late the "
                                              "images are")
    progress = gui.add_progress_bar(0.0)
    counter = gui.add_markdown("Frames: 0")
    frame = gui.add_image(np.zeros((*frame_shape, 3), np.uint8), label="Live ultrasound", format="jpeg",
                          jpeg_quality=JPEG_QUALITY)
    frame_status = gui.add_html(status_html("No frame yet.", GREY))
    with gui.add_folder("Calibration"):
        calibrate = gui.add_button("Calibrate", icon=viser.Icon.TARGET)
        results = gui.add_markdown("No calibration yet: the image plane is drawn at the mount's design pose.")
        curve = gui.add_image(np.full((40, 420, 3), 255, np.uint8), label="Held-out error vs poses", format="png",
                              visible=False)
    with gui.add_folder("Volume"):
        frames_per_pass = gui.add_number("Frames per pass", DEFAULT_FRAMES_PER_PASS, min=2, max=240, step=1)
        scan = gui.add_button("Scan volume", icon=viser.Icon.SCAN)
        reconstruct = gui.add_button("Reconstruct", icon=viser.Icon.CUBE)
        volume = gui.add_markdown("No reconstruction yet.")
        cloud_colors = gui.add_dropdown("Colour cloud by", CLOUD_COLORINGS, initial_value=CLOUD_COLORINGS[0])
    with gui.add_folder("Session"):
        session_path = gui.add_text("Folder", "")
        save = gui.add_button("Save session", icon=viser.Icon.DEVICE_FLOPPY)
        load = gui.add_button("Load session", icon=viser.Icon.FOLDER_OPEN)
    return Panel(connect, start, stop, resume, calibrate, scan, reconstruct, save, load, poses, translation, rotation,
                 speed, motion, latency_ms, measure_latency, frames_per_pass, session_path, status, progress, counter,
                 frame, frame_status, results, curve, volume, cloud_colors)


def md_text(value: object) -> str:
    """``value`` as literal text inside viser markdown, which renders raw HTML: HTML escaped and
    markdown's own marks backslash-escaped (file contents and folder names go through here)."""
    return "".join("\\" + c if c in "\\`*_{}[]()#+-.!|~<>" else c for c in html.escape(str(value), quote=True))


def status_html(text: str, color: str) -> str:
    return f'<div style="color:{color};font-weight:600;padding:2px 0">{html.escape(text)}</div>'


def _matrix_md(matrix: np.ndarray) -> str:
    rows = "\n".join("    " + " ".join(f"{v:9.3f}" for v in row) for row in np.asarray(matrix))
    return rows + "\n"


def calibration_md(calibration: Calibration, truth: dict | None) -> str:
    """The results: FRE, PRE3D, spacing, frames, the matrices, and the error against the twin's
    truth when the session has one."""
    m = calibration.metrics
    sx, sy = calibration.pixel_spacing_mm
    lines = []
    if "fre_mm" in m:
        lines.append(f"**FRE {m['fre_mm']:.3f} mm** · **PRE3D {m['pre3d_mm']:.3f} ± {m['pre3d_std_mm']:.3f} mm**  ")
        lines.append(f"frames: {md_text(m['frames_used'])} used of {md_text(m['frames_total'])}, "
                     f"{md_text(m.get('frames_rejected', 0))} rejected  ")
    if "objective" in m:
        lines.append(f"objective: {md_text(m['objective'])} ({md_text(m.get('objective_choice', ''))})  ")
    if m.get("cv_pre3d_mm") is not None:
        lines.append(f"PRE3D on held-out blocks of frames: {m['cv_pre3d_mm']:.3f} mm  ")
    if m.get("corner_error_95_mm") is not None:
        lines.append(f"**image corners ±{m['corner_error_95_mm']:.2f} mm (95 %)**  ")
    if m.get("phantom_pose") == "solved":
        lines.append("phantom pose solved: PRE3D measures consistency, the corner bound accuracy  ")
    for reason in m.get("weakly_determined") or []:
        lines.append(f"⚠ weakly determined: {md_text(reason)}  ")
    cv = m.get("cross_validation") or {}
    if cv.get("identity_translation_mm") is not None:
        lines.append(f"cross-validation: {cv['identity_translation_mm']:.3f} mm / {cv['identity_rotation_deg']:.3f}° "
                     f"(eq. 4.1), PRE3D {cv['pre3d_mm']:.3f} mm  ")
    lines.append(f"pixel spacing: {sx:.5f} × {sy:.5f} mm/px  ")
    if "temporal" in m:
        t = m["temporal"]
        lines.append(f"**image latency {t['image_latency_s'] * 1000:.1f} ± {t['std_error_s'] * 1000:.1f} ms** "
                     f"(measured on {md_text(t['frames_used'])} frames of the up-and-down motion)  ")
    if truth:
        dt, dr = transform_error(calibration.image_to_tool_rigid, np.array(truth["image_to_tool_rigid"]))
        lines.append(f"vs truth: {dt:.3f} mm / {dr:.3f}°  ")
    lines.append("\n`image_to_tool_rigid` (mm)\n\n" + _matrix_md(calibration.image_to_tool_rigid))
    if calibration.phantom_to_base is not None:
        lines.append("`phantom_to_base` (mm)\n\n" + _matrix_md(calibration.phantom_to_base))
    return "\n".join(lines)


def surface_md(report: ReconstructionReport, out_dir: str) -> str:
    text = f"{report['surface_points']} surface points from {report['frames']} frames  \n"
    if "surface_mean_mm" in report:
        text += (f"**Surface error mean {report['surface_mean_mm']:.3f} mm**, 95th percentile "
                 f"{report['surface_p95_mm']:.3f} mm (CAD to points {report['cad_to_points_mean_mm']:.3f} mm)  \n")
    return text + f"written to {md_text(out_dir)}"
