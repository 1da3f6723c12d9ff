"""Read a PLUS device-set XML: phantom, coordinate definitions, segmentation and volume settings.

Only what probecal uses is read. Matrices are 4x4 row-major, mm; ``transforms[("Phantom",
"Reference")]`` is PhantomToReference in PLUS's From->To naming, i.e. ``phantom_to_reference``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from probecal.core.errors import QUOTED_CHARS, InputError, quoted
from probecal.core.geometry.fan import FAN_RADIUS_STOP_PX, Fan
from probecal.core.geometry.phantom import (
    REACH_MM,
    NLayer,
    Phantom,
    Wire,
    check_layer_count,
    check_name,
    check_point,
    validate_layers,
)
from probecal.core.geometry.transforms import MAX_CONDITION, check_transform
from probecal.core.io.files import read_bytes
from probecal.core.io.jsonio import describe
from probecal.core.io.limits import PARSED_EXPANSION

BOX_MARGIN_MM = 5.0


@dataclass(frozen=True)
class SegmentationHints:
    """PLUS ``<Segmentation>`` hints (pixels and mm as PLUS gives them)."""

    approximate_spacing_mm: float | None = None
    clip_origin_px: tuple[int, int] | None = None
    clip_size_px: tuple[int, int] | None = None
    attributes: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class DeviceSet:
    """The parts of a PLUS device-set configuration that probecal reads."""

    path: Path
    name: str
    phantom: Phantom | None
    transforms: dict[tuple[str, str], np.ndarray]
    segmentation: SegmentationHints | None
    volume_reconstruction: dict[str, str] | None
    hole_filling: dict[str, str] | None = None
    """Attributes of the STICK ``<HoleFillingElement>`` of ``<VolumeReconstruction>``, if any."""

    def transform(self, source: str, target: str) -> np.ndarray | None:
        """``source_to_target`` if the file defines it directly or as its inverse; InputError
        when the inverse is needed and the matrix is singular."""
        if (source, target) in self.transforms:
            return self.transforms[(source, target)]
        if (target, source) in self.transforms:
            matrix = self.transforms[(target, source)]
            if np.linalg.cond(matrix[:3, :3]) > MAX_CONDITION:
                raise InputError(self.path, f"Transform {_name(target)}->{_name(source)} is singular; it cannot give "
                                            f"{_name(source)}->{_name(target)}")
            return np.linalg.inv(matrix)
        return None

    def rigid_transform(self, source: str, target: str) -> np.ndarray | None:
        """``source_to_target`` as :meth:`transform`, refused with InputError unless rigid (a pose
        such as PhantomToReference)."""
        matrix = self.transform(source, target)
        if matrix is None:
            return None
        return check_transform(matrix, f"Transform {_name(source)}->{_name(target)}", self.path, rigid=True)


def _name(text: str) -> str:
    """A name from the file (a frame, a wire) as is, or quoted when it would break the line."""
    return text if text.isprintable() and len(text) <= QUOTED_CHARS else quoted(text)


def numbers_from_text(text: str | None, source: Path, what: str, count: int | None = None) -> np.ndarray:
    """The finite numbers of a whitespace-separated attribute (``count`` of them when given);
    InputError naming ``source`` and ``what`` otherwise."""
    if text is None:
        raise InputError(source, f"{what} is missing")
    try:
        values = np.array([float(v) for v in text.split()], dtype=float)
    except ValueError:
        raise InputError(source, f"{what} is not a list of numbers: {quoted(text)}")
    if not np.all(np.isfinite(values)):
        raise InputError(source, f"{what} holds a number that is not finite: {quoted(text)}")
    if count is not None and values.size != count:
        raise InputError(source, f"{what} needs {count} numbers, got {values.size}")
    return values


def matrix_attribute(element: ET.Element, source: Path, what: str, attribute: str = "Matrix") -> np.ndarray:
    """The 4x4 of an element's ``attribute``: 16 finite numbers, row-major, the last row
    0 0 0 1 (PLUS style)."""
    matrix = numbers_from_text(element.get(attribute), source, f"{what} {attribute}", 16).reshape(4, 4)
    return check_transform(matrix, f"{what} {attribute}", source)


def number_attribute(element: ET.Element, name: str, source: Path, what: str) -> float:
    """One finite number from an element's attribute ``name``."""
    return float(numbers_from_text(element.get(name), source, f"{what} {name}", 1)[0])


