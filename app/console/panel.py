"""The console's side panel: controls, settings, the live frame, progress and results. Built
once on the server, so every tab shows the same handles."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import viser
import viser.uplot as uplot
from viser._gui_handles import GuiProgressBarHandle  # viser 1.1.1 does not export it

from probecal.app.bounds import (
    FRAMES,
    PIXEL_SIZE,
    POSE_RANGE_DEG,
    POSE_RANGE_MM,
    POSES,
    SECONDS,
    SPEED,
    TOLERANCE_MM,
    Bound,
)
from probecal.app.console.draw import SLICE_AXES, SLICE_VIEW, colour_bar
from probecal.app.console.scene import LAYERS, REGISTRATION_FULL_SCALE_MM
from probecal.app.console.text import Markup, TextBox, html, text_box
from probecal.app.report import (
    DEFAULT_TOLERANCE_MM,
    WIRE_COLUMNS,
    Block,
    Table,
    Verdict,
    cad_to_points_text,
    calibration_report,
    wire_check_report,
)
from probecal.core.acquisition.plan import PoseRanges
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.wirecheck import CheckSettings, WireCheck
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom, wire_label
from probecal.core.geometry.transforms import transform_error
from probecal.core.robot.ur3 import MotionLimits
from probecal.core.volume.reconstruct import ReconstructionReport
from probecal.core.volume.selfcheck import SelfCheckReport

GREEN = "#2f9e44"
RED = "#e03131"
GREY = "#666666"
DEFAULT_POSES = CheckSettings().min_frames + 8
"""The console's sweep: Check phantom's runs need ``min_frames`` frames that see each wire, and a
few frames may miss a wire or be refused."""
DEFAULT_FRAMES_PER_PASS = 40
CLI_POSES = 60
CLI_FRAMES_PER_PASS = 120

JPEG_QUALITY = 85
CLOUD_COLORINGS = ("height", "error to CAD")
LATENCY_MS = Bound(SECONDS.low * 1000, SECONDS.high * 1000, " ms")
"""The Image latency field's bounds: the command line's --latency, in ms."""
MOTIONS = {"stop at every pose": "stop", "continuous": "continuous"}
NO_VOLUME = "No volume yet."
NO_SELF_CHECK = "No self-check yet."
NO_PHANTOM_CHECK = "No phantom check yet."
NO_CALIBRATION = "No calibration yet: the image plane is drawn at the mount's design pose."
NO_CALIBRATION_TRACKED = "No calibration yet: the image is drawn where its wire dots place it in the phantom."
NO_SAVE = "Nothing to save yet: frames are saved as they are recorded; Save writes a calibration once made."


LAYER_HINTS = {
    "robot": "the arm (faded while the calibration is shown)",
    "probe": "the probe's body, from the flange to the image",
    "image plane": "the image where the calibration puts it, the last recorded frame on it",
    "phantom": "the phantom's box where the calibration (else the set-up) puts it",
    "wires": "the phantom's wires",
    "markers": "the dots found, registered to the phantom and coloured by their distance to their wires",
    "guidance": "a tracked probe's targets still to reach (the next one in orange) and the live image (purple)",
    "cloud": "the reconstructed surface",
    "self-check": "each view's surface of the last Self-check, in its colour",
    "CAD model": "the test object's CAD model where it sits",
    "volume": "the volume compounded during a scan",
    "slices": "where the Volume slices cut the reconstructed volume",
}

CURVE_SERIES = (uplot.Series(label="held-out hand-eye (mm)", stroke="#e03131", width=2),
                uplot.Series(label="PRE3D (mm)", stroke="#1c7ed6", width=2))
CURVE_KEYS: tuple[Literal["identity_translation_mm", "pre3d_mm"], ...] = ("identity_translation_mm", "pre3d_mm")
"""The held-out errors the calibration's error-vs-poses plot draws (``CurvePoint``), one series each."""

