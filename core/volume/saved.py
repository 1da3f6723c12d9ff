"""Results read back from the folders written into a volume session: its last reconstruction
(:func:`core.volume.reconstruct.reconstruct_session`) and its last self-check
(:func:`core.volume.selfcheck.write_self_check`), what a loaded session shows."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from probecal.core.errors import InputError
from probecal.core.io.files import inside
from probecal.core.io.jsonio import (
    expect_bool,
    expect_integer,
    expect_list,
    expect_number,
    expect_object,
    expect_string,
    optional,
    read_json,
    required,
)
from probecal.core.volume.pointcloud import read_ply
from probecal.core.volume.reconstruct import REPORT, Reconstruction, ReconstructionReport, height_colors
from probecal.core.volume.selfcheck import SelfCheckReport, view_file
from probecal.core.volume.volumefile import read_volume

FIGURES = ("surface_mean_mm", "surface_p95_mm", "cad_to_points_mean_mm", "cad_to_points_p95_mm")
"""The surface errors (mm) a report with a CAD comparison holds."""


def _newest(session_path: Path, prefix: str) -> Path | None:
    """The newest folder ``prefix``, ``prefix-2``, ... in a session folder that holds a report;
    None when there is none."""
    folders = [p for p in Path(session_path).glob(f"{prefix}*") if p.is_dir() and (p / REPORT).is_file()]
    newest = max(folders, key=lambda p: (p / REPORT).stat().st_mtime, default=None)
    return None if newest is None else inside(session_path, newest.name, session_path)


def _in(folder: Path, name: str) -> Path:
    """The file ``name`` of a saved result's ``folder``; InputError if a link leads it outside."""
    return inside(folder, name, folder / name)


def saved_reconstruction(session_path: Path) -> Path | None:
    """The newest reconstruction folder (``reconstruction``, ``reconstruction-2``, ...) in a
    session folder; None when there is none."""
    return _newest(session_path, "reconstruction")


def saved_self_check(session_path: Path) -> Path | None:
    """The newest self-check folder (``selfcheck``, ``selfcheck-2``, ...) in a session folder;
    None when there is none."""
    return _newest(session_path, "selfcheck")


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
    report = _checked_report(_in(folder, REPORT))
    points, heights = read_ply(_in(folder, "surface.ply"))
    errors = read_ply(_in(folder, "surface_error.ply"))[1] if (folder / "surface_error.ply").exists() else None
    if errors is not None and len(errors) != len(points):
        raise InputError(folder / "surface_error.ply", f"holds {len(errors)} points, surface.ply {len(points)}")
    volume = read_volume(_in(folder, "volume.nrrd"))
    return Reconstruction(points, heights if heights is not None else height_colors(points), errors, report, volume)


MAX_VIEWS = 36
"""The most views a saved self-check may name: one every 10 deg of wrist angle."""
PASS_INDICES = ("view", "pass_index", "against_view", "against_pass")
PASS_FIGURES = ("offset_norm_mm", "rotation_deg", "median_before_mm")
"""What a console shows of each pass a saved self-check compared: its indices and figures."""


@dataclass(frozen=True)
class SavedSelfCheck:
    """A self-check read back: its report, and each view's surface points (base frame, mm)."""

    report: SelfCheckReport
    views: list[np.ndarray]


def _checked_self_check(path: Path) -> SelfCheckReport:
    """A self-check's ``report.json``, with every field a console shows checked (InputError naming
    the field): the verdict, the cause, the largest offset trusted, every pass's indices and
    figures, and view files named as
    :func:`core.volume.selfcheck.view_file` names them."""
    data = read_json(path)
    required(data, "trusted", expect_bool, path)
    required(data, "cause", expect_string, path)
    required(data, "max_offset_mm", expect_number, path, positive=True)
    passes = required(data, "passes", expect_list, path)
    if not passes:
        raise InputError(path, "passes is empty: a self-check compares at least one pass")
    for k, item in enumerate(passes):
        expect_object(item, path, f"passes[{k}]")
        for key in PASS_INDICES:
            required(item, key, expect_integer, path, f"passes[{k}].", minimum=0)
        for key in PASS_FIGURES:
            required(item, key, expect_number, path, f"passes[{k}].")
    views = required(data, "views", expect_list, path)
    if not 1 <= len(views) <= MAX_VIEWS or views != [view_file(k) for k in range(len(views))]:
        raise InputError(path, f"views must be view_0.ply, view_1.ply, ... (1 to {MAX_VIEWS} of them)")
    return cast(SelfCheckReport, data)


def load_self_check(folder: Path) -> SavedSelfCheck:
    """The report and view surfaces in ``folder``; InputError naming the file at fault."""
    report = _checked_self_check(_in(folder, REPORT))
    views = []
    for name in report["views"]:
        points, _ = read_ply(_in(folder, name))
        if len(points) == 0 or not np.isfinite(points).all():
            raise InputError(folder / name, "holds no points, or points that are not finite numbers")
        views.append(points)
    return SavedSelfCheck(report, views)
