"""The digital twin: a UR3 carrying a linear or convex probe over an N-wire phantom or a test object in a
water tank, with exact ground truth (design §4).

Frames: ``base`` is the robot base (z up), ``tool`` the flange, ``image`` the pixel frame, and
``phantom``/``object`` the target's own frame. The true ``image_to_tool_rigid`` and the true
phantom placement differ from the nominal (design) ones by a few mm and degrees, drawn from the
seed, so a calibration has something real to find.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import ConvexProbe, LinearProbe, Probe, in_view
from probecal.core.geometry.setup import Setup, image_across_wires, nominal_image_to_tool, setup_from_centred_pose
from probecal.core.geometry.transforms import invert_transform, make_transform
from probecal.core.io.phantomfile import default_phantom
from probecal.core.robot.ur3 import DhDeviation, flange_offset, forward_kinematics
from probecal.core.twin.levels import SetupErrors, water_sound_speed

# Nominal placement of targets in the base frame: turned half-way about the vertical so that the
# image x axis matches the flange x axis of the robot's home pose, centred below it at (0, -300).
TARGET_ROTATION_IN_BASE = np.diag([-1.0, -1.0, 1.0])
PHANTOM_ORIGIN_IN_BASE_MM = np.array([60.0, -250.0, -80.0])


def random_offset(rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    """A rigid transform up to ``mm`` and ``deg`` off the identity per axis, drawn from ``rng``."""
    return make_transform(
        Rotation.from_euler("xyz", rng.uniform(-deg, deg, 3), degrees=True), rng.uniform(-mm, mm, 3)
    )


def pose_noise(rng: np.random.Generator, mm: float | np.ndarray, deg: float | np.ndarray) -> np.ndarray:
    """A rigid transform off the identity by ``deg`` and ``mm`` (normal, sd per axis, one value or
    one per axis; rotation drawn first), drawn from ``rng``: a tracker's error on one pose, applied
    on the right."""
    rotation = Rotation.from_rotvec(np.radians(rng.normal(0.0, deg, 3)))
    return make_transform(rotation, rng.normal(0.0, mm, 3))


def smooth_offsets(rng: np.random.Generator, n: int, rms: tuple[float, ...] | list[float],
                   cycles: float) -> np.ndarray:
    """(n, len(rms)) values along a smooth path of ``n`` samples, drawn from ``rng``: each column a
    sum of three sinusoids (``cycles``, twice and three times as many periods over the path;
    amplitudes 1, 1/2, 1/3 times a normal draw; random phases), scaled to the RMS ``rms`` (in its
    own units)."""
    along = np.linspace(0.0, 1.0, n)
    offsets = np.zeros((n, len(rms)))
    for axis, target in enumerate(rms):
        for harmonic in (1, 2, 3):
            phase = rng.uniform()
            offsets[:, axis] += rng.normal() / harmonic * np.sin(2 * np.pi * (harmonic * cycles * along + phase))
        offsets[:, axis] *= target / max(offsets[:, axis].std(), 1e-12)
    return offsets


TRACKER_DRIFT_CYCLES = 1.0
"""Periods of a tracker's slow wander over one recording (the slowest of its three sinusoids)."""


def pose_drift(rng: np.random.Generator, n: int, mm: float, deg: float) -> list[np.ndarray]:
    """``n`` rigid transforms wandering smoothly off the identity along a recording
    (:func:`smooth_offsets`, ``TRACKER_DRIFT_CYCLES``; RMS ``mm`` per axis, and ``deg`` about each
    axis as a rotation vector), drawn from ``rng``: a tracker's slow error, applied on the right."""
    offsets = smooth_offsets(rng, n, (mm, mm, mm, deg, deg, deg), TRACKER_DRIFT_CYCLES)
    return [make_transform(Rotation.from_rotvec(np.radians(o[3:])), o[:3]) for o in offsets]


