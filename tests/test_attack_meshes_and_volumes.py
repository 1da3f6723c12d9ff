"""Meshes and volume settings are checked before the work starts (issue 13): a CAD file that is no
usable mesh, a voxel size or an extent that would need more memory than there is, and an output
path that cannot be written each end in exit 2 with one line, with nothing written."""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import pytest
import trimesh

from probecal.core.acquisition.simulate import simulate_volume
from probecal.core.errors import InputError
from probecal.core.io.limits import ENV
from probecal.core.volume.cad import read_mesh
from probecal.core.volume.grid import VolumeGrid, VolumeSettings, output_grid
from tests.support.cli import HANG_TIMEOUT_S, run_cli
from tests.support.refusals import assert_one_line_error


def _binary_stl(triangles: np.ndarray, declared: int | None = None) -> bytes:
    """A binary STL of (n, 3, 3) triangles (mm), with a header that may lie about the count."""
    n = len(triangles) if declared is None else declared
    body = b"".join(struct.pack("<12fH", 0, 0, 0, *t.ravel(), 0) for t in np.asarray(triangles, np.float32))
    return b"\0" * 80 + struct.pack("<I", n) + body


GOOD = np.array([[[0, 0, 0], [10, 0, 0], [0, 10, 0]], [[0, 0, 0], [0, 10, 0], [0, 0, 10]]], float)


@pytest.mark.parametrize("name, content, problem", [
    ("zero-area.stl", _binary_stl(GOOD[:1] * [1, 0, 0]), "zero area"),
    ("nan.stl", _binary_stl(np.where(GOOD == 10, np.nan, GOOD)), "not a triangle mesh|not finite"),
    ("inf.stl", _binary_stl(np.where(GOOD == 10, np.inf, GOOD)), "not a triangle mesh|not finite"),
    ("empty.stl", b"", "mesh"),
    ("garbage.stl", bytes(range(256)) * 3, "mesh"),
    ("lying-count.stl", _binary_stl(GOOD, declared=2**32 - 1), "mesh"),
    ("text.obj", b"this is not a mesh\n", "mesh"),
    ("points.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                   b"property float z\nend_header\n0 0 0\n", "mesh"),
    ("huge-header.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
                        b"property float y\nproperty float z\nelement face 4000000000\n"
                        b"property list uchar int vertex_indices\nend_header\n", "mesh"),
])
def test_a_cad_file_that_is_no_usable_mesh_is_refused(tmp_path, name, content, problem):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InputError, match=problem) as caught:
        read_mesh(path)
    assert caught.value.path == path


def test_a_mesh_keeps_its_triangles_with_area(tmp_path):
    path = tmp_path / "mixed.stl"
    path.write_bytes(_binary_stl(np.concatenate([GOOD, GOOD[:1] * [1, 0, 0]])))
    mesh = read_mesh(path)
    assert len(mesh.faces) == 2 and mesh.area == pytest.approx(100.0)
    with pytest.raises(InputError, match="not found"):
        read_mesh(tmp_path / "missing.stl")
    with pytest.raises(InputError, match="not found"):
        read_mesh(tmp_path)


def test_a_big_mesh_file_is_refused_before_loading(tmp_path, monkeypatch):
    path = tmp_path / "big.stl"
    trimesh.creation.icosphere(subdivisions=5).export(path)
    monkeypatch.setenv(ENV, "1")
    with pytest.raises(InputError, match=f"limit of 1.0 MB.*{ENV}"):
        read_mesh(path)


@pytest.mark.parametrize("spacing", [0.0, -1.0, 1e-9, float("nan"), float("inf")])
def test_voxel_sizes_that_make_no_sense_are_refused(spacing):
    with pytest.raises(ValueError, match="spacing"):
        VolumeSettings(spacing_mm=(spacing, 1.0, 1.0))


