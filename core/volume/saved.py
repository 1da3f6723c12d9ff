"""A reconstruction read back from the folder :func:`core.volume.reconstruct.reconstruct_session`
wrote into a volume session: what a loaded session shows of its last reconstruction."""

from __future__ import annotations

from pathlib import Path
from typing import cast

from probecal.core.errors import InputError
from probecal.core.io.jsonio import expect_integer, expect_number, expect_object, optional, read_json, required
from probecal.core.volume.pointcloud import read_ply
from probecal.core.volume.reconstruct import REPORT, Reconstruction, ReconstructionReport, height_colors
from probecal.core.volume.volumefile import read_volume

FIGURES = ("surface_mean_mm", "surface_p95_mm", "cad_to_points_mean_mm", "cad_to_points_p95_mm")
"""The surface errors (mm) a report with a CAD comparison holds."""


def saved_reconstruction(session_path: Path) -> Path | None:
    """The newest reconstruction folder (``reconstruction``, ``reconstruction-2``, ...) in a
    session folder that holds a report; None when there is none."""
    folders = [p for p in Path(session_path).glob("reconstruction*") if p.is_dir() and (p / REPORT).is_file()]
    return max(folders, key=lambda p: (p / REPORT).stat().st_mtime, default=None)


def _checked_report(path: Path) -> ReconstructionReport:
    """``report.json``, with every figure a console shows checked (InputError naming the field)."""
    data = read_json(path)
    for key in ("frames", "surface_points"):
        required(data, key, expect_integer, path, minimum=0)
    for key in FIGURES:
        optional(data, key, expect_number, path)
    coverage = optional(data, "coverage", expect_object, path)
    if coverage is not None:
        planned = required(coverage, "planned", expect_integer, path, "coverage.", minimum=1)
        recorded = required(coverage, "recorded", expect_integer, path, "coverage.", minimum=0)
        if recorded > planned or coverage.get("unit") not in ("poses", "passes"):
            raise InputError(path, "coverage: recorded beyond planned, or a unit other than poses or passes")
    return cast(ReconstructionReport, data)


def load_reconstruction(folder: Path) -> Reconstruction:
    """The points, colours, volume and report in ``folder``; InputError naming the file at fault."""
    report = _checked_report(folder / REPORT)
    points, heights = read_ply(folder / "surface.ply")
    errors = read_ply(folder / "surface_error.ply")[1] if (folder / "surface_error.ply").exists() else None
    if errors is not None and len(errors) != len(points):
        raise InputError(folder / "surface_error.ply", f"holds {len(errors)} points, surface.ply {len(points)}")
    volume = read_volume(folder / "volume.nrrd")
    return Reconstruction(points, heights if heights is not None else height_colors(points), errors, report, volume)
