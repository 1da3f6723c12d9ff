"""The first step of a calibration: a session's frames ready to fit.

:func:`paired` pairs the frames with the robot's or tracker's poses at the image latency the
session measures (on a continuous sweep's temporal motion, :func:`pair_temporal`, or with the
calibration itself on a tracked recording, :func:`pair_tracked`), sets a fan image's markers right
for the stretch of its beams (:func:`set_right_fan`) and leaves out, with the reason, every frame
whose pattern was not found or whose pose is invalid. Markers are in pixels, poses are
``tool_to_base`` (mm), latencies in seconds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from probecal.core.acquisition.pairing import paired_again
from probecal.core.calibration.jointfit import WirePrior
from probecal.core.calibration.kinematics import ArmKinematics, PoseOutOfReach, arm_joints, out_of_reach, session_arm
from probecal.core.calibration.latency import (
    FIT_MAX_LAG_S,
    FittedLatency,
    TooFewEchoes,
    fitted_latency,
    session_latency,
    temporal_frames,
)
from probecal.core.calibration.objectives import REGISTRATION, WIRE_PRIOR, Mapper, Observations, check_pose_set, fit
from probecal.core.calibration.segment import FrameResult
from probecal.core.errors import InputError
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Spacing
from probecal.core.io.session import Session
from probecal.core.temporal.lag import LatencyEstimate


def observations(session: Session, results: list[FrameResult]) -> tuple[Observations, dict[int, str]]:
    """Frames with a found pattern and a valid pose; the others with the reason they are out. A
    session recorded by an arm whose kinematics probecal knows (manifest ``arm``) gives the
    joints of every frame, and the all-wire fit then fits the arm's kinematic errors too."""
    if session.phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    keep, left_out = [], {}
    for r in results:
        record = session.records[r.index]
        if not r.found:
            left_out[r.index] = f"pattern not found: {r.reason}"
        elif not record.pose_valid:
            left_out[r.index] = "no valid pose"
        else:
            keep.append(r)
    markers = np.array([r.markers for r in keep], dtype=float).reshape(len(keep), session.phantom.n_wires, 2)
    poses = np.array([session.records[r.index].tool_to_base for r in keep]).reshape(len(keep), 4, 4)
    arm = session_arm(session)
    try:
        joints = None if arm is None else arm_joints(poses, arm)
    except PoseOutOfReach as exc:
        assert arm is not None  # only an arm's joints are looked for
        raise out_of_reach(session, keep[exc.position].index, exc, arm) from None
    kinematics = None if arm is None or joints is None else ArmKinematics.at(joints, arm)
    return Observations(markers, poses, np.array([r.index for r in keep], dtype=int), kinematics=kinematics), left_out


def _usable(session: Session, results: list[FrameResult]) -> tuple[Observations, dict[int, str]]:
    """:func:`observations`, or InputError naming the session when no frame is usable."""
    obs, left_out = observations(session, results)
    if len(obs) == 0:
        reasons = sorted(set(left_out.values()))
        raise InputError(session.path, f"no usable frame among {len(session)} ({'; '.join(reasons[:3])})")
    return obs, left_out


def tracked_latency(session: Session, obs: Observations, phantom: Phantom, spacing0_mm: tuple[float, float],
                    known_y: np.ndarray | None, mapper: Mapper = map) -> FittedLatency:
    """The image latency of a recording whose frames were taken while the probe moved, with the
    tracker's poses kept as its pose stream (an imported PLUS recording), measured by the
    calibration itself (:func:`core.calibration.latency.fitted_latency`). InputError naming the
    session when it cannot be measured."""
    stream = session.pose_stream()
    assert stream is not None  # called for sessions that kept one
    times = np.array([np.nan if session.records[i].timestamp is None else session.records[i].timestamp
                      for i in obs.indices])
    registered = obs.registered(phantom, spacing0_mm, "point-to-wire", mapper).registrations
    ok = np.isfinite(times) & np.all(np.isfinite(registered.reshape(len(obs), 16)), axis=1)
    try:
        return fitted_latency(phantom, obs.markers_px[ok], times[ok], registered[ok], stream, spacing0_mm, known_y)
    except ValueError as exc:
        raise InputError(session.path, f"no image latency measured: {exc}")


