"""Convex probes and fan images (issue 33): the probe model, the twin imaging it, the fan
calibration that fits the sound speed's stretch of the beams, reconstruction of a fan calibration's
frames, and the command line."""

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from probecal.core.geometry.fan import Fan
from probecal.core.geometry.probe import BUILTIN_PROBES, ConvexProbe, LinearProbe, in_view, probe_from_dict
from probecal.core.geometry.transforms import transform_points
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error, assert_refused

CONVEX = BUILTIN_PROBES["convex-50"]


def test_a_convex_probe_images_a_fan_of_its_geometry():
    probe = ConvexProbe()
    s = probe.nominal_spacing_mm[0]
    assert probe.nominal_spacing_mm == (s, s) and probe.width_px * s == pytest.approx(probe.width_mm)
    fan = probe.fan
    assert fan.angles_deg == (-30.0, 30.0)
    assert fan.radius_start_px * s == pytest.approx(50.0) and (fan.radius_stop_px - fan.radius_start_px) * s == 70.0
    near_left, near_right, far_left, far_right = fan.corners_px()
    assert near_left[1] == pytest.approx(0.0) and near_right[1] == pytest.approx(0.0)  # the first row: the face's ends
    assert far_left[0] == pytest.approx(0.0, abs=1e-9) and far_right[0] == pytest.approx(probe.width_px)
    deepest = fan.origin_px[1] + fan.radius_stop_px  # the far arc's middle: the image's last row
    assert probe.height_px - 1 <= deepest < probe.height_px
    middle_of_face = (probe.width_px / 2, probe.face_below_first_row_mm / s)
    assert np.hypot(*np.subtract(middle_of_face, fan.origin_px)) == pytest.approx(fan.radius_start_px)
    mask = fan.mask(probe.width_px, probe.height_px)
    u, v = np.meshgrid(np.arange(probe.width_px), np.arange(probe.height_px))
    assert np.array_equal(mask, fan.contains(np.stack([u, v], axis=-1)))
    assert 0.45 < mask.mean() < 0.75
    assert not in_view(probe, [[5.0, 5.0]])[0] and in_view(probe, [[probe.width_px / 2, 200.0]])[0]
    assert in_view(LinearProbe(), [[5.0, 5.0]])[0]


def test_a_fan_in_a_slower_medium_lies_shallower_along_every_beam_than_it_shows():
    """The scanner converts echo times to depths at its own sound speed: in a slower medium every
    echo lies nearer the face along its own beam (no beam turns), which no affine map of the
    pixels follows; at equal speeds the pixels are the image's square spacing exactly."""
    probe = ConvexProbe(medium_sound_speed=1480.0)
    s, k = probe.nominal_spacing_mm[0], 1480.0 / 1540.0
    pixels = np.array([[300.0, 100.0], [60.0, 250.0], [550.0, 330.0]])
    mm = probe.mm_from_pixels(pixels)
    apex = np.array(probe.fan.origin_px) * s
    for p, q in zip(pixels * s, mm):
        shown, true = p - apex, q - apex
        assert shown[0] * true[1] - shown[1] * true[0] == pytest.approx(0.0, abs=1e-9)  # the same beam
        assert np.linalg.norm(true) - 50.0 == pytest.approx(k * (np.linalg.norm(shown) - 50.0))
    assert np.allclose(probe.pixels_from_mm(mm), pixels)
    assert np.allclose(probe.fan.stretched(probe.fan.stretched(pixels, k), 1 / k), pixels)
    matched = replace(probe, medium_sound_speed=1540.0)
    assert np.allclose(matched.mm_from_pixels(pixels), pixels * s)
    assert np.allclose(matched.affine_px_to_mm, [[s, 0, 0], [0, s, 0], [0, 0, 1]], atol=1e-12)
    affine = probe.affine_px_to_mm
    off = np.linalg.norm(pixels @ affine[:2, :2].T + affine[:2, 2] - mm, axis=1)
    assert off.max() > 0.1  # the closest affine map misses by a tenth of a millimetre and more


def test_probes_round_trip_through_their_dict_and_files(tmp_path):
    from probecal.core.errors import InputError
    from probecal.core.io.probefile import load_probe

    for probe in (LinearProbe(), ConvexProbe(), ConvexProbe(radius_mm=40.0, fov_deg=70.0, depth_mm=120.0)):
        assert probe_from_dict(json.loads(json.dumps(probe.to_dict()))) == probe
    assert load_probe("convex-50") == ConvexProbe() and load_probe("linear-38") == LinearProbe()
    path = tmp_path / "c3.json"
    path.write_text(json.dumps({"type": "convex", "radius_mm": 60.0, "fov_deg": 75.0, "depth_mm": 150.0}))
    assert load_probe(path) == ConvexProbe(radius_mm=60.0, fov_deg=75.0, depth_mm=150.0)
    for data, fragment in (({"type": "convex", "fov_deg": 180.0}, "field of view"),
                           ({"type": "convex", "start_depth_mm": 3.0}, "start depth"),
                           ({"type": "convex", "radius_mm": -1}, "radius_mm"),
                           ({"type": "curved"}, "type"),
                           ({"type": "linear", "radius_mm": 50}, "unknown keys 'radius_mm'")):
        path.write_text(json.dumps(data))
        assert_refused(lambda: load_probe(path), path, fragment)
    with pytest.raises(InputError, match="no such probe"):
        load_probe("convex-60")


