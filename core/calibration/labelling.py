"""Label wire dots: find the N-wire pattern among dot candidates (design §1 step 3).

In the spirit of PLUS's line finder: every N layer shows three collinear dots, the diagonal's dot
between the two outer ones, the outer dots as far apart as the outer wires (a little more when
the image plane is tilted), and the lines of the layers are parallel and as far apart as the
layers. The search enumerates collinear triples, then chains one triple per layer from the
shallowest layer down. Complete chains are ranked by how well one affine map of the image plane
into the phantom puts every dot on its own wire (:func:`affine_residual_mm`), which ties the
layers together: a wrong dot in any layer shows. A second, different chain that fits almost as
well makes the frame ambiguous: it is rejected rather than guessed. The affine map may shear,
and with parallel wires a wrong dot far along its layer's line hides in that shear, so the chosen
chain must also fit a rigid map (:func:`rigid_fit`) almost as well (:func:`rigid_excess_mm`).

Frames and units: dot candidates are pixels (u = column, v = row); the geometry checks run in
image mm, ``(u * sx, v * sy)`` with the approximate spacing ``(sx, sy)`` mm/px. The phantom is in
mm in its own frame.

Which layer is shallowest and which outer wire is on the left cannot always be told from one
frame (the default phantom is mirror-symmetric), so it comes from an :class:`Orientation`: the
phantom-frame directions along which the image's +u (left to right) and +v (depth) point.
Assumption: the N layers lie in parallel planes and their outer wires are parallel (true of the
thesis phantom and of PLUS's fCal and iCAL phantoms).

For comparison, ``core.calibration.pluslabelling`` clones PLUS's own search (its line finder and
first-fit labelling, near-ties decided as PLUS decides them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from probecal.core.geometry.phantom import DIAGONAL, Phantom

_ORTHOGONAL = np.zeros((9, 9))  # p^T Q p = a . b for the affine unknowns p = (o, a, b)
_ORTHOGONAL[3:6, 6:9] = _ORTHOGONAL[6:9, 3:6] = np.eye(3) / 2
RIGID_EXCESS_MM = 0.25  # a true pattern fits a rigid map almost as well as an affine one
RIVALS_CHECKED = 8  # patterns nearly as good as the best by the affine fit, told apart by the rigid one


@dataclass(frozen=True)
class Orientation:
    """Phantom-frame unit vectors along which image +u (lateral) and +v (depth) roughly point."""

    lateral: tuple[float, float, float]
    depth: tuple[float, float, float]


# probecal's simulated and robot sessions: the image x axis along phantom +x and depth along
# phantom -z, so wire 1 of each N (smaller x) is on the left and the layer with the largest z is
# the shallowest (core.acquisition.plan.image_across_wires).
SIMULATED = Orientation(lateral=(1.0, 0.0, 0.0), depth=(0.0, 0.0, -1.0))


def plus_orientation(phantom: Phantom) -> Orientation:
    """PLUS's labelling convention expressed as geometry.

    PLUS (PlusFidLabeling) sorts the lines by depth and gives them to the N layers in definition
    order, shallowest first, and within a line numbers the dots from right to left: the first
    wire of each N is the dot nearest the transducer's marked side, which is the right (largest u)
    in PLUS's "MF" image orientation. For fCal 1.2 that is image +u along phantom -x and depth
    along -z; for the iCAL/VLCUS phantom +u along +x and depth along -y.
    """
    first = phantom.layers[0].wires
    along = first[0].direction
    across = first[0].front - first[2].front  # from wire 3 (left) to wire 1 (right)
    lateral = across - np.dot(across, along) * along
    normal = np.cross(along, lateral)
    if len(phantom.layers) > 1:
        normal *= np.sign(np.dot(phantom.layers[-1].wires[0].front - first[0].front, normal)) or 1.0
    return Orientation(lateral=_unit(lateral), depth=_unit(normal))


def _unit(v: np.ndarray) -> tuple[float, float, float]:
    x, y, z = v / np.linalg.norm(v)
    return float(x), float(y), float(z)


@dataclass(frozen=True)
class Tolerances:
    """Acceptance limits of the pattern search (mm, degrees, fractions)."""

    scale_error: float = 0.10  # outer distances and layer gaps against the phantom's (spacing error)
    max_tilt_deg: float = 25.0  # image-plane tilt allowed for: distances grow up to 1 / cos(tilt)
    outer_consistency: float = 0.05  # spread of the outer-distance ratios across the layers
    gap_consistency: float = 0.15  # spread of the layer-gap ratios
    collinear_mm: float = 0.5  # middle dot's distance from the outer dots' line
    max_line_angle_deg: float = 30.0  # lines' angle from the image rows
    max_angle_difference_deg: float = 4.0  # between the lines of different layers
    max_shift_mm: float = 3.0  # along the lines, between consecutive layers, beyond the phantom's
    max_residual_mm: float = 0.3  # RMS distance of the dots from their wires under the best affine map
    ambiguity: float = 1.3  # a different pattern with a residual below ambiguity * best + ambiguity_mm
    ambiguity_mm: float = 0.02  # makes the frame ambiguous
    max_rigid_excess_mm: float = RIGID_EXCESS_MM  # rigid fit's RMS over the affine one (see rigid_excess_mm)

    @classmethod
    def from_plus_hints(cls, hints: dict[str, str]) -> Tolerances:
        """Defaults overridden by a PLUS ``<Segmentation>`` element's limits where it gives them."""
        pick = {
            "scale_error": ("MaxLinePairDistanceErrorPercent", 0.01),
            "collinear_mm": ("CollinearPointsMaxDistanceFromLineMm", 1.0),
            "max_residual_mm": ("CollinearPointsMaxDistanceFromLineMm", 1.0),
            "max_angle_difference_deg": ("MaxAngleDifferenceDegrees", 1.0),
            "max_shift_mm": ("MaxLineShiftMm", 1.0),
        }
        values = {name: float(hints[key]) * scale for name, (key, scale) in pick.items() if hints.get(key)}
        thetas = [abs(float(hints[k])) for k in ("MinThetaDegrees", "MaxThetaDegrees") if hints.get(k)]
        if thetas:
            values["max_line_angle_deg"] = max(thetas)
        return cls(**values)

    @classmethod
    def robust(cls) -> Tolerances:
        """Limits for real scanners without hand tuning: the nominal spacing may be 15 % off (and
        differ between u and v), a stepper or a rotated probe tilts the lines up to 60 degrees,
        and smeared real dots sit up to 1 mm off their line. The affine fit of the whole pattern
        (0.4 mm RMS) and the ambiguity test keep wrong patterns out."""
        return cls(scale_error=0.15, max_line_angle_deg=60.0, collinear_mm=1.0, max_residual_mm=0.4)

    def ratio_range(self) -> tuple[float, float]:
        """Allowed measured / phantom ratio of an outer distance or a layer gap."""
        return 1.0 - self.scale_error, (1.0 + self.scale_error) / np.cos(np.radians(self.max_tilt_deg))


