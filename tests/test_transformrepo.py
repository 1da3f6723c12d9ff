"""The transform repository: frame names read from PLUS transform names, paths found, composed and
inverted, validity carried along."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.geometry.transformrepo import TransformRepository, frame_splits, pick_split
from probecal.core.geometry.transforms import make_transform

N = 5
IDENTITY = np.tile(np.eye(4), (N, 1, 1))


def random_poses(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """(n, 4, 4) random rigid transforms, translations within 200 mm."""
    return np.array([make_transform(Rotation.random(random_state=rng), rng.uniform(-200, 200, 3)) for _ in range(n)])


def test_names_split_at_a_to_before_a_capital_as_plus_does():
    assert frame_splits("ProbeToStepperHome") == [("Probe", "StepperHome")]
    assert frame_splits("TemplateToStepperHome") == [("Template", "StepperHome")]
    assert frame_splits("ToolToTracker") == [("Tool", "Tracker")]
    assert frame_splits("ProbeToTopView") == [("Probe", "TopView")]
    assert frame_splits("StylusTo3DModel") == [("Stylus", "3DModel")]
    assert frame_splits("ProbeToToFCamera") == [("Probe", "ToFCamera"), ("ProbeTo", "FCamera")]
    for name in ("Tracker", "ToTracker", "ProbeTo", "Probetotracker", ""):
        assert frame_splits(name) == []


def test_an_ambiguous_name_takes_the_reading_joined_to_known_frames():
    assert pick_split("ProbeToTracker", set()) == ("Probe", "Tracker")
    assert pick_split("ProbeToToFCamera", {"ToFCamera", "Tracker"}) == ("Probe", "ToFCamera")
    assert pick_split("ProbeToToFCamera", {"FCamera"}) == ("ProbeTo", "FCamera")
    assert pick_split("ProbeToToFCamera", {"Probe", "FCamera"}) is None  # a tie: neither is preferred
    assert pick_split("ProbeToToFCamera", set()) is None
    assert pick_split("Tracker", {"Tracker"}) is None


def test_path_is_composed_inverted_and_valid_only_where_every_step_is():
    rng = np.random.default_rng(0)
    a_to_b, c_to_b, c_to_d = random_poses(rng), random_poses(rng), random_poses(rng)
    ok = np.ones(N, bool)
    c_to_b_ok = ok.copy()
    c_to_b_ok[1] = False
    repository = TransformRepository.build(
        N, {"AToB": a_to_b, "CToB": c_to_b, "CToD": c_to_d}, {"AToB": ok, "CToB": c_to_b_ok, "CToD": ok})
    found = repository.find("A", "D")
    assert found.path == "CToD @ inv(CToB) @ AToB"
    assert found.valid.tolist() == [True, False, True, True, True]
    expected = c_to_d @ np.linalg.inv(c_to_b) @ a_to_b
    assert np.allclose(found.matrices[found.valid], expected[found.valid], atol=1e-9)
    assert np.isnan(found.matrices[1]).all()
    back = repository.find("D", "A")
    assert back.path == "inv(AToB) @ CToB @ inv(CToD)"
    assert np.allclose((back.matrices @ found.matrices)[found.valid], np.eye(4), atol=1e-9)
    assert np.array_equal(repository.find("A", "B").matrices, a_to_b)
    assert np.array_equal(repository.find("A", "A").matrices, IDENTITY)
    assert repository.find("A", "E") is None and repository.find("E", "A") is None
    assert repository.frames == {"A", "B", "C", "D"}


def test_constants_join_the_per_frame_transforms_at_every_frame():
    rng = np.random.default_rng(1)
    probe_to_tracker, reference_to_tracker = random_poses(rng), random_poses(rng)
    phantom_to_reference, image_to_probe = random_poses(rng, 2)
    image_to_probe = image_to_probe @ np.diag([0.2, 0.3, 1.0, 1.0])  # holds the pixel spacing: not rigid
    ok = np.ones(N, bool)
    repository = TransformRepository.build(
        N, {"ProbeToTracker": probe_to_tracker, "ReferenceToTracker": reference_to_tracker},
        {"ProbeToTracker": ok, "ReferenceToTracker": ok},
        {("Phantom", "Reference"): phantom_to_reference, ("Image", "Probe"): image_to_probe})
    found = repository.find("Image", "Phantom")
    assert found.path == "inv(PhantomToReference) @ inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe"
    inv = np.linalg.inv
    expected = inv(phantom_to_reference) @ inv(reference_to_tracker) @ probe_to_tracker @ image_to_probe
    assert np.allclose(found.matrices, expected, atol=1e-9) and found.valid.all()
    constant = repository.find("Reference", "Phantom")
    assert np.allclose(constant.matrices, np.linalg.inv(phantom_to_reference), atol=1e-12)


def test_a_shortest_path_is_taken_and_per_frame_transforms_come_first():
    rng = np.random.default_rng(2)
    direct, via_1, via_2 = random_poses(rng), random_poses(rng), random_poses(rng)
    ok = np.ones(N, bool)
    repository = TransformRepository.build(
        N, {"AToX": via_1, "XToB": via_2, "AToB": direct}, {"AToX": ok, "XToB": ok, "AToB": ok},
        {("A", "B"): np.eye(4)})
    assert repository.find("A", "B").path == "AToB"


def test_an_ambiguous_stored_name_joins_through_the_frames_others_name():
    rng = np.random.default_rng(3)
    probe_to_camera, camera_to_tracker = random_poses(rng), random_poses(rng)
    ok = np.ones(N, bool)
    repository = TransformRepository.build(
        N, {"ProbeToToFCamera": probe_to_camera, "ToFCameraToTracker": camera_to_tracker, "HeadToTopToF": IDENTITY},
        {"ProbeToToFCamera": ok, "ToFCameraToTracker": ok, "HeadToTopToF": ok})
    found = repository.find("Probe", "Tracker")
    assert found.path == "ToFCameraToTracker @ ProbeToToFCamera"
    assert np.allclose(found.matrices, camera_to_tracker @ probe_to_camera, atol=1e-9)
    assert repository.unread == ["HeadToTopToF"]
    assert repository.describe() == ("the transforms held name the frames Probe, ToFCamera, Tracker; "
                                     "names read as no frame pair: HeadToTopToF")


def test_a_singular_transform_walked_backwards_leaves_that_frame_without_a_pose():
    rng = np.random.default_rng(4)
    x_to_y = random_poses(rng)
    x_to_y[1] = 0.0
    x_to_y[3, 3] = [0.0, 0.0, 0.0, 0.0]  # 16 finite numbers PLUS would read, but no inverse
    repository = TransformRepository.build(N, {"XToY": x_to_y}, {"XToY": np.ones(N, bool)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        found = repository.find("Y", "X")
    assert found.valid.tolist() == [True, False, True, False, True]
    assert np.allclose(found.matrices[0] @ x_to_y[0], np.eye(4), atol=1e-9)
    assert repository.find("X", "Y").valid.all()  # forwards it is as stored


@pytest.mark.parametrize("n", [0, 1])
def test_tiny_recordings(n):
    repository = TransformRepository.build(n, {"AToB": np.tile(np.eye(4), (n, 1, 1))}, {"AToB": np.ones(n, bool)})
    assert repository.find("B", "A").matrices.shape == (n, 4, 4)
