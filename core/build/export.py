"""``probecal phantom export``: everything needed to build a phantom, written into one folder that
appears whole or not at all."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import trimesh

from probecal.core.build.drawing import layer_svg, view_svg, wall_svg
from probecal.core.build.guide import guide_markdown, wiring_markdown
from probecal.core.build.mesh import frame_mesh
from probecal.core.build.walls import Frame, FrameDesign, frame_of
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.deviceset import phantom_device_set
from probecal.core.io.files import staged_folder
from probecal.core.io.jsonio import to_json_text
from probecal.core.io.phantomfile import dict_from_phantom

MESH_FILE = "frame.stl"
PLUS_FILE = "phantom.xml"


@dataclass(frozen=True)
class Export:
    """What an export wrote: the folder, its files (name: what it holds), the frame and its mesh."""

    folder: Path
    files: dict[str, str]
    frame: Frame
    mesh: trimesh.Trimesh


def layer_file(index: int, phantom: Phantom) -> str:
    """The drawing's file name of N layer ``index``."""
    name = "".join(c if c.isalnum() or c in "-_." else "_" for c in phantom.layers[index].name)
    return f"layer-{index + 1}-{name}.svg"


def export_phantom(phantom: Phantom, out_dir: str | Path, design: FrameDesign | None = None,
                   source: str | Path | None = None, *, check_commands: Sequence[str]) -> Export:
    """Write the printable frame (STL), the PLUS definition, our JSON definition, the drawings, the
    wiring list and the build guide of ``phantom`` into the new folder ``out_dir``. InputError
    naming ``source`` (the definition) when no two-walled frame can hold its wires. ``design``
    defaults to FrameDesign(); the guide shows ``check_commands`` to check the built phantom."""
    frame = frame_of(phantom, design or FrameDesign(), source)
    mesh = frame_mesh(frame)
    landmarks = [(m.name, m.position) for m in frame.landmarks()]
    texts: dict[str, tuple[str, str]] = {
        PLUS_FILE: ("the PLUS device-set XML: `<PhantomDefinition>` with the wires and the divots as landmarks, "
                    "and the frame as the phantom's model", phantom_device_set(phantom, landmarks, MESH_FILE)),
        "phantom.json": ("the probecal definition (the phantom the twin images and the imports take, or edited as "
                         "built)",
                         to_json_text(dict_from_phantom(phantom))),
        "wiring.md": ("which hole to which hole, wire lengths, line to cut, every hole's position",
                      wiring_markdown(frame)),
        "frame.svg": ("the frame in 3D", view_svg(mesh, f"{phantom.name}: the printed frame")),
        "wall-front.svg": ("the front wall from outside, with its holes", wall_svg(frame, "front")),
        "wall-back.svg": ("the back wall from outside, with its holes", wall_svg(frame, "back")),
    }
    for k, layer in enumerate(phantom.layers):
        what = f"layer {layer.name} from above, with its wires and holes"
        texts[layer_file(k, phantom)] = (what, layer_svg(frame, k))
    files = {MESH_FILE: f"the frame to print (watertight, {mesh.volume / 1000:.1f} cm3, phantom frame in mm)"}
    files.update({name: what for name, (what, _) in texts.items()})
    with staged_folder(out_dir, what="phantom export") as staging:
        mesh.export(staging / MESH_FILE)
        for name, (_, text) in texts.items():
            (staging / name).write_text(text)
        (staging / "BUILD.md").write_text(guide_markdown(frame, {"BUILD.md": "this guide", **files},
                                                                 check_commands))
    return Export(Path(out_dir), {"BUILD.md": "how to print, drill, thread and check it", **files}, frame, mesh)
