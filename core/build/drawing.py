"""Drawings of a phantom's frame as SVG, dimensioned in mm in the phantom frame: each N layer seen
from above (its wires between the walls, every hole labelled with its coordinates), each wall
seen from outside (where to drill), and a shaded view of the whole frame."""

from __future__ import annotations

from html import escape

import numpy as np
import trimesh

from probecal.core.build.walls import AXES, UP, Frame, Hole
from probecal.core.geometry.phantom import DIAGONAL, NLayer

Point2 = np.ndarray | tuple[float, float]
"""A point in the drawing's plane (mm)."""

PX_PER_MM = 6.0
PAD_MM = 22.0
FONT_MM = 2.0
WIRE = "#1f5fa8"
DIAGONAL_WIRE = "#c0392b"
WALL = "#b8b8b8"
INK = "#222"


def mm(value: float) -> str:
    """A length in mm as the drawings write it: up to 3 decimals, no trailing zeros."""
    return f"{value:.3f}".rstrip("0").rstrip(".").replace("-0", "0") if abs(value) >= 5e-4 else "0"


def point_text(point: np.ndarray) -> str:
    return "(" + ", ".join(mm(v) for v in point) + ")"


def _svg(lo: np.ndarray, hi: np.ndarray, title: str, body: list[str]) -> str:
    """An SVG document showing drawing coordinates (mm) ``lo``..``hi`` with a padding and a title."""
    x0, y0 = lo - PAD_MM
    w, h = hi - lo + 2 * PAD_MM
    w = max(w, len(title) * FONT_MM * 1.3 * 0.6 + 4)  # room for the title
    head = (f'<svg xmlns="http://www.w3.org/2000/svg" width="{w * PX_PER_MM:.0f}" height="{h * PX_PER_MM:.0f}" '
            f'viewBox="{x0:.3f} {y0:.3f} {w:.3f} {h:.3f}" font-family="sans-serif" font-size="{FONT_MM}">')
    background = f'<rect x="{x0:.3f}" y="{y0:.3f}" width="{w:.3f}" height="{h:.3f}" fill="white"/>'
    caption = _text(x0 + 2, y0 + 4, title, size=FONT_MM * 1.3, weight="bold")
    return "\n".join([head, f"<title>{escape(title)}</title>", background, caption, *body, "</svg>"]) + "\n"


def _text(x: float, y: float, text: str, size: float = FONT_MM, anchor: str = "start", weight: str = "normal",
          rotate: float = 0.0, fill: str = INK) -> str:
    turn = f' transform="rotate({rotate:g} {x:.3f} {y:.3f})"' if rotate else ""
    return (f'<text x="{x:.3f}" y="{y:.3f}" font-size="{size:g}" text-anchor="{anchor}" font-weight="{weight}" '
            f'fill="{fill}"{turn}>{escape(text)}</text>')


def _rect(lo: Point2, hi: Point2, fill: str = WALL) -> str:
    return (f'<rect x="{lo[0]:.3f}" y="{lo[1]:.3f}" width="{hi[0] - lo[0]:.3f}" height="{hi[1] - lo[1]:.3f}" '
            f'fill="{fill}" stroke="{INK}" stroke-width="0.2"/>')


def _line(a: Point2, b: Point2, colour: str, width: float = 0.35, dash: str = "") -> str:
    style = f' stroke-dasharray="{dash}"' if dash else ""
    return (f'<line x1="{a[0]:.3f}" y1="{a[1]:.3f}" x2="{b[0]:.3f}" y2="{b[1]:.3f}" stroke="{colour}" '
            f'stroke-width="{width:g}"{style}/>')


def _hole_mark(centre: Point2, hole: Hole) -> list[str]:
    """A hole drawn to scale, ringed so that it can be seen, with a cross through its centre."""
    x, y = centre
    r = hole.diameter_mm / 2
    return [f'<circle cx="{x:.3f}" cy="{y:.3f}" r="{r:.3f}" fill="{INK}"/>',
            f'<circle cx="{x:.3f}" cy="{y:.3f}" r="1.2" fill="none" stroke="{INK}" stroke-width="0.15"/>',
            _line((x - 2, y), (x + 2, y), INK, 0.1), _line((x, y - 2), (x, y + 2), INK, 0.1)]


def _axis_arrows(origin: Point2, right: str, up: str) -> list[str]:
    """Two arrows naming the phantom axes along the drawing's right and up."""
    x, y = origin
    return [_line((x, y), (x + 8, y), INK, 0.25), _line((x, y), (x, y - 8), INK, 0.25),
            _text(x + 9, y + 0.7, right), _text(x - 0.8, y - 9, up)]


def _plan(frame: Frame, point: np.ndarray) -> np.ndarray:
    """Seen from above: across the wires to the right, front wall at the bottom (drawing mm)."""
    return np.array([point[frame.across], -frame.outward * point[frame.axis]])


