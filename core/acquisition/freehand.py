"""The freehand twin: a person holding the twin's probe over its phantom, tracked by an optical
tracker, as a PLUS server would stream it.

At any time (s, the twin's own clock) it gives the hand's true probe pose, what the tracker
reports of it (ProbeToTracker and ReferenceToTracker: the probe's pose in the reference's frame,
off by the level's tracker noise on every report and by its slow drift, wandering with time), and
the frame the scanner images there, stamped as late as the scanner runs. The twin's ``base`` is
the tracked reference's frame, rigid with the phantom as the twin placed it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
from pyigtl.messages import MessageBase
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.hand import Hand, HandParams, sinusoids
from probecal.core.acquisition.igtl import IMAGE_DEVICE, image_message, transform_message
from probecal.core.acquisition.igtlstreamer import PLUS_MISSING, PLUS_OK, IgtlStreamer
from probecal.core.acquisition.plan import perturbed, pivot_mm
from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.setup import Setup, image_across_wires
from probecal.core.geometry.transforms import make_transform
from probecal.core.twin.levels import Level
from probecal.core.twin.scanner import TwinScanner, twin_scanner
from probecal.core.twin.twin import pose_noise

DRIFT_PERIOD_S = 15.0
"""The tracker drift's slowest period: the length of PLUS's tracked calibration recordings (7.5 to
15 s; the twin's recordings drift through one period each)."""
PROBE_DEVICE, REFERENCE_DEVICE = "ProbeToTracker", "ReferenceToTracker"
"""The devices the twin's tracker sends, as a PLUS server names them."""
REFERENCE_TO_TRACKER = make_transform(Rotation.from_euler("xyz", [160.0, 10.0, -20.0], degrees=True).as_matrix(),
                                      [40.0, -60.0, -900.0])
"""Where the reference sits in the tracker's frame: about a metre in front of the camera."""


def _drift(rng: np.random.Generator, rms: np.ndarray) -> Callable[[float], np.ndarray]:
    """A smooth error (6,: mm, deg) of time: per axis three sinusoids of ``DRIFT_PERIOD_S`` and
    its second and third harmonics, amplitudes 1, 1/2, 1/3 times a normal draw, scaled to ``rms``."""
    harmonics = np.arange(1, 4)[:, None]
    amps = rng.normal(size=(3, len(rms))) / harmonics
    phases = rng.uniform(0, 2 * np.pi, size=(3, len(rms)))
    return sinusoids(np.broadcast_to(harmonics / DRIFT_PERIOD_S, amps.shape), phases, amps, rms)


@dataclass(frozen=True)
class TrackerReport:
    """The tracker's reports at ``t`` (s, the twin's clock): ProbeToTracker, ReferenceToTracker (4x4 mm)."""

    t: float
    probe_to_tracker: np.ndarray
    reference_to_tracker: np.ndarray


@dataclass(frozen=True)
class ScannerFrame:
    """A frame stamped ``stamp`` (s, the twin's clock), imaged at ``offsets`` (the truth)."""

    stamp: float
    image: np.ndarray
    offsets: np.ndarray


@dataclass
class FreehandTwin:
    """The twin of ``seed`` at noise level ``noise``, held by a hand (see the module's docstring)."""

    seed: int = 0
    noise: str | Level = "bench"
    phantom: Phantom | None = None
    hand_params: HandParams = HandParams()
    scanner: TwinScanner = field(init=False)
    setup: Setup = field(init=False)  # the truth: phantom, probe, calibration, centre pose
    hand: Hand = field(init=False)

    def __post_init__(self) -> None:
        self.scanner = twin_scanner(self.seed, self.noise, self.phantom)
        twin = self.scanner.twin
        self.setup = Setup(twin.phantom, twin.probe, twin.phantom_to_base, twin.image_to_tool_rigid,
                           image_across_wires(twin.phantom, twin.probe))
        self.hand = Hand(np.zeros(6), self.hand_params, self.seed)
        errors = self.scanner.level.setup
        self._noise = np.random.default_rng([self.seed, 18])
        self._frames = np.random.default_rng([self.seed, 1])
        mm, deg = errors.tracker_drift
        self._drift = _drift(np.random.default_rng([self.seed, 20]), np.array([mm] * 3 + [deg] * 3))

    def true_pose(self, offsets: np.ndarray) -> np.ndarray:
        """The probe's true pose (``tool_to_base``, mm) at plan offsets from the centre pose."""
        image_to_phantom = perturbed(self.setup.image_to_phantom, pivot_mm(self.setup), offsets)
        return self.setup.tool_to_base(image_to_phantom)

    def tracked(self, t: float, tool_to_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the tracker reports at ``t`` of a probe at ``tool_to_base``: (ProbeToTracker,
        ReferenceToTracker), 4x4 mm."""
        mm, deg = self.scanner.level.setup.tracker_noise
        wander = self._drift(t)
        drift = make_transform(Rotation.from_rotvec(np.radians(wander[3:])).as_matrix(), wander[:3])
        seen = tool_to_base @ drift @ pose_noise(self._noise, mm, deg)
        return REFERENCE_TO_TRACKER @ seen, REFERENCE_TO_TRACKER.copy()

    def frame(self, tool_to_base: np.ndarray) -> tuple[np.ndarray, float]:
        """The scanner's frame at a true probe pose and how late it is stamped (s)."""
        image, _ = self.scanner.calibration_frame(tool_to_base, self._frames)
        return image, self.scanner.image_delay_s(self._frames)

    def truth(self) -> dict:
        """The twin's truth (``truth.json``): its calibration, spacing and phantom pose."""
        return self.scanner.twin.truth()


    def events(self, target: Callable[[float], np.ndarray | None], frame_hz: float = 10.0,
               tracker_hz: float = 50.0) -> Iterator[TrackerReport | ScannerFrame]:
        """The tracker's reports and the scanner's frames in the order of their times, for ever:
        the hand told ``target(t)`` (plan offsets, None: hold) at every report. A frame comes
        once its stamp is due, so it follows the reports of the poses it must be paired with."""
        every = max(1, round(tracker_hz / frame_hz))
        due: list[ScannerFrame] = []
        k = 0
        while True:
            t = k / tracker_hz
            offsets = self.hand.at(t, target(t))
            pose = self.true_pose(offsets)
            yield TrackerReport(t, *self.tracked(t, pose))
            if k % every == 0:
                image, delay = self.frame(pose)
                due.append(ScannerFrame(t + delay, image, offsets))
                due.sort(key=lambda f: f.stamp)
            while due and due[0].stamp <= t:
                yield due.pop(0)
            k += 1


STROKE_MM = 5.0
"""While the latency is measured the person moves the probe up and down this far either side of
the centre (mm, in depth), a stroke every ``STROKE_S``."""
STROKE_S = 1.2


LOST_S = 1.0
"""A person who has seen no reading of the probe for this long (s) stops correcting their aim by
the readings (the wires are out of view): they reach for the target as they judge it."""


class Person:
    """What the person holding the probe does with the console's guidance.

    ``guide(offsets)`` is the console: the target (plan offsets) it shows for a probe it reads at
    ``offsets`` (None before it has read one), or None while it asks for the up-and-down strokes
    that measure the latency. The person reads where the probe is from the console, which places
    it by its dots; told by :meth:`seen` how that reading compares with where the probe truly is,
    they aim off by the difference (the median over the last frames, so that a reading the
    console gets wrong now and then does not throw them)."""

    def __init__(self, guide: Callable[[np.ndarray | None], np.ndarray | None]):
        self.guide = guide
        self.offsets: np.ndarray | None = None  # the console's newest reading
        self._misread: list[np.ndarray] = []  # true minus read offsets of the last frames
        self._read_at: float | None = None  # the newest reading's time (s)
        self._t = 0.0

    def seen(self, read: np.ndarray, true: np.ndarray | None = None) -> None:
        """The console read a frame at ``read`` offsets; ``true``: where it truly was, when known."""
        self.offsets, self._read_at = read, self._t
        if true is not None:
            self._misread = [*self._misread[-19:], true - read]

    def __call__(self, t: float) -> np.ndarray:
        """Where the person means the probe to go at ``t`` (s)."""
        self._t = t
        goal = self.guide(self.offsets)
        if goal is None:
            return np.array([0.0, 0.0, STROKE_MM if int(t / STROKE_S) % 2 else -STROKE_MM, 0.0, 0.0, 0.0])
        if self._read_at is not None and t - self._read_at > LOST_S:
            self._misread = []
        return goal + (np.median(self._misread, axis=0) if self._misread else 0.0)


TRACKER_FAULTS = ("missing", "silent")
"""How the twin's tracker can fail: the probe's marker out of view (its TRANSFORM marked MISSING),
or no TRANSFORM at all."""


def twin_batches(twin: FreehandTwin, person: Person, start: float, frame_hz: float = 10.0,
                 fault: Callable[[], str | None] = lambda: None) -> Iterator[tuple[float, list[MessageBase]]]:
    """The freehand twin as a PLUS server streams it (:meth:`IgtlStreamer.play_batches`): every
    tracker report as ProbeToTracker and ReferenceToTracker, every frame as an IMAGE, stamped
    ``start`` plus the twin's time (s, this machine's clock) and due at the twin's time; the
    tracker failing as ``fault()`` says at each report (:data:`TRACKER_FAULTS`, None: it works)."""
    for event in twin.events(person, frame_hz):
        if isinstance(event, TrackerReport):
            stamp, failing = start + event.t, fault()
            if failing == "silent":
                continue
            status = PLUS_MISSING if failing == "missing" else PLUS_OK
            yield event.t, [transform_message(event.probe_to_tracker, stamp, PROBE_DEVICE, status),
                            transform_message(event.reference_to_tracker, stamp, REFERENCE_DEVICE, PLUS_OK)]
        else:
            yield event.stamp, [image_message(event.image, np.eye(4), start + event.stamp, IMAGE_DEVICE)]


class FreehandServer:
    """The freehand twin streamed by the PLUS-server stand-in on loopback, the hand following
    ``guide`` (see :class:`Person`): what ``--tracker sim`` connects to. Its tracker and images
    are read from ``port`` like any PLUS server's."""

    def __init__(self, guide: Callable[[np.ndarray | None], np.ndarray | None], seed: int = 0,
                 noise: str | Level = "bench", frame_hz: float = 10.0, clients: int = 2):
        self.twin = FreehandTwin(seed, noise)
        self.person = Person(guide)
        self.fault: str | None = None  # one of TRACKER_FAULTS while the tracker fails
        self._streamer = IgtlStreamer()
        self._streamer.play_batches(twin_batches(self.twin, self.person, time.time(), frame_hz, lambda: self.fault),
                                    wait_for_client_s=60.0, clients=clients)

    @property
    def port(self) -> int:
        return self._streamer.port

    def stall(self) -> None:
        """The tracker and the scanner fall silent (connections stay open)."""
        self._streamer.stall()

    def resume(self) -> None:
        self._streamer.resume()

    def close(self) -> None:
        self._streamer.kill()