def parse_xml(path: str | Path) -> ET.Element:
    """The root element of an XML file; InputError naming the file when it is missing, larger
    than the memory limit or not well-formed (expat refuses entity bombs)."""
    path = Path(path)
    try:
        return ET.fromstring(read_bytes(path, PARSED_EXPANSION))
    except ET.ParseError as exc:
        raise InputError(path, f"not valid XML ({exc})")


@dataclass(frozen=True)
class HintRange:
    """What a ``<Segmentation>`` attribute read as numbers must hold: ``count`` numbers in
    [low, high], whole ones when ``whole``."""

    count: int = 1
    low: float = -np.inf
    high: float = np.inf
    whole: bool = False


# The attributes probecal reads as numbers. Sizes are bounded to what a wire dot can be, so that
# no hint makes the segmenter build a structuring element of gigabytes.
NUMERIC_HINTS = {
    "ApproximateSpacingMmPerPixel": HintRange(low=0.01, high=5.0),
    "ClipRectangleOrigin": HintRange(2, 0, 1e6, whole=True),
    "ClipRectangleSize": HintRange(2, 1, 1e6, whole=True),
    "MorphologicalOpeningBarSizeMm": HintRange(low=0.01, high=50.0),
    "MorphologicalOpeningCircleRadiusMm": HintRange(low=0.01, high=5.0),
    "NumberOfMaximumFiducialPointCandidates": HintRange(low=1, high=1e4),
    "ThresholdImagePercent": HintRange(low=0, high=100),
    "MaxLinePairDistanceErrorPercent": HintRange(),
    "CollinearPointsMaxDistanceFromLineMm": HintRange(),
    "MaxAngleDifferenceDegrees": HintRange(),
    "AngleToleranceDegrees": HintRange(),
    "MaxLineShiftMm": HintRange(),
    "MinThetaDegrees": HintRange(),
    "MaxThetaDegrees": HintRange(),
}


def plus_numbers(attributes: Mapping[str, str], name: str, count: int, kind: type = float) -> tuple | None:
    """The ``count`` numbers (as ``kind``) of a PLUS attribute given as text; None when it is not
    given. ValueError for text that is not ``count`` finite numbers."""
    text = attributes.get(name)
    if text is None:
        return None
    try:
        floats = [float(v) for v in text.split()]
    except ValueError:
        raise ValueError(f"{name} is not a list of numbers: {text!r}") from None
    if not all(math.isfinite(v) for v in floats):
        raise ValueError(f"{name} has a number that is not finite: {text!r}")
    if len(floats) != count:
        raise ValueError(f"{name} needs {count} numbers, got {text!r}")
    return tuple(kind(v) for v in floats)


def plus_fan(attributes: Mapping[str, str]) -> Fan | None:
    """The clipping fan a ``<VolumeReconstruction>``'s attributes set (``FanAnglesDeg``,
    ``FanOriginPixel``, ``FanRadiusStartPixel``, ``FanRadiusStopPixel``, or the deprecated
    ``FanAngles``, ``FanOrigin``, ``FanDepth``, which PLUS still reads), with PLUS's defaults;
    None when they set none (no angles, or both 0, which PLUS takes as no fan). ValueError for a
    malformed value."""

    def setting(names: tuple[str, ...], count: int) -> tuple[float, ...] | None:
        """A setting by the first of its names given."""
        name = next((k for k in names if k in attributes), None)
        return None if name is None else plus_numbers(attributes, name, count)

    angles = setting(("FanAnglesDeg", "FanAngles"), 2)
    if angles is None or all(math.tan(math.radians(a)) == 0.0 for a in angles):
        return None
    origin = setting(("FanOriginPixel", "FanOrigin"), 2) or (0.0, 0.0)
    start = setting(("FanRadiusStartPixel",), 1) or (0.0,)
    stop = setting(("FanRadiusStopPixel", "FanDepth"), 1) or (FAN_RADIUS_STOP_PX,)
    return Fan((angles[0], angles[1]), (origin[0], origin[1]), start[0], stop[0])


