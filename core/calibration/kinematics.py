"""The arm's kinematic errors, identified together with the calibration.

A UR controller computes the flange pose from its joint angles with its kinematic table; the
real arm's links differ from that table by fractions of a millimetre and hundredths of a degree,
so the reported flange is off by an error that changes across the workspace (the twin's
``bench`` draws such deviations: ``core.twin.levels``). The phantom measures where the image is
at every pose, so those deviations can be fitted with the calibration where the poses allow it:
the flange is modelled as ``FK(q, deviation) @ inv(flange_offset(deviation))``, the real arm's
forward kinematics seen in the tool frame the controller reports (the constant part of the
error is part of the mount: :func:`core.robot.ur3.flange_offset`), with ``q`` the joint angles
that put the reported flange where it is (UR3 inverse kinematics, nearest the previous pose's).

The 24 standard DH deviations (joint offsets, d, a, twists) are fitted in units of
``DEVIATION_SD``, under a Gaussian prior of one unit: a direction the poses do not determine
stays where the table puts it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from probecal.core.geometry.transforms import invert_transform
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.ur3 import DhDeviation, Unreachable, closest_ik, flange_offset, forward_kinematics

ARMS = ("UR3",)
"""Arms whose kinematic table probecal knows (a session's manifest ``arm``)."""
LENGTH_SD_MM = 0.3
ANGLE_SD_RAD = np.radians(0.03)
"""Prior standard deviation of each DH length (d, a) and angle (joint offset, twist): the
tolerance of the twin's ``bench`` arm (``core.twin.levels.BENCH_SETUP``)."""
DEVIATION_SD = np.concatenate([np.full(6, ANGLE_SD_RAD), np.full(12, LENGTH_SD_MM), np.full(6, ANGLE_SD_RAD)])
STEP = 1e-3
"""Central-difference step of the poses' derivatives (units of ``DEVIATION_SD``)."""


def deviation(units: np.ndarray) -> DhDeviation:
    """The DH deviation of 24 parameters in units of ``DEVIATION_SD`` (theta, d, a, alpha)."""
    v = np.asarray(units, dtype=float) * DEVIATION_SD
    return DhDeviation(theta=v[0:6], d=v[6:12], a=v[12:18], alpha=v[18:24])


def arm_joints(tool_to_base: np.ndarray) -> np.ndarray | None:
    """(F, 6) joint angles (rad) that put a UR3's flange at each reported pose (F, 4, 4), each
    nearest the one before it (from the home configuration); None if a pose is out of reach."""
    joints, q = [], HOME_JOINTS
    try:
        for pose in tool_to_base:
            q = closest_ik(pose, q)
            joints.append(q)
    except Unreachable:
        return None
    return np.array(joints).reshape(len(tool_to_base), 6)


@dataclass(frozen=True)
class ArmKinematics:
    """The flange poses of an arm at joints ``q`` (F, 6) as a function of its DH deviations (24
    parameters in units of ``DEVIATION_SD``), for :func:`core.calibration.handeye.refine`."""

    q: np.ndarray

    n_params = len(DEVIATION_SD)

    def poses(self, units: np.ndarray) -> np.ndarray:
        """(F, 4, 4) ``tool_to_base`` (mm): where the flange is, in the tool frame the controller reports."""
        dev = deviation(units)
        return forward_kinematics(self.q, dev) @ invert_transform(flange_offset(dev))

    def derivatives(self, units: np.ndarray) -> np.ndarray:
        """(F, 4, 4, 24) derivative of :meth:`poses` by each parameter (central differences)."""
        out = np.empty((len(self.q), 4, 4, self.n_params))
        for k in range(self.n_params):
            step = np.zeros(self.n_params)
            step[k] = STEP
            out[..., k] = (self.poses(units + step) - self.poses(units - step)) / (2 * STEP)
        return out

    def subset(self, keep) -> ArmKinematics:
        return ArmKinematics(self.q[keep])

    def deviation(self, units: np.ndarray) -> DhDeviation:
        return deviation(units)