def paired_with_latency(session: Session, results: list[FrameResult],
                        latency_s: float | None) -> tuple[Session, list[FrameResult]]:
    """A continuous session's frames paired again from its pose stream with the image latency
    (s), without the frames of the temporal motion; any other session as it is."""
    if latency_s is None or not session.manifest.continuous:
        return session, results
    temporal = set(temporal_frames(session))
    return paired_again(session, latency_s), [r for r in results if r.index not in temporal]


def initial_spacing(session: Session, obs: Observations, phantom: Phantom) -> tuple[float, float]:
    """The scanner's nominal spacing if recorded, else PLUS's approximate spacing hint, else an
    estimate from the outer-dot distances against the outer-wire separations (sx = sy)."""
    if session.nominal_spacing_mm is not None:
        return session.nominal_spacing_mm
    ratios = []
    for k, layer in enumerate(phantom.layers):
        separation = np.linalg.norm(np.cross(layer.wires[0].direction, layer.wires[2].front - layer.wires[0].front))
        span = np.linalg.norm(obs.markers_px[:, 3 * k + 2] - obs.markers_px[:, 3 * k], axis=1)
        ratios.append(separation / span)
    value = float(np.nanmedian(np.concatenate(ratios)))
    return value, value


@dataclass(frozen=True)
class Paired:
    """A session's frames ready to fit: paired with the robot's or tracker's poses at the image
    latency the session measures (``latency``; None where it measures none), a fan image's
    markers set right for its beams' ``stretch``, the usable frames (``obs``) and those left out
    with the reason; the spacing every fit starts from (mm/px) and the phantom pose when known
    (``known_y``; None: solved)."""

    session: Session
    phantom: Phantom
    results: list[FrameResult]
    obs: Observations
    left_out: dict[int, str]
    spacing0_mm: tuple[float, float]
    known_y: np.ndarray | None
    latency: LatencyEstimate | FittedLatency | None = None
    fan: Fan | None = None
    stretch: float | None = None

    @property
    def applied_latency_s(self) -> float | None:
        """The latency the frames were paired with again (s), if any."""
        if self.latency is None or (isinstance(self.latency, FittedLatency) and not self.latency.applied):
            return None
        return self.latency.image_latency_s

    def usable_again(self, session: Session, results: list[FrameResult]) -> Paired:
        """These frames of ``session`` as :func:`observations` finds them, the spacing held as before."""
        obs, left_out = _usable(session, results)
        return replace(self, session=session, results=results, obs=replace(obs, spacing_held=self.obs.spacing_held),
                       left_out=left_out)


def pair_temporal(session: Session, results: list[FrameResult],
                  say: Callable[[str], None]) -> tuple[Session, list[FrameResult], LatencyEstimate | None]:
    """A continuous session with a temporal motion: its latency measured on that motion's frames,
    and the sweep's frames paired again with it (the motion's frames left out); a stream too slow
    for the motion leaves the latency to :func:`pair_tracked`. Any other session as it is."""
    temporal = set(temporal_frames(session))
    if not temporal or not session.manifest.continuous:
        return session, results, None
    say(f"measuring the image latency on the {len(temporal)} frames of the temporal motion")
    try:
        latency = session_latency(session, results)
    except TooFewEchoes as exc:  # a slow stream: the sweep's own frames fit it, as a tracked recording's do
        sweep = [r for r in results if r.index not in temporal]
        if not sweep:
            raise InputError(session.path, f"{exc.problem}, and every frame is of that motion: no frame of a sweep "
                                           "to calibrate from")
        say(f"{exc.problem}; fitting it on the sweep's frames instead")
        return session, sweep, None
    session, results = paired_with_latency(session, results, latency.image_latency_s)
    return session, results, latency


def set_right_fan(paired: Paired, say: Callable[[str], None], mapper: Mapper, prior: WirePrior) -> Paired:
    """A fan image's markers set right for the stretch of its beams (:func:`fan_stretch`, fitted
    on the markers at their echoes' peaks), holding the scanner's own spacing where the session
    gives one (PLUS's approximate hint is only a start); any other session's as they are."""
    session = paired.session
    fan = session.fan if session.nominal_spacing_mm is not None else None
    if fan is None:
        return paired
    say("fitting the stretch of the fan's beams (the medium's sound speed over the scanner's)")
    peaks, _ = _usable(session, [at_echo_peaks(r) for r in paired.results])
    stretch = fan_stretch(paired.phantom, replace(peaks, fan=fan), paired.spacing0_mm, paired.known_y, mapper, prior)
    results = [stretched(r, fan, stretch) for r in paired.results]
    obs, left_out = _usable(session, results)
    held = session.pixel_spacing_mm is not None
    return replace(paired, results=results, obs=replace(obs, spacing_held=held), left_out=left_out, fan=fan,
                   stretch=stretch)