def check_segmentation_hints(attributes: dict, source: Path, what: str = "Segmentation") -> dict[str, str]:
    """PLUS ``<Segmentation>`` attributes (text), each that probecal reads as numbers checked
    against :data:`NUMERIC_HINTS`; InputError naming ``source`` and the attribute."""
    for key, value in attributes.items():
        if not isinstance(value, str):
            raise InputError(source, f"{what}.{key} must be text, got {describe(value)}")
        if key not in NUMERIC_HINTS or not value.strip():
            continue
        hint = NUMERIC_HINTS[key]
        numbers = numbers_from_text(value, source, f"{what}.{key}", hint.count)
        if hint.whole and not all(v.isdigit() for v in value.split()):
            raise InputError(source, f"{what}.{key} must be whole non-negative pixels, got {quoted(value)}")
        if np.any(numbers < hint.low) or np.any(numbers > hint.high):
            raise InputError(source, f"{what}.{key} must lie in [{hint.low:g}, {hint.high:g}], got {quoted(value)}")
    return attributes


def _wire(element: ET.Element, default_name: str, path: Path) -> Wire:
    """A ``<Wire>`` of an NWire pattern: its name and end points (mm, phantom frame, within
    :data:`~probecal.core.geometry.phantom.REACH_MM`)."""
    name = element.get("Name", default_name)
    front, back = (check_point(numbers_from_text(element.get(end), path, f"wire {_name(name)} {end}", 3),
                               f"wire {_name(name)} {end}", path)
                   for end in ("EndPointFront", "EndPointBack"))
    return Wire(name, front, back)


def _phantom(root: ET.Element, path: Path) -> Phantom | None:
    definition = root.find(".//PhantomDefinition")
    if definition is None:
        return None
    # PLUS 2 writes <Pattern Type="NWire">; PLUS 1 (e.g. NwirePhantomFreehand) wrote <NWire>
    patterns = [p for p in definition.findall("./Geometry/*") if p.tag in ("Pattern", "NWire")]
    check_layer_count(len(patterns), path)
    layers = []
    for i, pattern in enumerate(patterns):
        if pattern.get("Type", "NWire") != "NWire":
            raise InputError(path, f"phantom pattern {i + 1} has unsupported type {quoted(pattern.get('Type', ''))}")
        elements = pattern.findall("Wire")
        if len(elements) != 3:
            raise InputError(path, f"NWire pattern {i + 1} has {len(elements)} wires, an N needs 3")
        first, diagonal, last = (_wire(w, f"{i + 1}.{j + 1}", path) for j, w in enumerate(elements))
        layers.append(NLayer(f"N{i + 1}", (first, diagonal, last)))
    if not layers:
        return None
    validate_layers(layers, path)
    points = [w.front for layer in layers for w in layer.wires]
    points += [w.back for layer in layers for w in layer.wires]
    points += [
        check_point(numbers_from_text(lm.get("Position"), path, "landmark Position", 3), "landmark Position", path)
        for lm in definition.findall("./Geometry/Landmarks/Landmark")
    ]
    extent = np.array(points)
    description = definition.find("Description")
    name = "PLUS phantom"
    if description is not None:
        name = " ".join(filter(None, [description.get("Name"), description.get("Version")])) or name
    box_min, box_max = (np.clip(corner, -REACH_MM, REACH_MM)  # the margin stays within reach, as the points do
                        for corner in (extent.min(axis=0) - BOX_MARGIN_MM, extent.max(axis=0) + BOX_MARGIN_MM))
    return Phantom(check_name(name, "phantom Description", path), tuple(layers), box_min, box_max)


