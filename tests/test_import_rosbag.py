"""`probecal import-rosbag`: ROS 1 and ROS 2 bags that the tests write themselves from a twin
session (rosbags writes both) read back to the session's frames and poses, by a PoseStamped topic
or by the tf tree, and calibrate as the session does; bad input is refused in one line."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.simulate import simulate_calibration
from probecal.core.calibration.kinematics import with_arm
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.geometry.transforms import invert_transform, make_transform
from probecal.core.io.session import load_session
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error

WRIST_TO_TOOL = make_transform(Rotation.from_euler("xyz", [0.0, 0.0, 90.0], degrees=True), [0.0, 0.0, 82.3])


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    return simulate_calibration(tmp_path_factory.mktemp("twin") / "s", n_poses=24, seed=4, noise="realistic")


def stamp(store, t: float):
    sec = int(t)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def header(store, t: float, frame: str = ""):
    fields = store.types["std_msgs/msg/Header"].__dataclass_fields__
    extra = {"seq": 0} if "seq" in fields else {}  # ROS 1's header counts its messages
    return store.types["std_msgs/msg/Header"](stamp=stamp(store, t), frame_id=frame, **extra)


def transform_msg(store, pose: np.ndarray):
    """geometry_msgs Transform fields (m) of a 4x4 (mm)."""
    x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
    translation = store.types["geometry_msgs/msg/Vector3"](*(pose[:3, 3] / 1000.0))
    return translation, store.types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


def unchanged(topic: str, i: int, raw: bytes) -> bytes:
    return raw


def write_bag(session, path: Path, ros: int, compressed: bool, poses: str, spoil=unchanged) -> None:
    """The session's frames on /us/image and its poses on /robot/pose (PoseStamped) or in /tf
    (base_link -> wrist_3_link moving, wrist_3_link -> tool0 on /tf_static); every message of
    the sweep as ``spoil(topic, frame number, serialized message)`` makes it."""
    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:  # ROS 1's store lacks tf2_msgs; a ROS 1 bag carries its definition
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    serialize = store.serialize_ros1 if ros == 1 else store.serialize_cdr
    writer = Writer1(path) if ros == 1 else Writer2(path, version=9)
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with writer:
        images = writer.add_connection("/us/image", image_type, typestore=store)
        if poses == "pose":
            pose_conn = writer.add_connection("/robot/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        else:
            tf_conn = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
            static_conn = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
            translation, rotation = transform_msg(store, WRIST_TO_TOOL)
            edge = store.types["geometry_msgs/msg/TransformStamped"](
                header=header(store, 0.5, "wrist_3_link"), child_frame_id="tool0",
                transform=store.types["geometry_msgs/msg/Transform"](translation=translation, rotation=rotation))
            writer.write(static_conn, 500_000_000, serialize(store.types["tf2_msgs/msg/TFMessage"](transforms=[edge]),
                                                            "tf2_msgs/msg/TFMessage"))
        for i, record in enumerate(session.records):
            t, ns = record.timestamp, int(record.timestamp * 1e9)
            pose = session.poses()[i]
            if poses == "pose":
                position = store.types["geometry_msgs/msg/Point"](*(pose[:3, 3] / 1000.0))
                x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
                orientation = store.types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)
                msg = store.types["geometry_msgs/msg/PoseStamped"](
                    header=header(store, t, "base_link"),
                    pose=store.types["geometry_msgs/msg/Pose"](position=position, orientation=orientation))
                writer.write(pose_conn, ns, spoil("/robot/pose", i, serialize(msg, "geometry_msgs/msg/PoseStamped")))
            else:
                translation, rotation = transform_msg(store, pose @ invert_transform(WRIST_TO_TOOL))
                edge = store.types["geometry_msgs/msg/TransformStamped"](
                    header=header(store, t, "base_link"), child_frame_id="wrist_3_link",
                    transform=store.types["geometry_msgs/msg/Transform"](translation=translation, rotation=rotation))
                writer.write(tf_conn, ns, serialize(store.types["tf2_msgs/msg/TFMessage"](transforms=[edge]),
                                                    "tf2_msgs/msg/TFMessage"))
            image = session.image(i)
            if compressed:
                data = np.frombuffer(cv2.imencode(".png", image)[1].tobytes(), np.uint8)
                msg = store.types[image_type](header=header(store, t), format="png", data=data)
            else:
                height, width = image.shape
                msg = store.types[image_type](header=header(store, t), height=height, width=width, encoding="mono8",
                                              is_bigendian=0, step=width, data=image.ravel())
            writer.write(images, ns, spoil("/us/image", i, serialize(msg, image_type)))


@pytest.mark.parametrize("ros, compressed, poses", [(2, False, "pose"), (1, True, "tf"), (1, False, "pose"),
                                                     (2, True, "tf")])
def test_a_bag_imports_back_to_the_sessions_frames_and_poses(twin, tmp_path, ros, compressed, poses):
    bag = tmp_path / ("sweep.bag" if ros == 1 else "sweep")
    write_bag(twin, bag, ros, compressed, poses)
    how = ["--pose-topic", "/robot/pose"] if poses == "pose" else ["--tf", "base_link", "tool0"]
    sx, sy = twin.probe.nominal_spacing_mm
    result = run_cli("import-rosbag", bag, tmp_path / "out", "--image-topic", "/us/image", *how, "--spacing", sx, sy)
    assert result.returncode == 0, result.stderr
    assert f"{len(twin)} frames" in result.stdout and "pose stream kept" in result.stdout, result.stdout
    imported = load_session(tmp_path / "out")
    assert np.abs(imported.poses() - twin.poses()).max() <= 1e-6
    assert [r.timestamp for r in imported.records] == pytest.approx([r.timestamp for r in twin.records], abs=1e-9)
    assert imported.has_pose_stream
    for i in (0, len(twin) - 1):
        assert np.array_equal(imported.image(i), twin.image(i))
    if (ros, poses) == (1, "tf"):
        own = calibrate_session(twin, segment_session(twin), with_validation=False).calibration
        back = with_arm(imported, twin.manifest.arm)
        again = calibrate_session(back, segment_session(back), with_validation=False).calibration
        assert np.abs(again.image_to_tool_rigid - own.image_to_tool_rigid).max() < 1e-6


def test_bad_bags_exit_2_in_one_line_and_write_nothing(twin, tmp_path):
    bag = tmp_path / "sweep"
    write_bag(twin, bag, 2, False, "pose")
    cases = [
        (["--image-topic", "/camera", "--pose-topic", "/robot/pose"], ("no topic /camera", "/us/image")),
        (["--image-topic", "/us/image", "--pose-topic", "/us/image"], ("/us/image holds sensor_msgs/msg/Image",)),
        (["--image-topic", "/us/image", "--tf", "base_link", "tool0"], ("no topic /tf",)),
        (["--image-topic", "/us/image", "--pose-topic", "/robot/pose"], ("no nominal pixel spacing",)),
    ]
    for args, fragments in cases:
        result = run_cli("import-rosbag", bag, tmp_path / "out", *args)
        assert_one_line_error(result, *fragments)
        assert not (tmp_path / "out").exists()
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\nnot really")
    result = run_cli("import-rosbag", tmp_path / "junk.bag", tmp_path / "out", "--image-topic", "/us/image",
                     "--pose-topic", "/robot/pose", "--spacing", "0.1")
    assert_one_line_error(result, "junk.bag", "not a ROS 1 or ROS 2 bag")
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def far_z(topic: str, i: int, raw: bytes) -> bytes:
    """Frame 3's pose 1e300 m up: the PoseStamped ends with position (x, y, z) and orientation
    (x, y, z, w), eight-byte floats."""
    if topic != "/robot/pose" or i != 3:
        return raw
    return bytes(raw[:-40]) + np.float64(1e300).tobytes() + bytes(raw[-32:])


def cut(topic: str, i: int, raw: bytes) -> bytes:
    return raw[: len(raw) // 2] if (topic, i) == ("/us/image", 2) else raw


def huge_length(image_bytes: int):
    """Frame 2's image data said to be 0xFFFFFFF0 bytes long: its length is the four bytes (CDR,
    little-endian) before its ``image_bytes``, which end the message."""
    def spoil(topic: str, i: int, raw: bytes) -> bytes:
        if (topic, i) != ("/us/image", 2):
            return raw
        at = len(raw) - image_bytes - 4
        return bytes(raw[:at]) + (0xFFFFFFF0).to_bytes(4, "little") + bytes(raw[at + 4:])
    return spoil


@pytest.mark.parametrize("case, fragments", [
    ("far pose", ("/robot/pose", "not a pose within 1e+12 mm")),
    ("cut message", ("a message cannot be read",)),
    ("huge length", ("a message cannot be read",)),
    ("fifo", ("metadata.yaml", "not a regular file")),
    ("garbage metadata", ("not a ROS 1 or ROS 2 bag",)),
])
def test_hostile_bags_exit_2_in_one_line_and_leave_nothing(twin, tmp_path, case, fragments):
    bag = tmp_path / "sweep"
    spoil = {"far pose": far_z, "cut message": cut, "huge length": huge_length(twin.image(0).size)}.get(case, unchanged)
    write_bag(twin, bag, 2, False, "pose", spoil)
    if case == "fifo":  # a reader that opened it would wait for ever
        (bag / "metadata.yaml").unlink()
        os.mkfifo(bag / "metadata.yaml")
    elif case == "garbage metadata":
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n  {{{\n")
    result = run_cli("import-rosbag", bag, tmp_path / "out", "--image-topic", "/us/image", "--pose-topic",
                     "/robot/pose", "--spacing", "0.1")
    assert_one_line_error(result, "sweep", *fragments)
    assert not any(p.name.startswith((".out", "out")) for p in tmp_path.iterdir())
