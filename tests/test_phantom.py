import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.errors import InputError
from probecal.core.geometry.phantom import nwire_ratio
from probecal.core.geometry.transforms import make_transform
from probecal.core.io.phantomfile import default_phantom, dict_from_phantom, load_phantom, phantom_path
from tests.support.paths import FCAL_CONFIG, VLCUS_CONFIG


def image_across(x0, y, z_top):
    """Image x along phantom x, depth along -z, normal along +y (rigid, mm)."""
    return make_transform(np.column_stack([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), [x0, y, z_top])


def test_default_phantom_matches_spec():
    p = default_phantom()
    assert len(p.layers) == 4 and p.n_wires == 12
    assert [layer.wires[0].front[2] for layer in p.layers] == [70, 60, 50, 40]
    for layer in p.layers:
        left, diag, right = layer.wires
        assert left.front[0] == 45 and right.front[0] == 75
        assert np.linalg.norm(left.back - left.front) == pytest.approx(80.0)
    assert np.allclose(p.layers[0].wires[1].front, [45, 10, 70])
    assert np.allclose(p.layers[3].wires[1].front, [75, 10, 40])  # reversed diagonal
    assert np.allclose(p.box_max - p.box_min, [150, 100, 100])
    cloud = p.point_cloud()
    assert cloud.shape == (12000, 3)
    assert np.allclose(p.wire_distances(cloud, np.repeat(np.arange(12), 1000)), 0, atol=1e-9)


def test_crossings_and_diagonal_ratio():
    p = default_phantom()
    # Plane y = 30: the diagonals of the top three layers are a quarter of the way along.
    crossings = p.crossings(image_across(40.0, 30.0, 80.0))
    assert len(crossings) == 12
    by_index = {c.index: c for c in crossings}
    for layer in range(4):
        left, mid, right = (by_index[3 * layer + w].point_image for w in range(3))
        ratio = nwire_ratio(left, mid, right)
        expected = 0.25 if layer < 3 else 0.75
        assert ratio == pytest.approx(expected)
        assert by_index[3 * layer + 1].t == pytest.approx(0.25)
        assert left[1] == pytest.approx(80 - (70 - 10 * layer))  # depth below the face
    # The crossing points lie on their wires.
    pts = np.array([c.point_phantom for c in crossings])
    assert np.allclose(p.wire_distances(pts, [c.index for c in crossings]), 0, atol=1e-9)
    # A plane beyond the wire ends crosses nothing.
    assert p.crossings(image_across(40.0, 95.0, 80.0)) == []


def test_plus_phantoms_parse(plus_data):
    fcal = load_phantom(FCAL_CONFIG)
    assert fcal.n_wires == 9 and fcal.wires[1].name == "2:I2_f2"
    assert np.allclose(fcal.wires[1].front, [40, 0, 10]) and np.allclose(fcal.wires[1].back, [25, 40, 10])
    vlcus = load_phantom(VLCUS_CONFIG)
    assert vlcus.n_wires == 6


def test_own_definition_round_trip(tmp_path):
    p = default_phantom()
    f = tmp_path / "p.json"
    f.write_text(json.dumps(dict_from_phantom(p)))
    q = load_phantom(f)
    assert np.allclose(q.lines(), p.lines())


@pytest.mark.parametrize(
    "mutate, problem",
    [
        (lambda d: d["layers"][0]["wires"].pop(), "needs 3"),
        (lambda d: d["layers"][0]["wires"][2].update(back=[80, 90, 70]), "not parallel"),
        (lambda d: d["layers"][0]["wires"][1].update(back=[75, 90, 75]), "out of the N plane"),
        (lambda d: d["layers"][0]["wires"][0].update(front=[45, 10, 170], back=[45, 90, 170]), ""),
        (lambda d: d.update(format="other"), "not a phantom definition"),
        (lambda d: d["layers"][0]["wires"][0].update(front="x"), "layers[0].wires[0].front must be"),
    ],
)
def test_invalid_definitions_are_refused(tmp_path, mutate, problem):
    d = dict_from_phantom(default_phantom())
    mutate(d)
    f = tmp_path / "bad.json"
    f.write_text(json.dumps(d))
    with pytest.raises(InputError) as info:
        load_phantom(f)
    assert problem in str(info.value) and str(f) in str(info.value)


def test_layer_shifts_move_each_layer_whole_about_its_centre():
    phantom = default_phantom()
    n = len(phantom.layers)
    assert np.allclose(phantom.layer_shifts(np.tile(np.eye(4), (n, 1, 1))), 0.0)
    moves = np.tile(np.eye(4), (n, 1, 1))
    moves[0, :3, :3] = Rotation.from_euler("z", 1.0, degrees=True).as_matrix()
    moves[1, :3, 3] = [0.5, -0.2, 0.1]
    ends = phantom.lines()
    placed = ends + phantom.layer_shifts(moves)
    assert np.allclose(placed[3:6] - ends[3:6], [0.5, -0.2, 0.1])  # the second layer, translated
    assert np.allclose(placed[6:], ends[6:])  # the others where they were
    first, moved = ends[:3].reshape(-1, 3), placed[:3].reshape(-1, 3)
    assert np.allclose(moved.mean(axis=0), first.mean(axis=0))  # turned about its centre
    assert np.allclose(np.linalg.norm(moved[:, None] - moved[None], axis=2),
                       np.linalg.norm(first[:, None] - first[None], axis=2))  # rigidly
    assert not np.allclose(moved, first)


def test_diagonal_shifts_move_only_the_diagonals_across_them_within_their_layers():
    phantom = load_phantom(phantom_path("fcal-2.0"))
    offsets = np.array([[0.5, -0.5], [1.0, 0.0], [0.0, -0.3]])
    shifts = phantom.diagonal_shifts(offsets)
    ends = phantom.lines()
    for k, layer in enumerate(phantom.layers):
        outer, diagonal, other = (w.back - w.front for w in layer.wires)
        normal = np.cross(outer, diagonal)
        moved = shifts[3 * k + 1]
        assert np.allclose(shifts[[3 * k, 3 * k + 2]], 0.0)  # the outer wires stay
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), np.abs(offsets[k]))
        assert np.allclose(moved @ diagonal, 0.0) and np.allclose(moved @ normal, 0.0)  # across, in the plane
    # Every layer keeps its N's shape in a frame: all its end points stay in its plane.
    placed = phantom.moved(shifts).lines()
    assert np.allclose(placed[..., 2].reshape(len(phantom.layers), -1).std(axis=1), 0.0)
    assert not np.allclose(placed, ends)
