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

from dataclasses import dataclass, replace
from typing import TypedDict

import numpy as np

from probecal.core.errors import InputError, Remedy
from probecal.core.io.session import MANIFEST, Session
from probecal.core.robot.armkinematics import model_of
from probecal.core.robot.contract import HOME_JOINTS
from probecal.core.robot.ur3 import (
    ARM_TABLES,
    ArmModel,
    DhDeviation,
    Unreachable,
    flange_offset,
    forward_kinematics,
)

ARMS = tuple(ARM_TABLES)
"""Arms whose kinematic table probecal knows (a session's manifest ``arm``)."""
LENGTH_SD_MM = 0.3
ANGLE_SD_RAD = np.radians(0.03)
"""Prior standard deviation of each DH length (d, a) and angle (joint offset, twist): the
tolerance of the twin's ``bench`` arm (``core.twin.levels.BENCH_SETUP``)."""
DEVIATION_SD = np.concatenate([np.full(6, ANGLE_SD_RAD), np.full(12, LENGTH_SD_MM), np.full(6, ANGLE_SD_RAD)])
DEVIATION_NAMES = tuple(f"{name}{joint}" for name in ("θ", "d", "a", "α") for joint in range(1, 7))
"""The deviations in ``DEVIATION_SD``'s order: per joint its zero (θ), d, a and twist (α)."""
UNDETERMINED_SHARE = 0.5
"""A deviation whose prior variance the markers remove less than this share of is reported as
not determined by the poses (:func:`undetermined`)."""
STEP = 1e-3
"""Central-difference step of the poses' derivatives (units of ``DEVIATION_SD``)."""


def deviation(units: np.ndarray) -> DhDeviation:
    """The DH deviation of 24 parameters in units of ``DEVIATION_SD`` (theta, d, a, alpha); for
    parameter sets (..., 24), each of its arrays is (..., 1, 6), one arm per set, to broadcast
    against the joints of every frame."""
    v = np.asarray(units, dtype=float) * DEVIATION_SD
    if v.ndim > 1:
        v = v[..., None, :]
    return DhDeviation(theta=v[..., 0:6], d=v[..., 6:12], a=v[..., 12:18], alpha=v[..., 18:24])


def undetermined(determined: np.ndarray) -> list[str]:
    """The names of the deviations the poses leave undetermined, given the share of each one's
    prior variance the markers remove (``Refined.kinematic_determined``): the fit leaves them
    near the table's values, whatever the real arm's are."""
    return [name for name, share in zip(DEVIATION_NAMES, determined) if share < UNDETERMINED_SHARE]


def with_arm(session: Session, model: str | None) -> Session:
    """``session`` recorded by the arm ``model`` (one of ``ARMS``; None: as its manifest says), for
    a recording that does not name its arm (a lab's own); InputError if it names another."""
    if model is None:
        return session
    named = session.manifest.arm
    if named is not None and named != model:
        raise InputError(session.path, f"recorded by the {named}, not the {model}")
    return replace(session, manifest=replace(session.manifest, arm=model))


def session_arm(session: Session) -> ArmModel | None:
    """The kinematics the controller computed ``session``'s poses with: the table its manifest's
    ``arm`` names, with the controller's calibration when the manifest records it
    (``arm_kinematics``, checked: :func:`core.robot.armkinematics.model_of`); None for an arm
    probecal does not know."""
    named = session.manifest.arm
    table = None if named is None else ARM_TABLES.get(named)
    if table is None:
        return None
    recorded = session.manifest.arm_kinematics
    if recorded is None:
        return ArmModel(table)
    model = model_of(recorded, session.path / MANIFEST)
    if model.table is not table:
        raise InputError(session.path / MANIFEST, f"arm_kinematics describe a {model.table.name}, arm names a {named}")
    return model


class PoseOutOfReach(ValueError):
    """A reported pose the arm cannot take: its ``position`` among the poses given, and why
    (where it lies, and how far out of the arm's reach)."""

    def __init__(self, position: int, problem: str):
        super().__init__(problem)
        self.position, self.problem = position, problem


def arm_joints(tool_to_base: np.ndarray, arm: ArmModel) -> np.ndarray:
    """(F, 6) joint angles (rad) that put the flange of ``arm`` at each reported pose (F, 4, 4),
    each nearest the one before it (from the home configuration). A pose is taken to the
    precision it was written to (its rotation made exactly one: ``ur3.check_pose``);
    PoseOutOfReach for the first that no joints reach."""
    joints, q = [], HOME_JOINTS
    for k, pose in enumerate(tool_to_base):
        try:
            q = arm.closest_ik(pose, q)
        except Unreachable as exc:
            raise PoseOutOfReach(k, str(exc)) from None
        joints.append(q)
    return np.array(joints).reshape(len(tool_to_base), 6)


def out_of_reach(session: Session, frame: int, exc: PoseOutOfReach, arm: ArmModel) -> InputError:
    """The one line that refuses ``session`` for its frame ``frame``'s pose, out of the reach of
    the arm it names (``arm``), and says how to go on."""
    return InputError(session.path, f"frame {frame}: {exc.problem}, so the poses are not the {arm.table.name}'s",
                      (Remedy.ARM,))


