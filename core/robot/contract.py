"""What every robot backend promises (design §4, §7): linear moves of the flange pose
``tool_to_base`` (4x4, mm; joints in rad), a stop that is always live, and a pose stream stamped
by the controller's own clock (``poses_since``) for pairing frames with poses. A backend converts
its controller's units (ur_rtde: metres and rotation vectors) once, at its boundary."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from probecal.core.errors import DeviceError
from probecal.core.geometry.transforms import make_transform
from probecal.core.robot.posestream import PoseSamples
from probecal.core.robot.ur3 import ArmModel, MotionLimits, closest_ik

HOME_TOOL_TO_BASE = make_transform(np.diag([-1.0, 1.0, -1.0]), [0.0, -300.0, 250.0])
"""Home flange pose: 300 mm in front of the base (-y), 250 mm up, tool z pointing down (-base z)."""
HOME_JOINTS = closest_ik(HOME_TOOL_TO_BASE, np.radians([90.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
"""Joints (rad) of ``HOME_TOOL_TO_BASE`` in the usual elbow-up, wrist-down configuration,
about (68.0, -92.5, 109.8, -107.3, -90.0, -22.0) degrees."""
HISTORY_S = 30.0
"""How far back (s) a robot's pose stream can be read."""


class RobotError(DeviceError):
    """The robot cannot do what was asked: not connected, already moving, move stopped or faulted."""


@runtime_checkable
class PoseSource(Protocol):
    """Anything that reports where the probe is: a robot, or a tracker with nothing to command.

    Poses are ``tool_to_base`` (4x4, mm): for a robot the flange in its base frame, for a tracker
    the probe's marker in the tracked reference's frame (PLUS's ProbeToReference).
    """

    @property
    def connected(self) -> bool: ...

    def connect(self) -> None: ...

    def disconnect(self) -> None:
        """Stop any motion and close the connection."""

    def tool_to_base(self) -> np.ndarray:
        """The newest measured pose (4x4, mm)."""

    def stop(self) -> None:
        """Halt at once where the robot is. Always safe, also when idle, not connected, or a
        source that moves nothing."""

    def poses_since(self, after: float) -> PoseSamples:
        """The pose stream after ``after`` (s on this machine's clock, ``time.time()``), at most
        the last ``HISTORY_S``: poses stamped by the device's own clock, mapped to this machine's,
        and kept where they arrive, so that a caller who is late loses nothing."""


@runtime_checkable
class Robot(PoseSource, Protocol):
    """A UR-like arm driven by linear tool-space moves (mm, rad, s)."""

    def joints(self) -> np.ndarray:
        """The measured joint angles (6,), rad."""

    def kinematics(self) -> ArmModel | None:
        """The kinematics the controller computes flange poses with (UR's table and its factory
        calibration), as it stated them on connect; None where it states none."""

    def move_linear(
        self,
        target_tool_to_base: np.ndarray,
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """moveL to a flange pose. Raises Unreachable (before any motion) or RobotError.

        A blocking move raises RobotError when it is stopped or faults before reaching the target.
        """

    def move_path(
        self,
        poses: list[np.ndarray],
        limits: MotionLimits | None = None,
        asynchronous: bool = False,
    ) -> None:
        """Move through flange poses without stopping (moveL with blends: straight segments,
        corners rounded, ``core.robot.trajectory``), ending at rest on the last. Raises
        Unreachable (before any motion) or RobotError, as ``move_linear``."""

    def is_moving(self) -> bool: ...

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the current move; False on timeout. Raises RobotError if the move faulted."""
