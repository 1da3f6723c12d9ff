"""Volume compounding (core.volume.compound): geometry, compounding semantics, hole filling, file output,
and agreement with PLUS's own reconstruction of SpinePhantomFreehand."""

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.io.session import load_session
from probecal.core.volume.compound import Compounder, fill_holes, reconstruct_sequence
from probecal.core.volume.fanangles import FanAutoDetect, detected_fan_angles
from probecal.core.volume.grid import Volume, VolumeGrid, VolumeSettings, output_grid
from probecal.core.volume.reconstruct import reconstruct_plus
from probecal.core.volume.volumefile import read_volume, write_volume
from tests.support.cli import run_cli
from tests.support.paths import PLUS
from tests.support.refusals import assert_one_line_error

SPINE = PLUS / "TestImages" / "SpinePhantomFreehand.igs.mha"
NN_MEAN = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml"
NN_MEAN_REF = PLUS / "TestImages" / "vtkVolumeReconstructorTestNNMEANvolumeRef.mha"


FAN = 'FanAnglesDeg="-25 25" FanOriginPixel="410 -40" FanRadiusStartPixel="60" FanRadiusStopPixel="600"'


def with_attributes(config: Path, out: Path, attributes: str) -> Path:
    """``config`` with more ``<VolumeReconstruction>`` attributes, written to ``out``."""
    out.write_text(config.read_text().replace("<VolumeReconstruction", f"<VolumeReconstruction {attributes}", 1))
    return out


def pose(spacing: float = 0.5, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """image_to_volume of an image lying in a z = const plane: pixel (u, v) -> offset + spacing * (u, v, 0)."""
    out = np.diag([spacing, spacing, 1.0, 1.0])
    out[:3, 3] = offset
    return out


def unit_grid(shape=(5, 8, 12)) -> VolumeGrid:
    """1 mm voxels, voxel (0, 0, 0) centred at the volume origin."""
    return VolumeGrid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), shape)


def compound(frames, poses, grid=None, **settings) -> np.ndarray:
    compounder = Compounder(VolumeSettings(**settings), grid or unit_grid())
    for frame, p in zip(frames, poses):
        compounder.insert(np.asarray(frame, np.uint8), p)
    return compounder.result().voxels


def test_constant_frame_lands_in_the_right_voxels():
    # A 21 x 11 px frame at 0.5 mm/px in the plane z = 3 mm covers x 0..10 mm, y 0..5 mm.
    frame = np.full((11, 21), 100, np.uint8)
    for interpolation in ("NEAREST_NEIGHBOR", "LINEAR"):
        voxels = compound([frame], [pose(offset=(0, 0, 3))], interpolation=interpolation)
        expected = np.zeros((5, 8, 12), np.uint8)
        expected[3, 0:6, 0:11] = 100
        assert np.array_equal(voxels, expected), interpolation


def test_pose_rotation_and_origin_are_applied():
    # Image x along volume -y, image y along volume +z, placed at (4, 6, 1) mm.
    image_to_volume = np.array([[0, 0, 1, 4], [-1, 0, 0, 6], [0, 1, 0, 1], [0, 0, 0, 1]], float)
    frame = np.zeros((3, 5), np.uint8)
    frame[2, 4] = 200  # pixel (u=4, v=2) -> (4, 2, 3) mm
    grid = VolumeGrid((1.0, -1.0, 0.0), (1.0, 1.0, 1.0), (5, 8, 6))
    voxels = compound([frame], [image_to_volume], grid)
    assert voxels[3, 3, 3] == 200  # (4, 2, 3) mm is voxel (3, 3, 3) of a grid starting at (1, -1, 0)
    assert np.count_nonzero(voxels == 200) == 1


def test_output_grid_fits_the_clipped_corners():
    settings = VolumeSettings(spacing_mm=(0.5, 0.5, 1.0), clip_origin_px=(2, 1), clip_size_px=(4, 3))
    poses = [pose(offset=(1.0, 2.0, 0.0)), None, pose(offset=(1.0, 2.0, 2.2)), np.full((4, 4), np.nan)]
    grid = output_grid(settings, (20, 10), poses)
    # Clip columns 2..6, rows 1..4 -> x 2..4 mm, y 2.5..4 mm; z 0..2.2 mm.
    assert np.allclose(grid.origin_mm, (2.0, 2.5, 0.0))
    assert grid.shape == (3, 4, 5)  # round(2.2 / 1) + 1, 1.5 / 0.5 + 1, 2 / 0.5 + 1
    with pytest.raises(ValueError, match="no frame has a valid pose"):
        output_grid(settings, (20, 10), [None])


