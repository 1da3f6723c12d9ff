"""PLUS interoperability: import a tracked sequence as a session, export a session as one.

On import the tool pose is ``ProbeToReference`` (``tool_to_base`` in probecal's names: the
tracker reference plays the robot base), the phantom comes from the device-set file, and its
``PhantomToReference`` becomes the session's known ``phantom_to_base``.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.plusconfig import read_device_set
from core.sequence import TrackedSequence, read_sequence, write_sequence
from core.session import Session, SessionWriter, load_session

Progress = Callable[[int, int], None]


def import_plus(
    sequence_file: str | Path,
    config_file: str | Path | None,
    out_dir: str | Path,
    tool: str = "Probe",
    reference: str = "Reference",
    progress: Progress | None = None,
) -> Session:
    """Turn a PLUS ``.igs.mha`` recording into a session in ``out_dir``.

    Everything is read and checked before anything is written; the session is assembled in a
    staging folder and renamed into place, so a failure leaves no partial output.
    """
    sequence_file, out_dir = Path(sequence_file), Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError(out_dir, "output folder exists and is not empty")
    staging = out_dir.with_name(f".{out_dir.name}.importing")
    if os.path.lexists(staging):
        raise InputError(staging, "left over from an interrupted import; remove it and try again")
    config = read_device_set(config_file) if config_file is not None else None
    seq = read_sequence(sequence_file)
    pose = seq.transform(tool, reference)
    pose_name = f"{tool}To{reference}"
    if pose is None:
        default = seq.fields.get("DefaultFrameTransformName", "").removesuffix("Transform")
        if default not in seq.transforms:
            names = ", ".join(sorted(seq.transforms)) or "none"
            raise InputError(sequence_file, f"no {pose_name} transform (transforms present: {names})")
        pose, pose_name = (seq.transforms[default], seq.statuses[default]), default
    poses, valid = pose
    image_ok = seq.image_ok if seq.image_ok is not None else np.ones(len(seq), bool)

    phantom_to_base = None
    if config is not None:
        phantom_to_reference = config.rigid_transform("Phantom", reference)
        if phantom_to_reference is not None:
            phantom_to_base = phantom_to_reference.tolist()
    manifest = {
        "kind": "imported",
        "source": {
            "sequence": str(sequence_file.resolve()),
            "config": str(Path(config_file).resolve()) if config_file is not None else None,
            "tool_pose": pose_name,
        },
        "image_size": [int(seq.frames.shape[2]), int(seq.frames.shape[1])],
        "pixel_spacing_mm": None,
        "phantom_to_base": phantom_to_base,
        "segmentation_hints": dict(config.segmentation.attributes) if config and config.segmentation else None,
    }
    writer = SessionWriter(staging, manifest, phantom=config.phantom if config else None)
    try:  # staging is this import's own folder from here on: on failure it is removed
        with writer:
            for i in range(len(seq)):
                writer.append(
                    seq.frames[i],
                    poses[i] if valid[i] else None,
                    timestamp=None if seq.timestamps is None else float(seq.timestamps[i]),
                    pose_timestamp=None if seq.timestamps is None else float(seq.timestamps[i]),
                    source_index=i,
                    image_valid=bool(image_ok[i]),
                )
                if progress:
                    progress(i + 1, len(seq))
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        if out_dir.exists():
            out_dir.rmdir()
        staging.rename(out_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return load_session(out_dir)


def export_plus(session: Session, out_file: str | Path, progress: Progress | None = None) -> None:
    """Write a session as a PLUS ``.igs.mha`` with ``ProbeToReferenceTransform`` per frame."""
    if len(session) == 0:
        raise InputError(session.path, "session has no frames to export")
    frames = []
    for i in range(len(session)):
        frames.append(session.image(i))
        if progress:
            progress(i + 1, len(session))
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise InputError(session.path, f"frames differ in size ({sorted(shapes)})")
    poses = session.poses()
    valid = np.array([r.pose_valid for r in session.records])
    timestamps = np.array([np.nan if r.timestamp is None else r.timestamp for r in session.records])
    seq = TrackedSequence(
        frames=np.stack(frames),
        transforms={"ProbeToReference": poses},
        statuses={"ProbeToReference": valid},
        timestamps=timestamps if np.all(np.isfinite(timestamps)) else None,
        image_ok=np.array([r.extra.get("image_valid", True) for r in session.records]),
    )
    write_sequence(out_file, seq)
