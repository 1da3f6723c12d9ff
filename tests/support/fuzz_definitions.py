"""The fuzzing harness's phantom and probe definition files made hostile: layers and wires past any
phantom, end points far off or not numbers, probes past any scanner, and frames or views past the
memory limit, through every command that reads them (``simulate`` with ``--phantom`` or
``--probe``, ``phantom export``, and ``segment``, ``calibrate`` and ``phantom check`` of a session
whose ``phantom.json`` or manifest's probe is hostile)."""

from __future__ import annotations

import json
import math
import random
import re
from collections.abc import Callable
from pathlib import Path

from tests.support.fuzz import HOSTILE_VALUES, Case, Mutation, short

PREFIX = "definition"
"""Every case's name starts with it (``--only definition``)."""

PHANTOM_COMMANDS = [("phantom", "export", "{in}/phantom.json", "{in}/pe"),
                    ("simulate", "calibration", "{in}/sim", "--poses", "2", "--phantom", "{in}/phantom.json")]
DEVICE_SET_COMMANDS = [("phantom", "export", "{in}/set.xml", "{in}/pe"),
                       ("simulate", "calibration", "{in}/sim", "--poses", "2", "--phantom", "{in}/set.xml")]
SESSION_COMMANDS = [("segment", "{in}/cal", "--out", "{in}/seg.json"),
                    ("calibrate", "{in}/cal", "--out", "{in}/c.json", "--method", "thesis"),
                    ("phantom", "check", "{in}/cal", "--calibration", "{in}/cal/truth.json", "--out", "{in}/pc.json")]
PROBE_COMMANDS = [("simulate", "calibration", "{in}/sim", "--poses", "2", "--probe", "{in}/probe.json"),
                  ("simulate", "volume", "{in}/sim", "--frames-per-pass", "2", "--probe", "{in}/probe.json")]
FAN_PROBE = ("simulate", "calibration", "{in}/sim", "--poses", "2", "--probe", "{in}/set.xml")

LAYER_COUNTS = (0, 1, 2, 16, 17, 100, 10_000)
WIRE_COUNTS = (0, 2, 4, 1000, 100_000)
COORDINATES: list[object] = [math.nan, math.inf, -math.inf, 1e300, -1e300, 1e12, 1e11, 1001.0, -1001.0, 999.0,
                             1e-300, 0, 10**400, "1", None]
XML_NUMBERS = ("1e300", "-1e300", "1e309", "nan", "inf", "1e11", "1001", "-999", "1e-300", "0x10", "", "1 2",
               "1 2 3 4", "abc")
PROBE_NUMBERS: list[object] = [0, 1, 7, 8, 8192, 8193, 100_000, 10**9, 1e9, 1e12, 1e-9, 0.001, 0.01, 179.9, 180,
                               1000, 1000.1, 300, 6000]
FAN_NUMBERS = ("0", "-1", "1e300", "1e308", "nan", "89.999", "1e-300", "100000", "8192")
IMAGE_SIZES = (("8192", "8192"), ("8", "8"), ("8192", "8"), ("8", "8192"), ("1100", "1100"), ("900", "900"),
               ("2000", "10"))
VIEW_COUNTS = (1, 2, 8, 9, 180, 10_000)

LINEAR = {"type": "linear", "n_elements": 128, "pitch_mm": 0.3, "depth_mm": 50.0, "width_px": 384,
          "height_px": 500, "nominal_sound_speed": 1540.0, "medium_sound_speed": 1480.0, "start_depth_mm": 0.0}
CONVEX = {"type": "convex", "radius_mm": 50.0, "fov_deg": 60.0, "n_elements": 128, "depth_mm": 70.0,
          "width_px": 600, "nominal_sound_speed": 1540.0, "medium_sound_speed": 1480.0, "start_depth_mm": 0.0}
