"""Calibration results: the design §2 JSON with the metrics a calibration reports, the PLUS
``<Transform From="Image" To="Probe">`` element, and reading a calibration back from any of the
forms a user may hand us."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, TypedDict, cast

import numpy as np

from probecal.core.calibration.kinematics import ARMS, DEVIATION_NAMES, MAX_ANGLE_DEG, MAX_LENGTH_MM, ArmDeviationJSON
from probecal.core.calibration.validity import ValidFor
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.transforms import check_transform, make_transform, nearest_rotation
from probecal.core.io.deviceset import device_set_xml, fan_attributes, matrix_attribute, parse_xml, read_device_set
from probecal.core.io.files import existing_file, write_atomic
from probecal.core.io.jsonio import (
    expect_integer,
    expect_list,
    expect_matrix,
    expect_number,
    expect_numbers,
    expect_object,
    expect_spacing,
    expect_string,
    expect_typed,
    optional,
    read_json,
    required,
    to_json_text,
)
from probecal.core.io.manifest import fan_from_json
from probecal.core.temporal.lag import FittedLatencyReport, LatencyReport

MIN_STRETCH = 0.8  # a fan calibration's stretch lies within this and its inverse (tissue and water: 0.93-1.05)
KEYS = ("image_to_tool", "image_to_tool_rigid", "pixel_spacing_mm", "phantom_to_base")


class HeldOut(TypedDict, total=False):
    """PRE3D on held-out blocks of consecutive frames (mm; mean and std of the lowest 95 %, pooled
    and per block, None where a block could not be held out) and, given the frames registered at
    the calibrated spacing, the thesis's eq. 4.1 identity error on them (mm, degrees)."""

    folds: int
    blocks: int
    pre3d_mm: float | None
    pre3d_std_mm: float | None
    pre3d_per_block_mm: list[float | None]
    identity_translation_mm: float | None
    identity_rotation_deg: float | None


class CurvePoint(TypedDict):
    """The held-out errors (mm, degrees) of a calibration from ``poses`` poses (thesis Fig. 4.5)."""

    poses: int
    identity_translation_mm: float | None
    identity_rotation_deg: float | None
    pre3d_mm: float | None


class VerdictJSON(TypedDict):
    """A result's verdict as its JSON keeps it: usable (None: nothing to judge it by), in words,
    and the tolerance (mm) it was judged against."""

    usable: bool | None
    text: str
    tolerance_mm: float


class ObjectiveRow(TypedDict):
    """One objective's line in the side-by-side table: its held-out PRE3D (mm), spacing (mm/px)
    and how many frames its fit rejected."""

    cv_pre3d_mm: float | None
    cv_pre3d_std_mm: float | None
    cv_pre3d_per_block_mm: list[float | None]
    cv_folds: int
    pixel_spacing_mm: list[float]
    frames_rejected: int


class CornerError(TypedDict):
    """The parts of the 95 % image-corner bound (mm): block-bootstrap refits, twice the block
    jackknife of the fits that each left a block of consecutive frames out, the other objectives'
    disagreement (and how far it goes beyond that objective's own random error, from its
    cross-validation folds), the refit with the markers at their echoes' peaks and the refit
    under the loose wire prior (None where the fit held its wires or the phantom pose was known)."""

    bootstrap_95_mm: float | None
    jackknife_95_mm: float | None
    objective_disagreement_mm: dict[str, float | None]
    objective_excess_mm: dict[str, float | None]
    fold_spread_mm: dict[str, float | None]
    echo_peak_disagreement_mm: float | None
    wire_prior_disagreement_mm: float | None
    resamples: int
    failed_resamples: int


class BoundMap(TypedDict):
    """The 95 % bound (mm, tool frame) at a grid of image points, each point on its own, from the
    corner bound's fits by its rule (``core.calibration.uncertainty.point_bounds_mm``): small
    where the wires pin the calibration down, large where it is extrapolated. ``points_px`` (u, v
    as the image shows them) row by row down the image (on a fan image, arcs from the near radius
    out, each from the fan's first angle to its second) and ``bound_mm`` of the same rows and
    columns (None where no refit could be made)."""

    points_px: list[list[list[float]]]
    bound_mm: list[list[float | None]]