VERDICT_COLOURS = {"off": RED, "unsure": "#f08c00", "within": GREEN}
"""The colour of each wire's error bar in the phantom check's plot, by its verdict."""
MM_AXIS = uplot.Axis(label="mm")
NUMBER_SCALES = {"x": uplot.Scale(time=False)}
"""A plot's x axis counts, not time (uPlot's default)."""

BUTTON_HINTS = {
    "measure_latency": "move the probe up and down over the phantom and measure how late the images are",
    "check_phantom": "after Calibrate: where each wire of the built phantom is, against its definition (probecal "
                     "phantom check)",
    "add_poses": "the poses Check phantom asks for, swept into the calibration session; then Calibrate and Check "
                 "phantom again on all its frames",
    "self_check": "after Calibrate: sweep the test object from two wrist angles into a new session and check that "
                  "the views' surfaces agree with the calibration held (probecal selfcheck)",
}
"""The hints of the buttons that have one while their step can run (the controller shows why not
while it cannot)."""

WIDE_SCREEN_PX = 1700
WIDE_PANEL_PX = 560
WIDE_SCREEN_CSS = Markup(f"<style>@media (min-width: {WIDE_SCREEN_PX}px) {{ "
                         f'.mantine-Paper-root[style*="width: 384px"] {{ width: {WIDE_PANEL_PX}px !important; '
                         f"left: auto !important; right: 15px !important; }} }}</style>")
"""On a screen at least :data:`WIDE_SCREEN_PX` wide the side panel (viser 1.1's floating panel of
"large" controls, 384 px, placed by its left edge) takes :data:`WIDE_PANEL_PX`, held to the right
edge, so that its tables and plots use the room."""

BOUND_LABEL = "Bound over the image"
BOUND_CAPTION = "95 % bound"
"""The live frame's legend once a calibration lays its bound map over it."""

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
    save_note: TextBox
    tolerance: viser.GuiNumberHandle
    status: TextBox
    progress: GuiProgressBarHandle
    counter: TextBox
    frame: viser.GuiImageHandle
    frame_status: TextBox
    guide: TextBox
    bound_scale: viser.GuiImageHandle
    results: TextBox
    report: TextBox
    curve: viser.GuiUplotHandle
    marker_scale: viser.GuiImageHandle
    volume: TextBox
    cloud_colors: viser.GuiDropdownHandle
    cloud_scale: viser.GuiImageHandle
    view_work: viser.GuiButtonHandle
    view_robot: viser.GuiButtonHandle
    check_phantom: viser.GuiButtonHandle
    add_poses: viser.GuiButtonHandle
    phantom_check: TextBox
    phantom_table: TextBox
    offsets: viser.GuiUplotHandle
    layers: dict[str, viser.GuiCheckboxHandle]
    slices: viser.GuiFolderHandle
    window: viser.GuiSliderHandle
    level: viser.GuiSliderHandle
    slice_at: dict[str, viser.GuiSliderHandle]
    slice_images: dict[str, viser.GuiImageHandle]
    self_check: viser.GuiButtonHandle
    self_check_result: TextBox

    # What the fields hold, checked where it is used (app.bounds): a page may send any value.

    def ranges(self) -> PoseRanges:
        translation = tuple(POSE_RANGE_MM.check(v, "Translation ± mm") for v in _three(self.translation.value))
        rotation = tuple(POSE_RANGE_DEG.check(v, "Rotation ± deg") for v in _three(self.rotation.value))
        return PoseRanges(translation, rotation)  # type: ignore[arg-type]  # three of each

    def limits(self) -> MotionLimits:
        return MotionLimits().scaled(SPEED.check(self.speed.value, "Speed"))

    def motion_choice(self) -> str:
        """"stop" or "continuous" (``core.acquisition.rig.Recording``)."""
        if self.motion.value not in MOTIONS:
            raise InputError(None, f"Motion: {self.motion.value!r} is not one of {', '.join(MOTIONS)}")
        return MOTIONS[self.motion.value]

    def pose_count(self) -> int:
        return int(POSES.check(self.poses.value, "Poses"))

    def frames_count(self) -> int:
        return int(FRAMES.check(self.frames_per_pass.value, "Frames per pass"))

    def latency_s(self) -> float:
        return LATENCY_MS.check(self.latency_ms.value, "Image latency") / 1000.0

    def spacing_mm(self) -> tuple[float, float]:
        values = self.spacing.value
        if not isinstance(values, (tuple, list)) or len(values) != 2:
            raise InputError(None, f"Pixel spacing: {values!r} is not two numbers")
        sx, sy = (PIXEL_SIZE.check(v, "Pixel spacing") for v in values)
        return sx, sy

    def tolerance_mm(self) -> float:
        return TOLERANCE_MM.check(self.tolerance.value, "Tolerance")


