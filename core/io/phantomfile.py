"""Phantom definition files: our JSON format (``probecal-phantom/1``, see
``static/phantoms/thesis_4layer.json``) and the NWire patterns of a PLUS device-set XML."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from probecal.core import STATIC_DIR
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import (
    NLayer,
    Phantom,
    Wire,
    check_layer_count,
    check_name,
    check_point,
    validate_layers,
)
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.files import existing_file
from probecal.core.io.jsonio import (
    expect_list,
    expect_numbers,
    expect_object,
    expect_string,
    optional,
    read_json,
    required,
)

FORMAT = "probecal-phantom/1"
DEFAULT_PHANTOM_FILE = STATIC_DIR / "phantoms" / "thesis_4layer.json"
BUILTIN_PHANTOMS = {
    "thesis-4layer": DEFAULT_PHANTOM_FILE,
    "fcal-1.2": STATIC_DIR / "phantoms" / "fCal_1.2.xml",
    "fcal-2.0": STATIC_DIR / "phantoms" / "fCal_2.0.xml",
}
"""The phantoms shipped in static/: the thesis's 4-layer box and PLUS's fCal 1.2 and 2.0 (their
device-set files' ``<PhantomDefinition>``), by the name ``probecal phantom`` knows them by."""


def _wire(data: Any, default_name: str, source: str | Path, name: str) -> Wire:
    """One wire of our definition format: optional ``name``, ``front`` and ``back`` (mm)."""
    wire = expect_object(data, source, name)
    return Wire(
        optional(wire, "name", expect_string, source, f"{name}.") or default_name,
        required(wire, "front", expect_numbers, source, f"{name}.", count=3),
        required(wire, "back", expect_numbers, source, f"{name}.", count=3),
    )


def _layer(data: Any, i: int, source: str | Path) -> NLayer:
    """Layer ``i`` (from 0) of our definition format: optional ``name`` and three wires."""
    name = f"layers[{i}]"
    layer = expect_object(data, source, name)
    wires = required(layer, "wires", expect_list, source, f"{name}.")
    if len(wires) != 3:
        raise InputError(source, f"layer {i + 1} has {len(wires)} wires, an N needs 3")
    layer_name = optional(layer, "name", expect_string, source, f"{name}.") or f"N{i + 1}"
    first, diagonal, last = (_wire(w, f"{i + 1}.{j + 1}", source, f"{name}.wires[{j}]") for j, w in enumerate(wires))
    return NLayer(layer_name, (first, diagonal, last))


def dict_from_phantom(phantom: Phantom) -> dict:
    """``phantom`` in our definition format (mm, phantom frame)."""
    return {
        "format": FORMAT,
        "name": phantom.name,
        "units": "mm",
        "box": {"min": phantom.box_min.tolist(), "max": phantom.box_max.tolist()},
        "layers": [
            {
                "name": layer.name,
                "wires": [{"name": w.name, "front": w.front.tolist(), "back": w.back.tolist()} for w in layer.wires],
            }
            for layer in phantom.layers
        ],
    }


def phantom_from_dict(data: Any, source: str | Path) -> Phantom:
    """Build and validate a phantom from our definition format (see :func:`dict_from_phantom`);
    InputError naming ``source`` and the field for anything malformed."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(source, f"not a phantom definition (expected \"format\": \"{FORMAT}\")")
    listed = required(data, "layers", expect_list, source)
    check_layer_count(len(listed), source)
    layers = [_layer(layer, i, source) for i, layer in enumerate(listed)]
    box = required(data, "box", expect_object, source)
    box_min = check_point(required(box, "min", expect_numbers, source, "box.", count=3), "box.min", source)
    box_max = check_point(required(box, "max", expect_numbers, source, "box.", count=3), "box.max", source)
    validate_layers(layers, source)
    if np.any(box_max <= box_min):
        raise InputError(source, "phantom box max must exceed min on every axis")
    ends = np.array([[w.front, w.back] for layer in layers for w in layer.wires]).reshape(-1, 3)
    if np.any(ends < box_min - 1e-6) or np.any(ends > box_max + 1e-6):
        raise InputError(source, "a wire end point lies outside the phantom box")
    name = check_name(optional(data, "name", expect_string, source) or "phantom", "name", source)
    return Phantom(name, tuple(layers), box_min, box_max)


def load_phantom(path: str | Path) -> Phantom:
    """Load a phantom from our JSON definition or from a PLUS device-set XML."""
    path = existing_file(path)
    if path.suffix.lower() == ".xml":
        config = read_device_set(path)
        if config.phantom is None:
            raise InputError(path, "no <PhantomDefinition> with NWire patterns in this file")
        return config.phantom
    return phantom_from_dict(read_json(path), path)


def phantom_path(spec: str | Path) -> Path:
    """The definition file of a built-in phantom's name (:data:`BUILTIN_PHANTOMS`), or ``spec``
    itself as a file's path."""
    return BUILTIN_PHANTOMS.get(str(spec), Path(spec))


def default_phantom() -> Phantom:
    """The thesis's 4-layer phantom (design §3), shipped in static/."""
    return load_phantom(DEFAULT_PHANTOM_FILE)