class CalibrationMetrics(TypedDict, total=False):
    """What ``probecal calibrate`` reports with a calibration (design §6; mm, degrees, mm/px). A
    calibration read from PLUS or an older file may hold none or only some of them."""

    method: str
    objective: str
    objective_choice: str
    frames_total: int
    frames_used: int
    frames_rejected: int
    frames_rejected_by_fit: int
    rejected_frames: dict[int, str]
    fre_mm: float
    fre_per_frame_mm: dict[int, float | None]
    calibration_residual_mm: float
    pre3d_mm: float
    pre3d_std_mm: float
    cv_pre3d_mm: float | None
    corner_error_95_mm: float | None
    corner_error: CornerError
    bound_map: BoundMap
    phantom_pose: str
    initial_pixel_spacing_mm: list[float]
    objectives: dict[str, ObjectiveRow]
    wire_shifts_mm: dict[str, float | None] | None
    arm_correction_mm: float | None
    arm_undetermined: list[str] | None
    image_latency_s: float | None
    temporal: LatencyReport | FittedLatencyReport
    cross_validation: HeldOut
    weakly_determined: list[str]
    error_vs_poses: list[CurvePoint]
    verdict: VerdictJSON


@dataclass(frozen=True)
class Calibration:
    """``image_to_tool_rigid`` (mm), pixel spacing (sx, sy) mm/px and, when known,
    ``phantom_to_base`` and the image latency (s: a frame stamped ``t`` shows the probe where it
    was at ``t - image_latency_s``), which every later sweep and reconstruction pairs with.
    ``image_to_tool`` includes the spacing (PLUS's ImageToProbe).

    A fan image's calibration also holds the fan (its pixels) and the ``stretch`` of every beam's
    depth below the face (the medium's sound speed over the scanner's): ``image_to_tool`` then
    maps its pixels once :meth:`set_right` has stretched them, which no affine map of the pixels
    as shown does exactly (:attr:`shown_image_to_tool` comes closest)."""

    image_to_tool_rigid: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    phantom_to_base: np.ndarray | None = None
    metrics: CalibrationMetrics = field(default_factory=lambda: CalibrationMetrics())
    affine: np.ndarray | None = None  # a given ImageToProbe that is not rigid-times-spacing (PLUS's)
    image_latency_s: float | None = None
    valid_for: ValidFor | None = None  # the images it was made from (core.calibration.validity)
    arm: ArmDeviationJSON | None = None  # the arm's kinematic deviations it found (core.calibration.kinematics)
    fan: Fan | None = None
    stretch: float | None = None

    @property
    def image_to_tool(self) -> np.ndarray:
        """Pixels to tool mm. A matrix read from PLUS is used as given: PLUS's least squares
        leaves its image axes a little skewed, and rounding it to rigid-times-spacing would move
        far pixels by a millimetre or more."""
        if self.affine is not None:
            return self.affine
        sx, sy = self.pixel_spacing_mm
        return self.image_to_tool_rigid @ np.diag([sx, sy, 1.0, 1.0])

    def set_right(self, pixels: np.ndarray) -> np.ndarray:
        """(..., 2) pixels as :attr:`image_to_tool` takes them: a fan image's with every beam's
        depth below the face stretched by :attr:`stretch`, any other's as they are."""
        if self.fan is None or self.stretch is None:
            return np.asarray(pixels, dtype=float)
        return self.fan.stretched(pixels, self.stretch)

    @cached_property
    def shown_image_to_tool(self) -> np.ndarray:
        """Pixels as the image shows them to tool mm: :attr:`image_to_tool`, or for a fan
        calibration the affine map closest to it over the fan (what PLUS and 3D Slicer take)."""
        if self.fan is None or self.stretch is None:
            return self.image_to_tool
        matrix = self.image_to_tool

        def in_tool(pixels: np.ndarray) -> np.ndarray:
            points = self.set_right(pixels)
            return points @ matrix[:3, :2].T + matrix[:3, 3]

        affine = self.fan.closest_affine(in_tool)  # (4, 3): the u, v and offset columns
        return np.column_stack([affine[:, :2], [*matrix[:3, 2], 0.0], affine[:, 2]])

    def to_dict(self) -> dict:
        fan = {} if self.fan is None else {"fan": self.fan.to_json(), "stretch": self.stretch}
        return {
            "image_to_tool": self.shown_image_to_tool,
            "image_to_tool_rigid": self.image_to_tool_rigid,
            "pixel_spacing_mm": list(self.pixel_spacing_mm),
            **fan,
            "phantom_to_base": self.phantom_to_base,
            "image_latency_s": self.image_latency_s,
            "valid_for": self.valid_for,
            "arm": self.arm,
            "metrics": self.metrics,
        }

    def plus_element(self) -> str:
        """The PLUS device-set element holding the result (ImageToProbe includes the spacing); for
        a fan calibration, a device set that also clips the volume to the fan as PLUS does
        (``<VolumeReconstruction>``, :func:`core.io.deviceset.fan_attributes`)."""
        error = self.metrics.get("pre3d_mm")
        if self.fan is not None:
            size = self.valid_for["image_size"] if self.valid_for is not None else np.ceil(  # the fan's own extent
                [self.fan.corners_px()[:, 0].max() + 1.0, self.fan.origin_px[1] + self.fan.radius_stop_px + 1.0])
            text = None if not isinstance(error, (int, float)) else f"{error:.4g}"
            return device_set_xml({("Image", "Probe"): (self.shown_image_to_tool, text)},
                                  volume_reconstruction=fan_attributes(self.fan, (int(size[0]), int(size[1]))))
        rows = "\n".join("        " + " ".join(f"{v:.9g}" for v in row) for row in self.image_to_tool)
        error_attr = f' Error="{error:.4g}"' if isinstance(error, (int, float)) else ""
        return f'<Transform From="Image" To="Probe"\n      Matrix="\n{rows}"{error_attr} />\n'

    @cached_property
    def json_text(self) -> str:
        """The calibration JSON as :meth:`write` writes it."""
        return to_json_text(self.to_dict())

    def write(self, path: str | Path) -> Path:
        """Write the JSON to ``path`` and the PLUS element beside it (same name, ``.xml``)."""
        path = Path(path)
        write_atomic(path, self.json_text)
        xml_path = path.with_suffix(".xml")
        write_atomic(xml_path, self.plus_element())
        return xml_path


