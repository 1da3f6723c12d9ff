"""A session's ``manifest.json`` as a typed, checked value.

:meth:`Manifest.from_json` checks the file field by field (an InputError naming the file and the
field); :meth:`Manifest.to_json` writes the fields back in one order, so that every producer's
manifest is the same file it always was. Keys this version does not know are kept in ``extra``
and written back after the known ones, so a newer manifest survives being rewritten (a sweep
resumed or extended).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.probe import Probe
from probecal.core.io.deviceset import check_segmentation_hints
from probecal.core.io.jsonio import (
    describe,
    expect_integer,
    expect_list,
    expect_matrix,
    expect_name_inside,
    expect_number,
    expect_numbers,
    expect_object,
    expect_spacing,
    expect_string,
    optional,
    required,
)
from probecal.core.io.probefile import check_probe, check_start_depth

FORMAT = "probecal-session/1"
PLUS_IMPORT = "imported"
"""The ``kind`` of a session imported from a PLUS recording."""
CONTINUOUS = "continuous"
"""The ``motion`` of a session recorded while the robot moved without stopping."""

JSONObject = dict[str, Any]
"""Nested JSON the manifest passes through as it was written (its own readers check its keys)."""
Matrix = tuple[tuple[float, ...], ...]
"""A 4x4 transform as the manifest holds it: four rows of four numbers (mm)."""


def matrix_of(transform: np.ndarray) -> Matrix:
    """A 4x4 array as the manifest holds it."""
    return tuple(tuple(row) for row in np.asarray(transform, dtype=float).tolist())


def _matrix(value: Any, source: Path, name: str) -> Matrix:
    """A rigid 4x4 (see :func:`expect_matrix`), its numbers kept as the file wrote them."""
    expect_matrix(value, source, name, rigid=True)
    return tuple(tuple(row) for row in value)


def _spacing(value: Any, source: Path, name: str) -> tuple[float, float]:
    """(sx, sy) mm/px (see :func:`expect_spacing`), its numbers kept as the file wrote them."""
    expect_spacing(value, source, name)
    return value[0], value[1]


def fan_from_json(value: Any, source: Path) -> Fan:
    """The manifest's ``fan`` (:class:`core.geometry.fan.Fan` in the frames' pixels, as
    ``Fan.to_json`` writes it); InputError naming ``source`` when it is malformed."""
    data = expect_object(value, source, "fan")
    angles = expect_numbers(data.get("angles_deg"), source, "fan.angles_deg", count=2)
    origin = expect_numbers(data.get("origin_px"), source, "fan.origin_px", count=2)
    start = expect_number(data.get("radius_start_px"), source, "fan.radius_start_px")
    stop = expect_number(data.get("radius_stop_px"), source, "fan.radius_stop_px")
    try:
        return Fan((float(angles[0]), float(angles[1])), (float(origin[0]), float(origin[1])), start, stop)
    except ValueError as exc:
        raise InputError(source, f"fan: {exc}") from None


@dataclass(frozen=True)
class RigSpec:
    """How a sweep was recorded, as the user named it, so that ``--resume`` rebuilds the rig:
    the robot and image specs (``sim``, ``ur:HOST``, ...), the twin's seed, the image latency
    (s), the scanner's nominal pixel spacing (sx, sy) mm/px and its image's start depth below
    the probe's face (mm); None where the user left it to the default. ``extra`` holds the keys
    this version does not know, written back as they were."""

    robot: str | None = None
    image: str | None = None
    seed: int | None = None
    latency_s: float | None = None
    spacing_mm: tuple[float, float] | None = None
    start_depth_mm: float | None = None
    extra: JSONObject = field(default_factory=dict)

    @classmethod
    def from_json(cls, value: Any, source: Path) -> RigSpec:
        """The manifest's ``rig`` checked field by field; InputError naming ``source`` and the field."""
        rig = expect_object(value, source, "rig")
        return cls(
            robot=optional(rig, "robot", expect_string, source, "rig."),
            image=optional(rig, "image", expect_string, source, "rig."),
            seed=optional(rig, "seed", expect_integer, source, "rig.", minimum=0),
            latency_s=optional(rig, "latency_s", expect_number, source, "rig."),
            spacing_mm=optional(rig, "spacing_mm", _spacing, source, "rig."),
            start_depth_mm=check_start_depth(rig, source, "rig."),
            extra={key: value for key, value in rig.items() if key not in _RIG_KEYS},
        )

    def to_json(self) -> JSONObject:
        return {"robot": self.robot, "image": self.image, "seed": self.seed, "latency_s": self.latency_s,
                "spacing_mm": None if self.spacing_mm is None else list(self.spacing_mm),
                "start_depth_mm": self.start_depth_mm, **self.extra}


MAX_DH_LENGTH_MM = 1e9
MAX_DH_ANGLE_DEG = 360.0
"""The largest DH deviations a session may record. A UR's factory calibration places the common
normal of its nearly parallel joint axes (2, 3 and 4) where those axes come closest, which can be
hundreds of metres away, with joint offsets of up to a right angle that cancel it: only absurd
values are refused here; whether the deviations still describe an arm of the named table is
checked where they are used (``core.robot.armkinematics``)."""
DH_KEYS = (("theta_deg", MAX_DH_ANGLE_DEG), ("d_mm", MAX_DH_LENGTH_MM), ("a_mm", MAX_DH_LENGTH_MM),
           ("alpha_deg", MAX_DH_ANGLE_DEG))