def _blob_angle_deg(image: np.ndarray) -> float:
    """The long axis of the brightest blob (deg from the image's x axis toward +y)."""
    mask = (image > 0.5 * image.max()).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    m = cv2.moments((labels == biggest).astype(np.uint8) * image, binaryImage=False)
    return math.degrees(0.5 * math.atan2(2 * m["mu11"], m["mu20"] - m["mu02"]))


def test_the_twin_turns_each_echo_to_its_beam_and_leaves_the_outside_of_the_fan_dark():
    from probecal.core.twin.bmode import BModeRenderer

    renderer = BModeRenderer(CONVEX, "harsh", 0)
    image = renderer.render(np.empty((0, 2)), rng=np.random.default_rng(1))
    outside = ~CONVEX.fan.mask(CONVEX.width_px, CONVEX.height_px)
    assert image[outside].max() == 0 and image[~outside].mean() > 3  # speckle inside only
    quiet = BModeRenderer(CONVEX, "none", 0)
    for u in (150.0, 300.0, 450.0):  # left, middle and right of the fan, 50 mm deep
        beam = math.atan2(u - CONVEX.fan.origin_px[0], 250.0 - CONVEX.fan.origin_px[1])
        dot = quiet.render(np.array([[u, 250.0]]))
        window = dot[220:280, int(u) - 40:int(u) + 40]
        # a dot is wider across its beam than along it: its long axis turns with the beam
        assert _blob_angle_deg(window.astype(np.float64)) == pytest.approx(-math.degrees(beam), abs=3.0)


@pytest.fixture(scope="module")
def convex_sweep(tmp_path_factory):
    from probecal.core.acquisition.simulate import simulate_calibration

    return simulate_calibration(tmp_path_factory.mktemp("convex") / "cal", n_poses=24, seed=3, noise="bench",
                                probe=CONVEX)


def test_a_convex_sweep_keeps_every_wire_in_the_fan_and_records_the_fan(convex_sweep):
    truth = convex_sweep.truth()
    assert convex_sweep.fan == CONVEX.fan and convex_sweep.manifest.probe.kind == "convex"
    for frame in truth["frames"]:
        markers = np.array(frame["markers_px"], dtype=float)
        assert np.isfinite(markers).all() and CONVEX.fan.contains(markers, 5.0).all()
    assert truth["stretch"] == pytest.approx(truth["setup"]["sound_speed_m_s"] / 1540.0)


def test_a_fan_calibration_fits_the_stretch_and_puts_the_fan_corners_near_the_truth(convex_sweep, tmp_path):
    from probecal.core.calibration.result import load_calibration
    from probecal.core.calibration.segment import segment_session
    from probecal.core.calibration.solve import calibrate_session

    results = segment_session(convex_sweep)
    assert sum(r.found for r in results) >= 23
    calibration = calibrate_session(convex_sweep, results, with_validation=False).calibration
    true = load_calibration(convex_sweep.path / "truth.json")
    assert calibration.fan == CONVEX.fan and calibration.pixel_spacing_mm == CONVEX.nominal_spacing_mm
    assert calibration.stretch == pytest.approx(true.stretch, rel=0.006)
    corners = CONVEX.fan.corners_px()

    def in_tool(cal, pixels, matrix=None):
        points = cal.set_right(pixels) if matrix is None else pixels
        return transform_points(cal.image_to_tool if matrix is None else matrix,
                                np.column_stack([points, np.zeros(len(points))]))

    exact = np.linalg.norm(in_tool(calibration, corners) - in_tool(true, corners), axis=1)
    assert exact.mean() < 0.5
    # PLUS takes the closest affine matrix over the fan: near the exact map, never on it
    shown = calibration.shown_image_to_tool
    apart = np.linalg.norm(in_tool(calibration, corners, shown) - in_tool(calibration, corners), axis=1)
    assert 0.05 < apart.max() < 1.0
    path = tmp_path / "cal.json"
    xml = calibration.write(path)
    again = load_calibration(path)
    assert again.fan == calibration.fan and again.stretch == pytest.approx(calibration.stretch)
    assert np.allclose(again.image_to_tool, calibration.image_to_tool)
    assert np.allclose(json.loads(path.read_text())["image_to_tool"], shown)
    assert np.allclose(load_calibration(xml).image_to_tool, shown, atol=1e-6)
    from probecal.core.io.deviceset import plus_fan, read_device_set

    assert plus_fan(read_device_set(xml).volume_reconstruction or {}) == CONVEX.fan  # PLUS clips to the fan too
    data = json.loads(path.read_text())
    for key, value, fragment in (("stretch", None, "both fan and stretch"), ("stretch", 2.0, "no sound speed's"),
                                 ("fan", {"angles_deg": [0, 1]}, "fan.origin_px")):
        path.write_text(json.dumps({**data, key: value}))
        assert_refused(lambda: load_calibration(path), path, fragment)


