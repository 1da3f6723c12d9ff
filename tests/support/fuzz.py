"""Hostile inputs for every reader and every subcommand (issue 35), structure-aware: valid files
made by probecal with one field made hostile (NaN, infinity, 0, negative, 1e-300, 1e300, a huge
integer, types swapped, deep nesting, long strings, paths out of the folder), files swapped for
FIFOs, links, folders, truncated or empty files and other formats under the same name, PLUS
headers with one field changed, compressed payloads, DICOM tags, pose table cells, and every
number option given a hostile value; then what is live: hostile OpenIGTLink peers a sweep
records from, every console field sent a hostile value by a page (``fuzz_console``), and every
command that writes run on a full disk (``smalldisk``).

Each case runs ``probecal`` as a user would, its arguments through ``probecal.app.cli.main`` (or
its own :data:`Runner`), in a child forked from a process that has already imported it (a case
then costs a fraction of a second), with ``PROBECAL_MAX_MEMORY_MB`` set, under a time limit, in a
folder of its own. Its outcome: ``ok`` (exit 0), ``refused`` (exit 2 and one line), ``ended
early`` (a sweep's exit 1 and its one line: it stopped at a hostile frame and kept what it
recorded, which must read back whole), or a failure: ``traceback`` (a traceback, another exit
code or more than one line), ``hang`` (past the time limit), ``left behind`` (a refused run
changed its folder or its disk: an output, a staging folder, an input altered) or ``memory`` (the
child's anonymous memory, read every ``MEMORY_POLL_S``, grew past the limit plus ``MARGIN_MB``
beyond what it was forked with).

Run ``python -m tests.support.fuzz --cases N [--seed S] [--workers W] [--report FILE]`` in a
fresh process (a forked child of a process with threads may deadlock); tests/test_fuzz.py and
benchmarks/fuzz_inputs.py do.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import os
import random
import select
import shutil
import signal
import stat
import sys
import tempfile
import time
import traceback
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.support.smalldisk import small_disk_refusal

LIMIT_MB = 100
"""``PROBECAL_MAX_MEMORY_MB`` for every case."""
MARGIN_MB = 200
"""What a case may take beyond the limit (MB of its own memory): the working memory of probecal's
own steps on the corpus's small, valid inputs, the console's among them (their largest is printed
with every run: about 140 MB)."""
TIME_LIMIT_S = 60.0
FAILURES = ("traceback", "hang", "left behind", "memory")

Mutation = Callable[[Path], None]
"""Makes a case's input hostile, in the case's folder."""
Runner = Callable[[list[str], Path], int]
"""Runs a case in its child, in place of the command line: its arguments (``{in}`` replaced) and
its folder in; its exit code out."""


@dataclass(frozen=True)
class Case:
    """One run: ``argv`` (with ``{in}`` for the case's folder), the corpus items it copies in, the
    mutation that makes them hostile and what runs it (None: the command line on ``argv``)."""

    name: str
    argv: tuple[str, ...]
    needs: tuple[str, ...]
    mutate: Mutation = lambda _folder: None
    run: Runner | None = None


@dataclass
class Outcome:
    case: str
    kind: str
    seconds: float
    taken_mb: float
    detail: str = ""


@dataclass
class Corpus:
    """Valid inputs made once: sessions (``cal``, ``vol``, ``cont``), a PLUS sequence, a phantom
    definition, a PLUS device set, frames with a pose table, PLUS video and tracker buffers and
    meshes."""

    root: Path
    items: dict[str, Path] = field(default_factory=dict)


# -- the corpus ---------------------------------------------------------------------------------

def build_corpus(root: Path) -> Corpus:
    """Every valid input the cases start from, under ``root``. Run it in a process of its own: what
    it takes would otherwise stay resident in the process the cases are forked from, and the cases
    would reuse it unseen."""
    import trimesh

    from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
    from probecal.core.io.jsonio import write_json
    from probecal.core.io.phantomfile import default_phantom, dict_from_phantom
    from probecal.core.io.plusdata import plus_data_dir
    from probecal.core.io.plusimport import export_plus

    plus = plus_data_dir()
    cal = simulate_calibration(root / "cal", n_poses=10, seed=1, noise="none")
    simulate_volume(root / "vol", seed=1, noise="none", n_frames=8)
    simulate_calibration(root / "cont", n_poses=4, seed=2, noise="none", motion="continuous",
                         image_latency_s=0.05)
    export_plus(cal, root / "seq.igs.mha")
    write_json(root / "phantom.json", dict_from_phantom(default_phantom()))
    shutil.copy(plus / "ConfigFiles" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_2.0.xml", root / "set.xml")
    shutil.copy(plus / "TestImages" / "WaterTankBottomTranslationVideoBuffer.igs.mha", root / "video.igs.mha")
    shutil.copy(plus / "TestImages" / "WaterTankBottomTranslationTrackerBuffer-trimmed.igs.mha",
                root / "tracker.igs.mha")
    frames = root / "frames"
    frames.mkdir()
    rows = []
    for i, record in enumerate(cal.records):
        shutil.copy(cal.path / record.image, frames / f"img{i}.png")
        rows.append(",".join(f"{v:.6f}" for v in record.tool_to_base.ravel()))
    (root / "poses.csv").write_text("\n".join(rows) + "\n")
    mesh = trimesh.load(root / "vol" / "test_object.stl")
    mesh.export(root / "m.obj")
    (root / "m.obj").write_text("mtllib m.mtl\n" + (root / "m.obj").read_text())
    (root / "m.mtl").write_text("newmtl a\nKd 1 1 1\n")
    (root / "gltf").mkdir()
    for name, data in mesh.export(file_type="gltf").items():  # the model and its buffers
        (root / "gltf" / ("m.gltf" if name.endswith(".gltf") else name)).write_bytes(data)
    (root / BOMB).write_bytes(bomb_tiff())
    _build_new_kinds(root)
    return corpus_at(root)


def _build_new_kinds(root: Path) -> None:
    """DICOM frames with their pose table, ROS 1 and ROS 2 bags, and compressed payloads that
    inflate past the limit (``COMPRESSED``)."""
    from tests.support.payloads import bomb_bag, deflated_dicom, frame, jpeg_dicom, plain_dicom, pose_table, sweep_bag

    (root / "dicom").mkdir()
    for i in range(3):
        plain_dicom(root / "dicom" / f"IM_{i + 1}.dcm", frame())
    pose_table(root / "dicom.csv", 3)
    sweep_bag(root / "sweep.bag", 1)
    sweep_bag(root / "sweep2", 2)
    deflated_dicom(root / "deflated.dcm", inflated_mb=BOMB_MB)
    jpeg_dicom(root / "jpeg-lie.dcm", 12000, 12000)
    bomb_bag(root / "lz4-bomb.bag", 1, "lz4", BOMB_MB)
    bomb_bag(root / "zstd-bomb", 2, "zstd message", BOMB_MB)


ITEMS = ("cal", "vol", "cont", "seq.igs.mha", "phantom.json", "set.xml", "video.igs.mha", "tracker.igs.mha", "frames",
         "poses.csv", "m.obj", "m.mtl", "gltf", "dicom", "dicom.csv", "sweep.bag", "sweep2")
"""The corpus's inputs, as the cases' arguments name them (``{in}/NAME``)."""
BOMB = "bomb.tif"
BOMB_MB = 3 * LIMIT_MB // 2
"""What the compressed payloads inflate to (MB): past the limit."""
COMPRESSED = {"dicom/IM_2.dcm": ("deflated.dcm", "jpeg-lie.dcm"), "sweep.bag": ("lz4-bomb.bag",),
              "sweep2": ("zstd-bomb",)}
"""Inputs and the compressed payloads that replace them: a deflated DICOM body, a JPEG stream
larger than its DICOM tags say, a ROS 1 bag's LZ4 chunk and a ROS 2 bag's zstd message."""


def corpus_at(root: Path) -> Corpus:
    """The corpus :func:`build_corpus` made under ``root``."""
    return Corpus(root, {p.name: p for p in root.iterdir()})


# -- hostile values -----------------------------------------------------------------------------

DEEP = "@@deep@@"
HOSTILE_VALUES: list[object] = [
    math.nan, math.inf, -math.inf, 0, -1, 1e-300, 1e300, 10**400, "", "x", "../../../etc/hostname",
    "/etc/hostname", [], {}, None, True, [1, 2, 3], "a" * 100_000, DEEP, [[0.0] * 4] * 4, -0.0,
]
REFUSED_PORTS = ["nan", "inf", "-1", "65536", "99999", "abc", "", "1e3", "1" + "0" * 400]
"""Port values ``serve`` must refuse (a valid one would start the console and run on)."""
HOSTILE_NUMBERS = ["nan", "inf", "-inf", "0", "-1", "1e-300", "1e300", "abc", "", "1" + "0" * 400, "-0", "0x10"]


def _json_text(value: object) -> str:
    text = json.dumps(value, allow_nan=True)
    return text.replace(json.dumps(DEEP), "[" * 100_000 + "]" * 100_000)


def _leaves(value: object, path: tuple = ()) -> Iterator[tuple]:
    """The paths (keys and indices) of ``value``'s members, containers and leaves alike."""
    if path:
        yield path
    if isinstance(value, dict):
        for key, member in value.items():
            yield from _leaves(member, (*path, key))
    elif isinstance(value, list):
        for index, member in enumerate(value[:4]):
            yield from _leaves(member, (*path, index))


def _set(value: object, path: tuple, new: object) -> None:
    for key in path[:-1]:
        value = value[key]  # type: ignore[index]
    value[path[-1]] = new  # type: ignore[index]


def json_field(name: str, path: tuple, new: object, line: int | None = None) -> Mutation:
    """The JSON file ``name`` (of a JSON-lines file, its ``line``) with the member at ``path`` set to ``new``."""
    def mutate(folder: Path) -> None:
        file = folder / name
        if line is None:
            data = json.loads(file.read_text())
            _set(data, path, new)
            file.write_text(_json_text(data))
            return
        lines = file.read_text().splitlines()
        data = json.loads(lines[line])
        _set(data, path, new)
        lines[line] = _json_text(data)
        file.write_text("\n".join(lines) + "\n")
    return mutate


def _fifo(file: Path) -> None:
    os.mkfifo(file)


def swapped(name: str, how: str) -> Mutation:
    """The file ``name`` replaced: ``empty``, ``half`` (cut in half), ``fifo``, ``link out`` (to a
    file outside), ``dangling`` (a link to nothing), ``folder``, ``noise`` (random bytes),
    ``tiff``, ``jpeg``, ``text`` (another format under the same name), ``bomb tiff`` (20000 x
    20000 px, deflate), ``forged ihdr`` (a PNG claiming 100000 x 100000 px), ``bad crc``."""
    def mutate(folder: Path) -> None:
        file = folder / name
        data = file.read_bytes() if file.is_file() else b""
        if file.is_dir() and not file.is_symlink():
            shutil.rmtree(file)
        else:
            file.unlink()
        if how == "empty":
            file.write_bytes(b"")
        elif how == "half":
            file.write_bytes(data[: len(data) // 2])
        elif how == "fifo":
            _fifo(file)
        elif how == "link out":
            file.symlink_to("/etc/hostname")
        elif how == "dangling":
            file.symlink_to(folder / "nothing-here")
        elif how == "folder":
            file.mkdir()
        elif how == "noise":
            file.write_bytes(random.Random(len(data)).randbytes(4096))
        elif how in ("tiff", "jpeg"):
            import cv2
            import numpy as np
            ok, encoded = cv2.imencode(".tif" if how == "tiff" else ".jpg", np.full((64, 64), 100, np.uint8))
            file.write_bytes(encoded.tobytes())
        elif how == "text":
            file.write_text("this is not what the name says\n")
        elif how == "bomb tiff":
            (folder / BOMB).rename(file)
        elif how == "forged ihdr":
            file.write_bytes(_forged_png(data))
        elif how == "bad crc":
            file.write_bytes(data[:29] + bytes([data[29] ^ 0xFF]) + data[30:])
        else:
            raise ValueError(how)
    return mutate


SWAPS = ("empty", "half", "fifo", "link out", "dangling", "folder", "noise", "tiff", "text")
IMAGE_SWAPS = (*SWAPS, "jpeg", "bomb tiff", "forged ihdr", "bad crc")


def _forged_png(data: bytes) -> bytes:
    ihdr = bytearray(data[8:33])
    ihdr[8:16] = (100_000).to_bytes(4, "big") * 2
    ihdr[21:25] = zlib.crc32(bytes(ihdr[4:21])).to_bytes(4, "big")
    return data[:8] + bytes(ihdr) + data[33:]


def bomb_tiff() -> bytes:
    """A 20000 x 20000 px grey TIFF compressed with deflate (about 400 kB; 400 MB decoded)."""
    import numpy as np
    from PIL import Image

    with tempfile.TemporaryDirectory() as tmp:
        Image.fromarray(np.zeros((20000, 20000), np.uint8)).save(Path(tmp) / BOMB, compression="tiff_adobe_deflate")
        return (Path(tmp) / BOMB).read_bytes()


def header_field(name: str, key: str, value: str | None) -> Mutation:
    """The PLUS MetaImage ``name`` with its header field ``key`` set to ``value`` (None: removed)."""
    def mutate(folder: Path) -> None:
        file = folder / name
        data = file.read_bytes()
        end = data.index(b"ElementDataFile")
        end = data.index(b"\n", end) + 1
        lines = data[:end].decode("latin-1").splitlines()
        out = [line for line in lines if not line.startswith(f"{key} =")]
        if value is not None:
            out.insert(min(2, len(out) - 1), f"{key} = {value}")
        file.write_bytes(("\n".join(out) + "\n").encode("latin-1") + data[end:])
    return mutate


HEADER_KEYS = ("NDims", "DimSize", "ElementType", "CompressedData", "CompressedDataSize", "BinaryData",
               "ElementDataFile", "ElementNumberOfChannels", "Seq_Frame0000_ProbeToReferenceTransform",
               "Seq_Frame0000_Timestamp", "Seq_Frame0001_ImageStatus", "UltrasoundImageOrientation")
HEADER_VALUES = (None, "0", "-1", "nan", "1e300", "99999999999999999999", "0 0 2000000000", "1 1 1", "abc", "",
                 "20000 20000 1", "MET_DOUBLE", "../../../etc/hostname", "LIST", "True")


# -- the commands and their inputs ---------------------------------------------------------------

IMPORT_DICOM = ("import-frames", "{in}/dicom", "{in}/id", "--poses", "{in}/dicom.csv")
BAG_TOPICS = ("--image-topic", "/us/image", "--pose-topic", "/robot/pose", "--spacing", "0.1")
IMPORT_BAG2 = ("import-rosbag", "{in}/sweep2", "{in}/ib", *BAG_TOPICS)
SESSION_COMMANDS: dict[str, list[tuple[str, ...]]] = {
    "cal": [("segment", "{in}/cal", "--out", "{in}/seg.json"),
            ("validate", "{in}/cal", "--calibration", "{in}/cal/truth.json", "--out", "{in}/val.json"),
            ("export-plus", "{in}/cal", "{in}/x.igs.mha"),
            ("phantom", "check", "{in}/cal", "--calibration", "{in}/cal/truth.json", "--out", "{in}/pc.json"),
            ("calibrate", "{in}/cal", "--out", "{in}/c.json", "--method", "thesis")],
    "vol": [("reconstruct", "{in}/vol", "--calibration", "{in}/vol/truth.json", "--out", "{in}/rec",
             "--cad", "{in}/vol/test_object.stl")],
    "cont": [("temporal-calibrate", "{in}/cont", "--out", "{in}/lag.json")],
}
FILE_COMMANDS: dict[str, list[tuple[str, ...]]] = {
    "seq.igs.mha": [("import-plus", "{in}/seq.igs.mha", "{in}/imp")],
    "phantom.json": [("phantom", "export", "{in}/phantom.json", "{in}/pe"),
                     ("simulate", "calibration", "{in}/sim", "--poses", "2", "--phantom", "{in}/phantom.json")],
    "set.xml": [("phantom", "export", "{in}/set.xml", "{in}/pe"),
                ("import-plus", "{in}/seq.igs.mha", "{in}/imp", "--config", "{in}/set.xml")],
    "poses.csv": [("import-frames", "{in}/frames", "{in}/if", "--poses", "{in}/poses.csv", "--spacing", "0.1")],
    "tracker.igs.mha": [("temporal-calibrate", "--video", "{in}/video.igs.mha", "--tracker", "{in}/tracker.igs.mha",
                         "--out", "{in}/lag.json")],
    "video.igs.mha": [("temporal-calibrate", "--video", "{in}/video.igs.mha", "--tracker", "{in}/tracker.igs.mha",
                       "--out", "{in}/lag.json")],
    "m.obj": [("reconstruct", "{in}/vol", "--calibration", "{in}/vol/truth.json", "--out", "{in}/rec",
               "--cad", "{in}/m.obj")],
    "gltf/m.gltf": [("reconstruct", "{in}/vol", "--calibration", "{in}/vol/truth.json", "--out", "{in}/rec",
                     "--cad", "{in}/gltf/m.gltf")],
    "dicom.csv": [IMPORT_DICOM],
    "dicom/IM_2.dcm": [IMPORT_DICOM],
    "sweep.bag": [("import-rosbag", "{in}/sweep.bag", "{in}/ib", *BAG_TOPICS)],
    "sweep2/metadata.yaml": [IMPORT_BAG2],
    "sweep2/sweep2.db3": [IMPORT_BAG2],
}
OPTIONS: list[tuple[tuple[str, ...], str, tuple[str, ...]]] = [
    (("simulate", "calibration", "{in}/sim", "--poses", "2"), option, ())
    for option in ("--poses", "--seed", "--depth-mm", "--start-depth-mm", "--frame-rate", "--image-latency")
] + [
    (("simulate", "calibration", "{in}/sim", "--poses", "2", "--motion", "continuous"), option, ())
    for option in ("--frame-rate", "--image-latency")
] + [
    (("simulate", "volume", "{in}/sim", "--frames-per-pass", "2"), option, ())
    for option in ("--frames-per-pass", "--speed", "--frame-rate", "--depth-mm")
] + [
    (("sweep", "calibration", "{in}/sw", "--poses", "2", "--time-scale", "0"), option, ())
    for option in ("--latency", "--time-scale", "--spacing", "--start-depth-mm", "--poses", "--speed", "--seed")
] + [
    (("reconstruct", "{in}/vol", "--calibration", "{in}/vol/truth.json", "--out", "{in}/rec"), "--voxel", ("vol",)),
    (("phantom", "export", "{in}/pe"), "--wire-diameter", ()),
    (("phantom", "export", "{in}/pe"), "--hole-diameter", ()),
    (("phantom", "check", "{in}/cal", "--calibration", "{in}/cal/truth.json", "--out", "{in}/pc.json"), "--tolerance",
     ("cal",)),
    (("temporal-calibrate", "{in}/cont", "--out", "{in}/lag.json"), "--max-lag", ("cont",)),
    (("import-frames", "{in}/frames", "{in}/if", "--poses", "{in}/poses.csv"), "--spacing", ("frames", "poses.csv")),
    (("import-frames", "{in}/frames", "{in}/if", "--poses", "{in}/poses.csv", "--spacing", "0.1"), "--depth-mm",
     ("frames", "poses.csv")),
    (("import-plus", "{in}/seq.igs.mha", "{in}/imp"), "--start-depth-mm", ("seq.igs.mha",)),
    (("serve", "--port"), "", ()),
    (("serve", "--publish"), "", ()),
]
OUTPUTS: list[tuple[tuple[str, ...], str, tuple[str, ...]]] = [
    (("segment", "{in}/cal", "--out"), "{in}/seg.json", ("cal",)),
    (("export-plus", "{in}/cal"), "{in}/x.igs.mha", ("cal",)),
    (("reconstruct", "{in}/vol", "--calibration", "{in}/vol/truth.json", "--out"), "{in}/rec", ("vol",)),
    (("phantom", "export", "thesis-4layer"), "{in}/pe", ()),
    (("simulate", "calibration", "--poses", "2"), "{in}/sim", ()),
    (("import-plus", "{in}/seq.igs.mha"), "{in}/imp", ("seq.igs.mha",)),
    (("temporal-calibrate", "{in}/cont", "--out"), "{in}/lag.json", ("cont",)),
]
OUTPUT_SWAPS = ("link to a folder", "link to a file", "file", "fifo", "full folder", "in a file", "dangling")


def output_swapped(target: str, how: str) -> Mutation:
    """The output ``target`` already there as something else (a link, a file, a FIFO...)."""
    def mutate(folder: Path) -> None:
        out = Path(target.replace("{in}", str(folder)))
        if how == "link to a folder":
            (folder / "elsewhere").mkdir()
            out.symlink_to(folder / "elsewhere")
        elif how == "link to a file":
            (folder / "elsewhere.txt").write_text("keep me\n")
            out.symlink_to(folder / "elsewhere.txt")
        elif how == "file":
            out.write_text("keep me\n")
        elif how == "fifo":
            _fifo(out)
        elif how == "full folder":
            out.mkdir()
            (out / "keep.txt").write_text("keep me\n")
        elif how == "in a file":
            (folder / "plain").write_text("keep me\n")
        elif how == "dangling":
            out.symlink_to(folder / "nothing-here")
    return mutate


def _output_argv(argv: tuple[str, ...], target: str, how: str) -> tuple[str, ...]:
    return (*argv, "{in}/plain/out" if how == "in a file" else target)


@functools.cache
def small_disk_refused() -> str | None:
    """Why the full-disk cases cannot run here (None: they run); tried once, when cases are made."""
    return small_disk_refusal()


def all_cases(corpus: Corpus, rng: random.Random) -> list[Case]:
    """Every case the harness knows, in a fixed order for a given ``rng``."""
    from tests.support.fuzz_console import console_cases, markup_cases, vanished_page_cases
    from tests.support.fuzz_definitions import definition_cases
    from tests.support.fuzz_robot import robot_cases
    from tests.support.fuzz_tracker import tracker_cases

    cases: list[Case] = []
    for session, commands in SESSION_COMMANDS.items():
        folder = corpus.items[session]
        json_files = [name for name in ("manifest.json", "phantom.json", "truth.json") if (folder / name).is_file()]
        for name in json_files:
            data = json.loads((folder / name).read_text())
            for path in list(_leaves(data)):
                for value in rng.sample(HOSTILE_VALUES, 3):
                    argv = rng.choice(commands)
                    cases.append(Case(f"{session}/{name} {'.'.join(map(str, path))} = {short(value)}: {argv[0]}",
                                      argv, (session,), json_field(f"{session}/{name}", path, value)))
        for name in ("records.jsonl", "posestream.jsonl"):
            if not (folder / name).is_file():
                continue
            data = json.loads((folder / name).read_text().splitlines()[0])
            for path in list(_leaves(data)):
                for value in rng.sample(HOSTILE_VALUES, 3):
                    argv = rng.choice(commands)
                    cases.append(Case(f"{session}/{name} line 1 {'.'.join(map(str, path))} = {short(value)}: "
                                      f"{argv[0]}", argv, (session,), json_field(f"{session}/{name}", path, value, 0)))
        files = [name for name in (*json_files, "records.jsonl", "frames/000000.png", "posestream.jsonl",
                                   "test_object.stl") if (folder / name).is_file()]
        for name in files:
            for how in IMAGE_SWAPS if name.endswith(".png") else SWAPS:
                for argv in commands:
                    cases.append(Case(f"{session}/{name} as {how}: {argv[0]}", argv,
                                      (session, *((BOMB,) if how == "bomb tiff" else ())),
                                      swapped(f"{session}/{name}", how)))
    for item, commands in FILE_COMMANDS.items():
        needs: tuple[str, ...] = ()  # what the command names (_with_needs)
        for how in SWAPS:
            for argv in commands:
                cases.append(Case(f"{item} as {how}: {argv[0]}", argv, needs, swapped(item, how)))
        if item.endswith(".mha"):
            for key in HEADER_KEYS:
                for value in rng.sample(HEADER_VALUES, 4):
                    argv = rng.choice(commands)
                    cases.append(Case(f"{item} {key} = {value}: {argv[0]}", argv, needs,
                                      header_field(item, key, value)))
        if item.endswith(".json"):
            data = json.loads((corpus.items[item]).read_text())
            for path in list(_leaves(data)):
                for value in rng.sample(HOSTILE_VALUES, 2):
                    argv = rng.choice(commands)
                    cases.append(Case(f"{item} {'.'.join(map(str, path))} = {short(value)}: {argv[0]}", argv, needs,
                                      json_field(item, path, value)))
    for frame in ("frames/img0.png",):
        for how in IMAGE_SWAPS:
            cases.append(Case(f"{frame} as {how}: import-frames", FILE_COMMANDS["poses.csv"][0],
                              ("frames", "poses.csv", *((BOMB,) if how == "bomb tiff" else ())), swapped(frame, how)))
    cases += _new_kind_cases(rng)
    cases += _peer_cases()
    cases += console_cases()
    cases += markup_cases() + vanished_page_cases()
    cases += robot_cases() + tracker_cases() + definition_cases(rng)
    if small_disk_refused() is None:
        cases += _disk_cases()
    for argv, option, needs in OPTIONS:
        for value in HOSTILE_NUMBERS if argv[0] != "serve" else REFUSED_PORTS:
            full = (*argv, value) if not option else (*argv, option, value)
            cases.append(Case(f"{' '.join(full[:2])} {option or argv[-1]} {value!r}", full, needs))
    for argv, target, needs in OUTPUTS:
        for how in OUTPUT_SWAPS:
            for force in ((), ("--force",)):
                full = (*_output_argv(argv, target, how), *force)
                cases.append(Case(f"{' '.join(argv[:2])} into {how}{' --force' if force else ''}", full, needs,
                                  output_swapped(target, how)))
    return cases


DICOM_TAGS: dict[str, tuple] = {
    "Rows": (0, 1, 65535), "Columns": (0, 1, 65535), "BitsAllocated": (0, 1, 12, 32, 64), "SamplesPerPixel": (0, 3, 4),
    "NumberOfFrames": ("0", "-1", "99999999"), "PhotometricInterpretation": ("MONOCHROME1", "RGB", "PALETTE COLOR"),
}
REGION_TAGS: dict[str, tuple] = {
    name: (math.nan, math.inf, -math.inf, 0.0, -1.0, 1e-300, 1e300)
    for name in ("PhysicalDeltaX", "PhysicalDeltaY", "ReferencePixelPhysicalValueY")
} | {"RegionLocationMaxX1": (0, 4294967295), "ReferencePixelY0": (-2147483648, 2147483647)}
"""DICOM tags a scanner's frame holds, and hostile values of their types (REGION_TAGS: in its
Sequence of Ultrasound Regions)."""


def dicom_tag(name: str, tag: str, value: object, in_region: bool) -> Mutation:
    """The DICOM frame ``name`` with its tag ``tag`` (in its first region when ``in_region``) set."""
    def mutate(folder: Path) -> None:
        import pydicom

        ds = pydicom.dcmread(folder / name)
        setattr(ds.SequenceOfUltrasoundRegions[0] if in_region else ds, tag, value)
        ds.save_as(folder / name, enforce_file_format=True)
    return mutate


def pose_cell(name: str, row: int, column: int, value: str) -> Mutation:
    """The pose table ``name`` with one cell set to ``value``."""
    def mutate(folder: Path) -> None:
        lines = (folder / name).read_text().splitlines()
        cells = lines[row].split(",")
        cells[column % len(cells)] = value
        lines[row] = ",".join(cells)
        (folder / name).write_text("\n".join(lines) + "\n")
    return mutate


def replaced_by(name: str, payload: str) -> Mutation:
    """The input ``name`` replaced by the corpus's ``payload`` (a file or a folder)."""
    def mutate(folder: Path) -> None:
        target = folder / name
        shutil.rmtree(target) if target.is_dir() else target.unlink()
        (folder / payload).rename(target)
    return mutate


def _new_kind_cases(rng: random.Random) -> list[Case]:
    """Compressed payloads, DICOM tags and pose table cells."""
    commands = {"dicom/IM_2.dcm": IMPORT_DICOM, "sweep.bag": FILE_COMMANDS["sweep.bag"][0], "sweep2": IMPORT_BAG2}
    cases = [Case(f"{name} as {payload}", commands[name], (payload,), replaced_by(name, payload))
             for name, payloads in COMPRESSED.items() for payload in payloads]
    for tags, in_region in ((DICOM_TAGS, False), (REGION_TAGS, True)):
        for tag, values in tags.items():
            for value in rng.sample(values, min(3, len(values))):
                cases.append(Case(f"dicom/IM_2.dcm {tag} = {short(value)}", IMPORT_DICOM, (),
                                  dicom_tag("dicom/IM_2.dcm", tag, value, in_region)))
    for table, argv in (("dicom.csv", IMPORT_DICOM), ("poses.csv", FILE_COMMANDS["poses.csv"][0])):
        for _ in range(12):
            row, column, value = rng.randrange(3), rng.randrange(16), rng.choice(HOSTILE_NUMBERS)
            cases.append(Case(f"{table} row {row} column {column} = {value!r}", argv, (),
                              pose_cell(table, row, column, value)))
    return cases


SWEEP_FROM_PEER = ("sweep", "calibration", "{in}/sw", "--poses", "3", "--time-scale", "0.05", "--image",
                   "igtl:127.0.0.1:{port}")
"""A short sweep, quick enough (the robot at 20 times its speed) and long enough to record many of
a peer's frames."""


def _peer_cases() -> list[Case]:
    """A sweep, stepwise and continuous, recording from each hostile OpenIGTLink peer."""
    from tests.support.peers import PEERS

    return [Case(f"OpenIGTLink peer {kind}: sweep{' continuous' if motion else ''}", (*SWEEP_FROM_PEER, *motion), (),
                 run=from_peer(kind))
            for kind in PEERS for motion in ((), ("--motion", "continuous"))]


def from_peer(kind: str) -> Runner:
    """The command line on ``argv`` with ``{port}`` the port of a hostile OpenIGTLink peer
    ``kind`` (``tests.support.peers``). A sweep that ends early keeps what it recorded, so its
    session must then read back whole, as ``segment`` reads it."""
    def run(argv: list[str], folder: Path) -> int:
        from tests.support.peers import start_peer

        port = start_peer(kind)
        code = command_line([a.replace("{port}", str(port)) for a in argv], folder)
        if (folder / "sw").exists():
            read_back(folder / "sw")
        return code
    return run


DISK = "{in}/disk"
DISK_COMMANDS: list[tuple[str, ...]] = [
    ("simulate", "calibration", f"{DISK}/sim", "--poses", "12"),
    ("simulate", "volume", f"{DISK}/sim", "--frames-per-pass", "8"),
    ("export-plus", "{in}/cal", f"{DISK}/x.igs.mha"),
    ("import-frames", "{in}/frames", f"{DISK}/if", "--poses", "{in}/poses.csv", "--spacing", "0.1"),
    ("import-plus", "{in}/seq.igs.mha", f"{DISK}/imp"),
    ("import-rosbag", "{in}/sweep.bag", f"{DISK}/ib", *BAG_TOPICS),
    ("reconstruct", "{in}/vol", "--calibration", "{in}/vol/truth.json", "--out", f"{DISK}/rec"),
    ("segment", "{in}/cal", "--out", f"{DISK}/seg.json"),
    ("validate", "{in}/cal", "--calibration", "{in}/cal/truth.json", "--out", f"{DISK}/val.json"),
    ("phantom", "export", "thesis-4layer", f"{DISK}/pe"),
    ("temporal-calibrate", "{in}/cont", "--out", f"{DISK}/lag.json"),
    ("sweep", "calibration", f"{DISK}/sw", "--poses", "3", "--time-scale", "0"),
]
"""Commands that write onto the small disk (``DISK``) what they make."""
FILLED_DISK_COMMANDS: list[tuple[tuple[str, ...], str]] = [
    (("calibrate", f"{DISK}/cal", "--method", "thesis"), "cal"),
    (("reconstruct", f"{DISK}/vol", "--calibration", f"{DISK}/vol/truth.json", "--out", f"{DISK}/vol/rec"), "vol"),
    (("temporal-calibrate", f"{DISK}/cont", "--out", f"{DISK}/cont/lag.json"), "cont"),
]
"""Commands that write beside their input (the corpus item named) on a disk it fills."""
DISK_KB = (8, 24, 64, 128, 512, 2048)


def _disk_cases() -> list[Case]:
    """Every command that writes, onto a full disk: a small tmpfs of its own (``smalldisk``), empty
    or holding the input and filled."""
    cases = []
    for argv in DISK_COMMANDS:
        for kb in DISK_KB:
            cases.append(Case(f"{' '.join(argv[:2])} onto a disk of {kb} kB", argv, (), _make_disk,
                              on_small_disk(kb)))
    for argv, item in FILLED_DISK_COMMANDS:
        cases.append(Case(f"{argv[0]} on a full disk", argv, (item,), _make_disk, on_small_disk(8192, item)))
    return cases


def _make_disk(folder: Path) -> None:
    (folder / "disk").mkdir()


def on_small_disk(kb: int, copied: str | None = None) -> Runner:
    """The command line on a tmpfs of ``kb`` on the case's ``disk`` folder (the corpus item
    ``copied`` moved onto it first, the rest of it then filled). What a run that failed left on
    the disk is written to ``{folder}.left``, since the disk goes with the process: a sweep's
    session, which must read back whole, apart."""
    def run(argv: list[str], folder: Path) -> int:
        from tests.support.smalldisk import enter_small_disk, fill

        disk = folder / "disk"
        enter_small_disk(disk, kb)
        if copied is not None:
            shutil.copytree(folder / copied, disk / copied)
            fill(disk)
        before = snapshot(disk)
        code = command_line(argv, folder)
        if code != 0:
            if argv[0] == "sweep" and (disk / "sw").exists():
                read_back(disk / "sw")
            left = changed_entries(before, snapshot(disk))
            (folder.parent / f"{folder.name}.left").write_text("".join(f"{name}\n" for name in left))
        return code
    return run


def read_back(session: Path) -> None:
    """A session a sweep kept, read whole as ``segment`` reads it, then set aside: kept, as it must
    be, not left behind."""
    from probecal.core.io.session import load_session

    loaded = load_session(session)
    for i in range(len(loaded)):
        loaded.image(i)
    shutil.rmtree(session)


def short(value: object) -> str:
    text = DEEP if value == DEEP else json.dumps(value, allow_nan=True)
    return text if len(text) <= 24 else text[:20] + "..."


# -- running a case ------------------------------------------------------------------------------

def snapshot(folder: Path) -> dict[str, tuple]:
    """Every entry under ``folder`` with its type, and a file's size and modification time (links
    not followed; a folder's own change with a file made and removed in it is no leftover)."""
    out = {}
    for path in sorted(folder.rglob("*")):
        info = path.lstat()
        kind = stat.S_IFMT(info.st_mode)
        out[str(path.relative_to(folder))] = (kind, 0, 0) if kind == stat.S_IFDIR else \
            (kind, info.st_size, info.st_mtime_ns)
    return out


def changed_entries(before: dict[str, tuple], after: dict[str, tuple]) -> list[str]:
    """The entries of two :func:`snapshot` that differ: made, removed or changed."""
    return sorted(name for name in set(before) | set(after) if before.get(name) != after.get(name))


def _child(case: Case, argv: list[str], folder: Path) -> None:
    """In the forked child: run the case and exit with its code."""
    code = 1
    try:
        os.setpgid(0, 0)
        streams = {0: os.devnull, 1: folder.parent / f"{folder.name}.out", 2: folder.parent / f"{folder.name}.err"}
        for fd, name in streams.items():
            target = os.open(name, os.O_RDONLY if fd == 0 else os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(target, fd)
            os.close(target)
        os.environ["PROBECAL_MAX_MEMORY_MB"] = str(LIMIT_MB)
        os.chdir(folder)
        code = command_line(argv, folder) if case.run is None else case.run(argv, folder)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        traceback.print_exc()
        code = 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def command_line(argv: list[str], _folder: Path) -> int:
    from probecal.app.cli import main

    return main(argv)


def _rss_kb() -> int:
    return _status_kb("self", "VmRSS")


def _status_kb(pid: int | str, field: str) -> int:
    """A memory figure (kB) of ``/proc/PID/status``; 0 once the process is gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    return int(next((line.split()[1] for line in text.splitlines() if line.startswith(f"{field}:")), 0))


MEMORY_POLL_S = 0.02
"""How often each running case's memory is read."""


@dataclass
class _Running:
    case: Case
    folder: Path
    pid: int
    pidfd: int
    started: float
    before: dict[str, tuple]
    anon_kb: tuple[int, int] = (0, 0)  # its anonymous memory when forked, and the most since

    def sample(self) -> None:
        """Read the case's anonymous memory again: its own memory, not what it shares with the
        process it was forked from and has not written (the libraries' pages, which its RSS
        counts only once it touches them, are counted by neither)."""
        now = _status_kb(self.pid, "RssAnon")
        self.anon_kb = (self.anon_kb[0] or now, max(self.anon_kb[1], now))

    @property
    def taken_mb(self) -> float:
        return max(self.anon_kb[1] - self.anon_kb[0], 0) / 1024


def _start(case: Case, corpus: Corpus, work: Path, number: int) -> _Running:
    folder = work / f"case{number}"
    folder.mkdir()
    for name in case.needs:
        source = corpus.items[name]
        if source.is_dir():
            shutil.copytree(source, folder / name, symlinks=True)
        else:
            shutil.copy(source, folder / name)
    case.mutate(folder)
    argv = [a.replace("{in}", str(folder)) for a in case.argv]
    before = snapshot(folder)
    pid = os.fork()
    if pid == 0:
        _child(case, argv, folder)
    run = _Running(case, folder, pid, os.pidfd_open(pid), time.monotonic(), before)
    run.sample()
    return run


def _finish(run: _Running, hung: bool) -> Outcome:
    if hung:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(run.pid, signal.SIGKILL)
    _, status = os.waitpid(run.pid, 0)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(run.pid, signal.SIGKILL)  # what it started (a process pool) goes with it
    os.close(run.pidfd)
    seconds = time.monotonic() - run.started
    code = os.waitstatus_to_exitcode(status)
    err = (run.folder.parent / f"{run.folder.name}.err").read_text(errors="replace")
    taken = run.taken_mb
    lines = [line for line in err.splitlines() if line.strip()]
    after = snapshot(run.folder)
    left_file = run.folder.parent / f"{run.folder.name}.left"
    left_on_disk = left_file.read_text().split() if left_file.is_file() else []
    if hung:
        kind, detail = "hang", f"still running after {TIME_LIMIT_S:g} s"
    elif "Traceback" in err or "Warning" in err or code not in (0, 1, 2) or (code == 2 and not _one_line(lines)) \
            or (code == 1 and not _ended_early(lines)):
        kind, detail = "traceback", f"exit {code}: " + " | ".join(lines[-3:])[:600]
    elif code != 0 and (after != run.before or left_on_disk):
        changed = changed_entries(run.before, after) + left_on_disk
        kind, detail = "left behind", f"{lines[-1][:200]}; changed: {changed[:5]}"
    elif taken > LIMIT_MB + MARGIN_MB:
        kind, detail = "memory", f"took {taken:.0f} MB"
    else:
        kind, detail = ("ok", "") if code == 0 else ("refused" if code == 2 else "ended early", lines[-1][:300])
    return Outcome(run.case.name, kind, seconds, taken, detail)


def _one_line(lines: list[str]) -> bool:
    """A refusal as probecal makes one: its one error line last, after nothing but progress lines
    (long work reports how far it got, ``app.progress``)."""
    return bool(lines) and ": error: " in lines[-1] and lines[-1].startswith("probecal") \
        and not any("error" in line for line in lines[:-1])


def _ended_early(lines: list[str]) -> bool:
    """A sweep that ended early (exit 1), as probecal says it: one line naming why and what it
    kept, after nothing but progress lines."""
    return bool(lines) and lines[-1].startswith("probecal: sweep ended early (") \
        and not any("error" in line for line in lines[:-1])


def preload() -> None:
    """What the commands import, imported before any child is forked (each then starts at once)."""
    import cv2  # noqa: F401
    import numpy  # noqa: F401
    import open3d  # noqa: F401
    import scipy.optimize  # noqa: F401
    import scipy.stats  # noqa: F401
    import SimpleITK  # noqa: F401
    import trimesh  # noqa: F401

    import probecal.app.cli  # noqa: F401
    import probecal.app.console.server  # noqa: F401
    import probecal.core.calibration.solve  # noqa: F401
    import probecal.core.volume.reconstruct  # noqa: F401
    import tests.support.page  # noqa: F401


def run_cases(cases: list[Case], corpus: Corpus, work: Path, workers: int,
              progress: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    """Every case run, ``workers`` at a time; their outcomes in the cases' order."""
    pending = list(enumerate(cases))
    running: dict[int, tuple[int, _Running]] = {}
    outcomes: dict[int, Outcome] = {}
    while pending or running:
        while pending and len(running) < workers:
            number, case = pending.pop(0)
            run = _start(case, corpus, work, number)
            running[run.pidfd] = (number, run)
        now = time.monotonic()
        wait = max(0.0, min(run.started + TIME_LIMIT_S for _, run in running.values()) - now)
        ready, _, _ = select.select(list(running), [], [], min(wait, MEMORY_POLL_S))
        for _, run in running.values():
            run.sample()
        now = time.monotonic()
        for fd in list(running):
            number, run = running[fd]
            if fd in ready or now - run.started >= TIME_LIMIT_S:
                del running[fd]
                outcomes[number] = _finish(run, fd not in ready)
                if progress is not None:
                    progress(outcomes[number])
                if outcomes[number].kind not in FAILURES:
                    shutil.rmtree(run.folder, ignore_errors=True)
    return [outcomes[k] for k in range(len(cases))]


def valid_cases() -> list[Case]:
    """The corpus as it is, through every command: how much probecal's own steps take."""
    seen = {}
    for commands in (*SESSION_COMMANDS.values(), *FILE_COMMANDS.values()):
        for argv in commands:
            seen.setdefault(argv, None)
    needs = {argv: _needs_of(argv) for argv in seen}
    return [Case(f"valid: {' '.join(argv[:2])}", argv, needs[argv]) for argv in seen]


def _needs_of(argv: tuple[str, ...]) -> tuple[str, ...]:
    text = " ".join(argv)
    found = tuple(name for name in ITEMS if "{in}/" + name in text)
    return (*found, "m.mtl") if "m.obj" in found else found


def _with_needs(case: Case) -> Case:
    needs = tuple(dict.fromkeys((*case.needs, *_needs_of(case.argv))))
    return dataclasses.replace(case, needs=needs)


def _built_apart(root: Path) -> Corpus:
    """:func:`build_corpus` in a child process, whose memory goes with it."""
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            build_corpus(root)
            code = 0
        except BaseException:
            traceback.print_exc()
        finally:
            os._exit(code)
    if os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) != 0:
        raise RuntimeError("the corpus could not be built")
    return corpus_at(root)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=2000, help="how many hostile cases (sampled evenly)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", type=Path, help="write every outcome here (JSON)")
    parser.add_argument("--keep", type=Path, help="keep the failures' folders here")
    parser.add_argument("--only", default="", help="only the cases whose names hold this text")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    preload()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        corpus = _built_apart(root / "corpus")
        rng = random.Random(args.seed)
        cases = [_with_needs(c) for c in all_cases(corpus, rng) if args.only in c.name]
        chosen = cases if args.cases >= len(cases) else [cases[round(k * len(cases) / args.cases)]
                                                         for k in range(args.cases)]
        work = Path(args.keep) if args.keep else root / "work"
        work.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        (work / "valid").mkdir()
        valid = run_cases(valid_cases(), corpus, work / "valid", args.workers)
        outcomes = run_cases(chosen, corpus, work, args.workers)
        seconds = time.monotonic() - started
    counts = Counter(o.kind for o in outcomes)
    print(f"{len(outcomes)} hostile cases of {len(cases)} known (seed {args.seed}), {seconds:.0f} s: "
          + ", ".join(f"{kind} {counts.get(kind, 0)}" for kind in ("ok", "refused", "ended early", *FAILURES)))
    worst = max(outcomes, key=lambda o: o.taken_mb)
    print(f"memory: PROBECAL_MAX_MEMORY_MB={LIMIT_MB}; the process the cases are forked from holds "
          f"{_rss_kb() / 1024:.0f} MB (the interpreter and what probecal imports); the most anonymous memory a "
          f"hostile case took beyond what it was forked with {worst.taken_mb:.0f} MB ({worst.case}); valid inputs "
          f"took up to "
          f"{max((o.taken_mb for o in valid), default=0):.0f} MB (margin allowed {MARGIN_MB} MB)")
    if small_disk_refused() is not None:
        print(f"full-disk cases skipped: {small_disk_refused()}")
    failed = [f"{o.case.removeprefix('valid: ')} {o.kind}" for o in valid if o.kind != "ok"]
    print(f"slowest case {max(o.seconds for o in outcomes):.1f} s; valid runs: "
          + (", ".join(failed) if failed else f"all {len(valid)} ok"))
    for outcome in outcomes:
        if outcome.kind in FAILURES:
            print(f"  {outcome.kind}: {outcome.case}: {outcome.detail}")
    if args.report:
        args.report.write_text(json.dumps({"valid": [o.__dict__ for o in valid],
                                           "outcomes": [o.__dict__ for o in outcomes]}, indent=1))
    return 1 if any(o.kind in FAILURES for o in outcomes) or any(o.kind != "ok" for o in valid) else 0


if __name__ == "__main__":
    sys.exit(main())
