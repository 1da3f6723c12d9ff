"""Where a phantom's wires meet the frame that holds them: two parallel walls, one hole at every
distinct wire end point, a base under both walls, and the landmarks (divots) a tracked stylus
touches to register the built phantom.

All coordinates are in mm in the phantom frame. The wires run horizontally, along x or y, from
the front wall's inner face to the back wall's; z points up, toward the probe (design §3), so the
base lies below the lowest wire.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom

AXES = "xyz"
UP = 2
FACE_TOLERANCE_MM = 1e-3  # how far an end point may lie off its wall's inner face
MIN_WEB_MM = 1.0  # the least material between two holes


@dataclass(frozen=True)
class FrameDesign:
    """The printed frame's dimensions (mm). A hole that carries ``n`` wires is ``hole_diameter_mm``
    plus ``n - 1`` wire diameters wide."""

    wire_diameter_mm: float = 0.3
    hole_diameter_mm: float = 0.5
    wall_thickness_mm: float = 5.0
    margin_mm: float = 10.0
    """How far each wall reaches beyond its outermost holes, sideways and up."""
    base_thickness_mm: float = 5.0
    clearance_mm: float = 10.0
    """From the base's top to the lowest wire: room for the wire's echo to clear the base's."""
    divot_depth_mm: float = 1.0
    """Depth of the 90-degree conical landmark divots (their radius at the surface is the same)."""
    groove_mm: float = 1.0
    """Width and depth of the engraved axes at the origin mark."""
    axis_length_mm: float = 10.0
    """Length of each engraved axis at the origin mark."""

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.hole_diameter_mm <= self.wire_diameter_mm:
            raise ValueError(f"holes of {self.hole_diameter_mm} mm cannot take a {self.wire_diameter_mm} mm wire")


@dataclass(frozen=True)
class Hole:
    """A hole through a wall at one wire end point: ``label`` (F1, F2, ... on the front wall, B1,
    ... on the back), ``centre`` on the wall's inner face (mm), the wires through it (definition
    order) and its diameter (mm)."""

    label: str
    wall: str
    centre: np.ndarray
    wires: tuple[str, ...]
    diameter_mm: float


@dataclass(frozen=True)
class Landmark:
    """A conical divot for a tracked stylus: its name and apex (mm), where a sharp tip rests."""

    name: str
    position: np.ndarray