@dataclass(frozen=True)
class Twin:
    """Ground truth of one simulated set-up.

    ``phantom`` is the definition the software knows; ``built_phantom`` the wires as built (None:
    exactly the definition). ``dh_deviation`` makes the arm put its flange elsewhere than it
    reports (None: where it reports): the real arm's deviation from the kinematics its controller
    computes with, UR's table or, with a ``controller`` calibration, the table off by that (a
    factory-calibrated UR: ``core.robot.ursim.arm_calibration``). ``image_to_flange_rigid`` is the
    mount on the real flange; the true calibration ``image_to_tool_rigid`` adds the constant part of the arm's error
    (``flange_to_tool``), as the controller's tool frame sees it. Image timestamps run
    ``image_latency_s`` late, with ``timestamp_jitter_s`` of jitter (s). ``water_temperature_c``
    set the probe's medium speed.
    """

    phantom: Phantom
    probe: Probe
    phantom_to_base: np.ndarray
    image_to_flange_rigid: np.ndarray
    nominal: Setup
    built_phantom: Phantom | None = None
    dh_deviation: DhDeviation | None = None
    controller: DhDeviation | None = None
    image_latency_s: float = 0.0
    timestamp_jitter_s: float = 0.0
    water_temperature_c: float | None = None

    @property
    def pixel_spacing_mm(self) -> tuple[float, float]:
        """The true spacing (mm/px): a fan image's square nominal pixels once its beams are
        stretched (:meth:`truth`'s ``fan`` and ``stretch``)."""
        return self.probe.true_spacing_mm if self.probe.fan is None else self.probe.nominal_spacing_mm

    @property
    def wires(self) -> Phantom:
        """The phantom as built: what the images show."""
        return self.built_phantom or self.phantom

    @property
    def flange_to_tool(self) -> np.ndarray:
        """The constant part of the arm's flange error (``core.robot.ur3.flange_offset``); identity for
        an arm that moves as its table says. ``image_to_tool_rigid`` includes it: it is the true
        calibration in the tool frame the controller reports."""
        if self.dh_deviation is None:
            return np.eye(4)
        reported = np.eye(4) if self.controller is None else flange_offset(self.controller)
        return invert_transform(reported) @ flange_offset(self.dh_deviation.plus(self.controller))

    @property
    def image_to_tool_rigid(self) -> np.ndarray:
        """The true calibration (mm): the mount seen from the tool frame the controller reports."""
        return self.flange_to_tool @ self.image_to_flange_rigid

    def actual_tool_to_base(self, reported_tool_to_base: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Where the tool frame is (mm) when the controller reports ``reported_tool_to_base`` at
        ``joints`` (rad): the real arm's kinematics applied to the reported pose, less the
        constant part of that error, which ``image_to_tool_rigid`` carries."""
        if self.dh_deviation is None:
            return reported_tool_to_base
        correction = (invert_transform(forward_kinematics(joints, self.controller))
                      @ forward_kinematics(joints, self.dh_deviation.plus(self.controller)))
        return reported_tool_to_base @ correction @ invert_transform(self.flange_to_tool)

    @property
    def image_to_tool(self) -> np.ndarray:
        """PLUS-style ``image_to_tool`` including the pixel spacing (design §2)."""
        return self.image_to_tool_rigid @ self.probe.scale_matrix()

    def image_to_phantom(self, tool_to_base: np.ndarray) -> np.ndarray:
        return invert_transform(self.phantom_to_base) @ tool_to_base @ self.image_to_tool_rigid

    def markers_px(self, tool_to_base: np.ndarray) -> np.ndarray:
        """(W, 2) true pixel positions of every wire crossing, phantom wire order; NaN where a
        wire does not cross the plane or crosses it out of view."""
        out = np.full((self.phantom.n_wires, 2), np.nan)
        for c in self.wires.crossings(self.image_to_phantom(tool_to_base)):
            pixel = self.probe.pixels_from_mm(c.point_image)
            if in_view(self.probe, pixel):
                out[c.index] = pixel
        return out

    def along_wires_mm(self, tool_to_base: np.ndarray) -> np.ndarray:
        """(W,) where every wire crosses the image plane along the phantom's wires as built, laid
        end to end in wire order (mm from the first wire's front end); NaN where it does not."""
        lines = self.wires.lines()
        lengths = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
        starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        out = np.full(len(lines), np.nan)
        for c in self.wires.crossings(self.image_to_phantom(tool_to_base)):
            out[c.index] = starts[c.index] + c.t * lengths[c.index]
        return out

    def wire_directions(self, tool_to_base: np.ndarray) -> np.ndarray:
        """(W, 3) unit direction of every wire as built, in the image frame, for a flange pose."""
        lines = self.wires.lines()
        d = lines[:, 1] - lines[:, 0]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d @ self.image_to_phantom(tool_to_base)[:3, :3]

    def truth(self) -> dict:
        """The design §2 keys with their true values, and the set-up's errors; for a convex probe,
        its fan and the sound speeds' stretch of its beams (``image_to_tool`` then maps the pixels
        as shown as closely as an affine map can: ``core.calibration.result.Calibration``)."""
        dh = self.dh_deviation
        probe = self.probe
        fan = {"fan": probe.fan.to_json(), "stretch": probe.stretch} if isinstance(probe, ConvexProbe) else {}
        return {
            "image_to_tool": self.image_to_tool,
            "image_to_tool_rigid": self.image_to_tool_rigid,
            "pixel_spacing_mm": list(self.pixel_spacing_mm),
            **fan,
            "phantom_to_base": self.phantom_to_base,
            "setup": {
                "image_to_flange_rigid": self.image_to_flange_rigid,
                "water_temperature_c": self.water_temperature_c,
                "sound_speed_m_s": self.probe.medium_sound_speed,
                "image_latency_s": self.image_latency_s,
                "timestamp_jitter_s": self.timestamp_jitter_s,
                "dh_deviation": _dh_json(dh),
                "controller_kinematics": _dh_json(self.controller),
                "wires_as_built": None if self.built_phantom is None else self.built_phantom.lines().tolist(),
            },
        }


def _dh_json(dh: DhDeviation | None) -> dict[str, list[float]] | None:
    return None if dh is None else {"theta_deg": np.degrees(dh.theta).tolist(), "d_mm": dh.d.tolist(),
                                    "a_mm": dh.a.tolist(), "alpha_deg": np.degrees(dh.alpha).tolist()}


def _built(phantom: Phantom, seed: int, rng: np.random.Generator, setup: SetupErrors) -> Phantom | None:
    """The phantom with every wire end point off by up to ``setup.phantom_tolerance_mm`` per axis
    (drawn from ``rng``), every diagonal's ends across it by up to ``diagonal_tolerance_mm``, every
    diagonal as a whole across itself by up to ``diagonal_shift_mm``, turned about its middle by up
    to ``diagonal_turn_mm`` at each end, and every layer moved as a whole by up to
    ``layer_tolerance`` (x, y, z mm, then deg about them; each from its own stream of ``seed``, so
    that the rest of a seed stays as it was); None when all are 0."""
    tolerance_mm, layer_tolerance = setup.phantom_tolerance_mm, setup.layer_tolerance
    if (tolerance_mm <= 0.0 and setup.diagonal_tolerance_mm <= 0.0 and setup.diagonal_shift_mm <= 0.0
            and setup.diagonal_turn_mm <= 0.0 and not any(layer_tolerance)):
        return None
    shifts = np.zeros((phantom.n_wires, 2, 3))
    if tolerance_mm > 0.0:
        shifts += rng.uniform(-tolerance_mm, tolerance_mm, shifts.shape)
    if setup.diagonal_tolerance_mm > 0.0:
        bound = setup.diagonal_tolerance_mm
        shifts += phantom.diagonal_shifts(np.random.default_rng([seed, 19]).uniform(-bound, bound,
                                                                                    (len(phantom.layers), 2)))
    if setup.diagonal_shift_mm > 0.0:
        bound = setup.diagonal_shift_mm
        whole = np.random.default_rng([seed, 23]).uniform(-bound, bound, len(phantom.layers))
        shifts += phantom.diagonal_shifts(np.column_stack([whole, whole]))
    if setup.diagonal_turn_mm > 0.0:
        bound = setup.diagonal_turn_mm
        turn = np.random.default_rng([seed, 29]).uniform(-bound, bound, len(phantom.layers))
        shifts += phantom.diagonal_shifts(np.column_stack([-turn, turn]))
    if any(layer_tolerance):
        layer_rng = np.random.default_rng([seed, 16])
        n = len(phantom.layers)
        layer_to_placed = np.tile(np.eye(4), (n, 1, 1))
        bounds = np.asarray(layer_tolerance, dtype=float)
        rotvecs = np.radians(layer_rng.uniform(-bounds[3:], bounds[3:], (n, 3)))
        layer_to_placed[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
        layer_to_placed[:, :3, 3] = layer_rng.uniform(-bounds[:3], bounds[:3], (n, 3))
        shifts += phantom.layer_shifts(layer_to_placed)
    return phantom.moved(shifts)


def make_twin(seed: int = 0, phantom: Phantom | None = None, probe: Probe | None = None,
              setup: SetupErrors = SetupErrors()) -> Twin:
    """A set-up whose true mount and phantom placement are drawn from ``seed``: the mount is off
    its design by up to 2 mm and 3 degrees per axis, the phantom by up to 2 mm and 2 degrees;
    then the ``setup`` errors (``core.twin.levels``), from their own stream so that the mount and
    placement of a seed are the same at every level.

    The planner knows only the mount's design and, as in the thesis (3.3), where the operator
    jogged the probe so that the wire pattern is centred in the live image: from that flange
    pose it infers where the phantom must be.
    """
    phantom = phantom or default_phantom()
    probe = probe or LinearProbe()
    rng = np.random.default_rng(seed)
    phantom_to_base = make_transform(TARGET_ROTATION_IN_BASE, PHANTOM_ORIGIN_IN_BASE_MM) @ random_offset(rng, 2.0, 2.0)
    face = nominal_image_to_tool(replace(probe, start_depth_mm=0.0)) @ random_offset(rng, 2.0, 3.0)
    # The operator centres the pattern in the image as the scanner labels its depths.
    labelled = face @ make_transform(np.eye(3), [0.0, probe.start_depth_mm, 0.0])
    centred_flange = phantom_to_base @ image_across_wires(phantom, probe) @ invert_transform(labelled)
    bench = np.random.default_rng([seed, 15])
    temperature = None
    if setup.water_temperature_c is not None:
        temperature = float(bench.uniform(*setup.water_temperature_c))
        probe = replace(probe, medium_sound_speed=round(water_sound_speed(temperature), 2))
    dh = (DhDeviation.draw(bench, setup.dh_length_mm, setup.dh_angle_deg)
          if setup.dh_length_mm or setup.dh_angle_deg else None)
    # The probe's face is where the seed put it; the first row lies as deep below it as the water's
    # sound speed makes the scanner's start depth.
    mount = face @ make_transform(np.eye(3), [0.0, probe.true_start_depth_mm, 0.0])
    return Twin(
        phantom=phantom,
        probe=probe,
        phantom_to_base=phantom_to_base,
        image_to_flange_rigid=mount,
        nominal=setup_from_centred_pose(phantom, probe, nominal_image_to_tool(probe), centred_flange),
        built_phantom=_built(phantom, seed, bench, setup),
        dh_deviation=dh,
        image_latency_s=float(bench.uniform(*setup.image_latency_s)),
        timestamp_jitter_s=setup.timestamp_jitter_s,
        water_temperature_c=temperature,
    )


