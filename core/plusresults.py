"""Read PLUS's own answers, to compare probecal against them.

- ``*.results.xml`` of fCal's probe calibration: the Image->Probe matrix (spacing included), the
  PRE3D statistics, and per frame the segmentation status, the segmented points (pixels, in wire
  order) and the tracked ProbeToReference pose.
- PLUS's segmentation test baselines (``*_Segmentation_baseline.xml``): per frame a success flag
  and the points.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.transforms import invert_transform, matrix_from_text


@dataclass(frozen=True)
class BaselineFrame:
    """One frame of a PLUS baseline: ``points`` (n, 2) pixels, None where PLUS failed."""

    found: bool
    points: np.ndarray | None
    probe_to_reference: np.ndarray | None = None


@dataclass(frozen=True)
class CalibrationResults:
    image_to_probe: np.ndarray
    pre3d_validation_mm: tuple[float, float]  # mean, std over the lowest 95 %
    pre3d_calibration_mm: tuple[float, float]
    validation: list[BaselineFrame]
    calibration: list[BaselineFrame]


def _parse(path: Path) -> ET.Element:
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(path, f"not valid XML ({exc})")


def _points(text_values: list[str]) -> np.ndarray:
    return np.array([[float(v) for v in text.split()[:2]] for text in text_values]).reshape(-1, 2)


def _frames(section: ET.Element) -> list[BaselineFrame]:
    out = []
    for frame in section.findall("Frame"):
        found = frame.get("SegmentationStatus") == "OK"
        points = _points([p.get("Position") for p in frame.findall("./SegmentedPoints/Point")])
        fields = {f.get("Name"): f.get("Value") for f in frame.iter("CustomFrameField")}
        pose = None
        if "ProbeToTrackerTransform" in fields and "ReferenceToTrackerTransform" in fields:
            pose = invert_transform(matrix_from_text(fields["ReferenceToTrackerTransform"])) @ matrix_from_text(
                fields["ProbeToTrackerTransform"]
            )
        out.append(BaselineFrame(found, points if found else None, pose))
    return out


def read_calibration_results(path: str | Path) -> CalibrationResults:
    """Parse fCal's ``ProbeCalibrationResult`` XML."""
    path = Path(path)
    root = _parse(path)
    transform = root.find("./CalibrationResults/Transform")
    stats = root.find(".//ReprojectionError3DStatistics")
    if transform is None or stats is None:
        raise InputError(path, "not a PLUS probe calibration result (no Transform or error statistics)")
    return CalibrationResults(
        image_to_probe=matrix_from_text(transform.get("Matrix")),
        pre3d_validation_mm=(float(stats.get("ValidationMeanMm")), float(stats.get("ValidationStdDevMm"))),
        pre3d_calibration_mm=(float(stats.get("CalibrationMeanMm")), float(stats.get("CalibrationStdDevMm"))),
        validation=_frames(root.find(".//ValidationData")),
        calibration=_frames(root.find(".//CalibrationData")),
    )


def read_segmentation_baseline(path: str | Path) -> list[BaselineFrame]:
    """Parse a PLUS segmentation test baseline: one entry per test case (frame)."""
    path = Path(path)
    out = []
    for case in _parse(path).findall("TestCase"):
        output = case.find("Output")
        found = output is not None and output.get("SegmentationSuccess") == "1"
        points = _points_flat(output.get("SegmentationPoints", "")) if found else None
        out.append(BaselineFrame(found, points))
    return out


def _points_flat(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()]).reshape(-1, 2)