def test_the_refit_finds_a_known_stretch_from_noiseless_markers():
    """Markers exactly where a fan in a slower medium shows the wires: the joint fit of a fan
    finds the stretch and the mount, the spacing held at the scanner's."""
    from probecal.core.acquisition.plan import calibration_plan
    from probecal.core.calibration.jointfit import refine
    from probecal.core.geometry.transforms import make_transform, transform_error
    from probecal.core.twin.twin import make_twin

    probe = ConvexProbe(medium_sound_speed=1490.0)
    twin = make_twin(2, probe=probe)
    poses = np.array(calibration_plan(twin.nominal, 20, seed=2).poses)
    markers = np.array([twin.markers_px(p) for p in poses])
    assert np.isfinite(markers).all()
    nudge = make_transform(np.eye(3), [0.5, -0.4, 0.3])
    fit = refine(twin.phantom, markers, poses, twin.image_to_tool_rigid @ nudge, twin.phantom_to_base,
                 probe.nominal_spacing_mm, fan=probe.fan)
    assert fit.stretch == pytest.approx(1490.0 / 1540.0, abs=1e-6)
    assert fit.pixel_spacing_mm == probe.nominal_spacing_mm
    translation, rotation = transform_error(fit.image_to_tool_rigid, twin.image_to_tool_rigid)
    assert translation < 1e-4 and rotation < 1e-5


def test_reconstruct_resamples_a_fan_calibration_s_frames_onto_pixels_set_right():
    from probecal.core.calibration.result import Calibration
    from probecal.core.volume.reconstruct import frames_set_right

    fan = Fan((-30.0, 30.0), (300.0, -216.5), 250.0, 600.0)
    calibration = Calibration(np.eye(4), (0.2, 0.2), fan=fan, stretch=0.95)
    assert frames_set_right(replace(calibration, fan=None, stretch=None), (384, 600)) is None
    resample = frames_set_right(calibration, (384, 600))
    assert resample is not None
    image = np.zeros((384, 600), np.uint8)
    shown = np.array([[420.0, 330.0]])
    cv2.circle(image, (420, 330), 3, 255, -1)
    right = resample(image)
    ys, xs = np.nonzero(right > 128)
    target = calibration.set_right(shown)[0]
    assert np.hypot(xs.mean() - target[0], ys.mean() - target[1]) < 0.5
    clip = resample.clip(replace(fan, radius_stop_px=500.0))
    assert clip.radius_start_px == 250.0 and clip.radius_stop_px == pytest.approx(250.0 + 0.95 * 250.0)


def test_simulate_with_a_convex_probe_from_the_command_line(tmp_path):
    from probecal.core.io.session import load_session

    result = run_cli("simulate", "calibration", tmp_path / "c", "--probe", "convex-50", "--poses", "3",
                     "--image-size", "300", "192")
    assert result.returncode == 0, result.stderr
    session = load_session(tmp_path / "c")
    assert session.image(0).shape == (192, 300) and session.fan == replace(CONVEX, width_px=300).fan
    probe_file = tmp_path / "wide.json"
    probe_file.write_text(json.dumps({"type": "convex", "radius_mm": 40, "fov_deg": 70, "depth_mm": 90}))
    result = run_cli("simulate", "volume", tmp_path / "v", "--probe", probe_file, "--frames-per-pass", "4")
    assert result.returncode == 0, result.stderr
    assert load_session(tmp_path / "v").manifest.probe.fov_deg == 70
    for args, fragment in ((["--probe", "convex-60"], "no such probe"),
                           (["--probe", "convex-50", "--start-depth-mm", "5"], "takes no --start-depth-mm"),
                           (["--probe", "convex-50", "--image-size", "300", "300"], "192 px high")):
        result = run_cli("simulate", "calibration", tmp_path / "bad", "--poses", "3", *args)
        assert_one_line_error(result, fragment)
        assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


