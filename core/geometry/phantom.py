"""N-wire phantom model: wires, layers, the box they live in, and where an image plane cuts them.

All coordinates are in mm in the phantom frame. An N layer holds three coplanar wires in
definition order; the middle one (index 1) is the diagonal, the other two are the parallel
outer wires (design §1, §3).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from probecal.core.errors import InputError, quoted
from probecal.core.geometry.transforms import invert_transform, transform_points

DIAGONAL = 1  # index of the diagonal wire within an N layer
WIRE_LETTERS = "LDR"  # an N's wires in definition order: outer, diagonal, outer


def wire_label(wire: int) -> str:
    """The short name of wire ``wire`` (its index in the definition) that the live image, the
    plots and the reports share: '2D' is the diagonal wire of the second N layer."""
    return f"{wire // 3 + 1}{WIRE_LETTERS[wire % 3]}"


@dataclass(frozen=True)
class Wire:
    """A straight wire from ``front`` to ``back`` (mm, phantom frame)."""

    name: str
    front: np.ndarray
    back: np.ndarray

    @property
    def direction(self) -> np.ndarray:
        d = self.back - self.front
        return d / np.linalg.norm(d)


@dataclass(frozen=True)
class NLayer:
    """Three coplanar wires shaped like an N: outer, diagonal, outer."""

    name: str
    wires: tuple[Wire, Wire, Wire]

    @functools.cached_property
    def diagonal_anchors(self) -> tuple[np.ndarray, np.ndarray]:
        """Where the diagonal's line meets the lines of outer wire 1 and outer wire 3 (phantom, mm)."""
        w1, w2, w3 = self.wires
        return (_line_intersection(w2.front, w2.back, w1.front, w1.back),
                _line_intersection(w2.front, w2.back, w3.front, w3.back))


