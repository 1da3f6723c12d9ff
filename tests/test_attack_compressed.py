"""Compressed payloads: what a file's header declares and what its decoder would make are both
checked before memory is taken, so a small file that inflates to hundreds of MB, or a frame
larger than its header says, is refused in one line (exit 2) with nothing written."""

from __future__ import annotations

import io
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.filewriter import write_file_meta_info
from pydicom.uid import DeflatedExplicitVRLittleEndian, ExplicitVRLittleEndian, JPEGBaseline8Bit, generate_uid

from probecal.core.io.sizes import encoded_size

US_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.6.1"
LIMIT_MB = 20
ROWS, COLUMNS = 48, 64


def frame() -> np.ndarray:
    return (np.arange(ROWS * COLUMNS) % 251).astype(np.uint8).reshape(ROWS, COLUMNS)


def image_dataset(transfer_syntax) -> Dataset:
    """A one-frame 8-bit grey ultrasound image's data set, its pixel data still to be given."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = US_IMAGE_STORAGE, generate_uid()
    meta.TransferSyntaxUID = transfer_syntax
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = US_IMAGE_STORAGE, meta.MediaStorageSOPInstanceUID, "US"
    ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = ROWS, COLUMNS, 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
    return ds


def jpeg_dicom(path: Path, width: int = COLUMNS, height: int = ROWS) -> None:
    """A JPEG-compressed DICOM frame whose JPEG header says ``width`` x ``height`` px (its Rows and
    Columns say 64 x 48, and the scan holds that many)."""
    jpeg = bytearray(cv2.imencode(".jpg", frame())[1].tobytes())
    at = jpeg.index(b"\xff\xc0")  # the baseline frame header: length, precision, height, width
    jpeg[at + 5: at + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    ds = image_dataset(JPEGBaseline8Bit)
    ds.PixelData = encapsulate([bytes(jpeg)])
    ds["PixelData"].VR = "OB"
    ds.save_as(path, enforce_file_format=True)


def deflated_dicom(path: Path, inflated_mb: int) -> None:
    """A deflated DICOM file whose body inflates to ``inflated_mb`` MB: a 64 x 48 frame, then zeros."""
    ds = image_dataset(ExplicitVRLittleEndian)
    ds.PixelData = frame().tobytes()
    body = io.BytesIO()
    ds.save_as(body, enforce_file_format=True)
    dataset = body.getvalue()[128 + 4:]
    meta_length = 12 + int.from_bytes(dataset[8:12], "little")  # the group length element, then the group
    ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
    deflater = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    with open(path, "wb") as f:
        f.write(b"\0" * 128 + b"DICM")
        write_file_meta_info(f, ds.file_meta)
        f.write(deflater.compress(dataset[meta_length:]))
        zeros = bytes(1 << 20)
        for _ in range(inflated_mb):
            f.write(deflater.compress(zeros))
        f.write(deflater.flush())


def pose_table(path: Path, count: int) -> Path:
    pose = np.eye(4)
    pose[:3, 3] = (300.0, 0.0, 200.0)
    path.write_text("".join(",".join(repr(float(v)) for v in pose.ravel()) + "\n" for _ in range(count)))
    return path


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


def bomb_bag(path: Path, ros: int, compression: str) -> None:
    """A bag whose one image message (raw mono8) is BOMB_MB MB of zeros, stored compressed:
    ROS 1 chunks (``lz4``, ``bz2``), a ROS 2 bag's messages (``zstd message``) or whole storage
    file (``zstd file``), or MCAP chunks (``mcap``)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    if ros == 1:
        writer = Writer1(path)
        writer.set_compression(Writer1.CompressionFormat[compression.upper()])
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP if compression == "mcap"
                         else StoragePlugin.SQLITE3)
        mode = {"mcap": CompressionMode.STORAGE, "zstd file": CompressionMode.FILE}.get(compression,
                                                                                         CompressionMode.MESSAGE)
        writer.set_compression(mode, CompressionFormat.ZSTD)
    side = int(np.sqrt(BOMB_MB << 20))
    header_fields = store.types["std_msgs/msg/Header"].__dataclass_fields__
    header = store.types["std_msgs/msg/Header"](stamp=store.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                                frame_id="", **({"seq": 0} if "seq" in header_fields else {}))
    image = store.types["sensor_msgs/msg/Image"](header=header, height=side, width=side, encoding="mono8",
                                                 is_bigendian=0, step=side, data=np.zeros(side * side, np.uint8))
    serialize = store.serialize_ros1 if ros == 1 else store.serialize_cdr
    with writer:
        connection = writer.add_connection("/us/image", "sensor_msgs/msg/Image", typestore=store)
        writer.write(connection, 1_000_000_000, serialize(image, "sensor_msgs/msg/Image"))


def understated(bag: Path) -> None:
    """Every chunk of a ROS 1 bag said to inflate to 1000 bytes (its header's ``size`` field)."""
    field = (9).to_bytes(4, "little") + b"size="
    data = bag.read_bytes()
    at = data.index(field) + len(field)
    bag.write_bytes(data[:at] + (1000).to_bytes(4, "little") + data[at + 4:])


@pytest.mark.parametrize("ros, compression", [(1, "lz4"), (1, "bz2"), (1, "lz4 understated"), (2, "zstd message"),
                                              (2, "zstd file"), (2, "mcap")])
def test_a_compressed_bag_is_refused_before_it_is_inflated(tmp_path, monkeypatch, ros, compression):
    bag = tmp_path / ("bomb.bag" if ros == 1 else "bomb")
    bomb_bag(bag, ros, compression.split()[0] if ros == 1 else compression)
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
