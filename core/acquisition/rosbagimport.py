"""Import a robot recording kept as a ROS 1 or ROS 2 bag (``core.io.rosbag``).

The frames are paired with the arm's poses by time as a live sweep's are
(``core.acquisition.pairing``): each frame stamped ``t`` takes the pose the stream holds at ``t -
latency`` (interpolated; none where the stream cannot place it, and the frame is kept without a
pose), and the whole pose stream is kept in the session, so that ``temporal-calibrate`` and
``calibrate`` can measure the latency and pair the frames again. The image axes are probecal's,
as for ``core.io.frameimport``. Everything is checked before anything is written, and the session
appears whole or not at all.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from probecal.core.acquisition.pairing import stream_buffer
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.files import fresh_folder
from probecal.core.io.frameimport import NominalSpacing
from probecal.core.io.imagefiles import first_odd_size, stored_frame
from probecal.core.io.manifest import Manifest
from probecal.core.io.plusimport import tracker_samples
from probecal.core.io.rosbag import image_frames, image_stamps, open_bag, pose_samples, tf_samples
from probecal.core.io.session import Session, load_session
from probecal.core.io.staging import imported_session

Progress = Callable[[int, int], None]
KIND = "imported-rosbag"


def import_rosbag(
    bag: str | Path,
    out_dir: str | Path,
    phantom: Phantom,
    spacing: NominalSpacing,
    image_topic: str,
    pose_topic: str | None = None,
    tf: tuple[str, str] | None = None,
    latency_s: float = 0.0,
    mirror: bool = False,
    progress: Progress | None = None,
    start_depth_mm: float | None = None,
) -> tuple[Session, str]:
    """Turn a bag into a session in ``out_dir``: the frames of ``image_topic`` with the poses of
    ``pose_topic`` (PoseStamped) or of the tf chain ``tf`` = (base, tool). Returns the session and
    where its poses came from, for the import's summary; ``start_depth_mm`` as for
    :func:`core.io.frameimport.import_frames`."""
    bag, out = Path(bag), fresh_folder(out_dir)
    if (pose_topic is None) == (tf is None):
        raise InputError(bag, "give the poses' topic or the tf chain (base and tool frames), one of them")
    with open_bag(bag) as reader:
        if pose_topic is not None:
            times, poses = pose_samples(reader, bag, pose_topic)
            source = f"{pose_topic} (PoseStamped)"
        else:
            assert tf is not None
            times, poses = tf_samples(reader, bag, *tf)
            source = f"tf {tf[1]} -> {tf[0]}"
        stamps = image_stamps(reader, bag, image_topic)
        headers = [s.header for s in stamps]
        first, odd = headers[0], first_odd_size(headers)
        if odd is not None:
            raise InputError(bag, f"{image_topic}: frame {odd} is {headers[odd].width}x{headers[odd].height} px, the "
                                  f"first {first.width}x{first.height}: every frame must have one size")
        sx, sy = spacing.at(first.width, first.height, bag)
        brightest = None
        if any(h.sixteen_bit for h in headers):
            brightest = max(int(frame.max()) for frame in image_frames(reader, bag, image_topic))
        stream_times, stream_poses = tracker_samples(times, poses, np.ones(len(times), bool))
        paired = stream_buffer(stream_times, stream_poses).poses_at(np.array([s.time_s for s in stamps]) - latency_s)
        manifest = Manifest(
            kind=KIND,
            source={"bag": str(bag.resolve()), "image_topic": image_topic, "poses": source,
                    "latency_s": latency_s, "mirrored": mirror},
            image_size=(first.width, first.height),
            pixel_spacing_mm=(sx, sy),
            start_depth_mm=start_depth_mm,
        )
        with imported_session(out, bag, manifest, phantom) as writer:
            for i, (stamp, frame, pose) in enumerate(zip(stamps, image_frames(reader, bag, image_topic), paired)):
                frame = stored_frame(frame, brightest, mirror)
                valid = bool(np.all(np.isfinite(pose)))
                writer.append(frame, pose if valid else None, timestamp=stamp.time_s,
                              pose_timestamp=stamp.time_s - latency_s, source_index=i)
                if progress:
                    progress(i + 1, len(stamps))
            writer.append_poses(stream_times, stream_poses)
    return load_session(out), source