def test_output_grid_from_plus_origin_and_extent():
    settings = VolumeSettings.from_plus(
        {"OutputSpacing": "0.5 0.5 2", "OutputOrigin": "10 20 30", "OutputExtent": "-2 5 0 3 1 1"}
    )
    grid = output_grid(settings)
    assert grid.shape == (1, 4, 8)
    assert np.allclose(grid.origin_mm, (9.0, 20.0, 32.0))


def test_settings_from_plus_attributes():
    settings = VolumeSettings.from_plus(
        {
            "OutputSpacing": "0.5 0.5 0.5", "ClipRectangleOrigin": "167 62", "ClipRectangleSize": "495 488",
            "Interpolation": "LINEAR", "Optimization": "FULL", "CompoundingMode": "MAXIMUM",
            "FillHoles": "ON", "NumberOfThreads": "1",
        },
        {"Type": "STICK", "StickLengthLimit": "5", "NumberOfSticksToUse": "2"},
    )
    assert settings.spacing_mm == (0.5, 0.5, 0.5) and settings.extent is None
    assert settings.clip_origin_px == (167, 62) and settings.clip_size_px == (495, 488)
    assert (settings.interpolation, settings.compounding, settings.fill_holes) == ("LINEAR", "MAXIMUM", True)
    assert (settings.stick_length, settings.sticks_used) == (5, 2)
    assert settings.clip_rectangle(820, 616) == (167, 62, 662, 550)  # PLUS includes origin + size
    assert VolumeSettings.from_plus({"ClipRectangleSize": "0 0"}).clip_size_px is None
    with pytest.raises(ValueError, match="OutputSpacing"):
        VolumeSettings.from_plus({"OutputSpacing": "0.5 0.5"})
    with pytest.raises(ValueError, match="interpolation"):
        VolumeSettings.from_plus({"Interpolation": "CUBIC"})


def test_mean_maximum_latest_on_one_voxel():
    frames = [np.full((1, 1), 10), np.full((1, 1), 30), np.full((1, 1), 20)]
    poses = [pose(offset=(2, 3, 1))] * 3
    for interpolation in ("NEAREST_NEIGHBOR", "LINEAR"):
        for mode, expected in (("MEAN", 20), ("MAXIMUM", 30), ("LATEST", 20)):
            voxels = compound(frames, poses, interpolation=interpolation, compounding=mode)
            assert voxels[1, 3, 2] == expected, (interpolation, mode)
            assert np.count_nonzero(voxels) == 1


def test_latest_is_the_last_pixel_written_across_the_bands_a_frame_is_cut_into():
    # Four rows 0.2 mm apart all fall in voxel (x 2, y 3, z 1): the frame's lanes each take two
    # rows, and LATEST keeps the last row; a later frame's first row wins over them all.
    column = np.array([[10], [20], [30], [40]], np.uint8)
    steps = pose(0.2, offset=(2.0, 2.7, 1.0))
    voxels = compound([column], [steps], compounding="LATEST")
    assert voxels[1, 3, 2] == 40 and np.count_nonzero(voxels) == 1
    later = np.array([[70], [0], [0], [0]], np.uint8)
    shifted = pose(0.2, offset=(2.0, 3.3, 1.0))  # only its first row reaches voxel y 3
    voxels = compound([column, later], [steps, shifted], compounding="LATEST")
    assert voxels[1, 3, 2] == 70
    assert compound([column, later], [steps, shifted], compounding="MAXIMUM")[1, 3, 2] == 70
    assert compound([later, column], [shifted, steps], compounding="LATEST")[1, 3, 2] == 40


def test_nearest_neighbour_rounds_to_the_closest_voxel():
    frame = np.array([[50, 90]], np.uint8)  # pixels at x = 1.4 mm and x = 1.9 mm
    voxels = compound([frame], [pose(offset=(1.4, 0, 0))])
    assert voxels[0, 0, 1] == 50 and voxels[0, 0, 2] == 90


def test_linear_spreads_with_trilinear_weights():
    # Pixel A (100) at x = 0.25 gives voxel 0 weight 0.75 and voxel 1 weight 0.25; pixel B (200)
    # at x = 0.75 the reverse: voxel 0 = (75 + 50) / 1, voxel 1 = (25 + 150) / 1.
    frame = np.array([[100, 200]], np.uint8)
    grid = unit_grid((2, 2, 3))
    voxels = compound([frame], [pose(offset=(0.25, 0, 0))], grid, interpolation="LINEAR")
    assert voxels[0, 0, 0] == 125 and voxels[0, 0, 1] == 175
    assert np.count_nonzero(voxels) == 2
    # MAXIMUM only writes voxels with a weight >= 1/8: a pixel at x = 0.9 skips voxel 0.
    voxels = compound([frame[:, :1]], [pose(offset=(0.9, 0, 0))], grid, interpolation="LINEAR", compounding="MAXIMUM")
    assert voxels[0, 0, 0] == 0 and voxels[0, 0, 1] == 100
    # A pixel off the grid (its +1 neighbours missing) is not pasted at all, as in PLUS.
    voxels = compound([frame[:, :1]], [pose(offset=(2.5, 0, 0))], grid, interpolation="LINEAR")
    assert not voxels.any()