def _legacy_registration(root: ET.Element, path: Path) -> np.ndarray | None:
    """PLUS 1's phantom registration, ``<Registration MatrixName="PhantomToPhantomReference">`` in
    the phantom's ``<Geometry>`` (phantom_to_reference, mm). PLUS 2 keeps it as the Phantom->Reference
    coordinate definition, where an identity is the placeholder written before any registration,
    so this one stands in for a missing or identity definition."""
    element = root.find(".//PhantomDefinition/Geometry/Registration[@MatrixName='PhantomToPhantomReference']")
    if element is None:
        return None
    return matrix_attribute(element, path, "Registration PhantomToPhantomReference", "MatrixValue")


def _segmentation(root: ET.Element, path: Path) -> SegmentationHints | None:
    element = root.find(".//Segmentation")
    if element is None:
        return None
    attrs = check_segmentation_hints(dict(element.attrib), path)

    def numbers(key: str) -> np.ndarray | None:
        text = attrs.get(key, "")
        return numbers_from_text(text, path, key) if text.strip() else None

    spacing, origin, size = (numbers(key) for key in ("ApproximateSpacingMmPerPixel", "ClipRectangleOrigin",
                                                      "ClipRectangleSize"))
    return SegmentationHints(
        approximate_spacing_mm=float(spacing[0]) if spacing is not None else None,
        clip_origin_px=(int(origin[0]), int(origin[1])) if origin is not None else None,  # 2 numbers, checked
        clip_size_px=(int(size[0]), int(size[1])) if size is not None else None,
        attributes=attrs,
    )


def read_device_set(path: str | Path) -> DeviceSet:
    """Parse a PLUS device-set XML. Raises InputError for a missing or malformed file: a
    transform that is not 16 finite numbers with the last row 0 0 0 1, a phantom or segmentation
    attribute that is not the numbers it must be."""
    path = Path(path)
    root = parse_xml(path)
    if root.tag != "PlusConfiguration":
        raise InputError(path, f"not a PLUS device-set file (root element <{quoted(root.tag)}>)")
    transforms = {}
    for t in root.findall("./CoordinateDefinitions/Transform"):
        source, target = t.get("From"), t.get("To")
        if not source or not target:
            raise InputError(path, "a <Transform> lacks From or To")
        transforms[(source, target)] = matrix_attribute(t, path, f"Transform {_name(source)}->{_name(target)}")
    legacy = _legacy_registration(root, path)
    if legacy is not None and np.array_equal(transforms.get(("Phantom", "Reference"), np.eye(4)), np.eye(4)):
        transforms[("Phantom", "Reference")] = legacy
    device_set = root.find(".//DeviceSet")
    volume = root.find(".//VolumeReconstruction")
    return DeviceSet(
        path=path,
        name=device_set.get("Name", path.stem) if device_set is not None else path.stem,
        phantom=_phantom(root, path),
        transforms=transforms,
        segmentation=_segmentation(root, path),
        volume_reconstruction=dict(volume.attrib) if volume is not None else None,
        hole_filling=_stick_element(volume),
    )


def _stick_element(volume: ET.Element | None) -> dict[str, str] | None:
    """Attributes of the STICK ``<HoleFillingElement>`` (PLUS's other kernels are not
    implemented; a volume that asks for them is filled with sticks of the default length)."""
    if volume is None:
        return None
    for element in volume.iterfind("./HoleFilling/HoleFillingElement"):
        if element.get("Type", "").upper() == "STICK":
            return dict(element.attrib)
    return None


def _number(value: float) -> str:
    """A coordinate written so that it reads back to the same float."""
    return np.format_float_positional(float(value), trim="-")