@dataclass(frozen=True)
class PatternModel:
    """What the N layers should look like, layers ordered from shallow to deep (mm).

    ``wire_index[l]`` are the phantom wire indices of the (left, middle, right) dots of layer l;
    ``diagonal_range[l]`` the span of the middle dot as a fraction of the left-to-right distance
    (exact for any cut, since the outer wires are parallel); ``gap_mm`` and ``shift_mm`` the
    distance between consecutive layer planes and the lateral offset of the next layer's outer
    wires' midpoint.
    """

    wire_index: np.ndarray  # (L, 3) int
    outer_mm: np.ndarray  # (L,)
    diagonal_range: np.ndarray  # (L, 2)
    gap_mm: np.ndarray  # (L - 1,)
    shift_mm: np.ndarray  # (L - 1,)
    wire_point: np.ndarray  # (L, 3, 3) a point of each of those wires, phantom mm
    wire_direction: np.ndarray  # (L, 3, 3) unit direction of each of those wires

    @property
    def n_layers(self) -> int:
        return len(self.outer_mm)

    @classmethod
    def from_phantom(cls, phantom: Phantom, orientation: Orientation) -> PatternModel:
        lateral, depth = np.asarray(orientation.lateral, float), np.asarray(orientation.depth, float)
        rows = []
        for k, layer in enumerate(phantom.layers):
            first, diagonal, last = layer.wires
            along = first.direction
            across = last.front - first.front
            across = across - np.dot(across, along) * along
            across /= np.linalg.norm(across)
            if np.dot(across, lateral) < 0:
                across = -across
            x_first, x_last = np.dot(first.front, across), np.dot(last.front, across)
            left, right = (0, 2) if x_first < x_last else (2, 0)
            x_left, outer = min(x_first, x_last), abs(x_last - x_first)
            span = (np.dot([diagonal.front, diagonal.back], across) - x_left) / outer
            rows.append({
                "index": [3 * k + left, 3 * k + DIAGONAL, 3 * k + right],
                "outer": outer,
                "span": np.sort(span),
                "depth": np.dot(first.front, depth),
                "normal": np.cross(along, across),
                "point": first.front,
                "middle": (first.front + last.front) / 2,
                "across": across,
            })
        rows.sort(key=lambda r: r["depth"])
        pairs = list(zip(rows, rows[1:]))
        gaps = [abs(np.dot(b["point"] - a["point"], a["normal"])) for a, b in pairs]
        shifts = [np.dot(b["middle"] - a["middle"], a["across"]) for a, b in pairs]
        return cls(
            wire_index=np.array([r["index"] for r in rows], dtype=int),
            outer_mm=np.array([r["outer"] for r in rows]),
            diagonal_range=np.array([r["span"] for r in rows]),
            gap_mm=np.array(gaps),
            shift_mm=np.array(shifts),
            wire_point=np.array([[phantom.wires[i].front for i in r["index"]] for r in rows]),
            wire_direction=np.array([[phantom.wires[i].direction for i in r["index"]] for r in rows]),
        )


    def without_layer(self, layer: int) -> PatternModel:
        """The pattern of the other layers: a sub-pattern to find when one layer's dots are not
        all seen. Gaps and shifts across the dropped layer add up (the layers are parallel)."""
        keep = [k for k in range(self.n_layers) if k != layer]
        gap = np.concatenate([[0.0], np.cumsum(self.gap_mm)])
        shift = np.concatenate([[0.0], np.cumsum(self.shift_mm)])
        return PatternModel(
            wire_index=self.wire_index[keep],
            outer_mm=self.outer_mm[keep],
            diagonal_range=self.diagonal_range[keep],
            gap_mm=np.diff(gap[keep]),
            shift_mm=np.diff(shift[keep]),
            wire_point=self.wire_point[keep],
            wire_direction=self.wire_direction[keep],
        )