def test_hole_filling_fills_a_one_voxel_gap():
    frame = np.full((9, 17), 50, np.uint8)  # 8 x 4 mm at 0.5 mm/px
    poses = [pose(offset=(0, 0, 0)), pose(offset=(0, 0, 2))]
    frames = [frame, frame * 3]
    grid = unit_grid((3, 5, 9))
    plain = compound(frames, poses, grid)
    assert not plain[1].any()
    filled = compound(frames, poses, grid, fill_holes=True)
    assert np.all(filled[1] == 100)  # halfway between 50 and 150
    assert np.array_equal(filled[[0, 2]], plain[[0, 2]])


def test_hole_filling_sticks_have_a_length_limit():
    values = np.zeros((5, 3, 3), np.uint8)
    values[0], values[4] = 40, 80  # filled planes 4 steps apart
    still_empty = fill_holes(values, values > 0, stick_length=4)  # ends at most 3 steps apart
    assert np.array_equal(still_empty, values)
    filled = fill_holes(values, values > 0, stick_length=5)
    assert filled[1:4, 1, 1].tolist() == [50, 60, 70]


def test_frames_without_a_valid_pose_are_skipped():
    compounder = Compounder(VolumeSettings(), unit_grid())
    frame = np.full((3, 3), 80, np.uint8)
    assert not compounder.insert(frame, None)
    assert not compounder.insert(frame, np.full((4, 4), np.nan))
    assert compounder.insert(frame, pose(offset=(1, 1, 1)))
    assert compounder.frames_inserted == 1
    calls = []
    volume = reconstruct_sequence(
        iter([frame, frame]), [None, pose(offset=(1, 1, 1))], VolumeSettings(), progress=lambda *a: calls.append(a)
    )
    assert volume.voxels.max() == 80
    assert calls == [(1, 2), (2, 2)]


def test_empty_or_poseless_input_raises_a_clear_error():
    with pytest.raises(ValueError, match="no frames"):
        reconstruct_sequence([], [], VolumeSettings())
    with pytest.raises(ValueError, match="no frame has a valid pose"):
        reconstruct_sequence([np.zeros((2, 2), np.uint8)], [None], VolumeSettings())
    with pytest.raises(ValueError, match="poses"):
        reconstruct_sequence([np.zeros((2, 2), np.uint8)], [pose(), pose()], VolumeSettings())
    with pytest.raises(ValueError, match="uint8"):
        Compounder(VolumeSettings(), unit_grid()).insert(np.zeros((2, 2), np.float32), pose())


@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_write_read_round_trip_keeps_origin_and_spacing(tmp_path, suffix):
    voxels = np.random.default_rng(0).integers(0, 256, (4, 5, 6), dtype=np.uint8)
    volume = Volume(voxels, (-74.5215, 165.5733, 29.0719), (0.5, 0.25, 2.0))
    path = tmp_path / f"volume{suffix}"
    write_volume(volume, path)
    back = read_volume(path)
    assert np.array_equal(back.voxels, voxels)
    assert np.allclose(back.origin_mm, volume.origin_mm) and np.allclose(back.spacing_mm, volume.spacing_mm)
    # ITK (as 3D Slicer) sees the same LPS geometry in both formats: origin, identity direction.
    image = sitk.ReadImage(str(path))
    assert np.allclose(image.GetOrigin(), volume.origin_mm) and np.allclose(image.GetDirection(), np.eye(3).ravel())
    assert image.GetSize() == (6, 5, 4)
    header = path.read_bytes()[:400]
    if suffix == ".nrrd":
        assert b"space: left-posterior-superior" in header
    else:
        assert b"TransformMatrix = 1 0 0 0 1 0 0 0 1" in header and b"Offset = -74.5215" in header
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary files left behind


def test_write_volume_rejects_other_formats(tmp_path):
    with pytest.raises(ValueError, match="nrrd or .mha"):
        write_volume(Volume(np.zeros((1, 1, 1), np.uint8), (0, 0, 0), (1, 1, 1)), tmp_path / "v.png")
    assert not any(tmp_path.iterdir())