def _line_intersection(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Where two coplanar lines meet (the point on line a closest to line b)."""
    d1, d2, w = a1 - a0, b1 - b0, a0 - b0
    m = np.array([[d1 @ d1, -(d1 @ d2)], [d1 @ d2, -(d2 @ d2)]])
    s, _ = np.linalg.solve(m, [-(w @ d1), -(w @ d2)])
    return a0 + s * d1


@dataclass(frozen=True)
class Crossing:
    """Where one wire crosses an image plane.

    ``t`` is the fraction along the wire from its front end (0..1); for the diagonal wire this is
    the ratio along the diagonal. ``point_image`` is in the image frame in mm (z = 0 on the plane).
    """

    layer: int
    wire: int
    t: float
    point_phantom: np.ndarray
    point_image: np.ndarray

    @property
    def index(self) -> int:
        """Index of the wire in the phantom's flat wire order (N by N, wires in definition order)."""
        return 3 * self.layer + self.wire


@dataclass(frozen=True)
class Phantom:
    """An N-wire phantom: layers of three wires plus the box (mm) that holds them."""

    name: str
    layers: tuple[NLayer, ...]
    box_min: np.ndarray
    box_max: np.ndarray

    @property
    def wires(self) -> list[Wire]:
        """All wires in definition order: N by N, and within an N in definition order."""
        return [w for layer in self.layers for w in layer.wires]

    @property
    def n_wires(self) -> int:
        return 3 * len(self.layers)

    def lines(self) -> np.ndarray:
        """(W, 2, 3) array of wire front and back end points, mm."""
        return np.array([[w.front, w.back] for w in self.wires])

    def layer_shifts(self, layer_to_placed: np.ndarray) -> np.ndarray:
        """(W, 2, 3) end-point shifts (mm) that move each layer rigidly about the centre of its
        end points by ``layer_to_placed`` ((L, 4, 4), that centre's frame, axes as the phantom's):
        layers strung or glued off their place, whole."""
        ends = self.lines().reshape(len(self.layers), -1, 3)  # every layer's end points
        centres = ends.mean(axis=1, keepdims=True)
        placed = np.einsum("lij,lpj->lpi", layer_to_placed[:, :3, :3], ends - centres) + layer_to_placed[:, None, :3, 3]
        return (placed + centres - ends).reshape(self.n_wires, 2, 3)

    def _diagonal_across(self) -> np.ndarray:
        """(L, 3) unit vectors across each layer's diagonal wire within the layer's plane."""
        across = []
        for layer in self.layers:
            outer, diagonal = (w.back - w.front for w in layer.wires[:2])
            direction = np.cross(np.cross(outer, diagonal), diagonal)
            across.append(direction / np.linalg.norm(direction))
        return np.array(across)

    def diagonal_shifts(self, offsets_mm: np.ndarray) -> np.ndarray:
        """(W, 2, 3) end-point shifts (mm) that move each layer's diagonal wire's front and back
        end by ``offsets_mm`` ((L, 2) mm) across the wire within its layer's plane: the N keeps its
        shape in every image, only the ratio its diagonal sets changes along the wires."""
        shifts = np.zeros((self.n_wires, 2, 3))
        shifts[1::3] = np.asarray(offsets_mm, dtype=float)[..., None] * self._diagonal_across()[:, None]
        return shifts

    def diagonal_turns(self, shifts_mm: np.ndarray) -> np.ndarray:
        """(L,) how far (mm) end-point shifts ``shifts_mm`` ((W, 2, 3)) turn each layer's diagonal
        about its middle within the layer: half its back end's shift across it less its front
        end's (``diagonal_shifts`` with offsets ``(-t, t)`` turns it by ``t``)."""
        ends = np.asarray(shifts_mm, dtype=float)[1::3]  # (L, 2, 3) the diagonals' end-point shifts
        return 0.5 * np.einsum("li,li->l", ends[:, 1] - ends[:, 0], self._diagonal_across())

    def moved(self, shifts_mm: np.ndarray) -> Phantom:
        """The phantom with every wire's front and back end points moved by ``shifts_mm``
        ((W, 2, 3) mm, definition order): a phantom as built, or as a calibration fitted it."""
        shifts = iter(np.asarray(shifts_mm, dtype=float))

        def moved_layer(layer: NLayer) -> NLayer:
            first, diagonal, last = (Wire(w.name, w.front + s[0], w.back + s[1]) for w, s in zip(layer.wires, shifts))
            return NLayer(layer.name, (first, diagonal, last))

        return replace(self, layers=tuple(moved_layer(layer) for layer in self.layers))

    def point_cloud(self, points_per_wire: int = 1000) -> np.ndarray:
        """The thesis's virtual phantom: (W * points_per_wire, 3) points evenly along every wire."""
        t = np.linspace(0.0, 1.0, points_per_wire)[:, None]
        return np.concatenate([w.front + t * (w.back - w.front) for w in self.wires])

    def center(self) -> np.ndarray:
        """Centre of the wire end points (mm), a natural aiming point for the probe."""
        return self.lines().reshape(-1, 3).mean(axis=0)

    def crossings(self, image_to_phantom: np.ndarray) -> list[Crossing]:
        """Every wire crossing of the image plane z = 0, for a rigid image (mm) to phantom transform.

        Wires parallel to the plane or cut outside their end points give no crossing.
        """
        phantom_to_image = invert_transform(image_to_phantom)
        ends = transform_points(phantom_to_image, self.lines())  # (W, 2, 3) in image mm
        wires = self.wires
        out = []
        for k, (a, b) in enumerate(ends):
            dz = a[2] - b[2]
            if abs(dz) < 1e-12:
                continue
            t = a[2] / dz
            if not 0.0 <= t <= 1.0:
                continue
            point_image = a + t * (b - a)
            point_image[2] = 0.0
            w = wires[k]
            out.append(
                Crossing(
                    layer=k // 3,
                    wire=k % 3,
                    t=float(t),
                    point_phantom=w.front + t * (w.back - w.front),
                    point_image=point_image,
                )
            )
        return out

    def crossing_points(self, image_to_phantom: np.ndarray) -> np.ndarray:
        """(W, 2) where every wire crosses the image plane z = 0 (image x, y mm), as
        :meth:`crossings` finds them, for all wires at once; NaN where a wire gives no crossing."""
        ends = transform_points(invert_transform(image_to_phantom), self.lines())  # (W, 2, 3) in image mm
        a, b = ends[:, 0], ends[:, 1]
        dz = a[:, 2] - b[:, 2]
        t = np.divide(a[:, 2], dz, out=np.full(len(dz), np.nan), where=np.abs(dz) >= 1e-12)
        t[~((t >= 0.0) & (t <= 1.0))] = np.nan
        return a[:, :2] + t[:, None] * (b - a)[:, :2]

    def wire_distances(self, points: np.ndarray, wire_indices: np.ndarray) -> np.ndarray:
        """Distance (mm) from each phantom-frame point to the infinite line of its wire."""
        return np.linalg.norm(wire_offsets(self.lines()[np.asarray(wire_indices)], points), axis=-1)



def wire_axes(lines: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For wires given by their end points (..., 2, 3), mm: each one's front end (..., 3), unit
    direction (..., 3), length (...,) in mm and the projection across it (..., 3, 3)."""
    lines = np.asarray(lines, dtype=float)
    span = lines[..., 1, :] - lines[..., 0, :]
    length = np.linalg.norm(span, axis=-1)
    d = span / length[..., None]
    return lines[..., 0, :], d, length, np.eye(3) - d[..., :, None] * d[..., None, :]


def wire_offsets(lines: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 3) offset (mm) of each point from the infinite line of its wire, across the wire: the
    wires' end points (..., 2, 3) broadcast against the points (..., 3), in one frame."""
    front, _, _, across = wire_axes(lines)
    return np.einsum("...ij,...j->...i", across, np.asarray(points, dtype=float) - front)


def nwire_ratio(left: np.ndarray, middle: np.ndarray, right: np.ndarray) -> float:
    """|LM| / |LR| from the three collinear dots of one N (thesis eq. 3.9); any consistent units."""
    return float(np.linalg.norm(middle - left) / np.linalg.norm(right - left))


MAX_LAYERS = 16
"""The most N layers a phantom definition may have (48 wires). PLUS's fCal 1.2 and 2.0 phantoms
have 3, its NwirePhantomFreehand and iCal phantoms 2, probecal's thesis-4layer 4: 16 is four
times the most of any, and more than a frame can show apart (16 layers a frame's 50 mm deep lie 3
mm apart). Every wire costs every crossing the planner and the twin compute and every frame's
labelling, so a definition of thousands of layers would run for hours before failing."""
REACH_MM = 1000.0
"""How far from the phantom frame's origin (mm, along each axis) a definition's points may lie:
PLUS's fCal phantoms and ours lie within 150 mm of theirs, and a phantom held in a water tank under
a UR3 (0.5 m reach) is smaller than a metre. Past it a point is a typing error or an attack (a wire
at 1e300 mm overflows the squares its geometry needs)."""


NAME_CHARS = 64
"""The longest name a phantom, a layer or a wire may have: PLUS's are a dozen characters
(``7:G1_g1``), and a name becomes a file's name when the phantom is exported to be built."""


def check_name(name: str, what: str, source: str | Path) -> str:
    """``name`` if it has at most :data:`NAME_CHARS` characters; InputError naming ``source``
    and ``what`` otherwise."""
    if len(name) > NAME_CHARS:
        raise InputError(source, f"{what} {quoted(name)} is longer than {NAME_CHARS} characters")
    return name


def check_layer_count(count: int, source: str | Path) -> None:
    """InputError naming ``source`` for a definition of more than :data:`MAX_LAYERS` N layers,
    before any of them is read."""
    if count > MAX_LAYERS:
        raise InputError(source, f"{count} N layers: a phantom has at most {MAX_LAYERS}")


def check_point(point: np.ndarray, what: str, source: str | Path) -> np.ndarray:
    """``point`` (mm, phantom frame) if every coordinate is finite and within :data:`REACH_MM` of
    the origin; InputError naming ``source`` and ``what`` otherwise (checked before any arithmetic
    on it)."""
    point = np.asarray(point, dtype=float)
    if not np.all(np.isfinite(point)):
        raise InputError(source, f"{what} is not finite")
    if not np.all(np.abs(point) <= REACH_MM):
        shown = " ".join(f"{v:g}" for v in point.ravel()[:3])
        raise InputError(source, f"{what} ({shown} mm) lies beyond {REACH_MM:g} mm of the phantom's origin")
    return point


PARALLEL_TOLERANCE = np.sin(np.radians(1.0))
"""How far from parallel (sine of the angle) the outer wires of an N may be, and how close to
them the diagonal may not be."""
PLANE_TOLERANCE_MM = 1.0
"""How far out of its N's plane a diagonal's end may lie. Both tolerances admit a phantom as
built (wires off by tenths of a mm, ``probecal phantom check --as-built``) and refuse a mistyped
definition."""


def validate_layers(layers: list[NLayer], source: str | Path) -> None:
    """Check a definition's layers: at most :data:`MAX_LAYERS`, names of at most
    :data:`NAME_CHARS`, every end point within :data:`REACH_MM` (:func:`check_point`), then the N
    geometry: parallel outer wires, a
    non-parallel coplanar diagonal (within :data:`PARALLEL_TOLERANCE` and
    :data:`PLANE_TOLERANCE_MM`). Raises InputError."""
    if not layers:
        raise InputError(source, "phantom has no N-wire layers")
    check_layer_count(len(layers), source)
    for layer in layers:
        check_name(layer.name, "layer name", source)
        for w in layer.wires:
            check_name(w.name, "wire name", source)
            check_point(w.front, f"wire {quoted(w.name)} front end", source)
            check_point(w.back, f"wire {quoted(w.name)} back end", source)
    for layer in layers:
        left, diag, right = layer.wires
        for w in layer.wires:
            if np.linalg.norm(w.back - w.front) < 1e-6:
                raise InputError(source, f"wire {quoted(w.name)} has zero length")
        if np.linalg.norm(np.cross(left.direction, right.direction)) > PARALLEL_TOLERANCE:
            raise InputError(source, f"layer {quoted(layer.name)}: outer wires are not parallel")
        if np.linalg.norm(np.cross(left.direction, diag.direction)) < PARALLEL_TOLERANCE:
            raise InputError(source, f"layer {quoted(layer.name)}: diagonal is parallel to the outer wires")
        normal = np.cross(left.direction, right.front - left.front)
        if np.linalg.norm(normal) < 1e-6:
            raise InputError(source, f"layer {quoted(layer.name)}: outer wires coincide")
        normal /= np.linalg.norm(normal)
        off_plane = max(abs(np.dot(p - left.front, normal)) for p in (diag.front, diag.back))
        if off_plane > PLANE_TOLERANCE_MM:
            raise InputError(
                source, f"layer {quoted(layer.name)}: diagonal is {off_plane:.3f} mm out of the N plane"
            )
