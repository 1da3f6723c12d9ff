"""Hostile payloads the tests and the fuzzing harness share: DICOM frames (honest, deflated to
inflate far past their size, or JPEG streams larger than their tags say), ROS bags whose compressed
storage inflates to hundreds of MB, and pose tables."""

from __future__ import annotations

import io
import zlib
from pathlib import Path

import cv2
import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.filewriter import write_file_meta_info
from pydicom.uid import DeflatedExplicitVRLittleEndian, ExplicitVRLittleEndian, JPEGBaseline8Bit, generate_uid

US_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.6.1"
ROWS, COLUMNS = 48, 64


def frame() -> np.ndarray:
    return (np.arange(ROWS * COLUMNS) % 251).astype(np.uint8).reshape(ROWS, COLUMNS)


def image_dataset(transfer_syntax, rows: int = ROWS, columns: int = COLUMNS) -> Dataset:
    """A one-frame 8-bit grey ultrasound image's data set of ``rows`` x ``columns`` px, its pixel
    data still to be given."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = US_IMAGE_STORAGE, generate_uid()
    meta.TransferSyntaxUID = transfer_syntax
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = US_IMAGE_STORAGE, meta.MediaStorageSOPInstanceUID, "US"
    ds.Rows, ds.Columns, ds.SamplesPerPixel, ds.PhotometricInterpretation = rows, columns, 1, "MONOCHROME2"
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


def bomb_bag(path: Path, ros: int, compression: str, mb: int) -> None:
    """A bag whose one image message (raw mono8) is ``mb`` MB of zeros, stored compressed:
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
    side = int(np.sqrt(mb << 20))
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


REGION = {"RegionSpatialFormat": 1, "RegionDataType": 1, "RegionFlags": 0, "RegionLocationMinX0": 0,
          "RegionLocationMinY0": 0, "RegionLocationMaxX1": COLUMNS - 1, "RegionLocationMaxY1": ROWS - 1,
          "PhysicalUnitsXDirection": 3, "PhysicalUnitsYDirection": 3, "PhysicalDeltaX": 0.01, "PhysicalDeltaY": 0.01,
          "ReferencePixelX0": COLUMNS // 2, "ReferencePixelY0": 0, "ReferencePixelPhysicalValueX": 0.0,
          "ReferencePixelPhysicalValueY": 0.0}
"""A scanner's region calibration of the whole 64 x 48 frame: 0.1 mm pixels, the first row at the
probe's face."""


def plain_dicom(path: Path, image: np.ndarray) -> None:
    """An uncompressed DICOM frame of ``image`` (ROWS x COLUMNS, uint8) with its REGION."""
    ds = image_dataset(ExplicitVRLittleEndian)
    ds.PixelData = image.tobytes()
    item = Dataset()
    for name, value in REGION.items():
        setattr(item, name, value)
    ds.SequenceOfUltrasoundRegions = [item]
    ds.save_as(path, enforce_file_format=True)


def sweep_bag(path: Path, ros: int, frames: int = 4) -> None:
    """A small sweep as a ROS 1 (file) or ROS 2 (folder) bag: ``frames`` mono8 images on /us/image
    and as many poses on /robot/pose (PoseStamped)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if ros == 1 else store.serialize_cdr
    seq = {"seq": 0} if "seq" in types["std_msgs/msg/Header"].__dataclass_fields__ else {}
    with Writer1(path) if ros == 1 else Writer2(path, version=9) as writer:
        images = writer.add_connection("/us/image", "sensor_msgs/msg/Image", typestore=store)
        poses = writer.add_connection("/robot/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        for k in range(frames):
            header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1 + k, nanosec=0),
                                                  frame_id="base_link", **seq)
            position = types["geometry_msgs/msg/Point"](0.3, 0.01 * k, 0.2)
            pose = types["geometry_msgs/msg/Pose"](position=position,
                                                   orientation=types["geometry_msgs/msg/Quaternion"](0, 0, 0, 1.0))
            writer.write(poses, (1 + k) * 1_000_000_000,
                         serialize(types["geometry_msgs/msg/PoseStamped"](header=header, pose=pose),
                                   "geometry_msgs/msg/PoseStamped"))
            image = types["sensor_msgs/msg/Image"](header=header, height=ROWS, width=COLUMNS, encoding="mono8",
                                                   is_bigendian=0, step=COLUMNS, data=np.roll(frame(), k).ravel())
            writer.write(images, (1 + k) * 1_000_000_000, serialize(image, "sensor_msgs/msg/Image"))
