"""Compressed payloads: what a file's header declares and what its decoder would make are both
checked before memory is taken, so a small file that inflates to hundreds of MB, or a frame
larger than its header says, is refused in one line (exit 2) with nothing written."""

from __future__ import annotations

import cv2
import pytest

from probecal.core.io.sizes import encoded_size
from tests.support.cli import run_cli
from tests.support.payloads import COLUMNS, ROWS, bomb_bag, deflated_dicom, frame, jpeg_dicom, pose_table, understated
from tests.support.refusals import assert_one_line_error

LIMIT_MB = 20


def test_a_frame_header_gives_the_size_a_decoder_would_make():
    jpeg = cv2.imencode(".jpg", frame())[1].tobytes()
    assert encoded_size(jpeg) == (COLUMNS, ROWS)
    assert encoded_size(jpeg[:10]) is None and encoded_size(b"not an image") is None
    codestream = b"\xff\x4f\xff\x51" + (41).to_bytes(2, "big") + bytes(2) + b"".join(
        v.to_bytes(4, "big") for v in (COLUMNS + 5, ROWS + 7, 5, 7))
    assert encoded_size(codestream) == (COLUMNS, ROWS)
    jp2 = b"\x00\x00\x00\x0cjP  \r\n\x87\n" + (8 + len(codestream)).to_bytes(4, "big") + b"jp2c" + codestream
    assert encoded_size(jp2) == (COLUMNS, ROWS)


@pytest.mark.parametrize("case, fragments", [
    ("deflated", ("IM_2.dcm", "inflating this deflated DICOM file would need", "more than the limit")),
    ("jpeg larger than its header", ("IM_2.dcm", "12000x12000 px", "Columns and Rows say 64x48")),
])
def test_compressed_dicom_is_refused_before_it_is_inflated(tmp_path, monkeypatch, case, fragments):
    monkeypatch.setenv("PROBECAL_MAX_MEMORY_MB", str(LIMIT_MB))
    images = tmp_path / "images"
    images.mkdir()
    jpeg_dicom(images / "IM_1.dcm")  # a valid control beside it
    if case == "deflated":
        deflated_dicom(images / "IM_2.dcm", inflated_mb=3 * LIMIT_MB)
    else:
        jpeg_dicom(images / "IM_2.dcm", 12000, 12000)
    out = tmp_path / "out"
    result = run_cli("import-frames", images, "--poses", pose_table(tmp_path / "poses.csv", 2), out,
                     "--spacing", "0.1")
    assert_one_line_error(result, *fragments)
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_honest_compressed_dicom_imports(tmp_path, monkeypatch):
    monkeypatch.setenv("PROBECAL_MAX_MEMORY_MB", str(LIMIT_MB))
    images = tmp_path / "images"
    images.mkdir()
    jpeg_dicom(images / "IM_1.dcm")
    deflated_dicom(images / "IM_2.dcm", inflated_mb=0)
    result = run_cli("import-frames", images, "--poses", pose_table(tmp_path / "poses.csv", 2), tmp_path / "out",
                     "--spacing", "0.1")
    assert result.returncode == 0, result.stderr


BOMB_MB = 3 * LIMIT_MB


@pytest.mark.parametrize("ros, compression", [(1, "lz4"), (1, "bz2"), (1, "lz4 understated"), (2, "zstd message"),
                                              (2, "zstd file"), (2, "mcap")])
def test_a_compressed_bag_is_refused_before_it_is_inflated(tmp_path, monkeypatch, ros, compression):
    bag = tmp_path / ("bomb.bag" if ros == 1 else "bomb")
    bomb_bag(bag, ros, compression.split()[0] if ros == 1 else compression, BOMB_MB)
    if compression == "lz4 understated":  # the size the decoder makes is counted, not the one declared
        understated(bag)
    assert sum(f.stat().st_size for f in ([bag] if ros == 1 else bag.iterdir())) < BOMB_MB << 17  # an eighth
    monkeypatch.setenv("PROBECAL_MAX_MEMORY_MB", str(LIMIT_MB))
    out = tmp_path / "out"
    result = run_cli("import-rosbag", bag, out, "--image-topic", "/us/image", "--pose-topic", "/robot/pose",
                     "--spacing", "0.1")
    fragment = "a chunk of the bag would need" if compression in ("lz4", "bz2", "mcap") else "inflating "
    assert_one_line_error(result, "bomb", fragment, "more than the limit")
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())