def test_plus_nn_mean_reconstruction_matches_plus(plus_data):
    volume = reconstruct_plus(SPINE, NN_MEAN)
    ref = read_volume(NN_MEAN_REF)
    assert volume.voxels.shape == ref.voxels.shape == (105, 106, 147)
    assert np.allclose(volume.origin_mm, ref.origin_mm, atol=1e-3)
    assert volume.spacing_mm == ref.spacing_mm == (0.5, 0.5, 0.5)
    a, b = volume.voxels.astype(float), ref.voxels.astype(float)
    both = (a > 0) & (b > 0)
    assert np.corrcoef(a[both], b[both])[0, 1] >= 0.99
    # Filled in one only: 3 % of the volume, nearly all faint voxels that PLUS's truncating
    # running mean takes down to 0.
    assert np.mean((a > 0) ^ (b > 0)) < 0.04


def test_the_fan_is_read_from_plus_settings_and_keeps_the_pixels_plus_keeps():
    """PLUS's documented example (a TRUS probe's fan), and its deprecated attribute names."""
    attributes = {"FanAnglesDeg": "-45 45", "FanOriginPixel": "380 20", "FanRadiusStartPixel": "120",
                  "FanRadiusStopPixel": "360"}
    fan = VolumeSettings.from_plus(attributes).fan
    assert fan == Fan((-45.0, 45.0), (380.0, 20.0), 120.0, 360.0)
    assert VolumeSettings.from_plus({"FanAngles": "-45 45", "FanOrigin": "380 20", "FanRadiusStartPixel": "120",
                                     "FanDepth": "360"}).fan == fan
    assert VolumeSettings.from_plus({"FanAnglesDeg": "0 0"}).fan is None  # PLUS: no fan
    assert VolumeSettings.from_plus({"FanAnglesDeg": "-30 30"}).fan == Fan((-30.0, 30.0), (0.0, 0.0), 0.0, 500.0)
    mask = fan.mask(800, 600)
    kept = {(380, 20 + 200): True,  # straight below the origin, between the radii
            (380, 20 + 100): False,  # nearer than the start radius
            (380, 20 + 361): False,  # beyond the stop radius
            (380 + 150, 20 + 160): True, (380 + 170, 20 + 160): False,  # either side of the 45 degree line
            (380 - 150, 20 + 160): True, (380 - 170, 20 + 160): False,
            (380, 10): False}  # above the origin
    for (u, v), inside in kept.items():
        assert mask[v, u] == inside, (u, v)
    for bad in ({"FanAnglesDeg": "-30 30", "FanRadiusStartPixel": "600"}, {"FanAnglesDeg": "-95 30"},
                {"FanAnglesDeg": "-30"}):
        with pytest.raises(ValueError):
            VolumeSettings.from_plus(bad)


@pytest.mark.parametrize("interpolation", ["NEAREST_NEIGHBOR", "LINEAR"])
@pytest.mark.parametrize("compounding", ["MEAN", "MAXIMUM", "LATEST"])
def test_every_mode_fills_only_the_fan(interpolation, compounding):
    """A frame whose pixels land on voxel centres: the voxels filled are the fan's pixels, in every
    interpolation and compounding mode, within the clip rectangle too."""
    fan = Fan((-30.0, 40.0), (20.0, 2.0), 5.0, 18.0)
    settings = {"interpolation": interpolation, "compounding": compounding, "fan": fan,
                "clip_origin_px": (3, 0), "clip_size_px": (30, 19)}
    voxels = compound([np.full((24, 40), 200)], [pose(1.0)], grid=unit_grid((1, 24, 40)), **settings)
    expected = fan.mask(40, 24)
    expected[:, :3] = False
    expected[20:, :] = False  # the clip rectangle's rows 0..19 (PLUS includes row y0 + height)
    expected[:, 34:] = False
    assert np.array_equal(voxels[0] > 0, expected)
    assert np.all(voxels[0][expected] == 200)