def _point(values: Iterable[float]) -> str:
    return " ".join(_number(v) for v in values)


def phantom_device_set(phantom: Phantom, landmarks: list[tuple[str, np.ndarray]] | None = None,
                       model_file: str | None = None) -> str:
    """A PLUS device-set XML holding ``phantom`` as a ``<PhantomDefinition>``: one NWire pattern
    per N layer with the wires' end points (mm, phantom frame) written to read back exactly, the
    ``landmarks`` (name, position mm) a stylus registers it by, and ``model_file`` (a mesh in the
    phantom frame) as the phantom's model for fCal's display."""
    root = ET.Element("PlusConfiguration", version="2.1")
    if model_file is not None:
        rendering = ET.SubElement(root, "Rendering", WorldCoordinateFrame="Reference")
        ET.SubElement(rendering, "DisplayableObject", Id="PhantomModel", Type="Model", ObjectCoordinateFrame="Phantom",
                      Opacity="0.6", File=model_file, ModelToObjectTransform=" ".join(_point(r) for r in np.eye(4)))
    definition = ET.SubElement(root, "PhantomDefinition")
    ET.SubElement(definition, "Description", Name=phantom.name, Type="Multi-N", Institution="probecal")
    geometry = ET.SubElement(definition, "Geometry")
    for layer in phantom.layers:
        pattern = ET.SubElement(geometry, "Pattern", Type="NWire")
        for wire in layer.wires:
            ET.SubElement(pattern, "Wire", Name=wire.name, EndPointFront=_point(wire.front),
                          EndPointBack=_point(wire.back))
    if landmarks:
        marks = ET.SubElement(geometry, "Landmarks")
        for name, position in landmarks:
            ET.SubElement(marks, "Landmark", Name=name, Position=_point(position))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def fan_attributes(fan: Fan, image_size: tuple[int, int]) -> dict[str, str]:
    """``<VolumeReconstruction>`` attributes that clip a (width, height) px image to ``fan`` as
    PLUS does: the fan (``FanAnglesDeg``, ``FanOriginPixel``, ``FanRadiusStartPixel``,
    ``FanRadiusStopPixel``) and the clip rectangle around it on the image; read back by
    :func:`plus_fan`."""
    width, height = image_size
    inside = np.argwhere(fan.mask(width, height))  # (row, column)
    (top, left), (bottom, right) = inside.min(axis=0), inside.max(axis=0)
    return {"FanAnglesDeg": _point(fan.angles_deg), "FanOriginPixel": _point(fan.origin_px),
            "FanRadiusStartPixel": _number(fan.radius_start_px), "FanRadiusStopPixel": _number(fan.radius_stop_px),
            "ClipRectangleOrigin": f"{left} {top}", "ClipRectangleSize": f"{right - left + 1} {bottom - top + 1}"}


def device_set_xml(transforms: dict[tuple[str, str], tuple[np.ndarray, str | None]],
                   segmentation: dict[str, str] | None = None,
                   volume_reconstruction: dict[str, str] | None = None) -> str:
    """A PLUS device-set XML: ``transforms`` (From, To) -> (4x4 matrix, Error or None) under
    ``<CoordinateDefinitions>``, then a ``<Segmentation>`` and a ``<VolumeReconstruction>`` with
    the given attributes."""
    root = ET.Element("PlusConfiguration", version="2.1")
    definitions = ET.SubElement(root, "CoordinateDefinitions")
    for (source, target), (matrix, error) in transforms.items():
        element = ET.SubElement(definitions, "Transform", From=source, To=target,
                                Matrix="  ".join(" ".join(f"{v:.9g}" for v in row) for row in matrix))
        if error is not None:
            element.set("Error", error)
    if segmentation:
        ET.SubElement(root, "Segmentation", segmentation)
    if volume_reconstruction:
        ET.SubElement(root, "VolumeReconstruction", volume_reconstruction)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"