def _three(value: object) -> tuple:
    """A vector field's three values; InputError unless it holds three."""
    if not isinstance(value, (tuple, list)) or len(value) != 3:
        raise InputError(None, f"{value!r} is not three numbers")
    return tuple(value)


def build_panel(server: viser.ViserServer, frame_shape: tuple[int, int]) -> Panel:
    """A column docked on the left holds what must stay in sight: the status (the step running,
    its progress, frames recorded and refused, the time left, the last result), Stop and the
    live frame; the side panel on the right holds the work in four steps."""
    gui = server.gui
    gui.configure_theme(control_width="large", dark_mode=False, show_logo=False, brand_color=(40, 90, 230),
                        show_share_button=False)  # and the server refuses the request (server.ConsoleServer)
    strip = gui.add_panel()
    with strip.add_tab("probecal", viser.Icon.ACTIVITY):
        status = text_box(gui, strip_status_html("Not connected: step 1, click Connect.", GREY))
        progress = gui.add_progress_bar(0.0)
        counter = text_box(gui, counter_html("No sweep yet."))
        guide = text_box(gui, "", visible=False)
        stop = gui.add_button("Stop", icon=viser.Icon.PLAYER_STOP, color="red",
                              hint="halt the robot at once; what is recorded stays recorded")
        frame = gui.add_image(np.zeros((*frame_shape, 3), np.uint8), label="Live ultrasound", format="jpeg",
                              jpeg_quality=JPEG_QUALITY)
        frame_status = text_box(gui, status_html("No frame yet.", GREY))
        bound_scale = gui.add_image(colour_bar(BOUND_CAPTION, 0.0, 1.0, "mm"), label=BOUND_LABEL, format="png",
                                    visible=False)
        text_box(gui, WIDE_SCREEN_CSS)
    strip.dock_left()
    strip.set_width(STRIP_WIDTH)
    steps = gui.add_tab_group()
    with steps.add_tab("1 Connect"):
        connect = gui.add_button("Connect", icon=viser.Icon.PLUG)
        motion = gui.add_dropdown("Motion", tuple(MOTIONS), initial_value=next(iter(MOTIONS)),
                                  hint="continuous: the robot does not stop; every frame of the stream is recorded "
                                       "and paired by time, and a calibration starts by measuring the image latency")
        speed = gui.add_slider("Speed (× UR default)", min=0.1, max=1.0, step=0.05, initial_value=1.0)
        latency_ms = gui.add_number("Image latency (ms)", 0.0, min=LATENCY_MS.low, max=LATENCY_MS.high, step=0.1,
                                    hint="how late the frames are stamped; Measure latency and Calibrate of a "
                                         "continuous sweep set it, sweeps pair frames with it")
        measure_latency = gui.add_button("Measure latency", icon=viser.Icon.CLOCK,
                                         hint=BUTTON_HINTS["measure_latency"])
        spacing = gui.add_vector2("Pixel spacing (mm/px)", (0.1, 0.1), min=(PIXEL_SIZE.low,) * 2,
                                  max=(PIXEL_SIZE.high,) * 2, step=0.0001,
                                  hint="the scanner's nominal spacing across and down the image: the live markers "
                                       "use it, sweeps record it and Calibrate starts from it")
    with steps.add_tab("2 Calibrate"):
        start = gui.add_button("Start sweep", icon=viser.Icon.PLAYER_PLAY, color="green")
        calibrate = gui.add_button("Calibrate", icon=viser.Icon.TARGET)
        check_phantom = gui.add_button("Check phantom", icon=viser.Icon.RULER_MEASURE,
                                       hint=BUTTON_HINTS["check_phantom"])
        add_poses = gui.add_button("Add poses and check again", icon=viser.Icon.PLUS,
                                   hint=BUTTON_HINTS["add_poses"])
        tolerance = gui.add_number("Tolerance (mm)", DEFAULT_TOLERANCE_MM, min=TOLERANCE_MM.low,
                                   max=TOLERANCE_MM.high, step=0.05,
                                   hint="how far the image corners (95 %) and a scanned surface may be off for the "
                                        "result to be usable; the verdicts and the marker colours follow it")
        poses = gui.add_number("Poses", DEFAULT_POSES, min=POSES.low, max=POSES.high, step=1,
                               hint=f"the console sweeps {DEFAULT_POSES} by default to be quick (Check phantom needs "
                                    f"{CheckSettings().min_frames} frames that see each wire); probecal sweep and "
                                    f"simulate take {CLI_POSES}")
        ranges = PoseRanges()
        translation = gui.add_vector3("Translation ± mm", ranges.translation_mm, min=(POSE_RANGE_MM.low,) * 3,
                                      max=(POSE_RANGE_MM.high,) * 3, step=0.5)
        rotation = gui.add_vector3("Rotation ± deg", ranges.rotation_deg, min=(POSE_RANGE_DEG.low,) * 3,
                                   max=(POSE_RANGE_DEG.high,) * 3, step=0.5)
        resume = gui.add_checkbox("Resume an unfinished sweep", True,
                                  hint="Start sweep and Scan volume continue a stopped or failed sweep's session")
        results = text_box(gui, status_html(NO_CALIBRATION, GREY))
        phantom_check = text_box(gui, status_html(NO_PHANTOM_CHECK, GREY))
        marker_scale = gui.add_image(colour_bar("marker to its wire", 0.0, REGISTRATION_FULL_SCALE_MM, "mm"),
                                     label="Registered markers", format="png")
        curve = gui.add_uplot(tuple(np.zeros(1) for _ in range(len(CURVE_SERIES) + 1)),
                              (uplot.Series(label="poses"), *CURVE_SERIES), title="Held-out error vs poses",
                              axes=(uplot.Axis(label="calibration poses"), MM_AXIS), aspect=1.8, scales=NUMBER_SCALES,
                              visible=False)
        offsets = gui.add_uplot((np.zeros(1), np.zeros(1)), (uplot.Series(label="wire"), uplot.Series()),
                                title="Wire offsets (± 1 standard error)", legend=uplot.Legend(show=False),
                                axes=(uplot.Axis(label="wire"), MM_AXIS), aspect=1.8, visible=False)
        with gui.add_folder("Full report", expand_by_default=False):
            report = text_box(gui, "")
            phantom_table = text_box(gui, "")
    with steps.add_tab("3 Scan"):
        scan = gui.add_button("Scan volume", icon=viser.Icon.SCAN)
        reconstruct = gui.add_button("Reconstruct", icon=viser.Icon.CUBE)
        self_check = gui.add_button("Self-check", icon=viser.Icon.ARROWS_EXCHANGE, hint=BUTTON_HINTS["self_check"])
        frames_per_pass = gui.add_number("Frames per pass", DEFAULT_FRAMES_PER_PASS, min=FRAMES.low, max=FRAMES.high,
                                         step=1,
                                         hint=f"a scan is several passes side by side, each of this many frames; "
                                              f"the console takes {DEFAULT_FRAMES_PER_PASS} a pass by default to be "
                                              f"quick, probecal sweep and simulate {CLI_FRAMES_PER_PASS}")
        volume = text_box(gui, status_html(NO_VOLUME, GREY))
        self_check_result = text_box(gui, status_html(NO_SELF_CHECK, GREY))
        cloud_colors = gui.add_dropdown("Colour cloud by", CLOUD_COLORINGS, initial_value=CLOUD_COLORINGS[0])
        cloud_scale = gui.add_image(colour_bar("height", 0.0, 1.0, "of the range"), label="Cloud colours",
                                    format="png", visible=False)
        with gui.add_folder("Volume slices", expand_by_default=True, visible=False) as slices:
            window = gui.add_slider("Window", min=1, max=255, step=1, initial_value=255)
            level = gui.add_slider("Level", min=0, max=255, step=1, initial_value=128)
            slice_at = {axis: gui.add_slider(f"{axis} (mm, base frame)", min=0.0, max=1.0, step=0.5,
                                             initial_value=0.0, hint=f"where the slice across {axis} cuts, drawn "
                                                                     "in the 3D view") for axis in SLICE_AXES}
            slice_images = {axis: gui.add_image(np.zeros((8, 8, 3), np.uint8), label=f"across {axis} "
                                                f"(+{SLICE_VIEW[axis][0]} up, +{SLICE_VIEW[axis][1]} right)",
                                                format="png") for axis in SLICE_AXES}
    with steps.add_tab("4 Session"):
        save = gui.add_button("Save session", icon=viser.Icon.DEVICE_FLOPPY)
        save_note = text_box(gui, status_html(NO_SAVE, GREY))
        session_path = gui.add_text("Folder", "", hint="the session Load session opens: a folder's name in the "
                                                         "sessions folder")
        load = gui.add_button("Load session", icon=viser.Icon.FOLDER_OPEN)
    with steps.add_tab("View"):
        view_work = gui.add_button("Frame the work", icon=viser.Icon.ZOOM_IN,
                                   hint="the camera on the phantom (calibration) or the object (volume)")
        view_robot = gui.add_button("Whole robot", icon=viser.Icon.ZOOM_OUT)
        layers = {layer: gui.add_checkbox(layer[0].upper() + layer[1:], True, hint=LAYER_HINTS[layer])
                  for layer in LAYERS}
    return Panel(connect, start, stop, resume, calibrate, scan, reconstruct, save, load, poses, translation, rotation,
                 speed, motion, latency_ms, measure_latency, spacing, frames_per_pass, session_path, save_note,
                 tolerance, status, progress, counter, frame, frame_status, guide, bound_scale, results, report,
                 curve, marker_scale, volume, cloud_colors, cloud_scale, view_work, view_robot, check_phantom,
                 add_poses, phantom_check, phantom_table, offsets, layers, slices, window, level, slice_at,
                 slice_images, self_check, self_check_result)


