"""A UR controller's calibrated kinematics (``core.robot.ur3.ArmModel``) as its primary interface
states them (``core.robot.primary.KinematicsInfo``) and as a session records them (the
manifest's ``arm_kinematics``), and the record made back into the model the poses were computed
with. Lengths in mm, angles in rad (degrees in the record).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from probecal.core.errors import InputError
from probecal.core.io.manifest import ControllerKinematics
from probecal.core.robot.primary import KinematicsInfo
from probecal.core.robot.ur3 import ARM_TABLES, ArmModel, DhDeviation, identify_arm

CHECK_JOINTS = np.random.default_rng(55).uniform(-np.pi, np.pi, (32, 6))
"""Joints (rad) across the whole joint space where a recorded model must put the flange within
``core.robot.ur3.ARM_MATCH_MM`` of its table's, as every UR's calibration does."""


def kinematics_info(model: ArmModel) -> KinematicsInfo:
    """What a controller computing with ``model`` states in its KinematicsInfo."""
    return KinematicsInfo(*model.dh())


def model_of_info(info: KinematicsInfo, joints: np.ndarray) -> ArmModel | None:
    """The model of the parameters a controller stated, its table named by where they put the
    flange at ``joints`` (rad); None for an arm probecal does not know."""
    return ArmModel.from_dh(info.theta, info.a, info.d, info.alpha, joints)


def record_of(model: ArmModel) -> ControllerKinematics:
    """The manifest's ``arm_kinematics`` of ``model``; ValueError for deviations beyond what a
    session may record (``core.io.manifest.MAX_DH_LENGTH_MM``)."""
    dev = model.deviation or DhDeviation(*np.zeros((4, 6)))
    return ControllerKinematics(model.table.name, *(tuple(float(v) for v in values) for values in (
        np.degrees(dev.theta), dev.d, dev.a, np.degrees(dev.alpha))))


def model_of(record: ControllerKinematics, source: Path) -> ArmModel:
    """The model a session's ``arm_kinematics`` records; InputError naming ``source`` when it names
    no known table or does not describe an arm of it (:data:`CHECK_JOINTS`)."""
    table = ARM_TABLES.get(record.model)
    if table is None:
        raise InputError(source, f"arm_kinematics.model: {record.model!r} is not an arm probecal knows "
                                 f"({', '.join(ARM_TABLES)})")
    model = ArmModel(table, DhDeviation(theta=np.radians(record.theta_deg), d=np.array(record.d_mm),
                                        a=np.array(record.a_mm), alpha=np.radians(record.alpha_deg)))
    poses = model.forward(CHECK_JOINTS)
    if any(identify_arm(q, pose) is not table for q, pose in zip(CHECK_JOINTS, poses)):
        raise InputError(source, f"arm_kinematics: these deviations do not describe a {table.name}")
    return model
