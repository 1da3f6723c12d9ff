"""Universal Robots' RTDE wire protocol (version 2): packages, recipes and variable types.

Pure encoding and decoding, no sockets. A package is a 3-byte header (big-endian uint16 size
including the header, uint8 type) and a payload; all numbers are big-endian. Poses on the wire
are UR's [x, y, z, rx, ry, rz] (metres, rotation vector in rad); ``ur_from_pose`` and
``pose_from_ur`` convert them to and from our 4x4 poses in mm.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from probecal.core.geometry.transforms import pose_from_xyz_rotvec, xyz_rotvec_from_pose

PROTOCOL_VERSION = 2
HEADER = struct.Struct(">HB")
NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"
REGISTER_COUNT = 48
"""Int and double registers 0..47 in each direction (24..47 is the upper range, PolyScope 5.3+)."""


class PackageType(IntEnum):
    """The package types of RTDE protocol version 2 (their ASCII letters)."""

    REQUEST_PROTOCOL_VERSION = ord("V")
    GET_URCONTROL_VERSION = ord("v")
    TEXT_MESSAGE = ord("M")
    DATA_PACKAGE = ord("U")
    CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
    CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
    CONTROL_PACKAGE_START = ord("S")
    CONTROL_PACKAGE_PAUSE = ord("P")


class RTDEProtocolError(ValueError):
    """Bytes that are not a valid RTDE package or payload."""


TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
"""struct format of each RTDE data type."""

_OUTPUTS_BY_TYPE = {
    "DOUBLE": (
        "timestamp", "actual_execution_time", "speed_scaling", "target_speed_fraction",
        "actual_momentum", "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
        "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
        "standard_analog_output1", "io_current", "tool_analog_input0", "tool_analog_input1",
        "tool_output_current", "tool_temperature", "tcp_force_scalar", "payload",
    ),
    "VECTOR6D": (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
        "actual_qd", "actual_qdd", "actual_current", "actual_current_window",
        "actual_current_as_torque", "joint_control_output", "actual_TCP_pose", "actual_TCP_speed",
        "actual_TCP_force", "target_TCP_pose", "target_TCP_speed", "joint_temperatures",
        "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
    ),
    "VECTOR3D": ("actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog"),
    "VECTOR6INT32": ("joint_mode",),
    "INT32": ("robot_mode", "safety_mode", "safety_status", "tool_mode", "tool_output_voltage"),
    "UINT32": (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "tool_analog_input_types", "script_control_line", "output_bit_registers0_to_31",
        "output_bit_registers32_to_63",
    ),
    "UINT64": ("actual_digital_input_bits", "actual_digital_output_bits"),
    "UINT8": ("tool_output_mode", "tool_digital_output0_mode", "tool_digital_output1_mode"),
}

_INPUTS_BY_TYPE = {
    "UINT8": (
        "standard_digital_output_mask", "standard_digital_output",
        "configurable_digital_output_mask", "configurable_digital_output",
        "tool_digital_output_mask", "tool_digital_output", "standard_analog_output_mask",
        "standard_analog_output_type",
    ),
    "UINT32": ("speed_slider_mask", "input_bit_registers0_to_31", "input_bit_registers32_to_63"),
    "DOUBLE": ("speed_slider_fraction", "standard_analog_output_0", "standard_analog_output_1"),
    "VECTOR6D": ("external_force_torque",),
}


def _registers(direction: str) -> dict[str, str]:
    """The int, double and single-bit registers of one direction ("input" or "output")."""
    table = {f"{direction}_int_register_{i}": "INT32" for i in range(REGISTER_COUNT)}
    table.update({f"{direction}_double_register_{i}": "DOUBLE" for i in range(REGISTER_COUNT)})
    table.update({f"{direction}_bit_register_{i}": "BOOL" for i in range(64, 128)})
    return table


def _by_name(groups: Mapping[str, tuple[str, ...]]) -> dict[str, str]:
    return {name: data_type for data_type, names in groups.items() for name in names}


INPUT_VARIABLES: dict[str, str] = {**_by_name(_INPUTS_BY_TYPE), **_registers("input")}
"""Variables a client may write (input recipes) -> RTDE data type."""

OUTPUT_VARIABLES: dict[str, str] = {
    **_by_name(_OUTPUTS_BY_TYPE),
    **_registers("output"),
    **INPUT_VARIABLES,
}
"""Variables a client may read (output recipes) -> RTDE data type; inputs can be read back."""


def default_value(data_type: str) -> Any:  # bool, int, float or a tuple, as data_type says
    """Zero of an RTDE data type: a number, False or a tuple for vectors."""
    fmt = TYPE_FORMATS[data_type]
    zero = False if fmt == "?" else 0.0 if fmt[-1] == "d" else 0
    return tuple([zero] * int(fmt[:-1])) if len(fmt) > 1 else zero


def encode_package(package_type: int, payload: bytes = b"") -> bytes:
    """Header plus payload."""
    size = HEADER.size + len(payload)
    if size > 0xFFFF:
        raise RTDEProtocolError(f"payload of {len(payload)} bytes does not fit one package")
    return HEADER.pack(size, package_type) + payload


def decode_header(header: bytes) -> tuple[int, int]:
    """(size including the header, type) of a 3-byte header; raises on an impossible size."""
    size, package_type = HEADER.unpack(header)
    if size < HEADER.size:
        raise RTDEProtocolError(
            f"package size {size} is smaller than its {HEADER.size}-byte header"
        )
    return size, package_type


def split_packages(buffer: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """The complete packages (type, payload) at the start of ``buffer`` and the bytes left over."""
    packages = []
    offset = 0
    while len(buffer) - offset >= HEADER.size:
        size, package_type = decode_header(buffer[offset : offset + HEADER.size])
        if len(buffer) - offset < size:
            break
        packages.append((package_type, bytes(buffer[offset + HEADER.size : offset + size])))
        offset += size
    return packages, bytes(buffer[offset:])


def _unpack(fmt: str, payload: bytes, what: str) -> tuple:
    try:
        return struct.unpack(fmt, payload)
    except struct.error as exc:
        raise RTDEProtocolError(f"malformed {what} payload ({len(payload)} bytes)") from exc


def encode_protocol_request(version: int = PROTOCOL_VERSION) -> bytes:
    """Payload of a 'V' request: the protocol version the client speaks."""
    return struct.pack(">H", version)


def decode_protocol_request(payload: bytes) -> int:
    return _unpack(">H", payload, "protocol version request")[0]


def encode_accepted(accepted: bool) -> bytes:
    """Payload of the one-byte replies to 'V', 'S' and 'P'."""
    return struct.pack(">B", int(accepted))


def decode_accepted(payload: bytes) -> bool:
    return bool(_unpack(">B", payload, "accepted reply")[0])


@dataclass(frozen=True)
class ControllerVersion:
    """The URControl version a 'v' request returns (e.g. 5.11.11.123456)."""

    major: int
    minor: int
    bugfix: int
    build: int

    def encode(self) -> bytes:
        return struct.pack(">4I", self.major, self.minor, self.bugfix, self.build)

    @classmethod
    def decode(cls, payload: bytes) -> ControllerVersion:
        return cls(*_unpack(">4I", payload, "controller version"))

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.bugfix}.{self.build}"


@dataclass(frozen=True)
class TextMessage:
    """An 'M' package: a message, its source and a warning level (0 exception .. 3 info)."""

    message: str
    source: str = "URSim"
    level: int = 3

    def encode(self) -> bytes:
        message, source = self.message.encode()[:255], self.source.encode()[:255]
        return (
            struct.pack(">B", len(message)) + message + struct.pack(">B", len(source)) + source
            + struct.pack(">B", self.level)
        )

    @classmethod
    def decode(cls, payload: bytes) -> TextMessage:
        try:
            n = payload[0]
            message = payload[1 : 1 + n]
            m = payload[1 + n]
            source = payload[2 + n : 2 + n + m]
            level = payload[2 + n + m]
        except IndexError as exc:
            raise RTDEProtocolError("malformed text message payload") from exc
        return cls(message.decode(errors="replace"), source.decode(errors="replace"), level)


def _names(text: bytes) -> list[str]:
    return [name for name in text.decode(errors="replace").split(",") if name]


def encode_output_setup(frequency_hz: float, names: Iterable[str]) -> bytes:
    """Payload of an 'O' request: update frequency (Hz) and comma-separated variable names."""
    return struct.pack(">d", frequency_hz) + ",".join(names).encode()


def decode_output_setup(payload: bytes) -> tuple[float, list[str]]:
    frequency = _unpack(">d", payload[:8], "output setup")[0]
    return frequency, _names(payload[8:])


def encode_input_setup(names: Iterable[str]) -> bytes:
    """Payload of an 'I' request: comma-separated variable names."""
    return ",".join(names).encode()


def decode_input_setup(payload: bytes) -> list[str]:
    return _names(payload)


def encode_setup_reply(recipe_id: int, types: Iterable[str]) -> bytes:
    """Payload of the reply to 'O' and 'I': recipe id and the comma-separated variable types."""
    return struct.pack(">B", recipe_id) + ",".join(types).encode()


def decode_setup_reply(payload: bytes) -> tuple[int, list[str]]:
    if not payload:
        raise RTDEProtocolError("empty recipe setup reply")
    return payload[0], _names(payload[1:])


@dataclass(frozen=True)
class Recipe:
    """An output or input recipe: its id, variable names and their RTDE types.

    A recipe whose variables are all known packs and unpacks data packages ('U').
    """

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    _struct: struct.Struct | None = field(init=False, repr=False, compare=False)
    _sizes: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        valid = bool(self.names) and all(t in TYPE_FORMATS for t in self.types)
        formats = [TYPE_FORMATS[t] for t in self.types] if valid else []
        layout = struct.Struct(">B" + "".join(formats)) if valid else None
        object.__setattr__(self, "_struct", layout)
        object.__setattr__(self, "_sizes", tuple(int(f[:-1]) if len(f) > 1 else 0 for f in formats))

    @property
    def valid(self) -> bool:
        """True when every variable was found (and none is in use by another client)."""
        return self._struct is not None

    def _layout(self) -> struct.Struct:
        if self._struct is None:
            raise RTDEProtocolError(f"recipe {self.recipe_id} has unknown variables: {self.types}")
        return self._struct

    def pack(self, values: Mapping[str, object]) -> bytes:
        """Payload of a data package: recipe id, then each variable's value in order."""
        flat: list = [self.recipe_id]
        for name, size in zip(self.names, self._sizes):
            value = values[name]
            if size:
                if not isinstance(value, Iterable):
                    raise TypeError(f"RTDE variable {name} takes {size} values, got {value!r}")
                flat.extend(value)
            else:
                flat.append(value)
        return self._layout().pack(*flat)

    def unpack(self, payload: bytes) -> dict[str, object]:
        """Variable name -> value of a data package's payload (vectors as tuples)."""
        layout = self._layout()
        if len(payload) != layout.size:
            raise RTDEProtocolError(
                f"data package of {len(payload)} bytes for recipe {self.recipe_id} "
                f"of {layout.size} bytes"
            )
        flat = layout.unpack(payload)
        if flat[0] != self.recipe_id:
            raise RTDEProtocolError(f"data package for recipe {flat[0]}, expected {self.recipe_id}")
        values, i = {}, 1
        for name, size in zip(self.names, self._sizes):
            values[name] = tuple(flat[i : i + size]) if size else flat[i]
            i += size or 1
        return values


def make_recipe(recipe_id: int, names: Sequence[str], table: Mapping[str, str]) -> Recipe:
    """A recipe whose types come from ``table``; unknown names get ``NOT_FOUND``."""
    return Recipe(recipe_id, tuple(names), tuple(table.get(name, NOT_FOUND) for name in names))


def ur_from_pose(a_to_b: np.ndarray) -> list[float]:
    """A 4x4 pose (mm) as UR's [x, y, z, rx, ry, rz] (metres, rotation vector in rad)."""
    xyz_mm, rotvec = xyz_rotvec_from_pose(a_to_b)
    return [*(xyz_mm / 1000.0), *rotvec]


def pose_from_ur(pose: ArrayLike) -> np.ndarray:
    """UR's [x, y, z, rx, ry, rz] (metres, rad) as a 4x4 pose in mm."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,):
        raise ValueError(f"a UR pose has 6 numbers, got shape {pose.shape}")
    return pose_from_xyz_rotvec(pose[:3] * 1000.0, pose[3:])