@dataclass(frozen=True)
class ControllerKinematics:
    """The kinematics the arm's controller computed the recorded flange poses with (its factory
    calibration): the table ``model`` names (``core.robot.ur3.ARM_TABLES``) and the standard DH
    deviations from it per joint (6 each), joint offsets ``theta_deg`` and twists ``alpha_deg`` in
    degrees, lengths ``d_mm`` and ``a_mm`` in mm; the shape of a calibration's ``arm``."""

    model: str
    theta_deg: tuple[float, ...]
    d_mm: tuple[float, ...]
    a_mm: tuple[float, ...]
    alpha_deg: tuple[float, ...]

    def __post_init__(self) -> None:
        for key, limit in DH_KEYS:
            values = np.asarray(getattr(self, key), dtype=float)
            if values.shape != (6,) or not np.all(np.abs(values) <= limit):
                raise ValueError(f"{key} must be 6 deviations within ±{limit:g}: these describe no arm")

    @classmethod
    def from_json(cls, value: Any, source: Path, name: str = "arm_kinematics") -> ControllerKinematics:
        """``value`` checked: a model name and four lists of 6 finite numbers within
        ``MAX_DH_LENGTH_MM`` and ``MAX_DH_ANGLE_DEG``; InputError naming ``source`` and the field."""
        data = expect_object(value, source, name)
        model = required(data, "model", expect_string, source, f"{name}.")
        lists = {key: tuple(float(v) for v in required(data, key, expect_numbers, source, f"{name}.", count=6))
                 for key, _ in DH_KEYS}
        try:
            return cls(model, **lists)
        except ValueError as exc:
            raise InputError(source, f"{name}.{exc}") from None

    def to_json(self) -> JSONObject:
        return {"model": self.model, "theta_deg": list(self.theta_deg), "d_mm": list(self.d_mm),
                "a_mm": list(self.a_mm), "alpha_deg": list(self.alpha_deg)}