class CalibrationSource(TypedDict):
    """Which calibration made a result: its file (None: not saved yet), the SHA-256 of the
    file's bytes (or of the JSON :meth:`Calibration.write` would write), and whether the one
    used was derived from it for other images (``core.calibration.presets``)."""

    file: str | None
    sha256: str
    derived: bool


def calibration_source(calibration: Calibration, file: str | Path | None = None,
                       derived: bool = False) -> CalibrationSource:
    """What a result records of the calibration that made it, read from ``file`` when it came
    from one (the one used was ``derived`` from it)."""
    data = Path(file).read_bytes() if file is not None else calibration.json_text.encode()
    return CalibrationSource(file=None if file is None else str(Path(file).resolve()),
                             sha256=hashlib.sha256(data).hexdigest(), derived=derived)


MAX_SKEW_DEG = 5.0  # PLUS's least-squares image axes are perpendicular to within hundredths of a degree


def calibration_from_matrix(image_to_tool: np.ndarray, source: Path) -> Calibration:
    """Split a PLUS ImageToProbe (rotation times spacing) into rigid part and spacing; InputError
    naming ``source`` when its image axes are zero, not perpendicular (within ``MAX_SKEW_DEG``) or
    its last row is not 0 0 0 1."""
    image_to_tool = check_transform(image_to_tool, "Image->Probe matrix", source)
    with np.errstate(over="ignore"):  # an overflowing axis is refused below
        sx, sy = np.linalg.norm(image_to_tool[:3, 0]), np.linalg.norm(image_to_tool[:3, 1])
    if not (np.isfinite(sx) and np.isfinite(sy) and sx > 0 and sy > 0):
        raise InputError(source, "Image->Probe matrix has a zero or overflowing image axis")
    x_axis, y_axis = image_to_tool[:3, 0] / sx, image_to_tool[:3, 1] / sy
    skew = abs(90.0 - np.degrees(np.arccos(np.clip(np.dot(x_axis, y_axis), -1.0, 1.0))))
    if skew > MAX_SKEW_DEG:
        raise InputError(source, f"Image->Probe matrix: the image axes are {skew:.1f} deg from perpendicular")
    rigid = make_transform(nearest_rotation(np.column_stack([x_axis, y_axis, np.cross(x_axis, y_axis)])),
                           image_to_tool[:3, 3])
    return Calibration(rigid, (float(sx), float(sy)), affine=np.array(image_to_tool, dtype=float))