def status_html(text: str, color: str) -> Markup:
    return html('<div style="color:{};font-weight:600;padding:2px 0">{}</div>', color, text)


def counter_html(text: str) -> Markup:
    """The strip's counter line, under its progress bar."""
    return html('<div style="padding:4px 0">{}</div>', text)


STATUS_LINES = 5
"""The status line's height in lines: its box keeps it whatever the text, so nothing below moves."""


def strip_status_html(text: str, color: str) -> Markup:
    """The status column's line: a box of :data:`STATUS_LINES` lines, long words (paths) broken,
    a longer text scrolling inside it."""
    return html('<div class="probecal-status" style="color:{};font-weight:600;line-height:1.35;height:{:.2f}em;'
                'overflow-y:auto;overflow-wrap:anywhere;padding:2px 0">{}</div>', color, STATUS_LINES * 1.35, text)


VERDICT_COLOURS_BY_USE = {True: GREEN, False: RED, None: GREY}
"""A verdict's colour: usable, not usable, nothing to judge by."""


def verdict_html(verdict: Verdict) -> Markup:
    """A verdict where the user looks first: bold, in its colour, with the next step."""
    return html('<div style="font-weight:700;font-size:14px;color:{};padding:2px 0">{}</div>',
                VERDICT_COLOURS_BY_USE[verdict.usable], verdict.text)


