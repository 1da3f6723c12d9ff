"""Probe definitions: the twin's built-in probes by name, probe files (JSON, the probe's dict
form), and the ``probe`` of a session's manifest, each checked before a probe is built from it."""

from __future__ import annotations

import math
from dataclasses import fields
from pathlib import Path
from typing import Any, TypeVar

from probecal.core.errors import InputError
from probecal.core.geometry.probe import (
    BUILTIN_PROBES,
    IMAGE_PX,
    PROBE_FIELDS,
    ConvexProbe,
    LinearProbe,
    Probe,
    probe_from_dict,
)
from probecal.core.io.deviceset import DeviceSet, plus_fan, read_device_set
from probecal.core.io.jsonio import (
    PIXEL_SPACING_MM,
    describe,
    expect_integer,
    expect_keys,
    expect_number,
    expect_object,
    optional,
    read_json,
)

_KINDS: dict[str, type[LinearProbe] | type[ConvexProbe]] = {"linear": LinearProbe, "convex": ConvexProbe}


def check_start_depth(data: dict, source: str | Path, prefix: str = "") -> float | None:
    """``start_depth_mm`` of ``data``: how far below the probe's face the first row lies (mm, 0 or more)."""
    value = optional(data, "start_depth_mm", expect_number, source, prefix)
    if value is not None and value < 0:
        raise InputError(source, f"{prefix}start_depth_mm must be 0 or more, got {value:g}")
    return value


def probe_refusal(probe: Probe) -> str | None:
    """Why ``probe`` is beyond any scanner's, None when it is not: a field out of its
    :data:`~probecal.core.geometry.probe.PROBE_FIELDS` bounds, a fan higher than
    :data:`~probecal.core.geometry.probe.IMAGE_PX` allows, or pixels (as the scanner states them or
    in the medium) outside :data:`~probecal.core.io.jsonio.PIXEL_SPACING_MM`, which a session of
    its frames could not hold. Each is checked before what it bounds is computed."""
    for key in fields(probe):
        span = PROBE_FIELDS[key.name]
        value = getattr(probe, key.name)
        if not span.holds(value):
            return f"{key.name} must lie within {span}, got {value:g}"
    if isinstance(probe, ConvexProbe) and not IMAGE_PX.holds(probe.height_px):
        return f"its fan {probe.width_px} px wide is {probe.height_px} px high: a frame is {IMAGE_PX} each way"
    low, high = PIXEL_SPACING_MM
    for what, spacing in (("its pixels", probe.nominal_spacing_mm),
                          ("its pixels in the medium", probe.true_spacing_mm)):
        if not all(low <= s <= high for s in spacing):
            return (f"{what} would be {spacing[0]:.3g} x {spacing[1]:.3g} mm (width over pixels across, depth over "
                    f"pixels down); a pixel is {low:g} to {high:g} mm")
    return None


ProbeKind = TypeVar("ProbeKind", bound=LinearProbe | ConvexProbe)


def checked_probe(probe: ProbeKind, source: str | Path | None, name: str = "the probe") -> ProbeKind:
    """``probe`` if :func:`probe_refusal` finds nothing; InputError naming ``source`` and
    ``name`` otherwise."""
    refusal = probe_refusal(probe)
    if refusal is not None:
        raise InputError(source, f"{name}: {refusal}")
    return probe


def check_probe(value: Any, source: str | Path, name: str = "probe") -> Probe:
    """The probe a dict states (``type`` "linear", the default, or "convex", and that probe's
    fields: whole numbers of 1 or more, other numbers positive; the start depth may be 0), within
    the bounds of any scanner's (:func:`probe_refusal`); InputError naming ``source`` and the
    field."""
    data = expect_object(value, source, name)
    kind = data.get("type", "linear")
    if not isinstance(kind, str) or kind not in _KINDS:
        raise InputError(source, f"{name}.type must be one of {', '.join(map(repr, _KINDS))}, got {describe(kind)}")
    probe_fields = {f.name: f.type for f in fields(_KINDS[kind])}  # name: "int" or "float"
    expect_keys(data, {"type", *probe_fields}, source, name)
    for key, kind_of in probe_fields.items():
        if kind_of == "int":
            optional(data, key, expect_integer, source, f"{name}.", minimum=1)
        elif key == "start_depth_mm":
            check_start_depth(data, source, f"{name}.")
        else:
            optional(data, key, expect_number, source, f"{name}.", positive=True)
    try:
        probe = probe_from_dict({key: value for key, value in data.items() if value is not None})  # null: absent
    except ValueError as exc:
        raise InputError(source, f"{name}: {exc}") from None
    return checked_probe(probe, source, name)


def load_probe(spec: str | Path) -> Probe:
    """A built-in probe by name (:data:`~probecal.core.geometry.probe.BUILTIN_PROBES`), a probe
    file's (.json) or the convex probe a PLUS device set's fan states (.xml,
    :func:`probe_from_device_set`); InputError naming the file when it is none of them."""
    if str(spec) in BUILTIN_PROBES:
        return BUILTIN_PROBES[str(spec)]
    path = Path(spec)
    if not path.suffix and not path.exists():
        raise InputError(path, f"no such probe: give one of {', '.join(BUILTIN_PROBES)} or a probe file (.json "
                               "or a PLUS device set)")
    if path.suffix.lower() == ".xml":
        return probe_from_device_set(read_device_set(path))
    return check_probe(read_json(path), path, "the probe")


def probe_from_device_set(config: DeviceSet) -> ConvexProbe:
    """The convex probe whose fan a device set's ``<VolumeReconstruction>`` states (in pixels of
    ``<Segmentation>``'s ``ApproximateSpacingMmPerPixel``): its face the fan's near radius, its
    depth from there to the far one, its field of view the fan's angles (which must lie evenly
    about the image's axis), as wide in pixels as the fan; InputError naming the file for a device
    set that states no such fan."""
    try:
        fan = None if config.volume_reconstruction is None else plus_fan(config.volume_reconstruction)
    except ValueError as exc:
        raise InputError(config.path, f"VolumeReconstruction: {exc}") from None
    if fan is None:
        raise InputError(config.path, "states no fan (VolumeReconstruction FanAnglesDeg): not a convex probe's images")
    spacing = None if config.segmentation is None else config.segmentation.approximate_spacing_mm
    if spacing is None or spacing <= 0:
        raise InputError(config.path, "states no pixel spacing (Segmentation ApproximateSpacingMmPerPixel) for its fan")
    left, right = fan.angles_deg
    if not math.isclose(left, -right, abs_tol=1e-6) or right <= 0:
        raise InputError(config.path, f"FanAnglesDeg {left:g} {right:g}: a convex probe's fan lies evenly about the "
                                      "image's axis")
    if fan.radius_start_px <= 0:
        raise InputError(config.path, "states no FanRadiusStartPixel: a convex probe's face is the fan's near radius")
    radius, depth = fan.radius_start_px * spacing, (fan.radius_stop_px - fan.radius_start_px) * spacing
    for key, value in (("radius_mm", radius), ("depth_mm", depth)):  # before the width is counted in pixels
        if not PROBE_FIELDS[key].holds(value):
            raise InputError(config.path, f"its fan's probe: {key} must lie within {PROBE_FIELDS[key]}, got {value:g}")
    width = round(2.0 * fan.radius_stop_px * math.sin(math.radians(right)))
    try:
        probe = ConvexProbe(radius_mm=radius, fov_deg=2.0 * right, depth_mm=depth, width_px=width)
    except ValueError as exc:
        raise InputError(config.path, str(exc)) from None
    return checked_probe(probe, config.path, "its fan's probe")
