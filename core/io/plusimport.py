"""PLUS interoperability: import a tracked sequence as a session, export a session as one.

On import the tool pose is ``ProbeToReference`` unless another is asked for (``tool_to_base`` in
probecal's names: the tracker reference plays the robot base), found with the phantom pose
``PhantomTo<reference>`` in a transform repository (core.geometry.transformrepo) of the recording's
transforms and the device set's; the phantom itself comes from the device set. Frames are stored
as PLUS holds them in memory (``MF``, :func:`core.io.sequence.oriented_mf`), the orientation of the
file kept in the manifest.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from probecal.core.errors import InputError
from probecal.core.geometry.transformrepo import Composed, TransformRepository, pick_split
from probecal.core.geometry.transforms import check_transform
from probecal.core.io.deviceset import DeviceSet, plus_fan, read_device_set
from probecal.core.io.files import fresh_folder
from probecal.core.io.limits import checked_bytes
from probecal.core.io.manifest import PLUS_IMPORT, Manifest, matrix_of
from probecal.core.io.sequence import TrackedSequence, oriented_mf, read_sequence, write_sequence
from probecal.core.io.session import Session, load_session
from probecal.core.io.staging import imported_session

Progress = Callable[[int, int], None]
FIXED_MM = 1e-6  # largest change (mm, and unitless for rotation entries) of a phantom pose that stays put


def _tool_pose(
    sequence_file: Path, seq: TrackedSequence, repository: TransformRepository, tool: str | None, reference: str | None
) -> tuple[str, str, Composed]:
    """(tool, reference, tool_to_reference) from the repository: ``tool`` (default Probe) to
    ``reference`` (default Reference); when neither is given and no path joins Probe to
    Reference, the file's ``DefaultFrameTransformName`` (e.g. ToolToTracker). InputError naming
    the frames the recording holds when no path joins the frames asked for."""
    asked = (tool or "Probe", reference or "Reference")
    requests = [asked]
    if tool is None and reference is None:
        default = seq.fields.get("DefaultFrameTransformName", "").removesuffix("Transform")
        if (pair := pick_split(default, repository.frames)) is not None:
            requests.append(pair)
    for source, target in requests:
        found = repository.find(source, target)
        if found is not None:
            return source, target, found
    raise InputError(sequence_file, f"no chain of transforms joins {asked[0]} to {asked[1]} (tool pose "
                                    f"{asked[0]}To{asked[1]}); {repository.describe()}")


def _phantom_pose(config: DeviceSet, repository: TransformRepository, reference: str) -> tuple[np.ndarray, str] | None:
    """(``phantom_to_reference``, the path it was composed along) from the repository when a
    path joins the two frames and the phantom stays put in the reference frame (the same pose,
    within FIXED_MM, at every frame where the path is valid); None otherwise. InputError naming
    the device set when that pose is not rigid."""
    found = repository.find("Phantom", reference)
    if found is None or not found.valid.any():
        return None
    poses = found.matrices[found.valid]
    if np.abs(poses - poses[0]).max() > FIXED_MM:
        return None
    return check_transform(poses[0], f"Phantom->{reference} ({found.path})", config.path, rigid=True), found.path


def import_plus(
    sequence_file: str | Path,
    config_file: str | Path | None,
    out_dir: str | Path,
    tool: str | None = None,
    reference: str | None = None,
    spacing_mm: tuple[float, float] | None = None,
    progress: Progress | None = None,
    start_depth_mm: float | None = None,
) -> Session:
    """Turn a PLUS ``.igs.mha`` recording into a session in ``out_dir`` with the poses
    ``tool_to_reference`` (see :func:`_tool_pose`) and, from the device set, the phantom and its
    pose ``phantom_to_reference`` (see :func:`_phantom_pose`). The manifest's ``source`` names the
    tool pose and the paths of stored transforms both were composed from; ``spacing_mm`` is the
    scanner's nominal pixel spacing (sx, sy mm/px), if known; ``start_depth_mm`` how far below
    the probe's face the first row lies, if known (``core.calibration.presets``).

    Everything is read and checked before anything is written; the session is assembled in a
    staging folder and renamed into place, so a failure leaves no partial output.
    """
    sequence_file, out_dir = Path(sequence_file), fresh_folder(out_dir)
    config = read_device_set(config_file) if config_file is not None else None
    seq = read_sequence(sequence_file)
    orientation = seq.fields.get("UltrasoundImageOrientation", "MF")
    frames = oriented_mf(seq.frames, orientation)
    constants = config.transforms if config is not None else None
    repository = TransformRepository.build(len(seq), seq.transforms, seq.statuses, constants)
    tool, reference, pose = _tool_pose(sequence_file, seq, repository, tool, reference)
    image_ok = seq.image_ok if seq.image_ok is not None else np.ones(len(seq), bool)
    phantom = _phantom_pose(config, repository, reference) if config is not None else None

    fan = None
    if config is not None and config.volume_reconstruction is not None:
        try:
            fan = plus_fan(config.volume_reconstruction)
        except ValueError as exc:
            raise InputError(config.path, f"VolumeReconstruction: {exc}") from None
    manifest = Manifest(
        kind=PLUS_IMPORT,
        source={
            "sequence": str(sequence_file.resolve()),
            "config": str(Path(config_file).resolve()) if config_file is not None else None,
            "tool_pose": f"{tool}To{reference}",
            "tool_pose_path": pose.path,
            "phantom_pose_path": phantom[1] if phantom else None,
        },
        image_size=(int(seq.frames.shape[2]), int(seq.frames.shape[1])),
        image_orientation_in_file=orientation,
        pixel_spacing_mm=None if spacing_mm is None else (float(spacing_mm[0]), float(spacing_mm[1])),
        start_depth_mm=start_depth_mm,
        phantom_to_base=matrix_of(phantom[0]) if phantom else None,
        segmentation_hints=dict(config.segmentation.attributes) if config and config.segmentation else None,
        fan=fan,
    )
    with imported_session(out_dir, sequence_file, manifest, config.phantom if config else None) as writer:
        for i in range(len(seq)):
            writer.append(
                frames[i],
                pose.matrices[i] if pose.valid[i] else None,
                timestamp=None if seq.timestamps is None else float(seq.timestamps[i]),
                pose_timestamp=None if seq.timestamps is None else float(seq.timestamps[i]),
                source_index=i,
                image_valid=bool(image_ok[i]),
            )
            if progress:
                progress(i + 1, len(seq))
        if seq.timestamps is not None:
            writer.append_poses(*tracker_samples(seq.timestamps, pose.matrices, pose.valid))
    return load_session(out_dir)


def tracker_samples(timestamps: np.ndarray, poses: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tracked poses a recording holds as a pose stream: the valid ones at their frames'
    timestamps (s), each later than the one kept before it. A frame's image may show the probe a
    little before or after its pose (the image latency, which ``probecal calibrate`` measures),
    so the frames can be paired again from these samples."""
    keep, last = [], -np.inf
    for i in np.flatnonzero(valid & np.isfinite(timestamps)):
        if timestamps[i] > last:
            keep.append(i)
            last = timestamps[i]
    return np.asarray(timestamps, float)[keep], np.asarray(poses)[keep]


def export_plus(session: Session, out_file: str | Path, progress: Progress | None = None) -> None:
    """Write a session as a PLUS ``.igs.mha`` with ``ProbeToReferenceTransform`` per frame."""
    if len(session) == 0:
        raise InputError(session.path, "session has no frames to export")
    first = session.image(0)
    # Every frame held, then stacked, then compressed: three copies at most.
    checked_bytes(session.path, f"exporting its {len(session)} frames", [len(session), first.nbytes, 3])
    frames = [first]
    for i in range(1, len(session)):
        frames.append(session.image(i))
        if frames[-1].shape != first.shape:  # before a larger frame is counted on
            raise InputError(session.path, f"frames differ in size ({first.shape} and {frames[-1].shape})")
        if progress:
            progress(i + 1, len(session))
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
