"""ROS 1 and ROS 2 bags, read with rosbags (pure Python, no ROS install): an image topic's frames
and the arm's poses, from a ``geometry_msgs/PoseStamped`` topic or from the tf tree.

Frames: ``sensor_msgs/Image`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8; colour to grey by
luminance) or ``sensor_msgs/CompressedImage`` (PNG, JPEG, ...). Poses: a PoseStamped is the
tool's pose in its header's frame (the base), in metres; a tf edge ``parent -> child`` is the
child's pose in the parent, and the chain from the tool up to the base is composed at the times
of its most frequent moving edge, the others interpolated (position linear, rotation Slerp).
Every message is stamped by its header (by the bag's record time where the header's is zero).
Poses come out as ``tool_to_base`` in mm.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from probecal.core.errors import InputError
from probecal.core.geometry.transforms import interpolate_pose, make_transform
from probecal.core.io.bagsizes import check_bag_sizes
from probecal.core.io.files import existing_file
from probecal.core.io.imagefiles import ImageHeader, decode_frame, image_header
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.io.limits import checked_bytes
from probecal.core.io.posetable import QUATERNION_TOLERANCE

DEFAULT_TYPESTORE = Stores.ROS2_HUMBLE  # message definitions for a ROS 2 bag that does not carry its own
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
POSE = "geometry_msgs/msg/PoseStamped"
TF = "tf2_msgs/msg/TFMessage"
TF_TOPICS = ("/tf", "/tf_static")
M_TO_MM = 1000.0
# Raw image encodings: (pixel type, channels, conversion of a colour frame to grey, or None).
ENCODINGS = {
    "mono8": (np.uint8, 1, None), "8UC1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None), "16UC1": (np.uint16, 1, None),
    "rgb8": (np.uint8, 3, cv2.COLOR_RGB2GRAY), "bgr8": (np.uint8, 3, cv2.COLOR_BGR2GRAY),
    "rgba8": (np.uint8, 4, cv2.COLOR_RGBA2GRAY), "bgra8": (np.uint8, 4, cv2.COLOR_BGRA2GRAY),
}


@dataclass(frozen=True)
class FrameStamp:
    """One image message, from its header alone: its time (s) and what its image holds."""

    time_s: float
    header: ImageHeader


@contextmanager
def open_bag(path: str | Path) -> Iterator[AnyReader]:
    """A reader of the ROS 1 (``.bag``) or ROS 2 (folder) bag at ``path``; InputError naming it
    when it is not one."""
    path = Path(path)
    # A FIFO, socket or device would block the reader: a ROS 1 bag is one regular file, and every
    # file of a ROS 2 bag's folder (metadata.yaml, the .db3 or .mcap storage) must be one too.
    for file in sorted(path.iterdir()) if path.is_dir() else [path]:
        existing_file(file)
    check_bag_sizes(path)
    reader = AnyReader([path], default_typestore=get_typestore(DEFAULT_TYPESTORE))
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own errors for every kind of unreadable bag
        raise InputError(path, f"not a ROS 1 or ROS 2 bag that can be read ({exc})") from None
    try:
        yield reader
    finally:
        reader.close()


def _connections(reader: AnyReader, path: Path, topics: tuple[str, ...], types: tuple[str, ...]) -> list:
    """The bag's connections on ``topics`` of one of ``types``; InputError naming what the bag holds."""
    found = [c for c in reader.connections if c.topic in topics]
    if not found:
        held = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})) or "nothing"
        raise InputError(path, f"no topic {' or '.join(topics)} in the bag; it holds {held}")
    wrong = [c for c in found if c.msgtype not in types]
    if wrong:
        raise InputError(path, f"{wrong[0].topic} holds {wrong[0].msgtype}, not {' or '.join(types)}")
    return found


def _messages(reader: AnyReader, path: Path, topics: tuple[str, ...],
              types: tuple[str, ...]) -> Iterator[tuple[Any, int, Any]]:
    """Every message on ``topics`` (of ``types``, see :func:`_connections`) in the bag's order: its
    connection, its record time (ns) and the message, deserialized (its fields as its type defines
    them); InputError naming the bag for one that cannot be read (cut short, a length past its end,
    storage that does not unpack)."""
    connections = _connections(reader, path, topics, types)  # its own InputError, before any message is read
    stream = reader.messages(connections)
    while True:
        try:
            connection, record_ns, raw = next(stream)
            message = reader.deserialize(raw, connection.msgtype)
        except StopIteration:
            return
        except Exception as exc:  # rosbags raises its own errors, and struct's, for every kind of broken message
            raise InputError(path, f"a message cannot be read ({type(exc).__name__}: {exc})") from None
        yield connection, record_ns, message


def _seconds(header: Any, record_ns: int) -> float:
    stamp = header.stamp.sec + header.stamp.nanosec * 1e-9
    return float(stamp) if stamp > 0 else record_ns * 1e-9


def _pose(position: Any, orientation: Any) -> np.ndarray:
    """4x4 (mm) from a ROS position (m) and unit quaternion (x, y, z, w)."""
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w])
    t = np.array([position.x, position.y, position.z]) * M_TO_MM
    if not (np.all(np.isfinite(q)) and np.all(np.abs(t) <= MAX_MAGNITUDE)) \
            or abs(np.linalg.norm(q) - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"not a pose within {MAX_MAGNITUDE:g} mm with a unit quaternion")
    return make_transform(Rotation.from_quat(q), t)


