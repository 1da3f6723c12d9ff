"""A tracked probe's poses over OpenIGTLink, from a PLUS server, 3D Slicer or a robot's own bridge:
a pose source with nothing to command.

The probe's pose is ``tool_to_base`` with the tracked reference as ``base`` (PLUS's
ProbeToReference). It comes either as one TRANSFORM in the reference's frame, or as two in the
tracker's frame, composed as PLUS's transform repository composes them:
``probe_to_reference = inv(reference_to_tracker) @ probe_to_tracker``, the two taken at the same
time. Timestamps are the sender's, mapped to this machine's clock as a robot's are
(:class:`~probecal.core.robot.posestream.ClockSync`), or kept as sent (``device_clock``) when the
frames come from the same server, stamped by the same clock: the two then pair as they were
stamped, as an import of that server's recording pairs them.

A pose the tracker marks invalid (PLUS's TransformStatus other than OK: the marker out of view),
or no pose for ``dropout_s``, *pauses* the stream with a reason, and it goes on when valid poses
come again. What a session's reader would refuse *ends* it, with :class:`BadTrackerData`: a
matrix, or a composed pose, that is not a rigid transform within the bounds every pose is held to
(``core.io.jsonio.MAX_MAGNITUDE``), timestamps that run backwards, more than ``MAX_RATE_HZ`` poses
a second, bytes that are not OpenIGTLink. A lost connection ends it with :class:`TrackerError`.

What the tracker says is quoted short in every message (a device name, a status), and what is
kept of it is bounded: the names of at most ``MAX_NAMES_SEEN`` devices it sends besides the wanted
ones, each wanted device's newest status as quoted.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from probecal.core.acquisition.igtlreader import MessageReader, ReaderStopped, connect_to, message_time, unpacked
from probecal.core.errors import QUOTED_CHARS, DeviceError, quoted
from probecal.core.geometry.transforms import invert_transform
from probecal.core.io.jsonio import MAX_MAGNITUDE
from probecal.core.robot.contract import HISTORY_S
from probecal.core.robot.posestream import ClockSync, PoseBuffer, PoseSamples

POLL_S = 0.02  # socket time-out: how often the reader looks at its stop flag
PAIR_TOLERANCE_S = 0.02  # probe and reference poses further apart in time are not composed
PAIR_WAIT_S = 0.2  # how long a probe pose waits for its reference pose (s of arrival time)
RIGID_TOLERANCE = 1e-3  # most a rotation's columns may stray from orthonormal (OpenIGTLink sends float32)
MAX_RATE_HZ = 1000  # a tracker's poses kept per second of history; more from one device is a flood
MAX_NAMES_SEEN = 64  # other devices' names kept to say what a server sends
NAMES_SAID = 5  # of which a message names at most this many
OK_STATUS = "OK"


class TrackerError(DeviceError):
    """The tracker cannot be used: no connection, no poses, or poses that are not poses."""


class BadTrackerData(TrackerError):
    """The tracker sent what no session may record (see the module's docstring): bad input, as a
    bad file is, where a lost connection is a fault."""


@dataclass(frozen=True)
class TrackerDevices:
    """Which TRANSFORM devices carry the probe's pose: ``probe`` alone, in the reference's frame
    (ProbeToReference), or ``probe`` and ``reference`` both in the tracker's frame
    (ProbeToTracker and ReferenceToTracker, as a PLUS server sends them)."""

    probe: str = "ProbeToTracker"
    reference: str | None = "ReferenceToTracker"

    @property
    def names(self) -> tuple[str, ...]:
        return (self.probe,) if self.reference is None else (self.probe, self.reference)

    def __str__(self) -> str:
        return " and ".join(quoted(n) for n in self.names)


def parse_devices(text: str) -> TrackerDevices:
    """``PROBE`` (in the reference's frame) or ``PROBE,REFERENCE`` (both in the tracker's frame);
    ValueError when it names no device, more than two, or one twice."""
    names = [n.strip() for n in text.split(",")]
    if not 1 <= len(names) <= 2 or not all(names) or len(set(names)) != len(names):
        raise ValueError(f"expected PROBE or PROBE,REFERENCE device names, got {text!r}")
    if any(len(n.encode()) > 20 for n in names):  # an OpenIGTLink header holds 20 bytes of device name
        raise ValueError(f"an OpenIGTLink device name is at most 20 bytes, got {text!r}")
    return TrackerDevices(names[0], names[1] if len(names) == 2 else None)


def probe_to_reference(probe_to_tracker: np.ndarray, reference_to_tracker: np.ndarray) -> np.ndarray:
    """The probe in the reference's frame from both in the tracker's, as PLUS composes them."""
    return invert_transform(reference_to_tracker) @ probe_to_tracker


def rigidity_problem(matrix: np.ndarray) -> str | None:
    """Why a 4x4 (mm) is not a rigid transform a session's readers take, or None when it is one:
    finite, no value past ``MAX_MAGNITUDE``, its rotation orthonormal and its determinant +1 to
    ``RIGID_TOLERANCE``, as ``core.io.session`` checks a record's pose and a pose sample."""
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        return "not a finite 4x4 matrix"
    if np.any(np.abs(matrix) > MAX_MAGNITUDE):
        return f"a value past {MAX_MAGNITUDE:g}"
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        return f"its last row is {np.round(matrix[3], 4).tolist()}, not [0, 0, 0, 1]"
    rotation = matrix[:3, :3]
    lengths = np.linalg.norm(rotation, axis=0)
    determinant = np.linalg.det(rotation)
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > RIGID_TOLERANCE or abs(determinant - 1) > RIGID_TOLERANCE:
        return (f"its rotation is not a rotation (columns {', '.join(f'{v:.4g}' for v in lengths)} long, "
                f"determinant {determinant:.4g})")
    return None


@dataclass
class _Sample:
    device_time: float
    pose: np.ndarray | None  # None: the tracker marked it invalid
    status: str  # as sent when OK, else quoted short
    arrived: float  # monotonic


class _Composer:
    """Turns the devices' samples into probe-in-reference poses at the probe's times, and says
    why none come (a device marked invalid, a reference that never matches in time)."""

    def __init__(self, devices: TrackerDevices):
        self.devices = devices
        self._pending: deque[_Sample] = deque()
        self._references: deque[_Sample] = deque(maxlen=64)
        self._status: dict[str, str] = {}  # each device's newest status

    @property
    def invalid(self) -> str | None:
        """Why the newest samples make no pose: a device the tracker marks invalid (None: none)."""
        bad = [f"{quoted(device)} {status}" for device, status in self._status.items() if status != OK_STATUS]
        return f"the tracker marks {' and '.join(bad)}" if bad else None

    def add(self, device: str, sample: _Sample) -> list[tuple[float, np.ndarray]]:
        """The poses (device time, probe_to_reference) that ``sample`` completes."""
        self._status[device] = sample.status
        if self.devices.reference is None:
            return [] if sample.pose is None else [(sample.device_time, sample.pose)]
        if device == self.devices.reference:
            self._references.append(sample)
        else:
            self._pending.append(sample)
        return self._release(time.monotonic())

    def _release(self, now: float) -> list[tuple[float, np.ndarray]]:
        out = []
        newest = self._references[-1].device_time if self._references else -np.inf
        while self._pending and (self._pending[0].device_time <= newest
                                 or now - self._pending[0].arrived > PAIR_WAIT_S):
            probe = self._pending.popleft()
            reference = min(self._references, key=lambda r: abs(r.device_time - probe.device_time), default=None)
            if (probe.pose is None or reference is None or reference.pose is None
                    or abs(reference.device_time - probe.device_time) > PAIR_TOLERANCE_S):
                continue
            out.append((probe.device_time, probe_to_reference(probe.pose, reference.pose)))
        return out


class IgtlTracker:
    """Poses of a tracked probe from an OpenIGTLink server (see the module's docstring).

    ``connect`` waits up to ``first_pose_s`` for the first pose and fails, naming the devices the
    server does send, when none comes. ``paused`` says why poses have stopped coming (None while
    they come) and raises the stream's TrackerError once it has ended: a stream that ended does not
    come back. ``failure`` is that error (None while the stream lasts), ``error`` its message.
    """

    def __init__(self, host: str, port: int, devices: TrackerDevices = TrackerDevices(),
                 connect_timeout_s: float = 2.0, first_pose_s: float = 3.0, dropout_s: float = 0.5,
                 device_clock: bool = False):
        self.host, self.port = host, port
        self.device_clock = device_clock
        self.devices = devices
        self.connect_timeout_s = connect_timeout_s
        self.first_pose_s = first_pose_s
        self.dropout_s = dropout_s
        self.name = f"tracker igtl:{host}:{port}"
        self._history = PoseBuffer(capacity=int(HISTORY_S * MAX_RATE_HZ))
        self._clock = ClockSync()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._first = threading.Event()
        self._seen: set[str] = set()  # TRANSFORM device names the server sent (bounded: ``_note_name``)
        self._arrivals: dict[str, deque[float]] = {}  # each wanted device's new poses in the last second
        self._last_arrival = 0.0  # monotonic time of the newest wanted message
        self._invalid: str | None = None
        self._newest_pose: np.ndarray | None = None
        self.failure: TrackerError | None = None

    @property
    def error(self) -> str | None:
        """Why the stream ended (None while it lasts)."""
        return None if self.failure is None else str(self.failure)

    @property
    def connected(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def connect(self) -> None:
        """Connect and wait for the first pose; TrackerError when none comes."""
        if self.connected:
            return
        self.failure = None
        sock = connect_to(self.host, self.port, self.connect_timeout_s, POLL_S, self.name, TrackerError)
        self._stop = threading.Event()
        self._first.clear()
        self._thread = threading.Thread(target=self._run, args=(sock, self._stop), name=self.name, daemon=True)
        self._thread.start()
        deadline = time.monotonic() + self.first_pose_s
        while not self._first.wait(POLL_S):
            if self.failure is not None or time.monotonic() > deadline:
                self.disconnect()
                raise self.failure or TrackerError(self._silence())

    def _silence(self) -> str:
        """Why no pose came within ``first_pose_s``, naming what the server does send."""
        others = sorted(self._seen - set(self.devices.names))
        missing = [n for n in self.devices.names if n not in self._seen]
        sent = ", ".join(map(quoted, others[:NAMES_SAID]))
        if len(others) > NAMES_SAID:
            sent += f" and {'at least ' if len(self._seen) >= MAX_NAMES_SEEN else ''}{len(others) - NAMES_SAID} more"
        if missing and others:
            return (f"{self.name}: no TRANSFORM {' or '.join(map(quoted, missing))} within {self.first_pose_s:g} s; "
                    f"the server sends {sent}")
        if missing:
            return f"{self.name}: no TRANSFORM {' or '.join(map(quoted, missing))} within {self.first_pose_s:g} s"
        return f"{self.name}: no valid pose within {self.first_pose_s:g} s ({self._invalid or 'never in time'})"

    def disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._thread = None

    def stop(self) -> None:
        """Nothing to halt: a tracker moves nothing."""

    @property
    def paused(self) -> str | None:
        """Why no poses are coming now, or None while they come; the stream's TrackerError once it
        has ended (BadTrackerData when the tracker sent what no session may record)."""
        if self.failure is not None:
            raise self.failure
        if self._invalid is not None:
            return f"{self.name}: {self._invalid}"
        quiet = time.monotonic() - self._last_arrival
        if self._first.is_set() and quiet > self.dropout_s:
            return f"{self.name}: no pose for {quiet:.1f} s"
        return None

    def tool_to_base(self) -> np.ndarray:
        """The newest pose (4x4 mm, probe in the reference's frame); TrackerError before any."""
        if self._newest_pose is None:
            raise TrackerError(f"{self.name}: no pose yet")
        return self._newest_pose.copy()

    def poses_since(self, after: float) -> PoseSamples:
        """The poses after ``after`` (s, this machine's clock; the sender's with ``device_clock``)."""
        offset = 0.0 if self.device_clock else self._clock.offset
        return PoseSamples.empty() if offset is None else self._history.since(after, offset)

    def _run(self, sock: socket.socket, stop: threading.Event) -> None:
        reader = MessageReader(sock, self.name, stop, BadTrackerData, lost=TrackerError)
        composer = _Composer(self.devices)
        newest: dict[str, float] = {}
        try:
            while not stop.is_set():
                message = reader.read()
                if message is not None and message[0]["message_type"] == "TRANSFORM":
                    self._take(*message, composer, newest)
        except ReaderStopped:
            pass
        except TrackerError as exc:
            self.failure = exc
        finally:
            sock.close()

    def _take(self, fields: dict, body: bytearray, composer: _Composer, newest: dict[str, float]) -> None:
        device = fields["device_name"]
        self._note_name(device)
        if device not in self.devices.names:
            return
        device_time = message_time(fields)
        if device_time < newest.get(device, -np.inf):
            raise BadTrackerData(f"{self.name}: timestamps run backwards: TRANSFORM {quoted(device)} stamped "
                                 f"{device_time:.3f} s after {newest[device]:.3f} s")
        if device_time == newest.get(device):
            return  # the same pose sent again
        newest[device] = device_time
        self._last_arrival = time.monotonic()
        self._check_rate(device, self._last_arrival)
        self._clock.observe(device_time, time.time())
        message = unpacked(fields, body, self.name, BadTrackerData)
        status = str(message.metadata.get("TransformStatus", OK_STATUS)).strip() or OK_STATUS
        pose = np.asarray(message.matrix, dtype=float) if status == OK_STATUS else None
        if pose is not None and (problem := rigidity_problem(pose)) is not None:
            raise BadTrackerData(f"{self.name}: TRANSFORM {quoted(device)} is not a rigid pose: {problem}")
        said = status if len(status) <= QUOTED_CHARS and status.isprintable() else quoted(status)  # kept short
        for device_time_ok, probe_to_reference in composer.add(device, _Sample(device_time, pose, said,
                                                                                 self._last_arrival)):
            if (problem := rigidity_problem(probe_to_reference)) is not None:
                raise BadTrackerData(f"{self.name}: TRANSFORMs {self.devices} compose to a pose no session may "
                                     f"hold: {problem}")
            self._history.add(probe_to_reference, device_time_ok)
            self._newest_pose = probe_to_reference
            self._first.set()
        self._invalid = composer.invalid

    def _note_name(self, device: str) -> None:
        """Keep a device's name to say what the server sends: the wanted ones always, at most
        ``MAX_NAMES_SEEN`` others (a server may send a new name with every message)."""
        if len(self._seen) < MAX_NAMES_SEEN or device in self.devices.names:
            self._seen.add(device)

    def _check_rate(self, device: str, now: float) -> None:
        """BadTrackerData when ``device`` sent more than ``MAX_RATE_HZ`` new poses in the last
        second (``now``, monotonic s): more than any tracker sends, and more than is kept."""
        arrivals = self._arrivals.setdefault(device, deque())
        arrivals.append(now)
        while arrivals[0] < now - 1.0:
            arrivals.popleft()
        if len(arrivals) > MAX_RATE_HZ:
            raise BadTrackerData(f"{self.name}: flooded: more than {MAX_RATE_HZ} poses of TRANSFORM {quoted(device)} "
                                 "in a second, more than any tracker sends")


class PoseFeed:
    """A pose source its producer pushes poses into (a simulation run faster than real time, a
    test): ``push`` a pose (4x4 mm) at a time (s), already on this machine's clock."""

    name = "pose feed"
    connected = True

    def __init__(self) -> None:
        self._history = PoseBuffer(capacity=int(HISTORY_S * MAX_RATE_HZ))

    def push(self, tool_to_base: np.ndarray, timestamp: float) -> None:
        self._history.add(tool_to_base, timestamp)

    def connect(self) -> None:
        """Always connected."""

    def disconnect(self) -> None:
        """Nothing to close."""

    def stop(self) -> None:
        """Nothing to halt."""

    def tool_to_base(self) -> np.ndarray:
        newest = self._history.newest
        if newest is None:
            raise TrackerError(f"{self.name}: no pose yet")
        pose, _ = self._history.pose_at(newest)
        assert pose is not None
        return pose

    def poses_since(self, after: float) -> PoseSamples:
        return self._history.since(after)