def _calibration_from_xml(path: Path) -> Calibration:
    """A PLUS device set with Image->Probe (and, if given, a rigid Phantom->Reference), or a bare
    ``<Transform From="Image" To="Probe">`` element."""
    root = parse_xml(path)
    if root.tag == "Transform" and root.get("From") == "Image" and root.get("To") == "Probe":
        return calibration_from_matrix(matrix_attribute(root, path, "Transform Image->Probe"), path)
    config = read_device_set(path)
    matrix = config.transform("Image", "Probe")
    if matrix is None:
        raise InputError(path, "no Image->Probe transform in this file")
    calibration = calibration_from_matrix(matrix, path)
    return replace(calibration, phantom_to_base=config.rigid_transform("Phantom", "Reference"))


def _calibration_from_json(path: Path) -> Calibration:
    """Our calibration JSON or a simulated session's truth.json, checked key by key."""
    data = read_json(path)
    rigid = required(data, "image_to_tool_rigid", expect_matrix, path, rigid=True)
    spacing = required(data, "pixel_spacing_mm", expect_spacing, path)
    optional(data, "image_to_tool", expect_matrix, path)
    phantom_to_base = optional(data, "phantom_to_base", expect_matrix, path, rigid=True)
    metrics = _metrics(data, path)
    fan = None if data.get("fan") is None else fan_from_json(data["fan"], path)
    stretch = optional(data, "stretch", expect_number, path, positive=True)
    if (fan is None) != (stretch is None):
        raise InputError(path, "a fan image's calibration needs both fan and stretch")
    if stretch is not None and not MIN_STRETCH <= stretch <= 1.0 / MIN_STRETCH:
        raise InputError(path, f"stretch {stretch:g} is no sound speed's: it must lie within {MIN_STRETCH:g} and "
                               f"{1.0 / MIN_STRETCH:.3g}")
    return Calibration(rigid, (float(spacing[0]), float(spacing[1])), phantom_to_base, metrics,
                       image_latency_s=_latency(data, path), valid_for=optional(data, "valid_for", _valid_for, path),
                       arm=optional(data, "arm", _arm, path), fan=fan, stretch=stretch)


REPORTED = ("objective", "objective_choice", "phantom_pose", "fre_mm", "calibration_residual_mm", "pre3d_mm",
            "pre3d_std_mm", "frames_rejected", "frames_rejected_by_fit")
"""The figures a report of a calibration with probecal's figures (``fre_mm``) always shows."""


def _metrics(data: dict, path: Path) -> CalibrationMetrics:
    """A calibration JSON's ``metrics``, each figure of the type :class:`CalibrationMetrics`
    gives it (a file may hold only some), the bound map checked point by point, and every figure
    a report shows present once ``fre_mm`` is: the console and ``calibrate`` show them."""
    written = optional(data, "metrics", expect_object, path) or {}
    optional(written, "bound_map", _bound_map, path, "metrics.")  # the console draws it over its frames
    expect_typed(written, CalibrationMetrics, path, "metrics")
    missing = [key for key in REPORTED if key not in written] if "fre_mm" in written else []
    if missing:
        raise InputError(path, f"metrics.{missing[0]} is missing")
    unknown = sorted(set(written.get("arm_undetermined") or []) - set(DEVIATION_NAMES))
    if unknown:
        raise InputError(path, f"metrics.arm_undetermined: {unknown[0][:20]!r} is no DH deviation (θ1 to α6)")
    return cast(CalibrationMetrics, written)


