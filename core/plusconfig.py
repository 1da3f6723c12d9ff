"""Read a PLUS device-set XML: phantom, coordinate definitions, segmentation and volume settings.

Only what probecal uses is read. Matrices are 4x4 row-major, mm; ``transforms[("Phantom",
"Reference")]`` is PhantomToReference in PLUS's From->To naming, i.e. ``phantom_to_reference``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.phantom import NLayer, Phantom, Wire, validate_layers
from core.transforms import matrix_from_text

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
        """``source_to_target`` if the file defines it directly or as its inverse."""
        if (source, target) in self.transforms:
            return self.transforms[(source, target)]
        if (target, source) in self.transforms:
            return np.linalg.inv(self.transforms[(target, source)])
        return None


def _floats(text: str | None, n: int, source: Path, what: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in (text or "").split()], dtype=float)
    except ValueError:
        raise InputError(source, f"{what} is not a list of numbers: {text!r}")
    if values.size != n or not np.all(np.isfinite(values)):
        raise InputError(source, f"{what} needs {n} finite numbers, got {text!r}")
    return values


def _phantom(root: ET.Element, path: Path) -> Phantom | None:
    definition = root.find(".//PhantomDefinition")
    if definition is None:
        return None
    patterns = definition.findall("./Geometry/Pattern")
    layers = []
    for i, pattern in enumerate(patterns):
        if pattern.get("Type") != "NWire":
            raise InputError(path, f"phantom pattern {i + 1} has unsupported type {pattern.get('Type')!r}")
        wires = [
            Wire(
                w.get("Name", f"{i + 1}.{j + 1}"),
                _floats(w.get("EndPointFront"), 3, path, f"wire {w.get('Name')} EndPointFront"),
                _floats(w.get("EndPointBack"), 3, path, f"wire {w.get('Name')} EndPointBack"),
            )
            for j, w in enumerate(pattern.findall("Wire"))
        ]
        if len(wires) != 3:
            raise InputError(path, f"NWire pattern {i + 1} has {len(wires)} wires, an N needs 3")
        layers.append(NLayer(f"N{i + 1}", tuple(wires)))
    if not layers:
        return None
    validate_layers(layers, path)
    points = [w.front for layer in layers for w in layer.wires]
    points += [w.back for layer in layers for w in layer.wires]
    points += [
        _floats(lm.get("Position"), 3, path, "landmark Position")
        for lm in definition.findall("./Geometry/Landmarks/Landmark")
    ]
    points = np.array(points)
    description = definition.find("Description")
    name = "PLUS phantom"
    if description is not None:
        name = " ".join(filter(None, [description.get("Name"), description.get("Version")])) or name
    return Phantom(name, tuple(layers), points.min(axis=0) - BOX_MARGIN_MM, points.max(axis=0) + BOX_MARGIN_MM)


def _segmentation(root: ET.Element, path: Path) -> SegmentationHints | None:
    element = root.find(".//Segmentation")
    if element is None:
        return None
    attrs = dict(element.attrib)
    spacing = attrs.get("ApproximateSpacingMmPerPixel")
    origin = attrs.get("ClipRectangleOrigin")
    size = attrs.get("ClipRectangleSize")
    return SegmentationHints(
        approximate_spacing_mm=float(_floats(spacing, 1, path, "ApproximateSpacingMmPerPixel")[0])
        if spacing
        else None,
        clip_origin_px=tuple(int(v) for v in _floats(origin, 2, path, "ClipRectangleOrigin")) if origin else None,
        clip_size_px=tuple(int(v) for v in _floats(size, 2, path, "ClipRectangleSize")) if size else None,
        attributes=attrs,
    )


def read_device_set(path: str | Path) -> DeviceSet:
    """Parse a PLUS device-set XML. Raises InputError for a missing or malformed file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(path, f"not valid XML ({exc})")
    if root.tag != "PlusConfiguration":
        raise InputError(path, f"not a PLUS device-set file (root element <{root.tag}>)")
    transforms = {}
    for t in root.findall("./CoordinateDefinitions/Transform"):
        source, target = t.get("From"), t.get("To")
        if not source or not target:
            raise InputError(path, "a <Transform> lacks From or To")
        try:
            transforms[(source, target)] = matrix_from_text(t.get("Matrix", ""))
        except ValueError as exc:
            raise InputError(path, f"Transform {source}->{target}: {exc}")
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