def session_html(path: Path) -> Markup:
    """Which session a result belongs to: its folder's name, the whole path on hover."""
    return html('<div style="color:{};font-size:12px">session <span title="{}" '
                'style="text-decoration:underline dotted">{}</span></div>', GREY, str(path), path.name)


def calibration_html(calibration: Calibration, verdict: Verdict, session: Path, truth: dict | None) -> Markup:
    """The calibration's verdict first, then against the twin's ``truth`` when the session has
    one, FRE, PRE3D and the latency in a smaller line, and the session it belongs to. Text escaped
    (a loaded file may hold anything)."""
    m = calibration.metrics
    more = []
    if truth:
        dt, dr = transform_error(calibration.image_to_tool_rigid, np.array(truth["image_to_tool_rigid"]))
        more.append(f"against the twin's truth {dt:.3f} mm / {dr:.3f}°")
    if "fre_mm" in m:
        more.append(f"FRE {m['fre_mm']:.3f} mm · PRE3D {m['pre3d_mm']:.3f} ± {m['pre3d_std_mm']:.3f} mm (consistency)")
    if calibration.image_latency_s is not None:
        more.append(f"image latency {calibration.image_latency_s * 1000:.1f} ms")
    return verdict_html(verdict) + html('<div style="color:{};padding:0 0 2px 0">{}</div>', GREY, " · ".join(more)) \
        + session_html(session)


