"""What probecal reads of a UR controller's primary and secondary client interfaces (ports 30001
and 30002, UR's "Client Interfaces" for e-Series 5.x): the Version message it sends on connect
and the KinematicsInfo sub-package of the RobotState messages it streams.

Pure encoding and decoding, no sockets. A package is a big-endian int32 size (the 5-byte header
included) and a uint8 type; a RobotState's sub-packages are framed the same way. KinematicsInfo
holds the controller's absolute DH parameters per joint: a checksum (uint32) each, then joint
offsets theta, lengths a and d, twists alpha (6 doubles each: rad and metres on the wire, mm
here) and a calibration status (uint32).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from probecal.core.robot.rtde import ControllerVersion

HEADER = struct.Struct(">iB")
ROBOT_STATE = 16
ROBOT_MESSAGE = 20
KINEMATICS_INFO = 5
VERSION_MESSAGE = 3
MAX_PACKAGE_BYTES = 1 << 16
"""The largest package a client takes (a controller's RobotState is about 1.5 kB)."""
_KINEMATICS = struct.Struct(">6I24dI")
_MESSAGE_HEADER = struct.Struct(">Qbb")  # timestamp, source, robot message type
_VERSION = struct.Struct(">BBii")  # major, minor, bugfix, build


class PrimaryProtocolError(ValueError):
    """Bytes that are not a valid primary-interface package or sub-package."""


@dataclass(frozen=True)
class KinematicsInfo:
    """A controller's absolute DH parameters per joint (6,): joint offsets ``theta`` and twists
    ``alpha`` (rad), lengths ``a`` and ``d`` (mm); the checksums and calibration status as sent."""

    theta: np.ndarray
    a: np.ndarray
    d: np.ndarray
    alpha: np.ndarray
    checksum: tuple[int, ...] = (0,) * 6
    calibration_status: int = 0

    def encode(self) -> bytes:
        """The KinematicsInfo sub-package, header included."""
        values = [*self.theta, *(self.a / 1000.0), *(self.d / 1000.0), *self.alpha]
        return frame(KINEMATICS_INFO, _KINEMATICS.pack(*self.checksum, *values, self.calibration_status))

    @classmethod
    def decode(cls, payload: bytes) -> KinematicsInfo:
        """From a sub-package's payload, which must be exactly the size it has."""
        if len(payload) != _KINEMATICS.size:
            raise PrimaryProtocolError(f"a KinematicsInfo of {len(payload)} bytes (expected {_KINEMATICS.size})")
        fields = _KINEMATICS.unpack(payload)
        values = np.array(fields[6:30]).reshape(4, 6)
        return cls(values[0], values[1] * 1000.0, values[2] * 1000.0, values[3], tuple(fields[:6]), fields[30])


def frame(package_type: int, payload: bytes) -> bytes:
    """A package (or sub-package): size, type, payload."""
    return HEADER.pack(HEADER.size + len(payload), package_type) + payload


def robot_state(*sub_packages: bytes) -> bytes:
    """A RobotState message of the given sub-packages."""
    return frame(ROBOT_STATE, b"".join(sub_packages))


def version_message(version: ControllerVersion, project: str = "URControl", build_date: str = "") -> bytes:
    """The Version message a controller sends first on connect."""
    name = project.encode()
    body = _MESSAGE_HEADER.pack(0, -1, VERSION_MESSAGE) + struct.pack(">b", len(name)) + name
    body += _VERSION.pack(version.major, version.minor, version.bugfix, version.build) + build_date.encode()
    return frame(ROBOT_MESSAGE, body)


def split_packages(buffer: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """The complete packages (type, payload) at the start of ``buffer`` and the bytes left over;
    PrimaryProtocolError for a size below the header's or above ``MAX_PACKAGE_BYTES``."""
    packages = []
    while len(buffer) >= HEADER.size:
        size, package_type = HEADER.unpack_from(buffer)
        if not HEADER.size <= size <= MAX_PACKAGE_BYTES:
            raise PrimaryProtocolError(f"a package of {size} bytes (from {HEADER.size} to {MAX_PACKAGE_BYTES})")
        if len(buffer) < size:
            break
        packages.append((package_type, buffer[HEADER.size:size]))
        buffer = buffer[size:]
    return packages, buffer


def kinematics_in(robot_state_payload: bytes) -> KinematicsInfo | None:
    """The KinematicsInfo among a RobotState's sub-packages, None if it has none; the others are
    skipped. PrimaryProtocolError when a sub-package's size runs past the message."""
    packages, rest = split_packages(robot_state_payload)
    if rest:
        raise PrimaryProtocolError(f"a RobotState whose sub-packages leave {len(rest)} bytes over")
    found = [payload for kind, payload in packages if kind == KINEMATICS_INFO]
    return KinematicsInfo.decode(found[0]) if found else None