def pose_samples(reader: AnyReader, path: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(M,) s and (M, 4, 4) ``tool_to_base`` (mm) of a PoseStamped topic, in time order."""
    samples = []
    for _, record_ns, msg in _messages(reader, path, (topic,), (POSE,)):
        try:
            samples.append((_seconds(msg.header, record_ns), _pose(msg.pose.position, msg.pose.orientation)))
        except ValueError as exc:
            raise InputError(path, f"{topic} at {record_ns * 1e-9:.3f} s: {exc}") from None
    return _in_time_order(path, topic, samples)


def _in_time_order(path: Path, what: str, samples: list) -> tuple[np.ndarray, np.ndarray]:
    if not samples:
        raise InputError(path, f"{what}: no poses in the bag")
    samples.sort(key=lambda s: s[0])
    return np.array([s[0] for s in samples]), np.array([s[1] for s in samples])


def tf_samples(reader: AnyReader, path: Path, base: str, tool: str) -> tuple[np.ndarray, np.ndarray]:
    """(M,) s and (M, 4, 4) ``tool_to_base`` (mm) composed from the tf tree (see the module docstring)."""
    edges: dict[str, tuple[str, list]] = {}  # child -> (parent, [(time, child_to_parent)])
    for _, record_ns, msg in _messages(reader, path, TF_TOPICS, (TF,)):
        for tr in msg.transforms:
            child, parent = tr.child_frame_id.strip("/"), tr.header.frame_id.strip("/")
            try:
                pose = _pose(tr.transform.translation, tr.transform.rotation)
            except ValueError as exc:
                raise InputError(path, f"tf {parent} -> {child}: {exc}") from None
            edges.setdefault(child, (parent, []))[1].append((_seconds(tr.header, record_ns), pose))
    chain: list[tuple[np.ndarray, np.ndarray]] = []
    frame = tool.strip("/")
    while frame != base.strip("/"):
        if frame not in edges or len(chain) > len(edges):
            raise InputError(path, f"no tf chain from {tool} up to {base}; the tree's frames: "
                                   f"{', '.join(sorted(set(edges) | {p for p, _ in edges.values()}))}")
        parent, samples = edges[frame]
        chain.append(_in_time_order(path, f"tf {parent} -> {frame}", samples))
        frame = parent
    moving = [c for c in chain if len(c[0]) > 1]
    if not moving:
        raise InputError(path, f"the tf chain from {tool} to {base} never moves: one pose, not a sweep")
    times = max(moving, key=lambda c: len(c[0]))[0]
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    keep = np.ones(len(times), bool)
    for edge_times, edge_poses in chain:  # from the tool up: each edge's pose goes on the left
        at, inside = _interpolated(edge_times, edge_poses, times)
        poses = at @ poses
        keep &= inside
    return times[keep], poses[keep]


def _interpolated(times: np.ndarray, poses: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) of a sampled edge at the times ``at`` (N,), and where they lie within its
    samples (a single sample holds at every time: a static edge)."""
    if len(times) == 1:
        return np.repeat(poses, len(at), axis=0), np.ones(len(at), bool)
    i = np.clip(np.searchsorted(times, at) - 1, 0, len(times) - 2)
    span = times[i + 1] - times[i]
    fraction = np.clip((at - times[i]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    out = np.array([interpolate_pose(poses[k], poses[k + 1], f) for k, f in zip(i, fraction)])
    return out, (at >= times[0]) & (at <= times[-1])


def image_stamps(reader: AnyReader, path: Path, topic: str) -> list[FrameStamp]:
    """Every frame of an image topic from its message alone (a compressed one's size from its
    encoded header), in the bag's order; nothing is decoded."""
    stamps = []
    for connection, record_ns, msg in _messages(reader, path, (topic,), (IMAGE, COMPRESSED)):
        t = _seconds(msg.header, record_ns)
        if connection.msgtype == COMPRESSED:
            stamps.append(FrameStamp(t, image_header(path, bytes(msg.data))))
        else:
            stamps.append(FrameStamp(t, ImageHeader(int(msg.width), int(msg.height),
                                                    msg.encoding in ("mono16", "16UC1"))))
    if not stamps:
        raise InputError(path, f"{topic}: no frames in the bag")
    return stamps


def image_frames(reader: AnyReader, path: Path, topic: str) -> Iterator[np.ndarray]:
    """Every frame of an image topic as a grey array (uint8 or uint16), in the bag's order."""
    for connection, _, msg in _messages(reader, path, (topic,), (IMAGE, COMPRESSED)):
        yield decode_frame(bytes(msg.data), path) if connection.msgtype == COMPRESSED else _raw_frame(msg, path)


def _raw_frame(msg: Any, path: Path) -> np.ndarray:
    """A ``sensor_msgs/Image`` as a grey array; InputError for an encoding it does not hold."""
    if msg.encoding not in ENCODINGS:
        raise InputError(path, f"image encoding {msg.encoding!r}: expected one of {', '.join(ENCODINGS)}")
    dtype, channels, to_gray = ENCODINGS[msg.encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * np.dtype(dtype).itemsize
    checked_bytes(path, "an image message", [height, step])
    if step < row_bytes or len(msg.data) < height * step:
        raise InputError(path, f"an image message of {width}x{height} px holds {len(msg.data)} bytes, too few")
    rows = np.frombuffer(bytes(msg.data), np.uint8, count=height * step).reshape(height, step)[:, :row_bytes]
    image = rows.copy().view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<"))
    image = image.reshape(height, width, channels).astype(dtype)
    return image[:, :, 0] if to_gray is None else cv2.cvtColor(image, to_gray)
