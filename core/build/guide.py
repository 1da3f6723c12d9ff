"""The wiring list and the build guide of a phantom's frame, as Markdown (mm, phantom frame)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from probecal.core.build.drawing import mm, point_text
from probecal.core.build.walls import AXES, UP, Frame

TAIL_MM = 40.0
"""Line left beyond each hole for tying off."""
TENSION_N = 4.0
"""Tension that keeps a 0.3 mm nylon line straight over 80 mm without creeping (about 400 g)."""


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *("| " + " | ".join(row) + " |" for row in rows)]


def wiring_markdown(frame: Frame) -> str:
    """Which hole to which hole, for every wire, with its length and the line to cut; then every
    hole with its position in the phantom frame and on its wall."""
    d = frame.design
    phantom = frame.phantom
    wall_mm = d.wall_thickness_mm
    rows: list[list[str]] = []
    pairs = list(zip(phantom.wires, frame.wire_holes()))
    for k in sorted(range(len(pairs)), key=lambda k: (pairs[k][0].front[UP], k)):  # bottom layer first
        wire, (front, back) = pairs[k]
        length = float(np.linalg.norm(wire.back - wire.front))
        rows.append([str(len(rows) + 1), wire.name, phantom.layers[k // 3].name,
                     f"{front.label} {point_text(front.centre)}", f"{back.label} {point_text(back.centre)}", mm(length),
                     f"{np.ceil(length + 2 * wall_mm + 2 * TAIL_MM):.0f}"])
    holes = []
    for hole in frame.holes:
        right, up = frame.seen_from_outside(hole.wall, hole.centre)
        holes.append([hole.label, hole.wall, *(mm(v) for v in hole.centre), mm(right), mm(up), mm(hole.diameter_mm),
                      ", ".join(hole.wires)])
    shared = [h for h in frame.holes if len(h.wires) > 1]
    lines = [
        f"# Wiring list: {phantom.name}",
        "",
        f"{phantom.n_wires} wires in {len(phantom.layers)} N layers, {mm(d.wire_diameter_mm)} mm line, "
        f"holes {mm(d.hole_diameter_mm)} mm. Coordinates in mm in the phantom frame (z up, toward the probe). "
        f"Thread the wires in this order: bottom layer first, so that the wires already taut stay out of reach.",
        "",
        "## Wires",
        "",
        *_table(["#", "wire", "layer", "front hole", "back hole", "length (mm)", "line to cut (mm)"],
                rows),
        "",
        f"Line to cut: the wire's length, both walls ({mm(wall_mm)} mm each) and {mm(TAIL_MM)} mm at each end to "
        "tie off.",
        "",
        "## Holes",
        "",
        f"Positions on a wall are seen from outside that wall: from its left edge and up from the base's top "
        f"({AXES[UP]} = {mm(frame.base_top_mm)} mm). Drill every hole straight through, along "
        f"{AXES[frame.axis]}.",
        "",
        *_table(["hole", "wall", "x", "y", "z", "from the left (mm)", "above the base (mm)", "diameter (mm)", "wires"],
                holes),
    ]
    if shared:
        lines += ["", f"{len(shared)} holes each carry two wires that end at the same point (their diameter is one "
                      f"wire larger): pass both lines through the one hole and tie each off on its own. Each line "
                      f"then sits up to {mm((shared[0].diameter_mm - d.wire_diameter_mm) / 2)} mm off the point."]
    return "\n".join(lines) + "\n"


def guide_markdown(frame: Frame, files: dict[str, str], check_commands: Sequence[str]) -> str:
    """How to print, drill, thread, tension and check the phantom; ``files`` maps each exported
    file's name to what it holds, ``check_commands`` are the commands that sweep, calibrate and
    check the built phantom (the command line's, given by the app)."""
    d = frame.design
    phantom = frame.phantom
    extent = frame.extent_mm
    mark = frame.origin_mark()
    origin_note = ("at the mark" if abs(mark[UP]) < 1e-9 else
                   f"{mm(abs(mark[UP]))} mm {'below' if mark[UP] > 0 else 'above'} the mark")
    clearance = (d.hole_diameter_mm - d.wire_diameter_mm) / 2
    listed = [f"- `{name}`: {what}" for name, what in files.items()]
    return "\n".join([
        f"# Building the {phantom.name} phantom",
        "",
        f"{phantom.n_wires} wires in {len(phantom.layers)} N layers, held by two walls "
        f"{mm(abs(frame.back_mm - frame.front_mm))} mm apart on a base; the printed frame measures "
        f"{' x '.join(mm(v) for v in extent)} mm (x, y, z). Every file is in the phantom frame, in mm: print the "
        "mesh as it is and the wires end where the definition says.",
        "",
        *listed,
        "",
        "## 1. Print the frame",
        "",
        "- PETG or PLA, 0.4 mm nozzle, layers of 0.12 to 0.2 mm, at least 4 perimeters and 30 % infill, so that the "
        "walls stay flat under the wires' tension.",
        "- Base down on the bed, no supports: the walls stand straight up, the divots and grooves open upward.",
        "- Do not scale in the slicer: the mesh is in mm. Check with calipers that the walls' inner faces are "
        f"{mm(abs(frame.back_mm - frame.front_mm))} mm apart (within 0.2 mm) and stand square to the base.",
        "- The phantom frame: the conical divot at the end of the two engraved grooves marks its origin "
        f"in x and y (the origin lies {origin_note}); the groove with the arrow head runs along +x, the other "
        f"along +y; z points up.",
        "",
        "## 2. Open the holes",
        "",
        f"Printed holes under 1 mm come out undersized. Open each one with a {mm(d.hole_diameter_mm)} mm drill bit in "
        f"a pin vise (a wire-sharing hole with its own size, see `wiring.md`), straight through along "
        f"{AXES[frame.axis]}, from outside; `wall-front.svg` and `wall-back.svg` show where each hole is.",
        "",
        "## 3. Thread and tension the wires",
        "",
        f"- Use {mm(d.wire_diameter_mm)} mm nylon monofilament (fishing line): it is straight, cheap and gives a "
        "bright, small dot.",
        "- One length of line per wire, cut as `wiring.md` says; thread the bottom layer first.",
        "- Tie a stopper knot (a double overhand) at one end, thread the line from outside through its front hole, "
        "across to its back hole and out.",
        f"- Pull the line taut with about {TENSION_N:g} N: hang a {TENSION_N / 9.81 * 1000:.0f} g weight from it over "
        "the wall's edge so that every wire gets the same tension. Put a drop of cyanoacrylate glue where the line "
        "leaves the hole outside, let it set, then tie off and cut the tail.",
        "- No wire may touch another. Look along each layer: the three wires must lie in one plane.",
        f"- A line may sit anywhere in its hole: up to {mm(clearance)} mm off the definition; the check below "
        "measures where each one ended up.",
        "",
        "## 4. Check the built phantom by scanning it",
        "",
        "Put the phantom in water (room temperature, left to stand so that bubbles leave the wires), record a "
        "calibration sweep and calibrate, then check the wires against the definition:",
        "",
        "```",
        *check_commands,
        "```",
        "",
        "`phantom check` locates every wire from the scan itself and prints how far it sits off the definition "
        "(mm, as a move of its holes in the walls' plane) where the scan saw it, with a standard error from four "
        "runs of consecutive frames; when the sweep covers enough of the wires, also both ends, how far the middle "
        "sags and the spread of the dots. A wire built off its definition shows as one wire consistently off while "
        "the others agree; a wire in the wrong hole is off by the holes' spacing, and a slack one sags: off toward "
        "-z where the sweep crossed it. A wire is named off only beyond "
        "doubt; where the runs disagree, or the dots scatter by more than the tolerance, the check says it "
        "cannot tell, and a longer sweep with more poses tells more. Re-thread or re-tension a wire named off, "
        "or keep the phantom as built: the check also writes the definition with the wires where the scan found "
        "them (those it cannot tell as defined) when asked.",
        "",
        "## 5. Use it with PLUS fCal",
        "",
        "`phantom.xml` holds the `<PhantomDefinition>` (the same wires, PLUS's layout) and the frame's model: copy "
        "both elements into your device-set file and the mesh beside it. Its landmarks are the divots, named as "
        "in the file: touch each with the tracked stylus in fCal's phantom registration. A landmark is a divot's "
        "apex, where a sharp tip rests; a ball tip of radius r rests r x 1.41 above it.",
        "",
    ])