def _inverted(transforms: np.ndarray) -> np.ndarray:
    """Rigid transforms (..., 4, 4) inverted."""
    inverse = np.zeros_like(transforms)
    inverse[..., :3, :3] = np.swapaxes(transforms[..., :3, :3], -1, -2)
    inverse[..., :3, 3] = -np.einsum("...ji,...j->...i", transforms[..., :3, :3], transforms[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def arm_poses(q: np.ndarray, dev: DhDeviation, arm: ArmModel) -> np.ndarray:
    """(F, 4, 4) ``tool_to_base`` (mm) at joints ``q`` (F, 6) of an arm off the kinematics its
    controller computes with (``arm``) by the deviations ``dev``: where its flange is, in the tool
    frame the controller reports (the constant part of the error, which the mount carries, left
    out: :func:`core.robot.ur3.flange_offset`); for a batch of deviations (:func:`deviation` of
    parameter sets (..., 24)), (..., F, 4, 4)."""
    base = arm.deviation
    total = dev.plus(base)
    reported_flange = np.eye(4) if base is None else flange_offset(base, arm.table)
    return forward_kinematics(q, total, arm.table) @ _inverted(flange_offset(total, arm.table)) @ reported_flange


@dataclass(frozen=True)
class ArmKinematics:
    """The flange poses of an arm at fixed joints as a function of its DH deviations (24
    parameters in units of ``DEVIATION_SD``), for :func:`core.calibration.jointfit.refine`.

    The poses are linear in the deviations about the table (``nominal`` + ``jacobian`` @ units):
    deviations of a few units move the flange by a few tenths of a millimetre, and what the
    linearisation leaves out is of the order of their square (micrometres), while the poses and
    their derivatives then cost nothing in the fit's iterations."""

    nominal: np.ndarray  # (F, 4, 4) the poses of the table's arm
    jacobian: np.ndarray  # (F, 4, 4, 24) their derivatives by each parameter

    n_params = len(DEVIATION_SD)

    @classmethod
    def at(cls, q: np.ndarray, arm: ArmModel) -> ArmKinematics:
        """``arm`` at joints ``q`` (F, 6): its poses and their central-difference derivatives
        (every perturbed arm at once)."""
        steps = STEP * np.eye(cls.n_params)
        perturbed = arm_poses(q, deviation(np.concatenate([steps, -steps])), arm)  # (48, F, 4, 4)
        jacobian = (perturbed[: cls.n_params] - perturbed[cls.n_params :]) / (2 * STEP)
        return cls(arm_poses(q, deviation(np.zeros(cls.n_params)), arm), np.moveaxis(jacobian, 0, -1))

    def poses(self, units: np.ndarray) -> np.ndarray:
        """(F, 4, 4) ``tool_to_base`` (mm) with the deviations ``units``."""
        return self.nominal + self.jacobian @ np.asarray(units, dtype=float)

    def subset(self, keep: np.ndarray) -> ArmKinematics:
        return ArmKinematics(self.nominal[keep], self.jacobian[keep])


class ArmDeviationJSON(TypedDict):
    """An arm's kinematic deviations as a calibration JSON holds them (``arm``): its model and
    the DH deviations per joint, angles in degrees and lengths in mm."""

    model: str
    theta_deg: list[float]
    d_mm: list[float]
    a_mm: list[float]
    alpha_deg: list[float]


MAX_LENGTH_MM = 10.0
MAX_ANGLE_DEG = 1.0
"""Deviations a calibration file may hold: beyond these it is not an arm that matches its table."""


def deviation_json(model: str, units: np.ndarray) -> ArmDeviationJSON:
    dev = deviation(units)
    return ArmDeviationJSON(model=model, theta_deg=np.degrees(dev.theta).round(6).tolist(),
                            d_mm=dev.d.round(6).tolist(), a_mm=dev.a.round(6).tolist(),
                            alpha_deg=np.degrees(dev.alpha).round(6).tolist())



def arm_deviation(arm: ArmDeviationJSON) -> DhDeviation:
    """The DH deviation a calibration file holds (degrees and mm) in rad and mm."""
    return DhDeviation(theta=np.radians(arm["theta_deg"]), d=np.asarray(arm["d_mm"], dtype=float),
                       a=np.asarray(arm["a_mm"], dtype=float), alpha=np.radians(arm["alpha_deg"]))


def through_arm(session: Session, arm: ArmDeviationJSON | None) -> Session:
    """``session`` with every frame's flange pose where the arm a calibration fitted (``arm``)
    puts it, when the session's manifest names that arm: mm, in that arm's base frame, the one
    the calibration's ``phantom_to_base`` is in. Unchanged when there is no fitted arm, or the
    session names another or none (a tracked recording); InputError naming the first frame whose
    pose is out of the arm's reach."""
    posed = [i for i, r in enumerate(session.records) if r.tool_to_base is not None]
    model = None if arm is None or session.manifest.arm != arm["model"] or not posed else session_arm(session)
    if arm is None or model is None:
        return session
    try:
        joints = arm_joints(np.array([session.records[i].tool_to_base for i in posed]), model)
    except PoseOutOfReach as exc:
        raise out_of_reach(session, posed[exc.position], exc, model) from None
    records = list(session.records)
    for i, pose in zip(posed, arm_poses(joints, arm_deviation(arm), model)):
        records[i] = replace(records[i], tool_to_base=pose)
    return replace(session, records=records)