HOSTILE_PROBES: list[dict] = [
    {**LINEAR, "width_px": 100_000, "height_px": 100_000},
    {**LINEAR, "width_px": 8192, "height_px": 8192},
    {**LINEAR, "depth_mm": 1e9},
    {**LINEAR, "pitch_mm": 1e-9},
    {**LINEAR, "width_px": 1, "height_px": 1},
    {**LINEAR, "n_elements": 128, "pitch_mm": 0.01, "width_px": 900, "height_px": 900, "depth_mm": 0.9},
    {**LINEAR, "n_elements": 8192, "pitch_mm": 10.0, "width_px": 8, "depth_mm": 1000.0, "height_px": 8},
    {**CONVEX, "width_px": 100_000},
    {**CONVEX, "radius_mm": 1e6},
    {**CONVEX, "fov_deg": 1.0, "depth_mm": 1000.0, "width_px": 8192},
    {**CONVEX, "fov_deg": 179.0, "radius_mm": 1000.0, "depth_mm": 1000.0, "width_px": 8},
    {**CONVEX, "width_px": 8192},
]
"""Probes past any scanner or past the memory limit, as the probe's reproductions made them."""


def definition_cases(rng: random.Random) -> list[Case]:
    """Every hostile definition case, in a fixed order for a given ``rng``."""
    return (_phantom_cases(rng) + _session_cases(rng) + _device_set_cases(rng) + _probe_cases(rng)
            + _option_cases())


# -- phantom definitions (JSON) -----------------------------------------------------------------------

PhantomEdit = Callable[[dict], None]


def _edited_json(name: str, edit: PhantomEdit) -> Mutation:
    """The JSON file ``name`` (in the case's folder) changed by ``edit``, written with NaN and
    infinity as JSON's extensions spell them and integers of any size."""
    def mutate(folder: Path) -> None:
        file = folder / name
        data = json.loads(file.read_text())
        edit(data)
        file.write_text(json.dumps(data, allow_nan=True))
    return mutate


def _layers(count: int) -> PhantomEdit:
    def edit(data: dict) -> None:
        data["layers"] = [data["layers"][k % len(data["layers"])] for k in range(count)]
    return edit


def _wires(layer: int, count: int) -> PhantomEdit:
    def edit(data: dict) -> None:
        wires = data["layers"][layer]["wires"]
        data["layers"][layer]["wires"] = [wires[k % len(wires)] for k in range(count)]
    return edit


def _coordinate(layer: int, wire: int, end: str, axis: int, value: object) -> PhantomEdit:
    def edit(data: dict) -> None:
        data["layers"][layer]["wires"][wire][end][axis] = value
    return edit


def _box(corner: str, axis: int, value: object) -> PhantomEdit:
    def edit(data: dict) -> None:
        data["box"][corner][axis] = value
    return edit


def _moved(offset: float) -> PhantomEdit:
    """Every point moved by ``offset`` mm along z: the phantom far off its origin, whole."""
    def edit(data: dict) -> None:
        for layer in data["layers"]:
            for wire in layer["wires"]:
                wire["front"][2] += offset
                wire["back"][2] += offset
        data["box"]["min"][2] += offset
        data["box"]["max"][2] += offset
    return edit


def _named(value: str) -> PhantomEdit:
    def edit(data: dict) -> None:
        data["layers"][0]["wires"][0]["name"] = value
        data["layers"][0]["name"] = value
    return edit


def _phantom_edits(rng: random.Random) -> list[tuple[str, PhantomEdit]]:
    """Hostile edits of a phantom definition, named."""
    edits: list[tuple[str, PhantomEdit]] = [(f"{n} layers", _layers(n)) for n in LAYER_COUNTS]
    edits += [(f"layer 1 of {n} wires", _wires(0, n)) for n in WIRE_COUNTS]
    for value in COORDINATES:
        layer, wire, end, axis = rng.randrange(3), rng.randrange(3), rng.choice(("front", "back")), rng.randrange(3)
        edits.append((f"layers[{layer}].wires[{wire}].{end}[{axis}] = {short(value)}",
                      _coordinate(layer, wire, end, axis, value)))
    for value in rng.sample(COORDINATES, 6):
        corner, axis = rng.choice(("min", "max")), rng.randrange(3)
        edits.append((f"box.{corner}[{axis}] = {short(value)}", _box(corner, axis, value)))
    edits += [(f"moved {offset:g} mm", _moved(offset)) for offset in (-900.0, 900.0, 2000.0, -1e6)]
    edits += [("names of 100 kB", _named("<b>" * 30_000)), ("names of control characters", _named("\x00\x1b[2J\n"))]
    return edits