@dataclass(frozen=True)
class Labelling:
    """Outcome of the pattern search: ``dots`` (L, 3) candidate indices of the (left, middle,
    right) dots per layer, shallow to deep, or None with the reason; ``ambiguous`` when more than
    one pattern fits, with ``rivals``: the best pattern, then every other that fits almost as well
    (each (L, 3) candidate indices); ``residual_mm`` the best pattern's :func:`affine_residual_mm`."""

    dots: np.ndarray | None
    reason: str
    residual_mm: float = np.inf
    ambiguous: bool = False
    rivals: tuple[np.ndarray, ...] = ()


@dataclass(frozen=True)
class _Triples:
    """Collinear dot triples (T of them) and their line features in image mm."""

    dots: np.ndarray  # (T, 3) left, middle, right candidate indices
    length: np.ndarray  # (T,) left-to-right distance
    fraction: np.ndarray  # (T,) middle dot's position along it, 0..1
    direction: np.ndarray  # (T, 2) unit, left to right
    midpoint: np.ndarray  # (T, 2) of the outer dots


def _triples(q: np.ndarray, longest: float, shortest: float, tol: Tolerances) -> _Triples:
    """All (left, middle, right) triples with the outer dots ``shortest..longest`` mm apart, a
    line within the angle limit, and a middle dot between them within ``collinear_mm``."""
    pairs = cKDTree(q).query_pairs(longest, output_type="ndarray").reshape(-1, 2)
    pairs = np.where((q[pairs[:, 0], 0] <= q[pairs[:, 1], 0])[:, None], pairs, pairs[:, ::-1])
    vec = q[pairs[:, 1]] - q[pairs[:, 0]]
    length = np.hypot(vec[:, 0], vec[:, 1])
    angle = np.degrees(np.abs(np.arctan2(vec[:, 1], vec[:, 0])))
    keep = (length >= shortest) & (angle <= tol.max_line_angle_deg)
    pairs, vec, length = pairs[keep], vec[keep], length[keep]
    direction = vec / length[:, None]
    rel = q[None, :, :] - q[pairs[:, 0]][:, None, :]  # (P, K, 2)
    along = np.einsum("pkc,pc->pk", rel, direction)
    across = np.abs(rel[..., 1] * direction[:, None, 0] - rel[..., 0] * direction[:, None, 1])
    fraction = along / length[:, None]
    inside = (fraction > 0.0) & (fraction < 1.0) & (across <= tol.collinear_mm)
    inside[np.arange(len(pairs))[:, None], pairs] = False
    p, k = np.nonzero(inside)
    left, right = pairs[p, 0], pairs[p, 1]
    return _Triples(
        dots=np.column_stack([left, k, right]).astype(int),
        length=length[p],
        fraction=fraction[p, k],
        direction=direction[p],
        midpoint=(q[left] + q[right]) / 2,
    )