@pytest.mark.parametrize("extent, origin", [
    ("0 100000 0 100000 0 100000", "0 0 0"),
    ("0 1e30 0 10 0 10", "0 0 0"),
    ("0 inf 0 10 0 10", "0 0 0"),
    ("0 nan 0 10 0 10", "0 0 0"),
    ("0 10 0 10 0 10", "0 inf 0"),
    ("0 10 0 10", "0 0 0"),
    ("a b c d e f", "0 0 0"),
    ("10 0 0 10 0 10", "0 0 0"),
])
def test_hostile_volume_extents_are_refused_before_allocating(extent, origin):
    attributes = {"OutputSpacing": "1 1 1", "OutputExtent": extent, "OutputOrigin": origin}
    with pytest.raises((ValueError, InputError)) as caught:
        output_grid(VolumeSettings.from_plus(attributes))
    assert any(word in str(caught.value) for word in ("limit", "finite", "numbers", "extent")), str(caught.value)


def test_a_fitted_volume_too_fine_for_memory_is_refused():
    pose = np.diag([1.0, 1.0, 1.0, 1.0])
    with pytest.raises(InputError, match=r"would need .* more than the limit"):
        output_grid(VolumeSettings(spacing_mm=(0.001,) * 3), (640, 480), [pose])
    grid = output_grid(VolumeSettings(spacing_mm=(1.0,) * 3), (640, 480), [pose])
    assert isinstance(grid, VolumeGrid) and grid.shape == (1, 480, 640)


@pytest.fixture(scope="module")
def volume_session(tmp_path_factory):
    return simulate_volume(tmp_path_factory.mktemp("vol") / "v", seed=3, noise="none", n_frames=8)


def test_reconstruct_refuses_bad_meshes_sizes_and_outputs_up_front(volume_session, tmp_path):
    calibration = volume_session.path / "truth.json"
    zero = tmp_path / "zero.stl"
    zero.write_bytes(_binary_stl(GOOD[:1] * [1, 0, 0]))
    out = tmp_path / "rec"
    assert_one_line_error(run_cli("reconstruct", volume_session.path, "--calibration", calibration, "--out", out,
                                  "--cad", zero), str(zero), "zero area")
    assert_one_line_error(run_cli("reconstruct", volume_session.path, "--calibration", calibration, "--out", out,
                                  "--voxel", "0.01"), "would need", "limit")
    config = tmp_path / "volume.xml"
    config.write_text('<PlusConfiguration><VolumeReconstruction OutputSpacing="1 1 1" OutputOrigin="0 0 0" '
                      'OutputExtent="0 inf 0 10 0 10"/></PlusConfiguration>')
    assert_one_line_error(run_cli("reconstruct", volume_session.path, "--calibration", calibration, "--out", out,
                                  "--volume-config", config), str(config), "OutputExtent")
    not_a_folder = tmp_path / "plain.txt"
    not_a_folder.write_text("a file")
    assert_one_line_error(run_cli("reconstruct", volume_session.path, "--calibration", calibration, "--out",
                                  not_a_folder / "such" / "folder"), "plain.txt is not a folder")
    assert not out.exists() and not list(tmp_path.glob(".rec*"))


# A mesh that names a FIFO beside it: trimesh would open it and wait for a writer for ever.
FIFO_NAMING_MESHES = {
    "obj": b"mtllib fifo\nv 0 0 0\nv 10 0 0\nv 0 10 0\nf 1 2 3\n",
    "gltf": json.dumps({
        "asset": {"version": "2.0"}, "buffers": [{"uri": "fifo", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}], "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}], "scene": 0}).encode(),
}


@pytest.mark.parametrize("suffix", sorted(FIFO_NAMING_MESHES))
def test_a_mesh_naming_a_fifo_never_blocks(volume_session, tmp_path, suffix):
    """The OBJ's material file is left out (trimesh drops materials it cannot read); the glTF's
    geometry is in the FIFO, so it is refused naming it."""
    os.mkfifo(tmp_path / "fifo")
    mesh = tmp_path / f"m.{suffix}"
    mesh.write_bytes(FIFO_NAMING_MESHES[suffix])
    out = tmp_path / "rec"
    result = run_cli("reconstruct", volume_session.path, "--calibration", volume_session.path / "truth.json",
                     "--out", out, "--cad", mesh, "--register", timeout_s=HANG_TIMEOUT_S)
    if suffix == "obj":
        assert result.returncode == 0 and (out / "report.json").is_file(), result.stderr
    else:
        assert_one_line_error(result, str(tmp_path / "fifo"), "not a regular file")
        assert not out.exists()