def _phantom_cases(rng: random.Random) -> list[Case]:
    return [Case(f"{PREFIX}: phantom.json {what}: {' '.join(argv[:2])}", argv, ("phantom.json",),
                 _edited_json("phantom.json", edit))
            for what, edit in _phantom_edits(rng) for argv in PHANTOM_COMMANDS]


def _session_cases(rng: random.Random) -> list[Case]:
    """A session's own phantom.json and its manifest's probe made hostile."""
    cases = [Case(f"{PREFIX}: cal/phantom.json {what}: {argv[0]}", argv, ("cal",),
                  _edited_json("cal/phantom.json", edit))
             for what, edit in _phantom_edits(rng) for argv in (rng.choice(SESSION_COMMANDS),)]
    for k, probe in enumerate(HOSTILE_PROBES):
        argv = SESSION_COMMANDS[k % len(SESSION_COMMANDS)]
        cases.append(Case(f"{PREFIX}: cal/manifest.json probe {_probe_name(probe)}: {argv[0]}", argv, ("cal",),
                          _edited_json("cal/manifest.json", _set("probe", probe))))
    for size in ((8192, 8192), (100_000, 100_000), (1, 1), (64, 64), (10**12, 10**12)):
        argv = rng.choice(SESSION_COMMANDS)
        cases.append(Case(f"{PREFIX}: cal/manifest.json image_size {size[0]} x {size[1]}: {argv[0]}", argv,
                          ("cal",), _edited_json("cal/manifest.json", _set("image_size", list(size)))))
    return cases


def _set(key: str, value: object) -> PhantomEdit:
    def edit(data: dict) -> None:
        data[key] = value
    return edit


# -- PLUS device sets ----------------------------------------------------------------------------------

TextEdit = Callable[[str], str]


def _edited_text(name: str, edit: TextEdit) -> Mutation:
    def mutate(folder: Path) -> None:
        file = folder / name
        file.write_text(edit(file.read_text()))
    return mutate


def _patterns(count: int) -> TextEdit:
    """The device set's phantom with its NWire patterns repeated to ``count``."""
    def edit(text: str) -> str:
        patterns = re.findall(r"<Pattern .*?</Pattern>", text, re.S)
        first, last = text.index(patterns[0]), text.index(patterns[-1]) + len(patterns[-1])
        return text[:first] + "\n".join(patterns[k % len(patterns)] for k in range(count)) + text[last:]
    return edit


def _xml_wires(count: int) -> TextEdit:
    """The first pattern with its wires repeated to ``count``."""
    def edit(text: str) -> str:
        pattern = re.search(r"<Pattern .*?</Pattern>", text, re.S)
        assert pattern is not None
        wires = re.findall(r"<Wire [^>]*/>", pattern.group(0))
        body = "\n".join(wires[k % len(wires)] for k in range(count))
        return text[:pattern.start()] + f'<Pattern Type="NWire">{body}</Pattern>' + text[pattern.end():]
    return edit


def _nth_attribute(attribute: str, nth: int, value: str) -> TextEdit:
    """The ``nth`` ``attribute`` of the file with one of its numbers set to ``value``."""
    def edit(text: str) -> str:
        found = list(re.finditer(f'{attribute}="([^"]*)"', text))
        match = found[nth % len(found)]
        numbers = match.group(1).split()
        numbers[nth % len(numbers)] = value
        return text[:match.start(1)] + " ".join(numbers) + text[match.end(1):]
    return edit


def _fan(attribute: str, value: str) -> TextEdit:
    """A convex probe's fan in the device set's ``<VolumeReconstruction>`` (its spacing the
    segmentation's 0.078 mm), with ``attribute`` set to ``value``."""
    def edit(text: str) -> str:
        fan = {"FanAnglesDeg": "-30 30", "FanOriginPixel": "410 -60", "FanRadiusStartPixel": "80",
               "FanRadiusStopPixel": "600", attribute: value}
        return text.replace("<VolumeReconstruction ", "<VolumeReconstruction "
                            + " ".join(f'{k}="{v}"' for k, v in fan.items()) + " ", 1)
    return edit


