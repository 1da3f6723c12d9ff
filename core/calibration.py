"""Calibration results: the SPEC §2 JSON, the PLUS ``<Transform From="Image" To="Probe">``
element, and reading a calibration back from any of the forms a user may hand us."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.files import write_atomic
from core.jsonio import to_json_text
from core.plusconfig import read_device_set
from core.transforms import is_rigid

KEYS = ("image_to_tool", "image_to_tool_rigid", "pixel_spacing_mm", "phantom_to_base")


@dataclass(frozen=True)
class Calibration:
    """``image_to_tool_rigid`` (mm), pixel spacing (sx, sy) mm/px and, when known,
    ``phantom_to_base``. ``image_to_tool`` includes the spacing (PLUS's ImageToProbe)."""

    image_to_tool_rigid: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    phantom_to_base: np.ndarray | None = None
    metrics: dict = field(default_factory=dict)
    affine: np.ndarray | None = None  # a given ImageToProbe that is not rigid-times-spacing (PLUS's)

    @property
    def image_to_tool(self) -> np.ndarray:
        """Pixels to tool mm. A matrix read from PLUS is used as given: PLUS's least squares
        leaves its image axes a little skewed, and rounding it to rigid-times-spacing would move
        far pixels by a millimetre or more."""
        if self.affine is not None:
            return self.affine
        sx, sy = self.pixel_spacing_mm
        return self.image_to_tool_rigid @ np.diag([sx, sy, 1.0, 1.0])

    def to_dict(self) -> dict:
        return {
            "image_to_tool": self.image_to_tool,
            "image_to_tool_rigid": self.image_to_tool_rigid,
            "pixel_spacing_mm": list(self.pixel_spacing_mm),
            "phantom_to_base": self.phantom_to_base,
            "metrics": self.metrics,
        }

    def plus_element(self) -> str:
        """The PLUS device-set element holding the result (ImageToProbe includes the spacing)."""
        rows = "\n".join("        " + " ".join(f"{v:.9g}" for v in row) for row in self.image_to_tool)
        error = self.metrics.get("pre3d_mm")
        error_attr = f' Error="{error:.4g}"' if isinstance(error, (int, float)) else ""
        return f'<Transform From="Image" To="Probe"\n      Matrix="\n{rows}"{error_attr} />\n'

    def write(self, path: str | Path) -> Path:
        """Write the JSON to ``path`` and the PLUS element beside it (same name, ``.xml``)."""
        path = Path(path)
        write_atomic(path, to_json_text(self.to_dict()))
        xml_path = path.with_suffix(".xml")
        write_atomic(xml_path, self.plus_element())
        return xml_path


def _matrix(data: dict, key: str, source: Path) -> np.ndarray:
    try:
        m = np.array(data[key], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise InputError(source, f"missing or malformed {key!r}")
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(source, f"{key!r} is not a finite 4x4 matrix")
    return m


def calibration_from_matrix(image_to_tool: np.ndarray, source: Path) -> Calibration:
    """Split a PLUS ImageToProbe (rotation times spacing) into rigid part and spacing."""
    sx, sy = np.linalg.norm(image_to_tool[:3, 0]), np.linalg.norm(image_to_tool[:3, 1])
    if sx <= 0 or sy <= 0:
        raise InputError(source, "Image->Probe matrix has a zero axis")
    x_axis, y_axis = image_to_tool[:3, 0] / sx, image_to_tool[:3, 1] / sy
    u, _, vt = np.linalg.svd(np.column_stack([x_axis, y_axis, np.cross(x_axis, y_axis)]))
    rigid = np.eye(4)
    rigid[:3, :3] = u @ vt
    rigid[:3, 3] = image_to_tool[:3, 3]
    return Calibration(rigid, (float(sx), float(sy)), affine=np.array(image_to_tool, dtype=float))


def load_calibration(path: str | Path) -> Calibration:
    """Our calibration JSON, a simulated session's truth.json, or a PLUS device-set XML (or a
    bare ``<Transform From="Image" To="Probe">`` element) holding an Image->Probe matrix."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    if path.suffix.lower() == ".xml":
        try:
            root = ET.parse(path).getroot()
        except ET.ParseError as exc:
            raise InputError(path, f"not valid XML ({exc})")
        if root.tag == "Transform" and root.get("From") == "Image" and root.get("To") == "Probe":
            matrix = np.array([float(v) for v in root.get("Matrix", "").split()]).reshape(4, 4)
            return calibration_from_matrix(matrix, path)
        config = read_device_set(path)
        matrix = config.transform("Image", "Probe")
        if matrix is None:
            raise InputError(path, "no Image->Probe transform in this file")
        calibration = calibration_from_matrix(matrix, path)
        return replace(calibration, phantom_to_base=config.transform("Phantom", "Reference"))
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({exc})")
    if not isinstance(data, dict):
        raise InputError(path, "not a calibration (expected a JSON object)")
    rigid = _matrix(data, "image_to_tool_rigid", path)
    if not is_rigid(rigid, tol=1e-4):
        raise InputError(path, "image_to_tool_rigid is not a rigid transform")
    try:
        spacing = tuple(float(v) for v in data["pixel_spacing_mm"])
    except (KeyError, TypeError, ValueError):
        raise InputError(path, "missing or malformed 'pixel_spacing_mm'")
    if len(spacing) != 2 or not all(np.isfinite(spacing)) or min(spacing) <= 0:
        raise InputError(path, "pixel_spacing_mm must be two positive numbers")
    phantom = _matrix(data, "phantom_to_base", path) if data.get("phantom_to_base") is not None else None
    return Calibration(rigid, spacing, phantom, data.get("metrics", {}))