CELL = "padding:1px 4px;text-align:right;white-space:nowrap"


def _table_html(table: Table) -> Markup:
    """A report's table that fits the side panel: small type, figures to the right, the marked row
    in bold; text escaped."""
    def row_html(cells: tuple[str, ...], tag: str, bold: bool) -> Markup:
        weight = "font-weight:700;" if bold else ""
        return Markup("<tr>{}</tr>").format(Markup("").join(
            html(f'<{tag} style="{CELL};{weight}{"text-align:left" if k == 0 and table.named else ""}">{{}}</{tag}>',
                 cell) for k, cell in enumerate(cells)))

    rows = Markup("").join(row_html(cells, "td", i == table.marked) for i, cells in enumerate(table.rows))
    title = html('<div style="margin:6px 0 2px 0">{}</div>', table.title) if table.title else Markup("")
    return html('{}<table style="border-collapse:collapse;font-size:11px;margin:2px 0 6px 0">'
                '<thead style="border-bottom:1px solid {}">{}</thead><tbody>{}</tbody></table>',
                title, GREY, row_html(table.header, "th", False), rows)


def _blocks_html(blocks: list[Block]) -> Markup:
    """A report's sentences as wrapped paragraphs and its tables as tables, in the panel's width."""
    return html('<div style="font-size:12px;line-height:1.35">{}</div>', Markup("").join(
        _table_html(block) if isinstance(block, Table) else html('<p style="margin:3px 0">{}</p>', block)
        for block in blocks))


def _matrix_table(title: str, matrix: np.ndarray) -> Table:
    """A transform's axes and origin (columns) by component (rows)."""
    return Table(title, ("", "x axis", "y axis", "z axis", "origin"),
                 tuple((axis, *(f"{v:.3f}" for v in row)) for axis, row in zip("xyz", np.asarray(matrix)[:3])))


def report_html(calibration: Calibration) -> Markup:
    """The report ``probecal calibrate`` prints and the transforms' axes and origins, for the Full
    report folder."""
    blocks = [*calibration_report(calibration), _matrix_table("image to tool, rigid (mm)",
                                                                calibration.image_to_tool_rigid)]
    if calibration.phantom_to_base is not None:
        blocks.append(_matrix_table("phantom to robot base (mm)", calibration.phantom_to_base))
    return _blocks_html(blocks)


def wire_check_html(verdict: Verdict, session: Path) -> Markup:
    """The phantom check's verdict where the user looks, and the session it checked."""
    return verdict_html(verdict) + session_html(session)


WIRE_PANEL_TABLES = (("wire", "dots", "offset", "±", "toward", "verdict"), ("wire", "front", "back", "sag", "spread"))
"""The wire table's columns (``app.report.WIRE_COLUMNS``) split in two tables that fit the panel:
where each wire is, then its ends and sag."""


