"""Check a built phantom against its definition from a calibration scan: where is each wire?

Every wire is located from its own dots, jointly with the calibration (the all-wire fit of
:func:`core.calibration.jointfit.refine`, each wire end free to move across its wire under a
loose prior). Only the wires' places relative to each other can be told: moving all of them
together is the same as moving the phantom, whose pose is solved. So the located wires are
aligned to the definition by a robust rigid fit, and what remains is each wire's offset: one
wire built off its definition stands out while the others agree. Then each wire's dots, seen
against the straight wire so located, show how far its middle sags.

All lengths are in mm in the phantom frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from probecal.core.calibration.frames import observations, paired_with_latency
from probecal.core.calibration.handeye import phantom_points_from_pixels
from probecal.core.calibration.jointfit import MIN_SCALE_MM, SCALE_PER_MEDIAN, Refined, WirePrior, refine
from probecal.core.calibration.objectives import Observations
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import FrameResult
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom, wire_axes
from probecal.core.io.session import Session

CHECK_SIGMA_MM = 1.0
"""The wire ends' prior (1 sd per axis): loose enough not to shrink a real offset, there to hold
the joint fit where the scan cannot tell (the phantom's pose against all wires moving together)."""
TOLERANCE_MM = 0.2
"""A wire end farther than this from its definition is named as off."""
ALIGN_SCALE_MM = 0.05
"""Robust scale of the rigid alignment: wires off by more than this barely pull it."""
RIDGE = 1e-3
"""Weight (per mm and per radian) holding the rigid alignment near zero where the data cannot tell."""
MAX_ROUNDS = 3
"""Fits with the wires found off left out, until the same wires are found off."""
OUTLIER = 3.0
"""A wire is left out of the calibration's fit when it is off by more than this many times the
median wire: a phantom whose wires are all a little off has no outlier to leave out."""
TAIL = 0.00135
"""A wire is named off (or within) only when its offset is beyond the tolerance (or inside it) by
more than its standard error times Student's t for this one-sided tail (3 sd of a normal) and
the runs that located it less one: a few runs say little about their own spread."""
MIN_SPAN = 0.4
"""The dots must cover this fraction of a wire's length for its sag to be told from its ends."""


@dataclass(frozen=True)
class CheckSettings:
    """How a check decides: a wire farther than ``tolerance_mm`` from its definition is off; the
    spread of the offsets that ``runs`` runs of consecutive frames give alone says how far an offset
    can be trusted; a wire needs ``min_dots`` dots (in the whole scan and in each run) to be
    located."""

    tolerance_mm: float = TOLERANCE_MM
    runs: int = 6
    min_dots: int = 6

    @property
    def min_frames(self) -> int:
        """Frames that must see a wire for every run to locate it: fewer leave it unsure."""
        return self.runs * self.min_dots


@dataclass(frozen=True)
class WireFound:
    """One wire as the scan found it: its dots (how many), the stretch of it they cover
    (fractions of its length from the front end), its offset from the definition across the wire
    (3,) in the middle of that stretch, where the scan pins it down best; its front and back ends'
    offsets and how far its middle sags below the straight line between them, when the dots cover
    enough of it to tell (else None); and the spread (RMS) of its dots. ``shift`` is that
    offset as a move of the wire within its walls' plane, as if its holes were drilled off (3,):
    a wire slid along itself looks the same, so this is what the scan can say of the holes.
    Offsets are NaN for a wire with too few dots to be located."""

    name: str
    layer: str
    dots: int
    seen: tuple[float, float]
    offset: np.ndarray
    shift: np.ndarray
    uncertainty_mm: float
    runs: int
    front_mm: np.ndarray | None
    back_mm: np.ndarray | None
    sag_mm: float | None
    scatter_mm: float

    @property
    def offset_mm(self) -> float:
        """How far (mm) the wire sits off its definition where the scan saw it, as a move of its
        holes within the walls' plane."""
        return float(np.linalg.norm(self.shift))

    @property
    def at(self) -> float:
        """Where along the wire the offset is given (fraction of its length from the front end)."""
        return float(np.mean(self.seen))

    def to_json(self) -> dict:
        def rounded(v: np.ndarray | float | None) -> list | float | None:
            return None if v is None or not np.all(np.isfinite(v)) else np.round(v, 4).tolist()

        return {
            "name": self.name,
            "layer": self.layer,
            "dots": self.dots,
            "seen_from_to": rounded(np.array(self.seen)),
            "offset_mm": rounded(self.offset_mm),
            "offset_across_mm": rounded(self.offset),
            "shift_in_wall_plane_mm": rounded(self.shift),
            "offset_standard_error_mm": rounded(self.uncertainty_mm),
            "runs": self.runs,
            "front_offset_mm": rounded(self.front_mm),
            "back_offset_mm": rounded(self.back_mm),
            "sag_mm": rounded(self.sag_mm),
            "scatter_mm": rounded(self.scatter_mm),
        }


@dataclass(frozen=True)
class WireCheck:
    """Every wire as found, the settings that judged them and how many frames showed them."""

    wires: list[WireFound]
    settings: CheckSettings
    frames_used: int
    shifts_mm: np.ndarray
    """(W, 2, 3) where the fit put every wire's ends, relative to the definition once aligned."""

    @property
    def tolerance_mm(self) -> float:
        return self.settings.tolerance_mm

    def verdict(self, wire: WireFound) -> str:
        """``off``: farther off than the tolerance, and than its margin (standard error times
        Student's t, see TAIL); ``within``: within the tolerance by that margin; else ``unsure``
        (the scan cannot tell), as for a wire not located or one whose dots scatter about it by
        more than the tolerance: errors that large come from the poses (tracking, timing), last
        for many frames and escape the runs' spread."""
        if wire.runs < 2 or not wire.scatter_mm <= self.tolerance_mm:
            return "unsure"
        offset, error = wire.offset_mm, margin(wire)
        if not np.isfinite(offset) or not np.isfinite(error):
            return "unsure"
        if offset > self.tolerance_mm and offset > error:
            return "off"
        return "within" if offset + error <= self.tolerance_mm else "unsure"

    def off(self) -> list[WireFound]:
        """The wires found off, worst first."""
        return sorted((w for w in self.wires if self.verdict(w) == "off"), key=lambda w: -w.offset_mm)

    def unsure(self) -> list[WireFound]:
        """The wires the scan cannot tell within or off the tolerance."""
        return [w for w in self.wires if self.verdict(w) == "unsure"]

    def as_built(self, phantom: Phantom) -> Phantom:
        """``phantom`` with every wire the scan can tell (off or within) where the scan found it,
        the others as defined."""
        told = np.array([self.verdict(w) != "unsure" for w in self.wires])
        return phantom.moved(np.where(told[:, None, None], np.nan_to_num(self.shifts_mm), 0.0))

    def to_json(self) -> dict:
        return {"tolerance_mm": self.tolerance_mm, "frames_used": self.frames_used,
                "runs": self.settings.runs, "min_dots": self.settings.min_dots, "tail": TAIL,
                "wires_off": [w.name for w in self.off()], "wires_unsure": [w.name for w in self.unsure()],
                "wires": [{**w.to_json(), "verdict": self.verdict(w)} for w in self.wires]}


MAX_POSES = 300
"""The most poses a check asks for: beyond, a sweep takes longer than a wire is worth."""


@dataclass(frozen=True)
class MorePoses:
    """What a longer sweep would tell: about how many ``poses`` in all would decide the unsure
    ``wires``; ``untold`` are those no sweep of up to :data:`MAX_POSES` would (a wire whose
    offset lies at the tolerance, or whose dots scatter by more than it)."""

    poses: int | None
    wires: list[str]
    untold: list[str]


def poses_to_tell(check: WireCheck) -> MorePoses | None:
    """For the wires ``check`` leaves unsure (None when none is), about how many poses would
    decide them: a wire's standard error shrinks as one over the square root of the frames that
    see it, and its margin (Student's t times it) must fall below its offset (one beyond the
    tolerance, to be off) or below the room between its offset and the tolerance (one inside it,
    to be within); a wire seen in too few frames for its runs needs them."""
    unsure = check.unsure()
    if not unsure:
        return None
    needed: dict[str, float] = {}
    for wire in unsure:
        frames = check.frames_used
        if wire.runs < 2 or not np.isfinite(wire.offset_mm):  # seen too seldom: every run needs its dots
            needed[wire.name] = frames * check.settings.min_frames / max(wire.dots, 1)
            continue
        # Off: beyond the tolerance and beyond its margin of zero; within: inside the tolerance by its margin.
        above = wire.offset_mm > check.tolerance_mm
        gap = wire.offset_mm if above else check.tolerance_mm - wire.offset_mm
        if not wire.scatter_mm <= check.tolerance_mm or gap <= 0:
            continue
        needed[wire.name] = frames * (margin(wire) / gap) ** 2
    told = {name: n for name, n in needed.items() if 1.1 * n <= MAX_POSES}  # a tenth more for the margin
    poses = None if not told else int(5 * np.ceil(1.1 * max(told.values()) / 5))
    return MorePoses(poses, sorted(told), [w.name for w in unsure if w.name not in told])


def margin(wire: WireFound) -> float:
    """How far a wire's offset must lie from the tolerance to be told (mm): its standard error
    times Student's t for :data:`TAIL` and its runs less one."""
    from scipy.stats import t as student_t  # slow to import; every calibration report loads this module

    return float(student_t.ppf(1.0 - TAIL, wire.runs - 1)) * wire.uncertainty_mm


def without_rigid_motion(lines: np.ndarray, shifts: np.ndarray, spans: np.ndarray, robust: bool = True) -> np.ndarray:
    """(W, 2, 3) end-point shifts, across the wires, less the rigid motion that best explains them
    over the stretch of each wire that was seen (``spans`` (W, 2): fractions of its length): the
    motion fitted robustly (unless not ``robust``: least squares), so that one wire off does not
    drag it, and held near zero in what the stretches cannot tell."""
    front, direction, length, across = wire_axes(lines)
    t = spans[..., None]
    points = (front[:, None] + t * (length[:, None, None] * direction[:, None])).reshape(-1, 3)
    seen = (shifts[:, None, 0] * (1 - t) + shifts[:, None, 1] * t).reshape(-1, 3)
    project = np.repeat(across, 2, axis=0)
    centre = points.mean(axis=0)

    def motion(p: np.ndarray, at: np.ndarray) -> np.ndarray:
        return Rotation.from_rotvec(p[:3]).apply(at - centre) + centre + p[3:] - at

    def remaining(p: np.ndarray) -> np.ndarray:
        misfit = np.einsum("eij,ej->ei", project, seen - motion(p, points)).ravel()
        return np.concatenate([misfit, RIDGE * p])

    fit = least_squares(remaining, np.zeros(6), loss="cauchy" if robust else "linear", f_scale=ALIGN_SCALE_MM)
    ends = lines.reshape(-1, 3)
    return np.einsum("eij,ej->ei", project, shifts.reshape(-1, 3) - motion(fit.x, ends)).reshape(shifts.shape)


def wall_normal(phantom: Phantom) -> np.ndarray:
    """The unit normal of the walls that hold the wires: the outer wires' mean direction."""
    directions = np.array([w.direction for layer in phantom.layers for w in (layer.wires[0], layer.wires[2])])
    mean = directions.mean(axis=0)
    return mean / np.linalg.norm(mean)


def in_wall_plane(offset: np.ndarray, direction: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """An offset across a wire (3,) as the move within the walls' plane (normal ``normal``) that
    gives it: the offset slid along the wire (unit ``direction``) until it lies in that plane."""
    return offset - (offset @ normal) / (direction @ normal) * direction


def _sag(t: np.ndarray, residuals: np.ndarray, min_dots: int) -> tuple[float | None, float]:
    """A wire's sag (mm, down) and the RMS spread of its dots (mm) about the straight wire or,
    where the sag can be told, about the sagging one: ``t`` (N,) the dots' fractions along the
    wire, ``residuals`` (N, 3) their offsets across the straight wire."""
    if len(t) < min_dots:
        return None, float("nan")
    if np.ptp(t) < MIN_SPAN:
        return None, float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
    design = np.column_stack([np.ones_like(t), t, 4.0 * t * (1.0 - t)])
    coef, *_ = np.linalg.lstsq(design, residuals, rcond=None)
    spread = residuals - design @ coef
    return float(-coef[2][2]), float(np.sqrt(np.mean(np.sum(spread**2, axis=1))))


def _wire_alone(line: np.ndarray, points: np.ndarray, noise_mm: float) -> np.ndarray:
    """(2, 3) shifts across the wire ``line`` (2, 3) of its front and back ends that best explain
    its dots ``points`` (N, 3), the calibration held: a robust linear fit of the dots' offsets
    across the wire along it, under the wire prior (noise ``noise_mm`` per dot)."""
    front, direction, length, project = wire_axes(line)
    across = np.linalg.svd(project)[0][:, :2]  # two unit vectors across the wire
    t = (points - front) @ direction / length
    seen = (points - front) @ across
    design = np.column_stack([1.0 - t, t])
    ridge = noise_mm / CHECK_SIGMA_MM

    def remaining(p: np.ndarray) -> np.ndarray:
        ends = p.reshape(2, 2)
        return np.concatenate([(seen - design @ ends).ravel(), ridge * p])

    scale = max(MIN_SCALE_MM, SCALE_PER_MEDIAN * noise_mm)
    fit = least_squares(remaining, np.zeros(4), loss="huber", f_scale=scale)
    return fit.x.reshape(2, 2) @ across.T


@dataclass(frozen=True)
class _Located:
    """One fit of the wires: where it put every end (W, 2, 3; phantom frame of its own pose), the
    dots in that frame (F, W, 3) and the calibration it came with."""

    shifts: np.ndarray
    points: np.ndarray
    fit: Refined


def _locate(phantom: Phantom, markers_px: np.ndarray, tool_to_base: np.ndarray, x: np.ndarray, y: np.ndarray,
            spacing_mm: tuple[float, float], left_out: np.ndarray) -> _Located:
    """The joint fit of the calibration and the wires, without the wires ``left_out`` (W,) bool.
    The phantom's pose ``y`` is held: with every wire free to move, moving the phantom is the same
    as moving all the wires together, so solving it too leaves the fit a freedom that only the
    wires' prior holds, along which it drifts on real recordings (the rigid motion of the wires is
    removed afterwards anyway). A wire far off its definition would bias the pixel spacing,
    which the wire pass then holds, so the wires ``left_out`` take no part in the fit.
    Each wire left out is then located alone from its dots, with the calibration so found."""
    held = markers_px.copy()
    held[:, left_out] = np.nan
    fit = refine(phantom, held, tool_to_base, x, y, spacing_mm, solve_y=False, prior=WirePrior(CHECK_SIGMA_MM))
    assert fit.wire_shifts_mm is not None  # the all-wire objective with a prior fits the wires
    points = phantom_points_from_pixels(tool_to_base, fit.image_to_tool_rigid, fit.phantom_to_base,
                                        fit.pixel_spacing_mm, np.nan_to_num(markers_px))
    shifts = fit.wire_shifts_mm.copy()
    noise = float(np.nanmedian(fit.residuals_mm)) / 1.18  # median distance of 2D noise / its sd
    lines = phantom.lines()
    for w in np.flatnonzero(left_out):
        valid = np.all(np.isfinite(markers_px[:, w]), axis=1)
        shifts[w] = _wire_alone(lines[w], points[valid, w], max(noise, MIN_SCALE_MM / SCALE_PER_MEDIAN))
    return _Located(shifts, points, fit)


def _seen_spans(phantom: Phantom, located: _Located, markers_px: np.ndarray,
                min_dots: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """(W, 2) the stretch of each wire its dots cover (5th to 95th percentile of their fractions of
    its length from the front end; NaN for a wire with fewer than ``min_dots`` dots) and every
    dot's fraction."""
    front, direction, length, _ = wire_axes(phantom.moved(located.shifts).lines())
    spans = np.full((phantom.n_wires, 2), np.nan)
    fractions = []
    for w in range(phantom.n_wires):
        valid = np.all(np.isfinite(markers_px[:, w]), axis=1)
        fractions.append((located.points[valid, w] - front[w]) @ direction[w] / length[w])
        if valid.sum() >= min_dots:
            spans[w] = np.percentile(fractions[w], [5, 95])
    return spans, fractions


def offsets_in_wall_plane(phantom: Phantom, shifts: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """(W, 3) each wire's offset in the middle of its seen stretch, as a move in the walls' plane."""
    normal = wall_normal(phantom)
    at = spans.mean(axis=1)[:, None]
    middle = (1 - at) * shifts[:, 0] + at * shifts[:, 1]
    return np.array([in_wall_plane(m, wire.direction, normal) for m, wire in zip(middle, phantom.wires)])


def _aligned(phantom: Phantom, raw: np.ndarray, spans: np.ndarray, located: np.ndarray) -> np.ndarray:
    """(W, 2, 3) the fitted ends ``raw`` less the rigid motion of all the ``located`` wires."""
    shifts = np.full(raw.shape, np.nan)
    shifts[located] = without_rigid_motion(phantom.lines()[located], raw[located], spans[located])
    return shifts


def check_wires(phantom: Phantom, obs: Observations, image_to_tool_rigid: np.ndarray, phantom_to_base: np.ndarray,
                spacing_mm: tuple[float, float], settings: CheckSettings = CheckSettings()) -> WireCheck:
    """Locate every wire of ``phantom`` from the labelled markers ``obs``, starting from a
    calibration (X, Y, spacing), and compare it with the definition. The wires found off are
    left out of the calibration's fit and located alone, until the wires left out are the wires
    found off (at most half of them). Then the same fit on each of ``settings.runs`` runs of
    consecutive frames says how far each offset can be trusted. InputError when no wire is seen often
    enough to be located."""
    markers = np.asarray(obs.markers_px, dtype=float)
    seen = np.sum(np.all(np.isfinite(markers), axis=2), axis=0)
    tolerance_mm, min_dots = settings.tolerance_mm, settings.min_dots
    if len(obs) == 0 or seen.max() < min_dots:
        raise InputError(None, f"too few dots to locate the wires (at most {int(seen.max(initial=0))} per wire, "
                               f"{min_dots} needed)")
    located_wires = seen >= min_dots
    left_out = np.zeros(phantom.n_wires, bool)
    for _ in range(MAX_ROUNDS):
        located = _locate(phantom, markers, obs.tool_to_base, image_to_tool_rigid, phantom_to_base, spacing_mm,
                          left_out)
        spans, fractions = _seen_spans(phantom, located, markers, min_dots)
        shifts = _aligned(phantom, located.shifts, spans, located_wires)
        offsets = offsets_in_wall_plane(phantom, shifts, spans)
        offset_mm = np.linalg.norm(offsets, axis=1)
        typical = float(np.nanmedian(offset_mm))
        off = np.zeros_like(left_out)
        worst = np.argsort(-np.nan_to_num(offset_mm))[: phantom.n_wires // 2]
        off[worst] = (offset_mm[worst] > tolerance_mm) & (offset_mm[worst] > OUTLIER * typical)
        if np.array_equal(off, left_out):
            break
        left_out = off
    uncertainty, runs = _block_uncertainty(phantom, obs, located.fit, left_out, spans, settings)
    front, _, _, across = wire_axes(phantom.moved(located.shifts).lines())
    found = []
    for w, wire in enumerate(phantom.wires):
        valid = np.all(np.isfinite(markers[:, w]), axis=1)
        sag, scatter = _sag(fractions[w], (located.points[valid, w] - front[w]) @ across[w].T, min_dots)
        at = float(np.mean(spans[w]))
        told = sag is not None
        found.append(WireFound(wire.name, phantom.layers[w // 3].name, int(seen[w]), (spans[w, 0], spans[w, 1]),
                               (1 - at) * shifts[w, 0] + at * shifts[w, 1], offsets[w],
                               float(uncertainty[w]), int(runs[w]),
                               shifts[w, 0] if told else None, shifts[w, 1] if told else None, sag, scatter))
    check = WireCheck(found, settings, len(obs), shifts)
    # A wire whose offset the runs cannot agree on has no ends or sag worth telling either.
    return replace(check, wires=[replace(w, front_mm=None, back_mm=None, sag_mm=None)
                                 if check.verdict(w) == "unsure" else w for w in found])


def _block_uncertainty(phantom: Phantom, obs: Observations, fit: Refined, left_out: np.ndarray,
                       spans: np.ndarray, settings: CheckSettings) -> tuple[np.ndarray, np.ndarray]:
    """(W,) standard error (mm) of each wire's offset: the spread of the offsets that the runs
    of consecutive frames give alone, over the square root of their number (NaN where fewer than
    two runs locate the wire); and (W,) how many runs located each wire. A run of frames sees
    the wires from fewer poses than the whole scan, so its calibration is less sure too: the
    spread carries that, as it should."""
    markers = np.asarray(obs.markers_px, dtype=float)
    runs = []
    for block in np.array_split(np.arange(len(obs)), settings.runs):
        seen = np.sum(np.all(np.isfinite(markers[block]), axis=2), axis=0) >= settings.min_dots
        if seen.sum() < phantom.n_wires // 2:
            continue
        located = _locate(phantom, markers[block], obs.tool_to_base[block], fit.image_to_tool_rigid,
                          fit.phantom_to_base, fit.pixel_spacing_mm, left_out & seen)
        aligned = _aligned(phantom, located.shifts, spans, seen & np.all(np.isfinite(spans), axis=1))
        runs.append(offsets_in_wall_plane(phantom, aligned, spans))
    if len(runs) < 2:
        return np.full(phantom.n_wires, np.nan), np.zeros(phantom.n_wires, int)
    runs_mm = np.array(runs)  # (R, W, 3), NaN where a run did not locate the wire
    count = np.sum(np.all(np.isfinite(runs_mm), axis=2), axis=0)
    spread = np.sqrt(np.nansum(np.sum((runs_mm - np.nanmean(runs_mm, axis=0)) ** 2, axis=2), axis=0)
                     / np.maximum(count - 1, 1))
    return np.where(count >= 2, spread / np.sqrt(np.maximum(count, 1)), np.nan), count


def check_session(session: Session, calibration: Calibration, results: list[FrameResult],
                  settings: CheckSettings = CheckSettings()) -> WireCheck:
    """:func:`check_wires` on a segmented calibration session, from its calibration (frames paired
    as the calibration paired them). InputError naming the session for unusable input."""
    phantom = session.phantom
    if phantom is None:
        raise InputError(session.path, "session has no phantom definition")
    phantom_to_base = calibration.phantom_to_base
    if phantom_to_base is None:
        phantom_to_base = session.phantom_to_base
    if phantom_to_base is None:
        raise InputError(session.path, "neither the calibration nor the session says where the phantom is "
                                       "(phantom_to_base)")
    session, results = paired_with_latency(session, results, calibration.image_latency_s)
    obs, _ = observations(session, results)
    try:
        return check_wires(phantom, obs, calibration.image_to_tool_rigid, phantom_to_base,
                           calibration.pixel_spacing_mm, settings)
    except InputError as exc:
        raise InputError(session.path, exc.problem)
