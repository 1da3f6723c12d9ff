"""The set-up as designed: the probe mount's design calibration, where the phantom is meant to sit
and the centre pose that puts the image plane across its wires (mm, 4x4 ``a_to_b``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from probecal.core.geometry.phantom import Phantom
from probecal.core.geometry.probe import Probe
from probecal.core.geometry.transforms import invert_transform, make_transform

# Design calibration of the probe mount: image x along tool x, depth (image y) along the tool z
# axis (out of the flange), the image's top-left pixel 100 mm beyond the flange.
MOUNT_OFFSET_MM = 100.0
# The probe face sits this far above the top wire layer (z = 80 for the default phantom, design §3).
PROBE_STANDOFF_MM = 10.0


@dataclass(frozen=True)
class Setup:
    """Where things are, as far as the planner knows (all mm, 4x4).

    ``image_to_tool_rigid`` is the probe mount's calibration without pixel spacing;
    ``image_to_phantom`` is the centre pose: the image plane across the wires.
    """

    phantom: Phantom
    probe: Probe
    phantom_to_base: np.ndarray
    image_to_tool_rigid: np.ndarray
    image_to_phantom: np.ndarray

    def tool_to_base(self, image_to_phantom: np.ndarray) -> np.ndarray:
        """Flange pose that puts the image plane at ``image_to_phantom``."""
        return self.phantom_to_base @ image_to_phantom @ invert_transform(self.image_to_tool_rigid)


def image_across_wires(phantom: Phantom, probe: Probe) -> np.ndarray:
    """``image_to_phantom`` of the centre pose: image plane normal to the wires (phantom y), the
    image centred over the wires, the probe face ``PROBE_STANDOFF_MM`` above the top layer,
    depth pointing down (-z)."""
    centre = phantom.center()
    axes = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    top = phantom.lines()[..., 2].max() + PROBE_STANDOFF_MM + probe.face_below_first_row_mm
    return make_transform(axes, [centre[0] - probe.width_mm / 2, centre[1], top])


def setup_from_centred_pose(phantom: Phantom, probe: Probe, image_to_tool_rigid: np.ndarray,
                            tool_to_base: np.ndarray) -> Setup:
    """What the planner knows once the operator has jogged the probe so that the wire pattern is
    centred in the live image (thesis 3.3): with the mount's design ``image_to_tool_rigid``, the
    phantom must sit where that flange pose puts the centre pose."""
    centred = image_across_wires(phantom, probe)
    phantom_to_base = tool_to_base @ image_to_tool_rigid @ invert_transform(centred)
    return Setup(phantom, probe, phantom_to_base, image_to_tool_rigid, centred)


def nominal_image_to_tool(probe: Probe) -> np.ndarray:
    """The mount's design ``image_to_tool_rigid`` (mm): the image's lateral centre on the probe's
    axis, its first row ``probe.start_depth_mm`` below the face (a convex face's middle lies
    ``face_below_first_row_mm`` below it)."""
    axes = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    depth = probe.start_depth_mm - probe.face_below_first_row_mm
    return make_transform(axes, [-probe.width_mm / 2, 0.0, MOUNT_OFFSET_MM + depth])