def test_fan_angle_auto_detection_keeps_the_sector_with_content_and_skips_blank_frames():
    """A frame whose fan holds echoes only from -20 to +10 degrees of its -30..30 fan (the probe
    lost contact on one side). With a window of two samples, PLUS's auto-detection opens the
    sector at the last dark sample before it and closes it at the first dark one after it, half
    a degree out at the arcs' spacing, then narrows it by its 3 degree margins; with its default
    window of 20 samples the sector comes out wider. A blank frame is left out."""
    attributes = {"FanAnglesDeg": "-30 30", "FanOriginPixel": "150 0", "FanRadiusStartPixel": "100",
                  "FanRadiusStopPixel": "180", "EnableFanAnglesAutoDetect": "TRUE",
                  "FanAnglesAutoDetectBrightnessThreshold": "40", "FanAnglesAutoDetectFilterRadiusPixel": "1"}
    settings = VolumeSettings.from_plus(attributes)
    assert settings.fan_auto_detect == FanAutoDetect(40.0, 1)
    v, u = np.mgrid[0:200, 0:300]
    angle = np.degrees(np.arctan2(u - 150, v))
    frame = np.where((angle >= -20) & (angle <= 10), 100, 0).astype(np.uint8)
    fan = settings.fan
    left, right = detected_fan_angles(frame, fan.origin_px, fan.radius_start_px, fan.radius_stop_px,
                                      fan.angles_deg, settings.fan_auto_detect)
    assert left == pytest.approx(-20 - 0.5 + 3, abs=0.5) and right == pytest.approx(10 + 0.5 - 3, abs=0.5)
    wide = detected_fan_angles(frame, fan.origin_px, fan.radius_start_px, fan.radius_stop_px, fan.angles_deg,
                               FanAutoDetect(40.0))
    assert wide[0] < left and wide[1] > right and wide[0] >= -30 and wide[1] <= 30
    kept = settings.kept_pixels(frame).astype(bool)
    assert np.array_equal(kept, Fan((left, right), fan.origin_px, 100.0, 180.0).mask(300, 200))
    compounder = Compounder(settings, unit_grid((1, 200, 300)))
    assert not compounder.insert(np.zeros((200, 300), np.uint8), pose(1.0))  # blank: left out
    assert compounder.insert(frame, pose(1.0))
    assert np.array_equal(compounder.result().voxels[0] > 0, kept & (frame > 0))


def test_a_plus_recording_compounded_through_a_fan_fills_only_what_the_fan_reaches(plus_data, tmp_path):
    """SpinePhantomFreehand through its device set, MAXIMUM compounding without hole filling, with
    and without a fan: every voxel the fan lets through is one the whole frames fill too (a
    maximum over fewer pixels), and the fan leaves out the frames' corners."""
    plain = tmp_path / "plain.xml"
    plain.write_text(NN_MEAN.read_text().replace('CompoundingMode="MEAN" FillHoles="ON"',
                                                 'CompoundingMode="MAXIMUM" FillHoles="OFF"'))
    fanned = with_attributes(plain, tmp_path / "fan.xml", FAN)
    whole, fan = reconstruct_plus(SPINE, plain).voxels > 0, reconstruct_plus(SPINE, fanned).voxels > 0
    assert whole.shape == fan.shape
    assert not np.any(fan & ~whole)
    assert 0.3 < fan.sum() / whole.sum() < 0.95


def test_a_recordings_fan_comes_in_with_its_import_and_clips_its_reconstruction(plus_data, tmp_path):
    """A PLUS recording imported with a device set that sets a fan keeps the fan in its session;
    reconstructing the session with a calibration that says nothing of a fan clips to it, as the
    report says."""
    configs = {"whole": NN_MEAN, "fan": with_attributes(NN_MEAN, tmp_path / "fan.xml", FAN)}
    for name, config in configs.items():
        assert run_cli("import-plus", SPINE, "--config", config, tmp_path / name).returncode == 0
        result = run_cli("reconstruct", tmp_path / name, "--calibration", NN_MEAN, "--out", tmp_path / f"out-{name}")
        assert result.returncode == 0, result.stderr
    fan = load_session(tmp_path / "fan").fan
    assert fan == Fan((-25.0, 25.0), (410.0, -40.0), 60.0, 600.0) and load_session(tmp_path / "whole").fan is None
    reports = {name: json.loads((tmp_path / f"out-{name}" / "report.json").read_text()) for name in configs}
    assert reports["whole"]["volume"]["fan"] is None and reports["fan"]["volume"]["fan"] == fan.to_json()
    filled = {name: np.count_nonzero(read_volume(tmp_path / f"out-{name}" / "volume.nrrd").voxels) for name in configs}
    assert 0 < filled["fan"] < 0.95 * filled["whole"]
    bad = with_attributes(NN_MEAN, tmp_path / "bad.xml", 'FanAnglesDeg="-25"')
    assert_one_line_error(run_cli("import-plus", SPINE, "--config", bad, tmp_path / "bad"), "bad.xml", "FanAnglesDeg")
    assert not (tmp_path / "bad").exists()


def test_plus_config_without_volume_reconstruction_is_an_input_error(plus_data):
    config = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber.xml"
    with pytest.raises(InputError, match="VolumeReconstruction"):
        reconstruct_plus(SPINE, config)
