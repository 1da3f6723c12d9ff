"""The command line's tracked probe (``--tracker``): a probe probecal does not move, held by hand or
by a robot that only reports its pose, its poses from a PLUS server, 3D Slicer or the robot's own
bridge over OpenIGTLink (``igtl:HOST:PORT``), or the freehand twin (``sim``: a hand following the
guidance, streamed by the PLUS-server stand-in on loopback). ``probecal sweep --tracker`` records
it guided (until the corner bound is within the tolerance) or every frame (``--motion continuous``).

Either ends at the first pose a session's reader would refuse, with exit code 2 and one line (as
for bad input); a stream that ends or breaks ends it with exit code 1 (as a robot's sweep ending
early). Both keep every frame recorded, and say where.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from probecal.app.progress import clear_line
from probecal.app.rigspec import parse_image_spec
from probecal.core.acquisition.freehand import FreehandServer, FreehandTwin
from probecal.core.acquisition.guidance import frames_probe, guide_setup
from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.imagesource import ImageSource
from probecal.core.acquisition.pairing import FramePairer
from probecal.core.acquisition.tracked import TrackedRecording, TrackedSetup, setup_from_device_set, tracked_manifest
from probecal.core.acquisition.tracker import IgtlTracker, TrackerDevices
from probecal.core.calibration.guided import (
    GUIDED_PHASE,
    GuidedAcquisition,
    GuidedRun,
    GuideSettings,
    GuideStep,
    first_targets,
)
from probecal.core.calibration.segment import Segmenter
from probecal.core.errors import InputError
from probecal.core.io.files import fresh_folder
from probecal.core.io.phantomfile import load_phantom, phantom_path
from probecal.core.io.session import SessionWriter

TWIN = "sim"
FIRST_FRAME_S = 5.0  # how long the first frame (which gives the image's size) may take


def parse_tracker_spec(text: str) -> tuple[str, int] | None:
    """``igtl:HOST:PORT`` as (host, port), or None for ``sim`` (the freehand twin)."""
    if text == TWIN:
        return None
    kind, _, rest = text.partition(":")
    host, _, port = rest.rpartition(":")
    if kind == "igtl" and host and port.isdigit() and 0 < int(port) < 65536:
        return host, int(port)
    raise InputError(None, f"--tracker {text!r}: expected sim or igtl:HOST:PORT")


@dataclass(frozen=True)
class TrackedSpec:
    """A tracked probe as the command line names it: ``--tracker``, ``--tracker-devices``,
    ``--image`` (None: the tracker's own server), ``--device-set`` or ``--phantom``, the scanner's
    ``--spacing`` and ``--start-depth-mm``, and the freehand twin's seed."""

    tracker: str
    devices: TrackerDevices = TrackerDevices()
    image: str | None = None
    device_set: Path | None = None
    phantom: str | None = None
    spacing_mm: tuple[float, float] | None = None
    start_depth_mm: float | None = None
    seed: int = 0

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> TrackedSpec:
        image = None if args.image in (None, TWIN) else args.image
        return cls(args.tracker, args.tracker_devices, image, args.device_set, args.phantom, args.spacing,
                   args.start_depth_mm, args.seed or 0)


@dataclass
class TrackedStreams:
    """A connected tracker and its image source; ``server`` the freehand twin's, when it is the
    twin."""

    tracker: IgtlTracker
    source: ImageSource
    server: FreehandServer | None = None

    def close(self) -> None:
        self.tracker.disconnect()
        self.source.close()
        if self.server is not None:
            self.server.close()


def open_streams(spec: TrackedSpec, guide=lambda offsets: None) -> TrackedStreams:
    """Connect the tracker ``spec`` names and open its images (by default the tracker's own
    server's IMAGE messages); the freehand twin's hand follows ``guide``."""
    where = parse_tracker_spec(spec.tracker)
    server, devices = None, spec.devices
    if where is None:
        server = FreehandServer(guide, spec.seed)
        where, devices = ("127.0.0.1", server.port), TrackerDevices()
    same = spec.image is None or spec.image == f"igtl:{where[0]}:{where[1]}"
    source = IgtlSource(*where, transform_device=None) if same else parse_image_spec(spec.image or "")
    if source is None:
        raise InputError(None, "--image sim images the robot's twin; a tracked probe's images come from its "
                               "own server or igtl:, video: or replay:")
    tracker = IgtlTracker(*where, devices, device_clock=same)  # its images stamped by its clock
    try:
        source.open()
        tracker.connect()
    except Exception:
        source.close()
        if server is not None:
            server.close()
        raise
    return TrackedStreams(tracker, source, server)


def tracked_setup(spec: TrackedSpec) -> TrackedSetup:
    """The phantom, its registered pose and the scanner's spacing: from ``--device-set``, else
    ``--phantom`` (its pose then solved), else the freehand twin's."""
    twin = FreehandTwin(spec.seed).setup if parse_tracker_spec(spec.tracker) is None else None
    if spec.device_set is not None:
        setup = setup_from_device_set(spec.device_set)
    elif spec.phantom is not None:
        setup = TrackedSetup(load_phantom(phantom_path(spec.phantom)))
    elif twin is not None:
        setup = TrackedSetup(twin.phantom)
    else:
        raise InputError(None, "which phantom? give --device-set (PLUS's, with its registered pose) or --phantom")
    spacing = spec.spacing_mm or (twin.probe.nominal_spacing_mm if twin is not None else None)
    return replace(setup, spacing_mm=spacing, start_depth_mm=spec.start_depth_mm)


def tracked_sweep(args: argparse.Namespace) -> int:
    """``probecal sweep calibration|volume OUT --tracker ...``."""
    out = fresh_folder(args.out_dir)
    guided = args.motion == "guided"
    if guided and args.what != "calibration":
        raise InputError(None, "guided acquisition records a calibration; record a volume with --motion continuous")
    holder: list[GuidedAcquisition] = []
    spec = TrackedSpec.from_args(args)
    setup = tracked_setup(spec)
    streams = open_streams(spec, lambda offsets: guide_of(holder, offsets))
    try:
        if not guided:
            return _continuous(streams, setup, out, args)
        return _guided(streams, setup, out, args, holder)
    finally:
        streams.close()


def guide_of(holder: list[GuidedAcquisition], offsets: np.ndarray | None) -> np.ndarray | None:
    """What the console shows the freehand twin's hand: the strokes (None) while the latency is
    measured, then the target it shows after the newest frame (``offsets``: the hand's reading,
    which the acquisition has already taken)."""
    if not holder or holder[0].phase != GUIDED_PHASE:
        return None
    return holder[0].showing


def _continuous(streams: TrackedStreams, setup: TrackedSetup, out: Path, args: argparse.Namespace) -> int:
    recording = TrackedRecording(streams.tracker, streams.source, out, args.what, setup)
    outcome = recording.run(args.frames)
    if recording.writer is not None and streams.server is not None:
        recording.writer.write_truth(streams.server.twin.truth())
    refused = f", {outcome.refused} refused ({outcome.refusals[0]})" if outcome.refusals else ""
    if outcome.error is not None:
        kept = f"{outcome.recorded} frames kept in {out}" if outcome.recorded else "nothing recorded"
        return _ended(outcome.error, outcome.bad_input, f"{kept}{refused}")
    print(f"{out}: {outcome.recorded} frames recorded{refused}")
    return 0


def _ended(error: str, bad_input: bool, kept: str) -> int:
    """Say in one line why a recording ended before it was done and what it ``kept``: exit code 2
    when the tracker sent bad data, 1 when a stream ended or broke."""
    clear_line()
    if bad_input:
        print(f"probecal: error: {error}; {kept}", file=sys.stderr)
        return 2
    print(f"probecal: sweep ended early ({error}): {kept}", file=sys.stderr)
    return 1


def _guided(streams: TrackedStreams, setup: TrackedSetup, out: Path, args: argparse.Namespace,
            holder: list[GuidedAcquisition]) -> int:
    writer, acquisition = guided_acquisition(streams, setup, out, args.tolerance)
    holder.append(acquisition)
    run = GuidedRun(acquisition, streams.source, lambda: streams.tracker.paused,
                    _status(acquisition))
    try:
        outcome = run.run()
    finally:
        if streams.server is not None:
            writer.write_truth(streams.server.twin.truth())
        writer.close()
        clear_line()
    said = _summary(acquisition)
    if outcome.enough:
        print(f"{out}: enough: {said}; 'probecal calibrate {out}' calibrates it")
        return 0
    return _ended(outcome.error or "stopped", outcome.bad_input, f"{said}; every frame kept is in {out}")


def guided_acquisition(streams: TrackedStreams, setup: TrackedSetup, out: Path, tolerance_mm: float,
                       settings: GuideSettings = GuideSettings()) -> tuple[SessionWriter, GuidedAcquisition]:
    """A new guided calibration session at ``out`` and its acquisition (``settings`` at the
    ``tolerance_mm`` given): the first frame gives the image's size; the phantom's pose is solved
    unless registered. Frames too small to guide are refused before the session is made."""
    if setup.phantom is None:
        raise InputError(None, "guided acquisition needs the phantom")
    first = streams.source.latest(FIRST_FRAME_S)
    size = (first.image.shape[1], first.image.shape[0])
    spacing = setup.spacing_mm or first.pixel_spacing_mm
    if spacing is None:
        raise InputError(None, "the scanner's pixel spacing is not known: give --spacing")
    guide = guide_setup(setup.phantom, frames_probe(size, spacing, setup.start_depth_mm or 0.0))
    settings = replace(settings, tolerance_mm=tolerance_mm, solve_phantom_pose=setup.phantom_to_base is None)
    try:
        first_targets(guide, settings)
    except InputError as exc:
        raise InputError(None, f"{streams.source.name}: {exc.problem}") from None
    writer = SessionWriter(out, tracked_manifest(streams.tracker, streams.source, "calibration", setup, first),
                           setup.phantom)
    acquisition = GuidedAcquisition(writer, guide, Segmenter.create(setup.phantom, spacing),
                                    FramePairer(streams.tracker), settings)
    return writer, acquisition


def _summary(acquisition: GuidedAcquisition) -> str:
    latency = "not measured" if acquisition.latency is None else f"{acquisition.latency.image_latency_s * 1000:.0f} ms"
    bound = "not measured" if acquisition.bound_mm is None else f"{acquisition.bound_mm:.2f} mm"
    return (f"{len(acquisition.writer)} frames recorded ({acquisition.kept} held still), image latency {latency}, "
            f"{int(acquisition.coverage.reached.sum())} targets reached, corner bound {bound} "
            f"(tolerance {acquisition.settings.tolerance_mm:g} mm)")


LOG_EVERY_S = 15.0
"""Off a terminal (a log), the guided acquisition's status is written as a line this often (s)."""


def _status(acquisition: GuidedAcquisition) -> Callable[[GuideStep | str], None]:
    """The acquisition's status on stderr: one line rewritten as frames come on a terminal, a
    line every ``LOG_EVERY_S`` otherwise."""
    logged = [time.monotonic()]

    def show(step: GuideStep | str) -> None:
        text = step if isinstance(step, str) else _summary(acquisition)
        if acquisition.phase != GUIDED_PHASE and not isinstance(step, str):
            text = "move the probe up and down over the wires: " + text
        if sys.stderr.isatty():
            sys.stderr.write("\r\033[K" + text[:150])
        elif time.monotonic() - logged[0] >= LOG_EVERY_S:
            logged[0] = time.monotonic()
            sys.stderr.write(text + "\n")
        sys.stderr.flush()
    return show
