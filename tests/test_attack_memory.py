"""What an input does not declare is counted against the memory limit too (issue 35): parsed text at
what parsing may take, JSON lines before they are parsed, a session's frames before they are
exported. Each file here is small, refused at once, and never takes the memory it would."""

from __future__ import annotations

import shutil
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.limits import ENV as MEMORY_ENV
from probecal.core.io.phantomfile import load_phantom
from probecal.core.io.session import POSE_STREAM, RECORDS, load_session, read_pose_stream
from probecal.core.volume.pointcloud import CLOSEST_PAIRS, surface_error
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error, assert_refused


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    return simulate_calibration(tmp_path_factory.mktemp("memory") / "s", n_poses=2, seed=1, noise="none").path


@pytest.fixture
def session(recorded, tmp_path) -> Path:
    return Path(shutil.copytree(recorded, tmp_path / "s"))


def refused_lightly(load: Callable[[], object], file: Path, *fragments: str) -> None:
    """``load()`` refused naming ``file``, having taken under 1 MB beyond the file's own bytes."""
    tracemalloc.start()
    try:
        assert_refused(load, file, *fragments)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < file.stat().st_size + (1 << 20), peak


def test_a_pose_stream_of_newlines_is_refused_before_a_line_is_parsed(session, monkeypatch):
    """150 MB of newlines took 2.4 GB under a 200 MB limit."""
    monkeypatch.setenv(MEMORY_ENV, "100")
    file = session / POSE_STREAM
    file.write_bytes(b"\n" * 20_000_000)
    refused_lightly(lambda: read_pose_stream(session), file, "20000000 pose samples would need", "100.0 MB")


def test_a_pose_sample_longer_than_any_is_refused(session):
    file = session / POSE_STREAM
    file.write_bytes(b"[" + b"0," * 100_000 + b"0]\n")
    assert_refused(lambda: read_pose_stream(session), file, "line 1 is 200003 bytes long")


def test_millions_of_minimal_records_are_refused_at_once(session, monkeypatch):
    """Two million minimal records took 129 s and 962 MB before their error."""
    monkeypatch.setenv(MEMORY_ENV, "100")
    file = session / RECORDS
    line = (file.read_text().splitlines()[0] + "\n").encode()
    file.write_bytes(line * 200_000)
    refused_lightly(lambda: load_session(session), file, "200000 records would need")


def test_records_holding_fields_of_their_own_are_counted_as_they_come(session, monkeypatch):
    monkeypatch.setenv(MEMORY_ENV, "1")
    file = session / RECORDS
    first = file.read_text().splitlines()[0]
    extra = '"note": [' + ",".join(["[]"] * 20_000) + "]"
    file.write_text("".join(first[:-1] + f', "index": {i}, {extra}}}\n' for i in range(2)))
    assert_refused(lambda: load_session(session), file, "the records' own fields up to line 1")


def test_json_and_xml_are_parsed_only_when_what_parsing_takes_fits(tmp_path, monkeypatch):
    """150 MB of ``[[],...]`` took 3.9 GB, 160 MB of ``<a/>`` 3.8 GB."""
    monkeypatch.setenv(MEMORY_ENV, "100")
    phantom = tmp_path / "p.json"
    phantom.write_text("[" + ",".join(["[]"] * 1_000_000) + "]")
    refused_lightly(lambda: load_phantom(phantom), phantom, "parsing this file would need")
    config = tmp_path / "set.xml"
    config.write_text("<r>" + "<a/>" * 600_000 + "</r>")
    refused_lightly(lambda: read_device_set(config), config, "parsing this file would need")


def test_export_plus_counts_every_record_of_a_frame_named_thousands_of_times(session, tmp_path, monkeypatch):
    """3000 records of one frame took 2.4 GB and exited 0 under a 100 MB limit."""
    file = session / RECORDS
    line = file.read_text().splitlines()[0]
    file.write_text("".join(line.replace('"index": 0', f'"index": {i}') + "\n" for i in range(3000)))
    out = tmp_path / "x.igs.mha"
    monkeypatch.setenv(MEMORY_ENV, "100")
    result = run_cli("export-plus", session, out)
    assert_one_line_error(result, str(session), "exporting its 3000 frames would need")
    assert not out.exists()


def test_a_cloud_far_off_its_cad_is_compared_in_bounded_memory():
    """A calibration 100 mm off puts every surface point far off the CAD, where trimesh's
    closest-point search looks at every face for every point: it took 260 MB at 10 000 points a
    call (found by the fuzzing harness). The points are looked up in calls of bounded size."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    points = mesh.sample(5000, seed=0) + [0.0, 0.0, 100.0]
    tracemalloc.start()
    try:
        error = surface_error(points, mesh, np.eye(4))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert 80.0 < error.points_to_cad_mean < 120.0
    assert peak < 400 * CLOSEST_PAIRS, peak  # about 150 bytes a point-face pair, and the mesh's own