def test_the_console_draws_a_convex_probe_s_image_as_its_fan(tmp_path):
    """On the twin with a convex probe the console outlines the image plane as the fan, shows the
    live frame with the fan's edges, puts the recorded frames on the plane clear outside the fan,
    and calibrates a fan calibration."""
    from probecal.app.console.draw import FAN_ARC_STEPS, FAN_EDGE
    from probecal.app.console.server import launch

    console = launch(port=0, sessions_dir=tmp_path, time_scale=0.0, probe=CONVEX)
    try:
        console.connect()
        console.wait()
        outline = console.view.scene.outline.points.copy()
        assert outline.shape == (2 * FAN_ARC_STEPS + 2, 2, 3)
        console.panel.poses.value = 12
        console.start_sweep()
        console.wait()
        frame = console.panel.frame.image
        assert frame.shape[:2] == (CONVEX.height_px, CONVEX.width_px)
        assert np.all(frame[0, 0] == 0) and np.any(np.all(frame == FAN_EDGE, axis=-1))
        texture = console.view.scene.plane_image.image
        assert texture.shape[-1] == 4 and texture[0, 0, 3] == 0 and texture[-1, texture.shape[1] // 2, 3] == 255
        console.calibrate()
        console.wait()
        assert console.calibration is not None and console.calibration.fan == CONVEX.fan
        assert console.calibration.stretch is not None
        moved = console.view.scene.outline.points
        assert not np.allclose(moved, outline)
    finally:
        console.close()


def test_a_convex_probe_reads_from_the_fan_a_plus_device_set_states(tmp_path):
    from probecal.core.io.deviceset import device_set_xml, fan_attributes
    from probecal.core.io.probefile import load_probe

    path = tmp_path / "PlusDeviceSet_convex.xml"
    for probe in (CONVEX, ConvexProbe(radius_mm=40.0, fov_deg=70.0, depth_mm=90.0, width_px=512)):
        s = probe.nominal_spacing_mm[0]
        path.write_text(device_set_xml({}, {"ApproximateSpacingMmPerPixel": f"{s!r}"},
                                       fan_attributes(probe.fan, (probe.width_px, probe.height_px))))
        assert load_probe(path) == probe
    attributes = fan_attributes(CONVEX.fan, (CONVEX.width_px, CONVEX.height_px))
    assert attributes["ClipRectangleOrigin"] == "1 0" and attributes["ClipRectangleSize"] == "599 384"
    spacing = {"ApproximateSpacingMmPerPixel": "0.2"}
    for segmentation, volume, fragment in (
            (spacing, {}, "states no fan"),
            ({}, attributes, "states no pixel spacing"),
            (spacing, {**attributes, "FanAnglesDeg": "-20 30"}, "evenly about"),
            (spacing, {**attributes, "FanRadiusStartPixel": "0"}, "FanRadiusStartPixel"),
            (spacing, {**attributes, "FanAnglesDeg": "-30 thirty"}, "FanAnglesDeg")):
        path.write_text(device_set_xml({}, segmentation, volume))
        assert_refused(lambda: load_probe(path), path, fragment)


def test_the_black_outside_a_fan_makes_no_dots_at_its_edges(tmp_path):
    """Speckle meeting the black outside a fan is a step a top-hat lifts into dots; the segmenter
    of a fan image fills the outside with the fan's local mean first."""
    from probecal.core.acquisition.simulate import simulate_calibration
    from probecal.core.calibration.segment import Segmenter, fan_filled

    fan = CONVEX.fan
    convex_sweep = simulate_calibration(tmp_path / "harsh", n_poses=20, seed=1, noise="harsh", probe=CONVEX)
    with_fan = Segmenter.for_session(convex_sweep)
    assert with_fan.fan == fan
    near_edge = {}
    sides = Fan(fan.angles_deg, fan.origin_px, 0.0, 1e9)  # the fan's side lines alone
    far = Fan((-89.0, 89.0), fan.origin_px, 0.0, fan.radius_stop_px)  # its far arc alone
    for name, segmenter in (("plain", replace(with_fan, fan=None)), ("fan", with_fan)):
        candidates = np.concatenate([segmenter(convex_sweep.image(i)).candidates for i in range(len(convex_sweep))])
        assert fan.contains(candidates).all() or name == "plain"
        near_edge[name] = int((~sides.contains(candidates, 6.0)).sum() + (~far.contains(candidates, 6.0)).sum())
    assert near_edge["fan"] <= 0.6 * near_edge["plain"], near_edge
    image = convex_sweep.image(0)
    filled = fan_filled(image, fan, 10.0)
    inside = fan.mask(CONVEX.width_px, CONVEX.height_px)
    assert np.array_equal(filled[inside], image[inside])
    grid = np.stack(np.meshgrid(np.arange(CONVEX.width_px), np.arange(CONVEX.height_px)), axis=-1).astype(float)
    beside = ~inside & fan.contains(grid + [4.0, 0.0])  # just outside the fan's left edge
    assert beside.sum() > 100 and filled[beside].mean() > 0.5 * image[inside].mean() > 0
