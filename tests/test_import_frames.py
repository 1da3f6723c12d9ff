"""`probecal import-frames`: a robot recording as a lab keeps it (image files and a pose table)
reads back to the session it was written from, in every pose layout, and bad input is refused in
one line with nothing written."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.kinematics import with_arm
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.io.frameimport import NominalSpacing, import_frames
from probecal.core.io.imagefiles import natural_key
from probecal.core.io.phantomfile import default_phantom
from probecal.core.io.posetable import read_pose_table
from probecal.core.io.session import load_session
from tests.support.cli import run_cli
from tests.support.payloads import image_dataset
from tests.support.refusals import assert_one_line_error


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """A small twin calibration sweep (stop and go, the robot's poses)."""
    return simulate_calibration(tmp_path_factory.mktemp("twin") / "s", n_poses=24, seed=4, noise="realistic")


def write_frames(session, folder: Path, name=lambda i: f"frame{i}.png", convert=lambda image: image) -> list[str]:
    """The session's frames as image files named ``name(i)`` (unpadded numbers: natural order)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = [name(i) for i in range(len(session))]
    for i, file in enumerate(names):
        cv2.imwrite(str(folder / file), convert(session.image(i)))
    return names


def write_rows(path: Path, rows, header=None, delimiter=",") -> Path:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f, delimiter=delimiter)
        if header:
            writer.writerow(header)
        writer.writerows([[v if isinstance(v, str) else repr(float(v)) for v in row] for row in rows])
    return path


def layouts(poses: np.ndarray) -> dict[str, tuple[list, list]]:
    """Each pose layout a lab might write: name -> (rows, extra command-line arguments)."""
    rotvec = Rotation.from_matrix(poses[:, :3, :3]).as_rotvec()
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    inverse = np.linalg.inv(poses)
    return {
        "4x4 matrices, one per row": ([p.ravel() for p in poses], []),
        "3x4 matrices, one per row": ([p[:3].ravel() for p in poses], []),
        "stacked 4x4 matrices": ([row for p in poses for row in p], []),
        "stacked 3x4 matrices": ([row for p in poses for row in p[:3]], []),
        "UR pose vectors": ([[*(p[:3, 3] / 1000), *r] for p, r in zip(poses, rotvec)], []),
        "positions and quaternions": ([[*p[:3, 3], *q] for p, q in zip(poses, quat)], ["--units", "mm"]),
        "base-to-flange": ([p.ravel() for p in inverse], ["--pose", "base-to-flange"]),
    }


def test_natural_order_puts_numbers_in_value_order():
    names = ["final (10).png", "img10.png", "final (2).png", "img2.png", "img1.png"]
    assert sorted(names, key=natural_key) == ["final (2).png", "final (10).png", "img1.png", "img2.png", "img10.png"]


@pytest.mark.parametrize("layout", ["4x4 matrices, one per row", "3x4 matrices, one per row", "stacked 4x4 matrices",
                                    "stacked 3x4 matrices", "UR pose vectors", "positions and quaternions",
                                    "base-to-flange"])
def test_every_pose_layout_reads_back_to_the_same_poses(twin, tmp_path, layout):
    poses = twin.poses()
    rows, args = layouts(poses)[layout]
    table_file = write_rows(tmp_path / "poses.csv", rows)
    table = read_pose_table(table_file, *(["mm"] if "--units" in args else [None]),
                            *(["base-to-flange"] if "--pose" in args else []))
    assert table.layout.startswith(layout.split(" (")[0]) or layout == "base-to-flange"
    assert table.units == ("m" if layout == "UR pose vectors" else "mm")
    assert np.abs(table.flange_to_base - poses).max() <= 1e-6


def test_a_session_written_as_image_files_imports_and_calibrates_as_itself(twin, tmp_path):
    names = write_frames(twin, tmp_path / "images")
    table = write_rows(tmp_path / "poses.txt", [[*p[:3, 3] / 1000, *Rotation.from_matrix(p[:3, :3]).as_rotvec()]
                                               for p in twin.poses()], delimiter=" ")
    sx, sy = twin.probe.nominal_spacing_mm
    result = run_cli("import-frames", tmp_path / "images", "--poses", table, tmp_path / "out",
                     "--spacing", sx, sy)
    assert result.returncode == 0, result.stderr
    assert "UR pose vectors" in result.stdout and "in m (guessed" in result.stdout, result.stdout
    imported = load_session(tmp_path / "out")
    assert [r.extra["file"] for r in imported.records] == names  # frame10 after frame9
    assert np.abs(imported.poses() - twin.poses()).max() <= 1e-6
    assert imported.pixel_spacing_mm == (sx, sy)
    for i in (0, len(twin) - 1):
        assert np.array_equal(imported.image(i), twin.image(i))
    own = calibrate_session(twin, segment_session(twin), with_validation=False).calibration
    back = with_arm(imported, twin.manifest.arm)
    again = calibrate_session(back, segment_session(back), with_validation=False).calibration
    assert np.abs(again.image_to_tool_rigid - own.image_to_tool_rigid).max() < 1e-6
    assert np.allclose(again.pixel_spacing_mm, own.pixel_spacing_mm, atol=1e-9)


def _pose_table(path: Path, poses: np.ndarray, number) -> Path:
    """Poses as a lab's script writes them: a 3x4 matrix a row, each value as ``number`` prints it."""
    path.write_text("".join(",".join(number(float(v)) for v in pose[:3].ravel()) + "\n" for pose in poses))
    return path


def test_a_pose_out_of_the_arms_reach_is_refused_naming_its_frame(twin, tmp_path):
    """A lab's table with a pose no UR3 reaches, calibrated with --arm UR3: refused in one line
    naming the frame and how far out it lies, rather than calibrated without the arm unsaid."""
    write_frames(twin, tmp_path / "images")
    far = twin.poses().copy()
    far[5, 0, 3] += 2000.0
    table = _pose_table(tmp_path / "far.csv", far, lambda v: f"{v:.6g}")
    sx, sy = twin.probe.nominal_spacing_mm
    assert run_cli("import-frames", tmp_path / "images", "--poses", table, tmp_path / "far",
                   "--spacing", sx, sy).returncode == 0
    result = run_cli("calibrate", tmp_path / "far", "--arm", "UR3", "--out", tmp_path / "far.json")
    assert_one_line_error(result, f"{tmp_path / 'far'}: frame 5: pose at (", "out of the UR3's reach: its wrist",
                          "mm out of the elbow's reach")
    assert not (tmp_path / "far.json").exists()


def test_a_table_with_file_and_time_columns_pairs_by_name_and_keeps_the_times(twin, tmp_path):
    n = 6
    write_frames(twin, tmp_path / "images", name=lambda i: f"f_{i:03d}.png")
    poses = twin.poses()[:n]
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    order = [3, 0, 5, 1, 4, 2]  # rows in another order than the files
    rows = [[f"f_{i:03d}.png", 10.0 + 0.5 * i, *poses[i, :3, 3], *quat[i]] for i in order]
    table = write_rows(tmp_path / "poses.csv", rows, header=["file", "t", "x", "y", "z", "qx", "qy", "qz", "qw"])
    session, read = import_frames(tmp_path / "images", table, tmp_path / "out", default_phantom(),
                                  NominalSpacing((0.1, 0.1)))
    assert read.layout.startswith("positions and quaternions") and read.files is not None
    assert [r.extra["file"] for r in session.records] == [f"f_{i:03d}.png" for i in order]
    assert np.abs(session.poses() - poses[order]).max() <= 1e-6
    assert [r.timestamp for r in session.records] == [10.0 + 0.5 * i for i in order]
    assert (tmp_path / "out" / "posestream.jsonl").is_file()


def test_colour_and_sixteen_bit_frames_become_grey(twin, tmp_path):
    image = twin.image(0)
    cv2.imwrite(str(tmp_path / "a.png"), cv2.merge([image, image, image]))
    brightest = int(image.max())
    cv2.imwrite(str(tmp_path / "b.png"), image.astype(np.uint16) * 16)
    table = write_rows(tmp_path / "poses.csv", [p.ravel() for p in twin.poses()[:2]])
    session, _ = import_frames(tmp_path, table, tmp_path / "out", default_phantom(), NominalSpacing(depth_mm=60.0))
    assert np.array_equal(session.image(0), image)
    expected = np.clip(np.rint(image.astype(np.float32) * 16 * (255.0 / (16 * brightest))), 0, 255)
    assert np.array_equal(session.image(1), expected.astype(np.uint8))
    height = image.shape[0]
    assert session.pixel_spacing_mm == pytest.approx((60.0 / height, 60.0 / height))


@pytest.fixture()
def recording(twin, tmp_path):
    """Three frames and their table, for the bad-input cases to spoil."""
    write_frames(twin, tmp_path / "images", name=lambda i: f"img{i + 1}.png")
    for i in range(3, len(twin)):
        (tmp_path / "images" / f"img{i + 1}.png").unlink()
    table = write_rows(tmp_path / "poses.csv", [p.ravel() for p in twin.poses()[:3]])
    return tmp_path / "images", table


def spoil_row(table: Path, row: int, change) -> None:
    rows = list(csv.reader(table.read_text().splitlines()))
    rows[row] = change(rows[row])
    table.write_text("\n".join(",".join(r) for r in rows) + "\n")


@pytest.mark.parametrize("case, fragments", [
    ("count", ("poses.csv", "3 poses for 2 images")),
    ("not a rotation", ("poses.csv", "line 2", "not a rotation")),
    ("nan", ("poses.csv", "line 3", "not a finite number")),
    ("far pose", ("poses.csv", "line 2", "1e+13", "at most 1e+09")),
    ("far time", ("poses.csv", "line 3", "1e+20", "at most 1e+09")),
    ("odd size", ("img2.png", "every frame must have one size")),
    ("not an image", ("img3.png", "not an image")),
    ("missing name", ("poses.csv", "'img9.png'", "not a file")),
    ("no spacing", ("images", "no nominal pixel spacing")),
    ("width", ("poses.csv", "5 pose values per row")),
])
def test_bad_input_exits_2_in_one_line_and_writes_nothing(recording, case, fragments):
    images, table = recording
    spacing = ["--spacing", "0.1"]
    if case == "count":
        (images / "img3.png").unlink()
    elif case == "not a rotation":
        spoil_row(table, 1, lambda r: [repr(2 * float(v)) if i < 3 else v for i, v in enumerate(r)])
    elif case == "nan":
        spoil_row(table, 2, lambda r: ["nan", *r[1:]])
    elif case == "far pose":  # a session holds nothing this far: refused at its row, not after the import
        spoil_row(table, 1, lambda r: [*r[:3], "1e13", *r[4:]])
    elif case == "far time":
        rows = table.read_text().splitlines()
        table.write_text("t," + ",".join(f"m{i}" for i in range(16)) + "\n"
                         + "\n".join(f"{1e20 if i == 1 else i},{r}" for i, r in enumerate(rows)) + "\n")
    elif case == "odd size":
        cv2.imwrite(str(images / "img2.png"), np.zeros((40, 30), np.uint8))
    elif case == "not an image":
        (images / "img3.png").write_bytes(b"this is not a PNG")
    elif case == "missing name":
        rows = table.read_text().splitlines()
        table.write_text("file," + ",".join(f"m{i}" for i in range(16)) + "\n"
                         + "\n".join(f"img{9 if i == 1 else i + 1}.png,{r}" for i, r in enumerate(rows)) + "\n")
    elif case == "no spacing":
        spacing = []
    elif case == "width":
        table.write_text("1,2,3,4,5\n" * 3)
    out = images.parent / "out"
    result = run_cli("import-frames", images, "--poses", table, out, *spacing)
    assert_one_line_error(result, *fragments)
    assert not out.exists()
    assert not any(p.name.startswith(".out") for p in images.parent.iterdir())


def test_a_plus_import_takes_an_anisotropic_spacing_and_a_start_depth(plus_data, tmp_path):
    config = (plus_data / "ConfigFiles" / "Testing"
              / "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml")
    result = run_cli("import-plus", plus_data / "TestImages" / "NwirePhantomFreehand.igs.mha", "--config", config,
                     tmp_path / "s", "--spacing", "0.078", "0.074", "--start-depth-mm", "4")
    assert result.returncode == 0, result.stderr
    session = load_session(tmp_path / "s")
    assert session.pixel_spacing_mm == (0.078, 0.074) and session.start_depth_mm == 4.0
    assert_one_line_error(run_cli("import-plus", plus_data / "TestImages" / "NwirePhantomFreehand.igs.mha",
                                  tmp_path / "t", "--spacing", "0.07", "0.07", "0.07"), "one or two numbers")


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif", ".bmp"])
def test_every_image_format_reads(twin, tmp_path, suffix):
    names = write_frames(twin, tmp_path / "images", name=lambda i: f"frame{i}{suffix}")
    for i in range(3, len(names)):
        (tmp_path / "images" / names[i]).unlink()
    table = write_rows(tmp_path / "poses.csv", [p.ravel() for p in twin.poses()[:3]])
    session, _ = import_frames(tmp_path / "images", table, tmp_path / "out", default_phantom(),
                               NominalSpacing((0.1, 0.1)))
    image = session.image(0)
    assert image.shape == twin.image(0).shape and image.dtype == np.uint8
    if suffix != ".jpg":  # lossless
        assert np.array_equal(image, twin.image(0))


ABOVE_PX, LEFT_PX = 40, 24  # the scanner's screen around its image region


def write_dicom(path: Path, image: np.ndarray, region: dict | None, frames: int = 1) -> None:
    """A scanner's DICOM export of one frame: ``image`` on a screen with text above and beside
    it, and (``region``) its Sequence of Ultrasound Regions."""
    from pydicom.dataset import Dataset
    from pydicom.uid import ExplicitVRLittleEndian

    screen = np.zeros((image.shape[0] + ABOVE_PX + 10, image.shape[1] + LEFT_PX + 16), np.uint8)
    cv2.putText(screen, "probe L12 depth 5 cm", (2, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 255)
    screen[ABOVE_PX:ABOVE_PX + image.shape[0], LEFT_PX:LEFT_PX + image.shape[1]] = image
    ds = image_dataset(ExplicitVRLittleEndian, *screen.shape)
    if frames > 1:
        ds.NumberOfFrames = frames
    ds.PixelData = np.repeat(screen[None], frames, axis=0).tobytes()
    if region is not None:
        item = Dataset()
        for name, value in region.items():
            setattr(item, name, value)
        ds.SequenceOfUltrasoundRegions = [item]
    ds.save_as(path, enforce_file_format=True)


def twin_region(session, start_depth_mm: float = 0.0) -> dict:
    """The region calibration of the twin's frames placed on the screen of :func:`write_dicom`:
    its reference pixel at the region's top, ``start_depth_mm`` below the probe's face."""
    sx, sy = session.probe.nominal_spacing_mm
    width, height = session.image_size
    return {"RegionSpatialFormat": 1, "RegionDataType": 1, "RegionFlags": 0,
            "RegionLocationMinX0": LEFT_PX, "RegionLocationMinY0": ABOVE_PX,
            "RegionLocationMaxX1": LEFT_PX + width - 1, "RegionLocationMaxY1": ABOVE_PX + height - 1,
            "PhysicalUnitsXDirection": 3, "PhysicalUnitsYDirection": 3,
            "PhysicalDeltaX": sx / 10, "PhysicalDeltaY": sy / 10,
            "ReferencePixelX0": width // 2, "ReferencePixelY0": 0,
            "ReferencePixelPhysicalValueX": 0.0, "ReferencePixelPhysicalValueY": start_depth_mm / 10}


def test_a_scanners_dicom_export_gives_its_region_calibration(twin, tmp_path):
    """Frames exported as DICOM by the scanner, on its screen with text around them: the region
    calibration they carry gives the nominal spacing and start depth, the frames are cut to the
    image region, and the session reads back as the one they came from."""
    n = 6
    for i in range(n):
        write_dicom(_mkdir(tmp_path / "images") / f"IM_{i + 1}.dcm",
                    twin.image(i), twin_region(twin, 2.5))
    table = write_rows(tmp_path / "poses.csv", [p.ravel() for p in twin.poses()[:n]])
    result = run_cli("import-frames", tmp_path / "images", "--poses", table, tmp_path / "out")
    assert result.returncode == 0, result.stderr
    assert "region calibration" in result.stdout, result.stdout
    imported = load_session(tmp_path / "out")
    assert imported.pixel_spacing_mm == pytest.approx(twin.probe.nominal_spacing_mm, rel=1e-9)
    assert imported.start_depth_mm == pytest.approx(2.5)
    assert imported.image_size == twin.image_size
    assert imported.manifest.scanner_region["region_px"][:2] == [LEFT_PX, ABOVE_PX]
    for i in range(n):
        assert np.array_equal(imported.image(i), twin.image(i))
    # What the command line gives wins over what the files say.
    result = run_cli("import-frames", tmp_path / "images", "--poses", table, tmp_path / "given",
                     "--spacing", "0.11", "0.09", "--start-depth-mm", "0")
    assert result.returncode == 0, result.stderr
    given = load_session(tmp_path / "given")
    assert given.pixel_spacing_mm == (0.11, 0.09) and given.start_depth_mm == 0.0


def _mkdir(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@pytest.mark.parametrize("case, fragments", [
    ("no region", ("images", "no nominal pixel spacing")),
    ("other region", ("IM_2.dcm", "ultrasound region", "differs from IM_1.dcm's", "one preset per import")),
    ("region off the frame", ("IM_1.dcm", "lies outside the")),
    ("region depth", ("IM_1.dcm", "reference pixel depth", "not a finite depth")),
    ("cine", ("IM_3.dcm", "3 frames in one DICOM file")),
    ("not DICOM", ("IM_2.dcm", "not a DICOM image")),
])
def test_bad_dicom_exits_2_in_one_line_and_writes_nothing(twin, tmp_path, case, fragments):
    images = _mkdir(tmp_path / "images")
    region = twin_region(twin)
    for i in range(3):
        this = dict(region)
        if case == "other region" and i == 1:
            this["PhysicalDeltaY"] *= 1.2
        if case == "region off the frame":
            this["RegionLocationMaxX1"] += 500
        if case == "region depth":
            this["ReferencePixelPhysicalValueY"] = 1e308
        write_dicom(images / f"IM_{i + 1}.dcm", twin.image(i), None if case == "no region" else this,
                    frames=3 if case == "cine" and i == 2 else 1)
    if case == "not DICOM":
        (images / "IM_2.dcm").write_bytes(b"DICM? no")
    table = write_rows(tmp_path / "poses.csv", [p.ravel() for p in twin.poses()[:3]])
    out = tmp_path / "out"
    assert_one_line_error(run_cli("import-frames", images, "--poses", table, out), *fragments)
    assert not out.exists()