def layer_svg(frame: Frame, index: int) -> str:
    """N layer ``index`` seen from above: the walls, its three wires and their holes with the
    holes' coordinates (mm, phantom frame)."""
    layer: NLayer = frame.phantom.layers[index]
    holes = frame.wire_holes()[3 * index:3 * index + 3]
    z = np.mean([w.front[UP] for w in layer.wires])
    body = []
    corners = []
    for wall in ("front", "back"):
        lo, hi = frame.wall_box(wall)
        a, b = _plan(frame, lo), _plan(frame, hi)
        corners += [a, b]
        body.append(_rect(np.minimum(a, b), np.maximum(a, b)))
    for k, wire in enumerate(layer.wires):
        colour = DIAGONAL_WIRE if k == DIAGONAL else WIRE
        body.append(_line(_plan(frame, wire.front), _plan(frame, wire.back), colour, 0.4 if k == DIAGONAL else 0.35))
    drawn = set()
    for front, back in holes:
        for hole in (front, back):
            if hole.label in drawn:
                continue
            drawn.add(hole.label)
            centre = _plan(frame, hole.centre)
            body += _hole_mark(centre, hole)
            outside = 1.0 if hole.wall == "front" else -1.0
            edge = centre[1] + outside * (frame.design.wall_thickness_mm + 1.5)
            body.append(_text(centre[0] + 0.7 * outside, edge, f"{hole.label} {point_text(hole.centre)}",
                              rotate=90 * outside))
    lo, hi = np.min(corners, axis=0), np.max(corners, axis=0)
    legend_y = hi[1] + PAD_MM - 6
    for k, (wire, (front, back)) in enumerate(zip(layer.wires, holes)):
        length = float(np.linalg.norm(wire.back - wire.front))
        body.append(_text(lo[0] - PAD_MM + 2, legend_y + k * 2.6, f"{wire.name}: {front.label} to {back.label}, "
                          f"{mm(length)} mm", fill=DIAGONAL_WIRE if k == DIAGONAL else WIRE))
    hi = hi + [0.0, 8.0]
    body += _axis_arrows((hi[0] + 4, lo[1] + 10), AXES[frame.across],
                         ("" if frame.outward > 0 else "-") + AXES[frame.axis])
    title = f"Layer {layer.name} at {AXES[UP]} = {mm(z)} mm, seen from above (mm, phantom frame)"
    return _svg(lo, hi + [10.0, 0.0], title, body)


def _face(frame: Frame, wall: str, point: np.ndarray) -> np.ndarray:
    """Wall ``wall`` seen from outside (drawing mm, y down)."""
    right, up = frame.seen_from_outside(wall, point)
    return np.array([right, -up])


def wall_svg(frame: Frame, wall: str) -> str:
    """The ``front`` or ``back`` wall seen from outside, every hole labelled, and beside it a table
    of the holes: coordinates (mm, phantom frame), diameter and the wires through each."""
    lo3, hi3 = frame.wall_box(wall)
    a, b = _face(frame, wall, lo3), _face(frame, wall, hi3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    body = [_rect(lo, hi)]
    holes = [h for h in frame.holes if h.wall == wall]
    for hole in holes:
        centre = _face(frame, wall, hole.centre)
        body += _hole_mark(centre, hole)
        body.append(_text(centre[0] + 1.0, centre[1] - 1.3, hole.label, size=FONT_MM * 0.8, rotate=-45))
    right = _face(frame, wall, np.eye(3)[frame.across])[0] - _face(frame, wall, np.zeros(3))[0]
    body += _axis_arrows((hi[0] + 4, hi[1]), ("" if right > 0 else "-") + AXES[frame.across], AXES[UP])
    x = hi[0] + 16
    columns = (0.0, 7.0, 26.0, 33.0)  # hole, coordinates, diameter, wires (mm from the table's left)
    rows = [("hole", f"({', '.join(AXES)}) mm", "\u2300 mm", "wires")]
    rows += [(h.label, point_text(h.centre), mm(h.diameter_mm), ", ".join(h.wires)) for h in holes]
    for k, row in enumerate(rows):
        body += [_text(x + dx, lo[1] + k * 2.7, cell, weight="bold" if k == 0 else "normal")
                 for dx, cell in zip(columns, row)]
    width = columns[-1] + max(len(row[-1]) for row in rows) * FONT_MM * 0.6
    table_hi = np.array([x + width, max(hi[1], lo[1] + len(rows) * 2.7)])
    at = frame.front_mm if wall == "front" else frame.back_mm
    title = (f"{wall.capitalize()} wall, seen from outside: inner face at {AXES[frame.axis]} = {mm(at)} mm, "
             f"drill along {AXES[frame.axis]} (mm, phantom frame)")
    return _svg(lo, table_hi, title, body)


def view_svg(mesh: trimesh.Trimesh, title: str) -> str:
    """The mesh seen from the front, above and to the right (orthographic, flat shaded; faces
    drawn back to front)."""
    azimuth, elevation = np.radians(-35.0), np.radians(30.0)
    forward = -np.array([np.cos(elevation) * np.sin(azimuth), -np.cos(elevation) * np.cos(azimuth),
                         np.sin(elevation)])  # from the eye into the scene
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    light = -forward + up * 0.6
    light /= np.linalg.norm(light)
    triangles = mesh.triangles
    normals = mesh.face_normals
    facing = normals @ forward < 0
    shade = np.clip(normals @ light, 0.0, 1.0) * 0.75 + 0.2
    depth = (triangles.mean(axis=1) @ forward)
    flat = np.stack([triangles @ right, -(triangles @ up)], axis=-1)
    lo, hi = flat.reshape(-1, 2).min(axis=0), flat.reshape(-1, 2).max(axis=0)
    body = []
    for k in np.argsort(-depth):
        if not facing[k]:
            continue
        g = int(255 * shade[k])
        points = " ".join(f"{x:.2f},{y:.2f}" for x, y in flat[k])
        body.append(f'<polygon points="{points}" fill="rgb({g},{g},{min(255, g + 12)})" '
                    f'stroke="rgb({g},{g},{min(255, g + 12)})" stroke-width="0.05"/>')
    return _svg(lo, hi, title, body)