def _device_set_cases(rng: random.Random) -> list[Case]:
    edits: list[tuple[str, TextEdit]] = [(f"{n} NWire patterns", _patterns(n)) for n in (17, 1000)]
    edits += [(f"a pattern of {n} wires", _xml_wires(n)) for n in (2, 4, 100_000)]
    for attribute in ("EndPointFront", "EndPointBack", "Position"):
        for value in rng.sample(XML_NUMBERS, 5):
            nth = rng.randrange(9)
            edits.append((f"{attribute} #{nth} = {value!r}", _nth_attribute(attribute, nth, value)))
    cases = [Case(f"{PREFIX}: set.xml {what}: {' '.join(argv[:2])}", argv, ("set.xml",),
                  _edited_text("set.xml", edit))
             for what, edit in edits for argv in DEVICE_SET_COMMANDS]
    for attribute in ("FanAnglesDeg", "FanOriginPixel", "FanRadiusStartPixel", "FanRadiusStopPixel"):
        count = 2 if attribute in ("FanAnglesDeg", "FanOriginPixel") else 1
        for value in rng.sample(FAN_NUMBERS, 4):
            text = " ".join([value] * count)
            cases.append(Case(f"{PREFIX}: set.xml fan {attribute} = {text!r}: simulate --probe", FAN_PROBE,
                              ("set.xml",), _edited_text("set.xml", _fan(attribute, text))))
    return cases


# -- probe files ---------------------------------------------------------------------------------------

def _probe_name(probe: dict) -> str:
    base = CONVEX if probe.get("type") == "convex" else LINEAR
    changed = " ".join(f"{k}={short(v)}" for k, v in probe.items() if k == "type" or base.get(k) != v)
    return changed or "unchanged"


def _probe_file(probe: dict) -> Mutation:
    """A probe file ``probe.json`` of ``probe``'s fields, made in the case's folder."""
    def mutate(folder: Path) -> None:
        (folder / "probe.json").write_text(json.dumps(probe, allow_nan=True))
    return mutate


def _probe_cases(rng: random.Random) -> list[Case]:
    probes = list(HOSTILE_PROBES)
    for base in (LINEAR, CONVEX):
        for key in base:
            if key == "type":
                continue
            for value in rng.sample(PROBE_NUMBERS, 4) + rng.sample(HOSTILE_VALUES, 2):
                probes.append({**base, key: value})
    probes += [{**LINEAR, "type": value} for value in ("phased", None, 1)]
    probes += [{**LINEAR, "extra": 1}, {**LINEAR, "n_elements": None, "width_px": None}, {**CONVEX, "fov_deg": None}]
    return [Case(f"{PREFIX}: probe.json {_probe_name(probe)}: {' '.join(argv[:2])}", argv, (), _probe_file(probe))
            for k, probe in enumerate(probes) for argv in (PROBE_COMMANDS[k % len(PROBE_COMMANDS)],)]


# -- options -------------------------------------------------------------------------------------------

def _option_cases() -> list[Case]:
    cases = []
    for what, more in (("calibration", ("--poses", "2")), ("volume", ("--frames-per-pass", "2"))):
        for probe in ("linear-38", "convex-50"):
            for width, height in IMAGE_SIZES:
                argv = ("simulate", what, "{in}/sim", *more, "--probe", probe, "--image-size", width, height)
                cases.append(Case(f"{PREFIX}: simulate {what} --probe {probe} --image-size {width} {height}", argv,
                                  ()))
            for depth in ("0.1", "1000"):
                argv = ("simulate", what, "{in}/sim", *more, "--probe", probe, "--depth-mm", depth)
                cases.append(Case(f"{PREFIX}: simulate {what} --probe {probe} --depth-mm {depth}", argv, ()))
    for count in VIEW_COUNTS:
        views = ",".join(str(k * 360 // count) for k in range(count))
        argv = ("simulate", "volume", "{in}/sim", "--frames-per-pass", "2", "--views", views)
        cases.append(Case(f"{PREFIX}: simulate volume --views of {count}", argv, ()))
    return cases