def wire_table_html(check: WireCheck, phantom: Phantom) -> Markup:
    """Every wire as ``probecal phantom check`` reports it, for the Full report folder."""
    blocks: list[Block] = []
    for block in wire_check_report(check, phantom):
        if isinstance(block, Table):
            blocks += [block.columns([WIRE_COLUMNS.index(name) for name in names]) for names in WIRE_PANEL_TABLES]
        else:
            blocks.append(block)
    return _blocks_html(blocks)


def wire_offset_plot(check: WireCheck) -> tuple[tuple[np.ndarray, ...], tuple[uplot.Series, ...], uplot.Axis,
                                                    dict[str, uplot.Scale]]:
    """The phantom check's offsets for viser's plot: every wire's offset (a dot) with its standard
    error (a bar coloured by its verdict) against the tolerance (dashed); the data, series, wire
    axis and scales. Each bar is a series of its own, holding only its two ends at its wire (the
    plot joins a series' points, and its data cannot hold gaps)."""
    n = len(check.wires)
    x = np.repeat(np.arange(n, dtype=float), 2)
    offsets = np.array([w.offset_mm for w in check.wires])
    errors = np.array([w.uncertainty_mm for w in check.wires])
    bars = []
    for k in range(n):
        bar = np.full(2 * n, np.nan)
        bar[2 * k:2 * k + 2] = max(offsets[k] - errors[k], 0.0), offsets[k] + errors[k]
        bars.append(bar)
    data = (x, np.repeat(offsets, 2), np.full(2 * n, check.tolerance_mm), *bars)
    series = (uplot.Series(label="wire"),
              uplot.Series(label="offset (mm)", stroke="rgba(0,0,0,0)",
                           points={"show": True, "size": 7, "fill": "#222222", "stroke": "#222222"}),
              uplot.Series(label="tolerance (mm)", stroke=GREY, width=1, dash=(4, 4), points={"show": False}),
              *(uplot.Series(label=wire_label(k), stroke=VERDICT_COLOURS[check.verdict(wire)], width=2,
                             points={"show": False}) for k, wire in enumerate(check.wires)))
    axis = uplot.Axis(label="wire (layer, L/D/R)", splits=tuple(float(k) for k in range(n)),
                      values=tuple(wire_label(k) for k in range(n)))
    top = float(np.nanmax([check.tolerance_mm, *(offsets + errors)])) * 1.15
    return data, series, axis, {"x": uplot.Scale(time=False, range=(-0.5, n - 0.5)),
                                "y": uplot.Scale(auto=False, range=(0.0, top))}


def surface_html(report: ReconstructionReport, verdict: Verdict, out_dir: Path) -> Markup:
    """The reconstruction's verdict first, then its figures and the session it belongs to."""
    text = f"{report['surface_points']} surface points from {report['frames']} frames"
    if "surface_mean_mm" in report:
        text += (f" · surface to CAD {report['surface_mean_mm']:.3f} mm mean, {report['surface_p95_mm']:.3f} mm 95th "
                 f"percentile · CAD to points {cad_to_points_text(report)}")
    return verdict_html(verdict) + html('<div style="color:{};padding:0 0 2px 0">{}; in {}</div>', GREY, text,
                                        out_dir.name) + session_html(out_dir.parent)


def self_check_html(verdict: Verdict, report: SelfCheckReport, report_file: Path) -> Markup:
    """The self-check's verdict first, then its worst pass and where its report is, and the session
    it checked."""
    worst = max(report["passes"], key=lambda p: p["offset_norm_mm"])
    text = (f"worst: pass {worst['pass_index']} of view {worst['view']}, {worst['offset_norm_mm']:.3f} mm and "
            f"{worst['rotation_deg']:.2f} deg off pass {worst['against_pass']} of view {worst['against_view']} "
            f"(median surface distance {worst['median_before_mm']:.3f} mm); report {report_file}")
    return verdict_html(verdict) + html('<div style="color:{};padding:0 0 2px 0;overflow-wrap:anywhere">{}</div>',
                                        GREY, text) + session_html(report_file.parent.parent)
