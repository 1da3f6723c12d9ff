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

from probecal.core.errors import InputError
from probecal.core.geometry.transforms import check_transform, invert_transform
from probecal.core.io.deviceset import matrix_attribute, number_attribute, numbers_from_text, parse_xml


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


def _points(frame: ET.Element, path: Path, what: str) -> np.ndarray:
    """(n, 2) pixels of a frame's ``<SegmentedPoints>``: each ``Position`` is "u v" or "u v 0"."""
    points = []
    for k, point in enumerate(frame.findall("./SegmentedPoints/Point")):
        values = numbers_from_text(point.get("Position"), path, f"{what} point {k + 1} Position")
        if values.size not in (2, 3):
            raise InputError(path, f"{what} point {k + 1} Position needs 2 or 3 numbers, got {values.size}")
        points.append(values[:2])
    return np.array(points, dtype=float).reshape(-1, 2)


def _pose(fields: dict[str | None, str | None], path: Path, what: str) -> np.ndarray | None:
    """ProbeToReference from a frame's tracker fields, when it has both of them (rigid, mm)."""
    matrices = []
    for name in ("ProbeToTrackerTransform", "ReferenceToTrackerTransform"):
        if name not in fields:
            return None
        matrix = numbers_from_text(fields[name], path, f"{what} {name}", 16).reshape(4, 4)
        matrices.append(check_transform(matrix, f"{what} {name}", path, rigid=True))
    probe_to_tracker, reference_to_tracker = matrices
    return invert_transform(reference_to_tracker) @ probe_to_tracker


def _frames(section: ET.Element | None, path: Path) -> list[BaselineFrame]:
    if section is None:
        return []
    out = []
    for i, frame in enumerate(section.findall("Frame")):
        what = f"{section.tag} frame {i + 1}"
        found = frame.get("SegmentationStatus") == "OK"
        fields = {f.get("Name"): f.get("Value") for f in frame.iter("CustomFrameField")}
        points = _points(frame, path, what)
        out.append(BaselineFrame(found, points if found else None, _pose(fields, path, what)))
    return out


def read_calibration_results(path: str | Path) -> CalibrationResults:
    """Parse fCal's ``ProbeCalibrationResult`` XML; InputError naming the file for anything
    missing or malformed."""
    path = Path(path)
    root = parse_xml(path)
    transform = root.find("./CalibrationResults/Transform")
    stats = root.find(".//ReprojectionError3DStatistics")
    if transform is None or stats is None:
        raise InputError(path, "not a PLUS probe calibration result (no Transform or error statistics)")

    def statistic(name: str) -> float:
        return number_attribute(stats, name, path, "ReprojectionError3DStatistics")

    return CalibrationResults(
        image_to_probe=matrix_attribute(transform, path, "CalibrationResults Transform"),
        pre3d_validation_mm=(statistic("ValidationMeanMm"), statistic("ValidationStdDevMm")),
        pre3d_calibration_mm=(statistic("CalibrationMeanMm"), statistic("CalibrationStdDevMm")),
        validation=_frames(root.find(".//ValidationData"), path),
        calibration=_frames(root.find(".//CalibrationData"), path),
    )


def read_segmentation_baseline(path: str | Path) -> list[BaselineFrame]:
    """Parse a PLUS segmentation test baseline: one entry per test case (frame)."""
    path = Path(path)
    out = []
    for i, case in enumerate(parse_xml(path).findall("TestCase")):
        output = case.find("Output")
        found = output is not None and output.get("SegmentationSuccess") == "1"
        points = None
        if found:
            assert output is not None  # found only with an Output element
            what = f"test case {i + 1} SegmentationPoints"
            values = numbers_from_text(output.get("SegmentationPoints", ""), path, what)
            if values.size % 2:
                raise InputError(path, f"{what} has an odd count ({values.size})")
            points = values.reshape(-1, 2)
        out.append(BaselineFrame(found, points))
    return out


def confirmed_by_neighbours(markers: np.ndarray, index: int, baseline: list[np.ndarray | None]) -> bool:
    """Whether a pattern ``markers`` (W, 2) px found in frame ``index``, where the PLUS baseline
    (points per frame, None where PLUS found no pattern) has none, is confirmed by PLUS's points
    on both neighbouring frames: every dot within 1 px, plus half the distance its wire moves
    between the neighbours, of their mean (a frame PLUS missed in a smooth motion)."""
    if index == 0 or index + 1 >= len(baseline):
        return False
    before, after = baseline[index - 1], baseline[index + 1]
    if before is None or after is None:
        return False
    allowed = 1.0 + np.linalg.norm(after - before, axis=1) / 2
    return bool((np.linalg.norm(markers - (before + after) / 2, axis=1) <= allowed).all())