@dataclass(frozen=True)
class Frame:
    """The frame of a phantom: two walls across ``axis`` with their inner faces at ``front_mm``
    and ``back_mm``, spanning ``across`` (the other horizontal axis) over ``across_mm`` and z over
    ``z_mm``; the base under both; the holes and the landmarks."""

    phantom: Phantom
    design: FrameDesign
    axis: int
    across: int
    front_mm: float
    back_mm: float
    across_mm: tuple[float, float]
    z_mm: tuple[float, float]
    holes: tuple[Hole, ...]

    @property
    def outward(self) -> float:
        """+1 when the back wall lies at the larger coordinate along ``axis``, else -1."""
        return 1.0 if self.back_mm > self.front_mm else -1.0

    @property
    def base_top_mm(self) -> float:
        return self.z_mm[0]

    def wall_box(self, wall: str) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners (mm) of the ``front`` or ``back`` wall."""
        inner, sign = (self.front_mm, -self.outward) if wall == "front" else (self.back_mm, self.outward)
        outer = inner + sign * self.design.wall_thickness_mm
        return self._box((min(inner, outer), max(inner, outer)), self.across_mm, self.z_mm)

    def base_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners (mm) of the base: under both walls, and wide enough for the origin
        mark wherever the origin lies."""
        t = self.design.wall_thickness_mm
        along = (min(self.front_mm, self.back_mm) - t, max(self.front_mm, self.back_mm) + t)
        reach = self.design.axis_length_mm + 2 * self.design.groove_mm
        mark = self.design.margin_mm / 2
        along = (min(along[0], -mark), max(along[1], reach))
        across = (min(self.across_mm[0], -mark), max(self.across_mm[1], reach))
        top = self.base_top_mm
        return self._box(along, across, (top - self.design.base_thickness_mm, top))

    def _box(self, along: tuple[float, float], across: tuple[float, float],
             z: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.zeros(3), np.zeros(3)
        for axis, (a, b) in ((self.axis, along), (self.across, across), (UP, z)):
            lo[axis], hi[axis] = a, b
        return lo, hi

    def origin_mark(self) -> np.ndarray:
        """Where the phantom origin's mark is: on the base's top, straight above or below the
        origin (mm)."""
        point = np.zeros(3)
        point[UP] = self.base_top_mm
        return point

    def landmarks(self) -> tuple[Landmark, ...]:
        """Divots a stylus can touch: the origin mark, two on top of each wall and four on the
        base's top between the walls, all in view from above."""
        inset = self.design.margin_mm / 2
        t = self.design.wall_thickness_mm
        sides = (self.across_mm[0] + inset, self.across_mm[1] - inset)
        points = [("origin", self.origin_mark())]
        for wall, inner in (("front", self.front_mm), ("back", self.back_mm)):
            sign = -self.outward if wall == "front" else self.outward
            for side, across in zip(("left", "right"), sides):
                points.append((f"{wall} wall {side}", self._point(inner + sign * t / 2, across, self.z_mm[1])))
        for wall, inner in (("front", self.front_mm), ("back", self.back_mm)):
            sign = self.outward if wall == "front" else -self.outward
            for side, across in zip(("left", "right"), sides):
                points.append((f"base {wall} {side}", self._point(inner + sign * inset, across, self.base_top_mm)))
        return tuple(Landmark(name, point) for name, point in points)

    def _point(self, along: float, across: float, z: float) -> np.ndarray:
        point = np.zeros(3)
        point[self.axis], point[self.across], point[UP] = along, across, z
        return point

    def seen_from_outside(self, wall: str, point: np.ndarray) -> np.ndarray:
        """``point`` (mm) as someone facing the ``front`` or ``back`` wall from outside sees it:
        (to the right, up) in mm, from the wall's bottom left corner."""
        normal = np.eye(3)[self.axis] * (self.outward if wall == "back" else -self.outward)
        right = np.cross(-normal, np.eye(3)[UP])
        lo, hi = self.wall_box(wall)
        left = min(right @ lo, right @ hi)
        return np.array([right @ point - left, point[UP] - self.base_top_mm])

    def wire_holes(self) -> list[tuple[Hole, Hole]]:
        """The (front, back) holes of every wire, in definition order."""
        by_wire: dict[tuple[str, str], Hole] = {(h.wall, w): h for h in self.holes for w in h.wires}
        return [(by_wire[("front", w.name)], by_wire[("back", w.name)]) for w in self.phantom.wires]

    @property
    def extent_mm(self) -> np.ndarray:
        """The printed frame's size (x, y, z) in mm."""
        boxes = [self.wall_box("front"), self.wall_box("back"), self.base_box()]
        return np.max([hi for _, hi in boxes], axis=0) - np.min([lo for lo, _ in boxes], axis=0)


def _face(points: np.ndarray, what: str, source: str | Path | None) -> tuple[int, float]:
    """The axis (x or y) on which every point of ``points`` (N, 3) shares one coordinate, and that
    coordinate; InputError when there is none."""
    for axis in (0, 1):
        spread = np.ptp(points[:, axis])
        if spread <= FACE_TOLERANCE_MM:
            return axis, float(np.mean(points[:, axis]))
    raise InputError(source, f"the wires' {what} end points do not lie on one wall: a printable frame needs them all "
                             "at one x or one y (the wires run horizontally, z up)")


def _holes(phantom: Phantom, wall: str, prefix: str, ends: np.ndarray, design: FrameDesign,
           across: int) -> list[Hole]:
    """One hole per distinct end point on a wall, labelled top row first, then along ``across``."""
    groups: list[tuple[np.ndarray, list[str]]] = []
    for wire, point in zip(phantom.wires, ends):
        for centre, names in groups:
            if np.linalg.norm(centre - point) <= FACE_TOLERANCE_MM:
                names.append(wire.name)
                break
        else:
            groups.append((point, [wire.name]))
    groups.sort(key=lambda g: (-g[0][UP], g[0][across]))
    return [Hole(f"{prefix}{k + 1}", wall, centre, tuple(names),
                 design.hole_diameter_mm + (len(names) - 1) * design.wire_diameter_mm)
            for k, (centre, names) in enumerate(groups)]


def _check_spacing(holes: list[Hole], source: str | Path | None) -> None:
    for i, a in enumerate(holes):
        for b in holes[i + 1:]:
            web = np.linalg.norm(a.centre - b.centre) - (a.diameter_mm + b.diameter_mm) / 2
            if web < MIN_WEB_MM:
                raise InputError(source, f"holes {a.label} and {b.label} leave {web:.2f} mm of wall between them, "
                                         f"less than the {MIN_WEB_MM:g} mm a print holds")


def frame_of(phantom: Phantom, design: FrameDesign = FrameDesign(), source: str | Path | None = None) -> Frame:
    """The frame that holds ``phantom``'s wires; InputError naming ``source`` (the definition's
    file) when the wires do not run between two parallel walls or holes crowd each other."""
    lines = phantom.lines()
    axis, front = _face(lines[:, 0], "front", source)
    back_axis, back = _face(lines[:, 1], "back", source)
    if back_axis != axis or abs(back - front) <= FACE_TOLERANCE_MM:
        raise InputError(source, f"the wires' front ends lie at {AXES[axis]} = {front:g} mm but their back ends do "
                                 "not lie on a wall parallel to it")
    across = 1 - axis
    holes = (_holes(phantom, "front", "F", lines[:, 0], design, across)
             + _holes(phantom, "back", "B", lines[:, 1], design, across))
    for wall in ("front", "back"):
        _check_spacing([h for h in holes if h.wall == wall], source)
    centres = np.array([h.centre for h in holes])
    margin = design.margin_mm
    return Frame(
        phantom=phantom,
        design=design,
        axis=axis,
        across=across,
        front_mm=front,
        back_mm=back,
        across_mm=(float(centres[:, across].min() - margin), float(centres[:, across].max() + margin)),
        z_mm=(float(centres[:, UP].min() - design.clearance_mm), float(centres[:, UP].max() + margin)),
        holes=tuple(holes),
    )