def _bound_map(value: Any, path: Path, name: str) -> BoundMap:
    """A calibration JSON's ``metrics.bound_map``: rows of points (two numbers each) and the same
    rows of bounds (a number each, or null)."""
    data = expect_object(value, path, name)
    points = required(data, "points_px", expect_list, path, f"{name}.")
    bounds = required(data, "bound_mm", expect_list, path, f"{name}.", length=len(points))
    for k, (row, values) in enumerate(zip(points, bounds)):
        row = expect_list(row, path, f"{name}.points_px[{k}]")
        expect_list(values, path, f"{name}.bound_mm[{k}]", length=len(row))
        for point in row:
            expect_numbers(point, path, f"{name}.points_px[{k}]", count=2)
        for v in values:
            if v is not None:
                expect_number(v, path, f"{name}.bound_mm[{k}]")
    return cast(BoundMap, data)


def _arm(value: Any, path: Path, name: str) -> ArmDeviationJSON:
    """A calibration JSON's ``arm``: a known model and four lists of 6 deviations, each within
    what an arm that matches its table can be off by."""
    data = expect_object(value, path, name)
    model = required(data, "model", expect_string, path, f"{name}.")
    if model not in ARMS:
        raise InputError(path, f"{name}.model: {model!r} is not an arm probecal knows ({', '.join(ARMS)})")
    out: dict[str, Any] = {"model": model}
    for key, limit in (("theta_deg", MAX_ANGLE_DEG), ("d_mm", MAX_LENGTH_MM), ("a_mm", MAX_LENGTH_MM),
                       ("alpha_deg", MAX_ANGLE_DEG)):
        values = required(data, key, expect_numbers, path, f"{name}.", count=6)
        if np.abs(values).max() > limit:
            raise InputError(path, f"{name}.{key}: a deviation beyond {limit:g} is not an arm that matches its table")
        out[key] = [float(v) for v in values]
    return cast(ArmDeviationJSON, out)


def _valid_for(value: Any, path: Path, name: str) -> ValidFor:
    """A calibration JSON's ``valid_for``, checked field by field."""
    data = expect_object(value, path, name)
    size = required(data, "image_size", expect_list, path, f"{name}.", length=2)
    width, height = (expect_integer(v, path, f"{name}.image_size", minimum=1) for v in size)
    spacing = optional(data, "nominal_spacing_mm", expect_spacing, path, f"{name}.")
    return ValidFor(image_size=[width, height], nominal_spacing_mm=None if spacing is None else spacing.tolist(),
                    depth_mm=optional(data, "depth_mm", expect_number, path, f"{name}.", positive=True),
                    source=optional(data, "source", expect_string, path, f"{name}."),
                    start_depth_mm=optional(data, "start_depth_mm", expect_number, path, f"{name}."))


def _latency(data: dict, path: Path) -> float | None:
    """``image_latency_s`` of a JSON file's object, or its ``setup``'s (truth.json: the twin's)."""
    latency = optional(data, "image_latency_s", expect_number, path)
    setup = optional(data, "setup", expect_object, path)
    if latency is None and setup is not None:
        latency = optional(setup, "image_latency_s", expect_number, path, "setup.")
    return latency


def load_calibration(path: str | Path) -> Calibration:
    """Our calibration JSON, a simulated session's truth.json, or a PLUS device-set XML (or a
    bare ``<Transform From="Image" To="Probe">`` element) holding an Image->Probe matrix.
    InputError naming the file and the field for anything malformed."""
    path = existing_file(path)
    return _calibration_from_xml(path) if path.suffix.lower() == ".xml" else _calibration_from_json(path)


def read_valid_for(path: str | Path) -> ValidFor | None:
    """What the calibration in a JSON file says it was made for (None: it does not say)."""
    path = existing_file(path)
    return optional(expect_object(read_json(path), path, "the file"), "valid_for", _valid_for, path)


def read_image_latency(path: str | Path) -> float:
    """The image latency (s) a file records: ``image_latency_s`` of a calibration JSON (``probecal
    calibrate``) or of ``probecal temporal-calibrate``'s JSON, or the twin's in a truth.json.
    InputError naming the file when it records none."""
    path = existing_file(path)
    latency = _latency(expect_object(read_json(path), path, "the file"), path)
    if latency is None:
        raise InputError(path, "records no image_latency_s: calibrate a continuous sweep, or run probecal "
                               "temporal-calibrate")
    return latency