@dataclass(frozen=True)
class Manifest:
    """What a session is: how it was recorded or imported, and what is known of its frames.

    Lengths in mm, times in s, pixel sizes in mm/px; ``phantom_to_base`` and ``object_to_base``
    map the phantom's and the test object's frames to the robot base (or tracker reference) frame.
    None is unknown or not stated. ``phantom`` and ``cad_mesh`` name files inside the session
    folder; ``extra`` holds the keys this version does not know, written back as they were.
    """

    created: str | None = None  # ISO 8601, UTC, seconds: set by the session's writer
    kind: str | None = None  # calibration, volume, temporal, imported, imported-frames, ...
    source: JSONObject | None = None  # where the frames came from, in the producer's words
    arm: str | None = None  # the arm table the poses follow (core.robot.ur3.ARMS); None: unknown
    arm_kinematics: ControllerKinematics | None = None  # what the controller computed them with; None: not stated
    image_size: tuple[int, int] | None = None  # (width, height) px
    image_orientation_in_file: str | None = None  # a PLUS recording's image orientation (MF, MFA, ...)
    pixel_spacing_mm: tuple[float, float] | None = None  # the scanner's nominal (sx, sy)
    start_depth_mm: float | None = None  # the first row's depth below the probe's face
    phantom_to_base: Matrix | None = None  # the known phantom pose
    object_to_base: Matrix | None = None  # the known test-object pose
    segmentation_hints: JSONObject | None = None  # a PLUS device set's <Segmentation> attributes (text)
    plan: JSONObject | None = None  # the sweep's plan (SweepPlan.summary): poses, passes, estimated_robot_time_s
    fan: Fan | None = None  # a scan-converted recording's fan, in the frames' pixels
    scanner_region: JSONObject | None = None  # a DICOM export's region calibration (ScannerRegion.to_json)
    rig: RigSpec | None = None
    workspace: JSONObject | None = None  # the robot's workspace box and speed limits (Workspace.to_dict)
    cad_mesh: str | None = None  # the test object's mesh file
    motion: str | None = None  # "continuous" (CONTINUOUS); None: the robot stopped at every pose
    frame_rate_hz: float | None = None  # the scanner's, in a continuous sweep
    speed_mm_s: float | None = None  # the probe's along a continuous volume sweep's passes
    probe: Probe | None = None
    phantom: str | None = None  # the phantom definition's file
    dropped_frames: int | None = None  # frames the scanner dropped (not recorded)
    robot_time_s: float | None = None  # how long the robot moved
    extra: JSONObject = field(default_factory=dict)

    @property
    def continuous(self) -> bool:
        """Whether the frames were recorded while the robot moved without stopping."""
        return self.motion == CONTINUOUS

    @classmethod
    def from_json(cls, data: Any, root: Path, source: Path) -> Manifest:
        """The manifest ``data`` read from ``source``, checked field by field (InputError naming
        ``source`` and the field); the files it names must lie inside the session folder ``root``."""
        manifest = expect_object(data, source, "the manifest")
        if manifest.get("format") != FORMAT:
            raise InputError(source, f"unknown session format {describe(manifest.get('format'))} "
                                     f"(expected {FORMAT!r})")
        size = None
        if manifest.get("image_size") is not None:
            size = expect_list(manifest["image_size"], source, "image_size", length=2)
            for axis, value in zip(("width", "height"), size):
                expect_integer(value, source, f"image_size ({axis})", minimum=1)
        hints = optional(manifest, "segmentation_hints", expect_object, source)
        if hints is not None:
            check_segmentation_hints(hints, source, "segmentation_hints")
        return cls(
            kind=optional(manifest, "kind", expect_string, source),
            source=optional(manifest, "source", expect_object, source),
            created=optional(manifest, "created", expect_string, source),
            arm=optional(manifest, "arm", expect_string, source),
            arm_kinematics=optional(manifest, "arm_kinematics", ControllerKinematics.from_json, source),
            image_size=None if size is None else (size[0], size[1]),
            image_orientation_in_file=optional(manifest, "image_orientation_in_file", expect_string, source),
            pixel_spacing_mm=optional(manifest, "pixel_spacing_mm", _spacing, source),
            start_depth_mm=check_start_depth(manifest, source),
            phantom_to_base=optional(manifest, "phantom_to_base", _matrix, source),
            object_to_base=optional(manifest, "object_to_base", _matrix, source),
            segmentation_hints=hints,
            plan=optional(manifest, "plan", expect_object, source),
            fan=None if manifest.get("fan") is None else fan_from_json(manifest["fan"], source),
            scanner_region=optional(manifest, "scanner_region", expect_object, source),
            rig=None if manifest.get("rig") is None else RigSpec.from_json(manifest["rig"], source),
            workspace=optional(manifest, "workspace", expect_object, source),
            cad_mesh=optional(manifest, "cad_mesh", expect_name_inside, source, root=root),
            motion=optional(manifest, "motion", expect_string, source),
            frame_rate_hz=optional(manifest, "frame_rate_hz", expect_number, source),
            speed_mm_s=optional(manifest, "speed_mm_s", expect_number, source),
            probe=None if manifest.get("probe") is None else check_probe(manifest["probe"], source),
            phantom=optional(manifest, "phantom", expect_name_inside, source, root=root),
            dropped_frames=optional(manifest, "dropped_frames", expect_integer, source, minimum=0),
            robot_time_s=optional(manifest, "robot_time_s", expect_number, source),
            extra={key: value for key, value in manifest.items() if key not in _KEYS},
        )

    def to_json(self) -> JSONObject:
        """The manifest as ``manifest.json`` holds it. What every producer states is written even
        when unknown (null): the spacing, start depth, phantom pose, probe and phantom; a sweep
        (a session with a plan) states its arm, a PLUS import its segmentation hints. Other
        fields are written when known."""
        stated = {
            "arm": self.plan is not None,
            "pixel_spacing_mm": True,
            "start_depth_mm": True,
            "phantom_to_base": True,
            "segmentation_hints": self.kind == PLUS_IMPORT,
            "probe": True,
            "phantom": True,
        }
        values: JSONObject = {
            "format": FORMAT,
            "created": self.created,
            "kind": self.kind,
            "source": self.source,
            "arm": self.arm,
            "arm_kinematics": None if self.arm_kinematics is None else self.arm_kinematics.to_json(),
            "image_size": None if self.image_size is None else list(self.image_size),
            "image_orientation_in_file": self.image_orientation_in_file,
            "pixel_spacing_mm": None if self.pixel_spacing_mm is None else list(self.pixel_spacing_mm),
            "start_depth_mm": self.start_depth_mm,
            "phantom_to_base": _matrix_json(self.phantom_to_base),
            "object_to_base": _matrix_json(self.object_to_base),
            "segmentation_hints": self.segmentation_hints,
            "plan": self.plan,
            "fan": None if self.fan is None else self.fan.to_json(),
            "scanner_region": self.scanner_region,
            "rig": None if self.rig is None else self.rig.to_json(),
            "workspace": self.workspace,
            "cad_mesh": self.cad_mesh,
            "motion": self.motion,
            "frame_rate_hz": self.frame_rate_hz,
            "speed_mm_s": self.speed_mm_s,
            "probe": None if self.probe is None else self.probe.to_dict(),
            "phantom": self.phantom,
            "dropped_frames": self.dropped_frames,
            "robot_time_s": self.robot_time_s,
        }
        return {**{key: value for key, value in values.items() if value is not None or stated.get(key, False)},
                **self.extra}


def _matrix_json(matrix: Matrix | None) -> list[list[float]] | None:
    return None if matrix is None else [list(row) for row in matrix]


_KEYS = {"format", *(f.name for f in fields(Manifest) if f.name != "extra")}
_RIG_KEYS = {f.name for f in fields(RigSpec) if f.name != "extra"}
"""The keys a manifest's (and its rig's) fields hold; any other is kept in ``extra``."""