def _pair_checks(tr: _Triples, a: np.ndarray, b: np.ndarray, model: PatternModel, layer: int,
                 tol: Tolerances) -> tuple[np.ndarray, np.ndarray]:
    """For triples a (layer) x b (layer + 1): allowed mask and gap ratio (A, B)."""
    da, db = tr.direction[a][:, None], tr.direction[b][None, :]
    cos = np.clip((da * db).sum(-1), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    mean_dir = da + db
    mean_dir /= np.linalg.norm(mean_dir, axis=-1, keepdims=True)
    normal = np.stack([-mean_dir[..., 1], mean_dir[..., 0]], axis=-1)  # points to +v (deeper)
    step = tr.midpoint[b][None, :] - tr.midpoint[a][:, None]
    gap = (step * normal).sum(-1) / model.gap_mm[layer]
    scale = (tr.length[a][:, None] / model.outer_mm[layer] + tr.length[b][None, :] / model.outer_mm[layer + 1]) / 2
    shift = (step * mean_dir).sum(-1) - model.shift_mm[layer] * scale
    lo, hi = tol.ratio_range()
    ok = (angle <= tol.max_angle_difference_deg) & (gap >= lo) & (gap <= hi) & (np.abs(shift) <= tol.max_shift_mm)
    return ok, gap


def _affine_system(points_mm: np.ndarray, model: PatternModel) -> tuple[np.ndarray, np.ndarray]:
    """Design (C, 3n, 9) and target (1, 3n) of the affine map ``p = o + x a + y b`` that puts C
    candidate labellings' dots ``points_mm`` (C, L, 3, 2) on their wires (see below)."""
    c = len(points_mm)
    x, y = points_mm[..., 0].reshape(c, -1, 1, 1), points_mm[..., 1].reshape(c, -1, 1, 1)
    d = model.wire_direction.reshape(-1, 3)
    project = np.eye(3) - d[:, :, None] * d[:, None, :]  # (n, 3, 3) removes the along-wire part
    design = np.concatenate([np.broadcast_to(project, x.shape[:2] + (3, 3)), x * project, y * project], axis=-1)
    target = np.einsum("nij,nj->ni", project, model.wire_point.reshape(-1, 3)).reshape(1, -1)
    return design.reshape(c, -1, 9), target


def predict_layer_mm(points_mm: np.ndarray, model: PatternModel, full: PatternModel, layer: int) -> np.ndarray:
    """Image mm (3, 2) where ``full``'s layer ``layer`` cuts the image plane, from one labelling
    ``points_mm`` (L, 3, 2) of ``model`` (a sub-pattern of ``full``): the rigid map of
    :func:`rigid_fit` fitted to those dots, then each wire ``w + t d`` met by ``o + x a + y b``."""
    _, o, a, b = rigid_fit(points_mm, model)
    out = np.empty((3, 2))
    for k in range(3):
        point, direction = full.wire_point[layer, k], full.wire_direction[layer, k]
        x, y, _ = np.linalg.lstsq(np.column_stack([a, b, -direction]), point - o, rcond=None)[0]
        out[k] = x, y
    return out


def affine_offsets_mm(points_mm: np.ndarray, model: PatternModel) -> np.ndarray:
    """Offsets (C, n, 3) in mm, in the phantom frame and across each wire, of labelled dots from
    their wires after the best affine map of the image plane into the phantom, for C candidate
    labellings: ``points_mm`` (C, L, 3, 2) image mm.

    The map ``p = o + x a + y b`` has 9 unknowns; every dot gives two equations (its distance from
    its wire), so with two or more layers a wrong dot shows as an offset.
    """
    design, target = _affine_system(points_mm, model)
    solution = np.linalg.pinv(design) @ np.broadcast_to(target, (len(design), target.shape[1]))[..., None]
    return ((design @ solution)[..., 0] - target).reshape(len(design), -1, 3)


def affine_residual_mm(points_mm: np.ndarray, model: PatternModel) -> np.ndarray:
    """RMS distance (mm) of labelled dots from their wires after the best affine map of the image
    plane into the phantom (see :func:`affine_offsets_mm`), for C candidate labellings."""
    offsets = affine_offsets_mm(points_mm, model)
    return np.sqrt((offsets**2).sum(axis=(-1, -2)) / offsets.shape[1])


def _rigid_and_affine(points_mm: np.ndarray, model: PatternModel) -> tuple[float, float, np.ndarray]:
    """RMS distances (mm) of one labelling's dots from their wires under the best rigid and
    the best affine map, and the rigid map's (o, a, b) as one 9-vector (see :func:`rigid_fit`)."""
    design, target = _affine_system(points_mm[None], model)
    design, target = design[0], target[0]
    normal = design.T @ design
    normal += 1e-12 * np.trace(normal) * np.eye(9)  # two layers leave directions along the wires free
    whiten = np.linalg.inv(np.linalg.cholesky(normal))
    eigenvalues, basis = np.linalg.eigh(whiten @ _ORTHOGONAL @ whiten.T)
    c = basis.T @ (whiten @ (design.T @ target))

    def solution(mu: float) -> np.ndarray:
        return whiten.T @ (basis @ (c / (1.0 + mu * eigenvalues)))

    terms = list(zip((eigenvalues * c**2).tolist(), eigenvalues.tolist()))  # plain floats: Brent calls it often

    def orthogonality(mu: float) -> float:  # a . b of the solution for this multiplier
        return sum(weight / (1.0 + mu * value) ** 2 for weight, value in terms)

    # The root lies between the poles; near a pole the function blows up only within that pole's
    # own scale (1 / |eigenvalue|), which may be far below the gap between the poles.
    low, high = -1.0 / eigenvalues[-1], -1.0 / eigenvalues[0]
    span = high - low
    a, b = low + 1e-9 * min(span, -low), high - 1e-9 * min(span, high)
    if orthogonality(a) * orthogonality(b) < 0.0:
        # The tolerance is the near pole's scale: reaching it from the far one takes Brent's method
        # over a hundred steps when the root lies far from both; a root short of it still fits.
        mu = brentq(orthogonality, a, b, xtol=1e-12 * min(span, -low, high), maxiter=1000, disp=False)
    else:  # the target has no part along an extreme direction: the nearest to orthogonal there
        mu = min((a, b), key=lambda m: abs(orthogonality(m)))
    rigid = solution(mu)
    n = target.shape[0] // 3

    def rms(p: np.ndarray) -> float:
        return float(np.sqrt(((design @ p - target) ** 2).sum() / n))

    return rms(rigid), rms(solution(0.0)), rigid


def rigid_fit(points_mm: np.ndarray, model: PatternModel) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The map an image plane really has, ``p = o + x a + y b`` with ``a = sx r1`` and
    ``b = sy r2`` for a rotation's first two columns (8 unknowns), fitted to one labelling's dots
    ``points_mm`` (L, 3, 2) image mm: the RMS distance (mm) of the dots from their wires, and
    ``o``, ``a``, ``b`` (phantom mm per image mm).

    The affine map of :func:`affine_residual_mm` may shear, so with parallel wires a wrong
    middle dot can hide in it and two layers leave it free along the wires; the rigid map
    cannot. Any two orthogonal vectors are a rotation's columns scaled, so the rigid map is
    the affine least-squares problem under the one constraint ``a . b = 0``: its Lagrange
    condition ``(H + mu Q) p = g`` becomes, in the eigenbasis of ``Q`` whitened by ``H``, a
    scalar equation in ``mu`` that is monotonic between its poles and solved by Brent's method
    (the global minimum, in well under a millisecond).
    """
    rms, _, solution = _rigid_and_affine(points_mm, model)
    o, a, b = np.split(solution, 3)
    return rms, o, a, b


def rigid_excess_mm(points_mm: np.ndarray, model: PatternModel) -> float:
    """How much worse (mm RMS) one labelling's dots ``points_mm`` (L, 3, 2) image mm fit their
    wires under :func:`rigid_fit` than under the affine map: near 0 for a true pattern (0.03 mm
    on fCal frames, 0.16 mm on the USTC recording), tenths of a mm when a wrong dot hides in
    the affine map's shear."""
    rigid, affine, _ = _rigid_and_affine(points_mm, model)
    return rigid - affine


def rigid_residual_mm(points_mm: np.ndarray, model: PatternModel) -> tuple[float, np.ndarray]:
    """:func:`rigid_fit`'s RMS distance (mm) and its scales (sx, sy) relative to the
    approximate spacing."""
    rms, _, a, b = rigid_fit(points_mm, model)
    return rms, np.array([np.linalg.norm(a), np.linalg.norm(b)])


def _spread(ratios: np.ndarray) -> np.ndarray:
    """Relative spread max / min - 1 of each row of ratios."""
    return ratios.max(axis=1) / ratios.min(axis=1) - 1.0


def label_dots(points_px: np.ndarray, spacing_mm: tuple[float, float], model: PatternModel,
               tol: Tolerances, max_patterns: int = 20000) -> Labelling:
    """Find the N-wire pattern among dot candidates (pixels) and label its dots by layer and wire."""
    n_layers = model.n_layers
    if len(points_px) < 3 * n_layers:
        return Labelling(None, f"{len(points_px)} dot candidates, the pattern needs {3 * n_layers}")
    q = np.asarray(points_px, float) * np.asarray(spacing_mm, float)
    lo, hi = tol.ratio_range()
    tr = _triples(q, hi * model.outer_mm.max(), lo * model.outer_mm.min(), tol)
    per_layer = []
    for layer in range(n_layers):
        ratio = tr.length / model.outer_mm[layer]
        margin = 0.02 + tol.collinear_mm / np.maximum(tr.length, 1e-9)
        first, last = model.diagonal_range[layer]
        ok = (ratio >= lo) & (ratio <= hi) & (tr.fraction >= first - margin) & (tr.fraction <= last + margin)
        per_layer.append(np.nonzero(ok)[0])
        if not len(per_layer[-1]):
            return Labelling(None, f"no collinear dot triple fits layer {layer + 1} (from the top)")
    chains = per_layer[0][:, None]
    gaps = np.empty((len(chains), 0))
    for layer in range(n_layers - 1):
        a, b = per_layer[layer], per_layer[layer + 1]
        ok, gap = _pair_checks(tr, a, b, model, layer, tol)
        row = np.searchsorted(a, chains[:, -1])
        c, j = np.nonzero(ok[row])
        chosen = b[j]
        earlier = tr.dots[chains[c]].reshape(len(c), 3 * chains.shape[1])
        fresh = ~(earlier[:, :, None] == tr.dots[chosen][:, None, :]).any(axis=(1, 2))
        c, j, chosen = c[fresh], j[fresh], chosen[fresh]
        gaps = np.column_stack([gaps[c], gap[row[c], j]])
        chains = np.column_stack([chains[c], chosen])
        if not len(chains):
            return Labelling(None, f"no dot line at the expected distance below layer {layer + 1}")
        if len(chains) > max_patterns:
            return Labelling(None, f"over {max_patterns} candidate patterns: too many dots that line up")
    outer = tr.length[chains] / model.outer_mm
    ok = _spread(outer) <= tol.outer_consistency
    if n_layers > 2:
        ok &= _spread(gaps) <= tol.gap_consistency
    if not ok.any():
        return Labelling(None, "dot lines found, but their spacings disagree with the phantom")
    chains = chains[ok]
    patterns = tr.dots[chains]
    residual = affine_residual_mm(q[patterns], model)
    order = np.argsort(residual)
    close = order[residual[order] <= tol.ambiguity * residual[order[0]] + tol.ambiguity_mm]
    if len(close) > 1:  # rivals: the rigid fit tells them apart
        patterns, residual = patterns[close[:RIVALS_CHECKED]], np.empty(min(len(close), RIVALS_CHECKED))
        for k, pattern in enumerate(patterns):
            residual[k], scale = rigid_residual_mm(q[pattern], model)
            if not ((scale >= lo) & (scale <= hi)).all():
                residual[k] = np.inf
        order = np.argsort(residual)
    best = patterns[order[0]]
    fit = float(residual[order[0]])
    if fit > tol.max_residual_mm:
        return Labelling(None, f"dots off their wires by {fit:.2f} mm RMS", fit)
    moved = np.linalg.norm(q[patterns[order[1:]]] - q[best][None], axis=-1)
    differs = (moved > tol.collinear_mm).any(axis=(1, 2))
    close = residual[order[1:]] <= tol.ambiguity * fit + tol.ambiguity_mm
    if (differs & close).any():
        return Labelling(None, "ambiguous: another dot pattern fits almost as well", fit, ambiguous=True,
                         rivals=(best, *patterns[order[1:]][differs & close]))
    excess = rigid_excess_mm(q[best], model)
    if excess > tol.max_rigid_excess_mm:
        return Labelling(None, f"dots fit their wires only if the image is sheared (rigid fit {excess:.2f} mm "
                         "worse): a dot is not its wire's", fit)
    return Labelling(best, "ok", fit)


# PLUS's own pattern search (PlusFidLineFinder, PlusFidLabeling), for sessions imported from PLUS:
# with PLUS's dot candidates it reproduces PLUS's success flags and points.


