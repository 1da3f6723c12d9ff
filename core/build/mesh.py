"""The printable frame as a watertight triangle mesh (trimesh, booleans by manifold3d), in the
phantom frame in mm: print it as it is and the wire end points sit where the definition says."""

from __future__ import annotations

import numpy as np
import trimesh

from probecal.core.build.walls import UP, Frame

HOLE_SECTIONS = 24
DIVOT_SECTIONS = 24


def _box(lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh:
    return trimesh.creation.box(bounds=np.array([lo, hi]))


def _along(axis: int) -> np.ndarray:
    """A rotation taking trimesh's primitive axis (z) onto phantom axis ``axis``."""
    target = np.eye(3)[axis]
    if axis == UP:
        return np.eye(4)
    return trimesh.geometry.align_vectors([0.0, 0.0, 1.0], target)


def _hole(frame: Frame, centre: np.ndarray, diameter_mm: float) -> trimesh.Trimesh:
    """A drill through the whole wall at ``centre`` (on the inner face), along the wall's normal."""
    length = 2 * frame.design.wall_thickness_mm + 2.0
    cylinder = trimesh.creation.cylinder(radius=diameter_mm / 2, height=length, sections=HOLE_SECTIONS,
                                         transform=_along(frame.axis))
    cylinder.apply_translation(centre)
    return cylinder


def _divot(depth_mm: float, apex: np.ndarray) -> trimesh.Trimesh:
    """A 90-degree cone pointing down with its apex at ``apex``, reaching ``depth_mm`` up to the
    surface and 1 mm above it (so the cut is clean)."""
    height = depth_mm + 1.0
    cone = trimesh.creation.cone(radius=height, height=height, sections=DIVOT_SECTIONS)
    cone.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1.0, 0.0, 0.0]))  # apex down, base at z=0
    cone.apply_translation(apex + [0.0, 0.0, height])
    return cone


def _axis_grooves(frame: Frame) -> list[trimesh.Trimesh]:
    """Two grooves in the base's top along +x and +y from the origin mark, each beginning a groove
    width away from it so that the divot there stays whole."""
    d = frame.design
    mark = frame.origin_mark()
    grooves = []
    for axis in (0, 1):
        lo, hi = mark.copy(), mark.copy()
        lo[axis] += d.groove_mm * 1.5
        hi[axis] += d.groove_mm * 1.5 + d.axis_length_mm
        other = 1 - axis
        lo[other] -= d.groove_mm / 2
        hi[other] += d.groove_mm / 2
        lo[UP] -= d.groove_mm
        hi[UP] += 1.0
        grooves.append(_box(lo, hi))
    # An arrow head on the x axis only, so the axes cannot be mistaken for each other.
    tip = mark.copy()
    tip[0] += d.groove_mm * 1.5 + d.axis_length_mm
    head = [tip + [0.0, s * d.groove_mm * 1.5, 0.0] for s in (-1.0, 1.0)] + [tip + [d.groove_mm * 2.5, 0.0, 0.0]]
    corners = [p + [0.0, 0.0, dz] for p in head for dz in (-d.groove_mm, 1.0)]
    grooves.append(trimesh.Trimesh(vertices=np.array(corners)).convex_hull)
    return grooves


def frame_mesh(frame: Frame) -> trimesh.Trimesh:
    """The frame (walls, base, holes, divots and the origin's engraved axes) as one watertight
    mesh in the phantom frame, mm."""
    solid = trimesh.boolean.union([_box(*frame.wall_box("front")), _box(*frame.wall_box("back")),
                                   _box(*frame.base_box())], engine="manifold")
    cuts = [_hole(frame, h.centre, h.diameter_mm) for h in frame.holes]
    cuts += [_divot(frame.design.divot_depth_mm, m.position) for m in frame.landmarks()]
    cuts += _axis_grooves(frame)
    mesh = trimesh.boolean.difference([solid, *cuts], engine="manifold")
    mesh.metadata["name"] = f"{frame.phantom.name} frame"
    return mesh