def pair_tracked(paired: Paired, say: Callable[[str], None], mapper: Mapper) -> Paired:
    """A session that kept its pose stream and measured no latency yet: the latency that best fits
    its frames (:func:`tracked_latency`), and its frames paired again with it where it matters."""
    session, obs = paired.session, paired.obs
    if paired.latency is not None or not session.has_pose_stream:
        return paired
    say(f"measuring the image latency: the {len(obs)} frames fitted at every lag within "
        f"{FIT_MAX_LAG_S:g} s of their tracked poses")
    latency = tracked_latency(session, obs, paired.phantom, paired.spacing0_mm, paired.known_y, mapper)
    paired = replace(paired, latency=latency)
    if not latency.applied:
        return paired
    return paired.usable_again(paired_again(session, latency.image_latency_s), paired.results)


def paired(session: Session, results: list[FrameResult], solve_phantom_pose: bool, say: Callable[[str], None],
           mapper: Mapper, prior: WirePrior) -> Paired:
    """The first step of :func:`calibrate_session`: the frames paired at the measured latency
    (:func:`pair_temporal`, :func:`pair_tracked`), a fan's set right (:func:`set_right_fan`); the
    pose set refused at once if it cannot determine a calibration."""
    if len(session) == 0:
        raise InputError(session.path, "session has no frames")
    phantom = session.phantom
    if phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    session, results, latency = pair_temporal(session, results, say)
    obs, left_out = _usable(session, results)
    known_y = None if solve_phantom_pose else session.phantom_to_base
    frames = Paired(session, phantom, results, obs, left_out, initial_spacing(session, obs, phantom), known_y, latency)
    check_pose_set(obs.tool_to_base, known_y is None)  # before any slow work
    return pair_tracked(set_right_fan(frames, say, mapper, prior), say, mapper)


def fan_stretch(phantom: Phantom, obs: Observations, spacing0_mm: Spacing, known_y: np.ndarray | None,
                mapper: Mapper = map, prior: WirePrior = WIRE_PRIOR) -> float:
    """The stretch of a fan image's beams (the medium's sound speed over the scanner's) that the
    ``all-wire`` fit finds for markers as the image shows them (``obs.fan`` set; calibrate gives
    them at their echoes' peaks, :func:`at_echo_peaks`), the spacing held at the scanner's."""
    registered = obs.registered(phantom, spacing0_mm, REGISTRATION["all-wire"], mapper)
    stretch = fit(phantom, registered, spacing0_mm, "all-wire", known_y, prior=prior).stretch
    assert stretch is not None  # a fan's fit solves it
    return stretch


def at_echo_peaks(result: FrameResult) -> FrameResult:
    """A frame's segmentation with each marker's row at its echo's peak where the segmentation
    found one (``peak_rows``): a wire's echo peaks on it, while the tail below pulls a centroid
    deeper the deeper it lies, which reads as a stretch of the beams (on the twin's ``bench``:
    +4.4 per mille from the centroids, +1.1 from the peaks, over seeds 0-4)."""
    if result.markers is None or result.peak_rows is None:
        return result
    rows = np.where(np.isfinite(result.peak_rows), result.peak_rows, result.markers[:, 1])
    return replace(result, markers=np.column_stack([result.markers[:, 0], rows]))


def stretched(result: FrameResult, fan: Fan, stretch: float) -> FrameResult:
    """A frame's segmentation with its markers (and their echoes' peak rows) where a fan image
    shows them once every beam is stretched by ``stretch`` (:meth:`Fan.stretched`)."""
    if result.markers is None:
        return result
    rows = None
    if result.peak_rows is not None:
        rows = fan.stretched(np.column_stack([result.markers[:, 0], result.peak_rows]), stretch)[:, 1]
    return replace(result, markers=fan.stretched(result.markers, stretch), peak_rows=rows)
