"""Find the wire dots in B-mode frames and label them (design §1 step 3, thesis 3.4).

A :class:`Segmenter` is one of three strategies behind one interface (a frame in, a
:class:`FrameResult` out), chosen by name (:data:`SEGMENTERS`):

- ``probecal`` (:class:`ProbecalSegmenter`, the default): PLUS's morphology, its sizes tuned on
  each recording without ground truth, labelled with robust limits
  (:func:`core.calibration.labelling.label_dots`); fine frames are binned to about 0.1 mm/px.
- ``thesis`` (:class:`ThesisSegmenter`): the thesis's finder: a 7x7 median filter, a
  disk-shaped morphological clean-up, a threshold, 8-connected components, a size filter and
  intensity-weighted sub-pixel centroids, retried with other parameters when the pattern is
  not found.
- ``plus`` (:class:`PlusSegmenter`): PLUS's (PlusFidSegmentation, PlusFidLineFinder,
  PlusFidLabeling) with PLUS's settings: for each of four bar directions the bar opening is
  subtracted, then a disk opening; a threshold at a fraction of the cleaned region's maximum;
  centroids weighted by the full gray levels of 8-connected blobs; PLUS's line finder and
  first-fit labelling (:func:`core.calibration.labelling.plus_label_dots`). On PLUS's fCal and
  VLCUS recordings this reproduces PLUS's success flags in every frame and its points to
  0.001 px. One check is added: a pattern whose dots no affine map of the image puts on their
  wires is rejected (tissue frames can fool PLUS's line finder).

Frames: pixels (u = column, v = row), markers in the phantom definition's wire order (N by N,
within an N in definition order); distances in mm.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import cv2
import numpy as np

from probecal.core.calibration.dots import (
    DISK_RADIUS_MM,
    MAX_AREA_MM2,
    MAX_CANDIDATES,
    MEDIAN_MM,
    MIN_AREA_MM2,
    MIN_CONTRAST,
    NO_DOTS,
    PLUS_BAR_MM,
    THRESHOLD,
    DotParams,
    Dots,
    PlusDotParams,
    as_gray,
    echo_peak_rows,
    find_dots,
    find_plus_dots,
    odd,
    overlay_keep,
    plus_dot_params,
    plus_dot_sets,
    refined_centroids,
)
from probecal.core.calibration.labelling import (
    RIGID_EXCESS_MM,
    SIMULATED,
    Labelling,
    Orientation,
    PatternModel,
    Tolerances,
    affine_residual_mm,
    label_dots,
    plus_orientation,
    predict_layer_mm,
    rigid_excess_mm,
)
from probecal.core.calibration.pluslabelling import PlusLineModel, plus_label_dots
from probecal.core.errors import InputError, Remedy
from probecal.core.geometry.fan import Fan
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.jsonio import write_json
from probecal.core.io.limits import checked_bytes
from probecal.core.io.session import Session


@dataclass(frozen=True)
class FrameResult:
    """Segmentation of one frame. ``markers`` (n_wires, 2) pixels in phantom wire order when
    ``found``; ``candidates`` (K, 2) every dot candidate, for display; ``index`` the session's;
    ``peak_rows`` (n_wires,) each marker's echo-peak row (px, :func:`core.calibration.dots.echo_peak_rows`
    at the segmenter's spacing), when :func:`segment_session` found the pattern."""

    index: int
    found: bool
    markers: np.ndarray | None
    reason: str
    candidates: np.ndarray
    residual_mm: float = float("nan")  # RMS distance of the markers from their wires under an affine map
    peak_rows: np.ndarray | None = None


SEGMENTERS = ("probecal", "thesis", "plus")
THRESHOLDS = (0.1, 0.05, 0.2)  # probecal's: fractions of the cleaned frame's maximum, tried in turn
DISK_CHOICES_PX = (1, 2, 3, 4)  # opening disk radii a recording is tuned over
BAR_CHOICES_MM = (PLUS_BAR_MM, 4.0)  # bar lengths, PLUS's first
TUNE_ENOUGH = 0.9  # fraction of the tuning runs that must find the pattern before longer bars are tried
TUNE_FRAMES = 24  # frames, spread over the recording, that the tuning segments
# A frame at least twice as fine as WORK_SPACING_MM is binned (n x n pixels averaged, n as large as
# keeps it at least that fine) before its dots are found: the dots are about a millimetre wide
# whatever the scanner's resampling, so a 3 Mpx frame at 0.025 mm/px (binned 4 x 4) costs about
# what the twin's 384x500 frames at 0.1 mm/px do (benchmarks/bench_segmentation.py, fine frames).
WORK_SPACING_MM = 0.1
REFINE_RADIUS_MM = 0.8  # the found dots' centroids are then taken again at full resolution within this
SPLIT_ECHO_MM = 3.0  # rival patterns' dots this close are one echo smeared across the slice (split_echoes_merged)
NEAR_PREDICTION_MM = 1.0  # a dot this close to where the other layers put it is that wire's
RIGID_EXCESS_FACTOR = 3.0  # a recording's rigid-excess limit: this many times its median, at least
FAINT = 0.03  # candidates under this fraction of a typical wire echo are speckle (real wire dots: >= 0.07)


def split_echoes_merged(dots: Dots, labelling: Labelling, spacing_mm: tuple[float, float]) -> Dots | None:
    """When rival patterns (an ambiguous ``labelling``) differ only in candidates within
    ``SPLIT_ECHO_MM`` of each other, those are one wire's echo split in two (a diagonal's echo
    is long across the beam's thickness, and high resolution resolves its speckle): the
    candidates with each such group made one (:meth:`Dots.merged`). None when a rival differs
    by more: a different pattern."""
    best, *rivals = labelling.rivals
    scale = np.asarray(spacing_mm)
    pairs = {(int(a), int(b)) for rival in rivals for a, b in zip(best.ravel(), rival.ravel()) if a != b}
    if not pairs or any(np.linalg.norm((dots.positions[a] - dots.positions[b]) * scale) > SPLIT_ECHO_MM
                        for a, b in pairs):
        return None
    groups: dict[int, set[int]] = {}
    for a, b in pairs:
        union = groups.get(a, {a}) | groups.get(b, {b})
        for i in union:
            groups[i] = union
    unique = {frozenset(g) for g in groups.values()}
    return dots.merged([sorted(g) for g in unique])


@dataclass(frozen=True)
class Segmenter(ABC):
    """Finds and labels the wire dots of one phantom in frames of one scanner set-up: one of the
    strategies of :data:`SEGMENTERS`, made by :meth:`create` (or :meth:`for_session`), each a
    callable from a frame to its :class:`FrameResult`:

    - :class:`ProbecalSegmenter` (``probecal``, the default): PLUS's morphology tuned per
      recording, labelled with robust limits;
    - :class:`ThesisSegmenter` (``thesis``): the thesis's dot finder and the twin's limits;
    - :class:`PlusSegmenter` (``plus``): PLUS's dot finder and labelling with PLUS's settings,
      as a reference.

    ``spacing_mm`` is the approximate (sx, sy) mm/px used for sizes and geometry checks;
    ``roi`` (x, y, width, height) px; ``fan``: a fan image's (its pixels).
    """

    kind: ClassVar[str]
    n_wires: int
    model: PatternModel
    tolerances: Tolerances
    spacing_mm: tuple[float, float]
    roi: tuple[int, int, int, int] | None = None
    fan: Fan | None = None

    @classmethod
    def create(
        cls,
        phantom: Phantom,
        spacing_mm: tuple[float, float],
        orientation: Orientation = SIMULATED,
        hints: dict[str, str] | None = None,
        use_roi: bool = True,
        kind: str = "probecal",
        work_spacing_mm: float = WORK_SPACING_MM,
    ) -> Segmenter:
        """A segmenter of ``kind`` for ``phantom`` at an approximate spacing. ``hints`` are a PLUS
        ``<Segmentation>`` element's attributes: they set the ROI and sizes (and, for the
        ``plus`` kind, PLUS's thresholds and line limits), never the algorithm. A ``probecal``
        segmenter bins frames at least twice as fine as ``work_spacing_mm`` (0: never)."""
        if kind not in SEGMENTERS:
            raise ValueError(f"unknown segmenter {kind!r}")
        hints = hints or {}
        setup = _SetUp(phantom, (float(spacing_mm[0]), float(spacing_mm[1])), orientation, hints,
                       _hinted_roi(hints) if use_roi else None, work_spacing_mm)
        return STRATEGIES[kind].made(setup)

    @classmethod
    @abstractmethod
    def made(cls, setup: _SetUp) -> Segmenter:
        """This strategy's segmenter for ``setup``."""

    @classmethod
    def for_session(cls, session: Session, orientation: Orientation | None = None, use_roi: bool = True,
                    kind: str = "probecal", use_hints: bool = True,
                    work_spacing_mm: float = WORK_SPACING_MM) -> Segmenter:
        """The segmenter a session calls for: its phantom, spacing and PLUS hints.

        The orientation defaults to PLUS's convention (:func:`core.calibration.labelling.plus_orientation`)
        for sessions whose frames come as PLUS holds them (imported from PLUS recordings, or
        streamed by a PLUS server: the manifest states their orientation), else to probecal's
        (:data:`core.calibration.labelling.SIMULATED`).
        The spacing is PLUS's ApproximateSpacingMmPerPixel, else the session's nominal spacing,
        else its probe's. Without ``use_hints`` that spacing is the only PLUS setting used (a
        robot session's case). ``work_spacing_mm`` as in :meth:`create`. Raises InputError
        without a phantom or a spacing.
        """
        if session.phantom is None:
            raise InputError(session.path, "session has no phantom definition to label the markers with")
        hints = session.manifest.segmentation_hints or {}
        if not use_hints:
            hints = {k: v for k, v in hints.items() if k == "ApproximateSpacingMmPerPixel"}
        if hints.get("ApproximateSpacingMmPerPixel"):
            spacing = (float(hints["ApproximateSpacingMmPerPixel"]),) * 2
        elif session.pixel_spacing_mm is not None:
            spacing = session.pixel_spacing_mm
        elif session.probe is not None:
            spacing = session.probe.nominal_spacing_mm
        else:
            raise InputError(session.path, "no pixel spacing known (no probe, spacing or PLUS segmentation hints; "
                                           "give the nominal one when importing)", (Remedy.SPACING,))
        if orientation is None:
            plus_frames = session.manifest.image_orientation_in_file is not None  # as PLUS holds them
            orientation = plus_orientation(session.phantom) if plus_frames else SIMULATED
        segmenter = cls.create(session.phantom, spacing, orientation, hints, use_roi, kind, work_spacing_mm)
        return replace(segmenter, fan=session.fan)

    def tune(self, frames: list[np.ndarray], progress: Progress | None = None) -> Segmenter:
        """The segmenter with the sizes that suit these frames (a sample of one recording); only
        :class:`ProbecalSegmenter` tunes, telling ``progress(sizes tried, sizes to try)``."""
        return self

    def describe(self) -> str:
        """One line that says which algorithm runs with which parameters."""
        sx, sy = self.spacing_mm
        return f"{self.kind} segmenter at {sx:.3f} x {sy:.3f} mm/px"

    def __call__(self, image: np.ndarray, index: int = 0) -> FrameResult:
        """Segment one frame (uint8 gray, or colour)."""
        return self._segment(as_gray(image), index)

    @abstractmethod
    def _segment(self, gray: np.ndarray, index: int) -> FrameResult:
        """One frame's segmentation (uint8 gray)."""


@dataclass(frozen=True)
class _SetUp:
    """What :meth:`Segmenter.create` makes a segmenter from."""

    phantom: Phantom
    spacing_mm: tuple[float, float]
    orientation: Orientation
    hints: dict[str, str]
    roi: tuple[int, int, int, int] | None
    work_spacing_mm: float

    @property
    def pixel_mm(self) -> float:
        return float(np.sqrt(self.spacing_mm[0] * self.spacing_mm[1]))

    def common(self) -> dict[str, Any]:
        """The fields every strategy's segmenter takes from the set-up."""
        return {"n_wires": self.phantom.n_wires, "model": PatternModel.from_phantom(self.phantom, self.orientation),
                "spacing_mm": self.spacing_mm, "roi": self.roi}


def _hinted_roi(hints: dict[str, str]) -> tuple[int, int, int, int] | None:
    """The ROI (x, y, width, height) px of PLUS's clip rectangle hints, if given."""
    if not (hints.get("ClipRectangleOrigin") and hints.get("ClipRectangleSize")):
        return None
    x, y = (int(v) for v in hints["ClipRectangleOrigin"].split())
    width, height = (int(v) for v in hints["ClipRectangleSize"].split())
    return (x, y, width, height)


def _sizes_text(attempts: tuple[PlusDotParams, ...], sizes_from: str, roi: tuple[int, int, int, int] | None) -> str:
    """The bars, opening disk and thresholds of PLUS's morphology, and the ROI, in words."""
    params = attempts[0]
    thresholds = "/".join(f"{100 * p.threshold:g}" for p in attempts)
    roi_text = f", ROI {roi}" if roi else ""
    return (f"bars {2 * params.bar_px + 1} px, opening disk radius {params.disk_px} px ({sizes_from}), "
            f"thresholds {thresholds} %{roi_text}")


@dataclass(frozen=True)
class _Labelled(Segmenter):
    """A strategy that finds candidate sets of dots and labels them with
    :func:`core.calibration.labelling.label_dots`."""

    @abstractmethod
    def _dot_sets(self, gray: np.ndarray) -> Iterator[Dots]:
        """The dot candidates of each parameter set in turn, found only when asked for."""

    def _segment(self, gray: np.ndarray, index: int) -> FrameResult:
        return self._label(gray, index, self._dot_sets(gray))

    def _label(self, gray: np.ndarray, index: int, dot_sets: Iterable[Dots]) -> FrameResult:
        """Label the first good pattern among the candidate sets: a pattern that fits its wires
        within half the residual limit is taken at once; otherwise every set is tried and the
        best-fitting pattern wins. An ambiguous frame is rejected: other parameters would only
        pick one of the rival patterns."""
        best, failure, richest = None, None, NO_DOTS
        for dots in dot_sets:
            richest = dots if len(dots.positions) > len(richest.positions) else richest
            labelling = label_dots(dots.positions, self.spacing_mm, self.model, self.tolerances)
            if labelling.ambiguous and (whole := split_echoes_merged(dots, labelling, self.spacing_mm)) is not None:
                dots = whole
                labelling = label_dots(dots.positions, self.spacing_mm, self.model, self.tolerances)
            if labelling.ambiguous:
                return FrameResult(index, False, None, labelling.reason, dots.positions)
            if labelling.dots is None:
                failure = failure or (dots, labelling.reason)
            elif best is None or labelling.residual_mm < best[1].residual_mm:
                best = (dots, labelling)
            if best and best[1].residual_mm <= self.tolerances.max_residual_mm / 2:
                break
        if best is None:
            assert failure is not None  # at least one dot set is tried, and each gives best or failure
            if gray.max() - gray.min() < MIN_CONTRAST:
                return FrameResult(index, False, None, "no echoes: the frame is blank", failure[0].positions)
            return self._unlabelled(index, richest, failure)
        dots, labelling = best
        assert labelling.dots is not None  # only a labelling that found the pattern becomes best
        markers = np.empty((self.n_wires, 2))
        markers[self.model.wire_index.ravel()] = dots.positions[labelling.dots.ravel()]
        return FrameResult(index, True, markers, "ok", dots.positions, labelling.residual_mm)

    def _unlabelled(self, index: int, richest: Dots, failure: tuple[Dots, str]) -> FrameResult:
        """A frame no candidate set gave the pattern in: the first failure's reason."""
        return FrameResult(index, False, None, failure[1], failure[0].positions)


@dataclass(frozen=True)
class ProbecalSegmenter(_Labelled):
    """probecal's own: PLUS's morphology (:func:`core.calibration.dots.find_plus_dots`, bars of
    2 mm, an opening disk tuned per recording by :meth:`tune`) at the thresholds
    :data:`THRESHOLDS` (``dot_attempts``), candidates under :data:`FAINT` of a typical wire echo
    dropped (a missing dot must not be replaced by speckle), labelled by
    :func:`core.calibration.labelling.label_dots` with
    :meth:`core.calibration.labelling.Tolerances.robust` limits (a pattern that fits its wires
    only under a sheared map is refused: a wrong dot hides in the shear); for phantoms of three
    or more layers a pattern with one layer incomplete is completed from where the other layers
    put its dots, or the frame is rejected naming the wire that is not seen.

    ``sizes_from`` says where the opening disk came from; ``keep`` (H, W) uint8, 0 on the
    scanner's overlay (:func:`core.calibration.dots.overlay_keep`), is ANDed with frames of its
    size before the dots are found; frames are binned ``binning`` x ``binning`` first
    (:data:`WORK_SPACING_MM`). A fan image's black outside the fan takes the local mean of the
    fan's pixels first (:func:`fan_filled`), so that its edges make no dots, and candidates
    outside it are dropped."""

    kind: ClassVar[str] = "probecal"
    dot_attempts: tuple[PlusDotParams, ...] = ()
    sizes_from: str = "default"
    keep: np.ndarray | None = field(default=None, compare=False, repr=False)
    binning: int = 1

    @classmethod
    def made(cls, setup: _SetUp) -> ProbecalSegmenter:
        pixel, (sx, sy) = setup.pixel_mm, setup.spacing_mm
        if (n := int(setup.work_spacing_mm / pixel)) >= 2:
            work = cls.made(replace(setup, spacing_mm=(sx * n, sy * n)))
            return replace(work, spacing_mm=(sx, sy), binning=n)
        plus = plus_dot_params(setup.hints, pixel)
        sizes_from = "PLUS hint" if setup.hints.get("MorphologicalOpeningCircleRadiusMm") else "default"
        attempts = tuple(replace(plus, threshold=t, max_candidates=MAX_CANDIDATES, whole_frame=True)
                         for t in THRESHOLDS)
        return cls(**setup.common(), tolerances=Tolerances.robust(), dot_attempts=attempts, sizes_from=sizes_from)

    def with_sizes(self, bar_px: int, disk_px: int, sizes_from: str) -> ProbecalSegmenter:
        """The same segmenter with other bar half-length and opening disk radius (px)."""
        attempts = tuple(replace(p, bar_px=bar_px, disk_px=disk_px) for p in self.dot_attempts)
        return replace(self, dot_attempts=attempts, sizes_from=sizes_from)

    def tune(self, frames: list[np.ndarray], progress: Progress | None = None) -> ProbecalSegmenter:
        """The sizes that suit these frames (a sample of one recording), chosen without ground
        truth: each opening disk radius of :data:`DISK_CHOICES_PX` is run at each threshold
        alone, and the one that finds the pattern most often over all of them wins (the most
        stable: a disk that loses dots at some threshold is too big, one that lets speckle in is
        too small); ties go to the larger disk, which rejects more speckle. The bars are PLUS's
        2 mm; when that finds the pattern in under :data:`TUNE_ENOUGH` of the runs, longer bars
        of :data:`BAR_CHOICES_MM` are tried (dots wider than the bar are removed with the
        lines). The scanner's overlay (:func:`core.calibration.dots.overlay_keep`) is masked
        first, and kept masked unless the frames unmasked give the pattern more often. The sizes
        are chosen with no limit on how much worse a rigid fit of a pattern is than an affine one
        (:func:`core.calibration.labelling.rigid_excess_mm`); that limit is then
        :data:`RIGID_EXCESS_FACTOR` times the median excess of the tuning frames' patterns (when
        most give one), at least :data:`core.calibration.labelling.RIGID_EXCESS_MM`, so that a
        scanner whose images are slightly non-rigid keeps its patterns. Sizes set by a PLUS hint
        are kept as they are. ``progress(sizes tried, sizes to try)`` is told after each."""
        if self.sizes_from != "default" or not frames:
            return self
        if self.binning > 1:
            tuned = self._binned().tune([self._binned_frame(as_gray(frame)) for frame in frames], progress)
            return replace(tuned, spacing_mm=self.spacing_mm, roi=self.roi, binning=self.binning)
        pixel = float(np.sqrt(np.prod(self.spacing_mm)))
        loose = replace(self, tolerances=replace(self.tolerances, max_rigid_excess_mm=np.inf))
        grays = [as_gray(frame) for frame in frames]
        keep = overlay_keep(grays)
        masked = grays if keep is None else [cv2.bitwise_and(gray, keep) for gray in grays]
        runs = len(frames) * len(self.dot_attempts)
        sizes = len(BAR_CHOICES_MM) * len(DISK_CHOICES_PX)
        scores = []  # (found, -bar px, disk px): most found, then PLUS's shorter bar, then the larger disk
        for bar_mm in BAR_CHOICES_MM:
            bar = max(int(round(bar_mm / pixel)), 1)
            for disk in DISK_CHOICES_PX:
                scores.append((loose.with_sizes(bar, disk, "tuned")._found_runs(masked), -bar, disk))
                if progress:
                    progress(len(scores), sizes)
            if max(scores)[0] >= TUNE_ENOUGH * runs:
                break
        found, bar, disk = max(scores)
        tuned = loose.with_sizes(-bar, disk, "tuned")
        unmasked = found if keep is None else tuned._found_runs(grays)
        if unmasked <= found:
            tuned = replace(tuned, keep=keep)
        limit = max(RIGID_EXCESS_MM, RIGID_EXCESS_FACTOR * tuned._median_rigid_excess(grays))
        tuned = replace(tuned, tolerances=replace(tuned.tolerances, max_rigid_excess_mm=limit))
        return replace(tuned, sizes_from=f"tuned on {len(frames)} frames: pattern in {max(found, unmasked)} "
                                         f"of {runs} runs")

    def _found_runs(self, grays: list[np.ndarray]) -> int:
        """How many (frame, threshold) runs find the pattern, each threshold alone."""
        return sum(on_two_threads(lambda gray: sum(self._label(gray, 0, [dots]).found
                                                   for dots in self._dot_sets(gray)), grays))

    def _median_rigid_excess(self, grays: list[np.ndarray]) -> float:
        """Median :func:`core.calibration.labelling.rigid_excess_mm` (mm) of the patterns found in ``grays``;
        0 unless most of them give one (a few finds may be wrong ones)."""
        excess = []
        for result in on_two_threads(self, grays):
            if result.markers is not None:  # the pattern was found
                points = result.markers[self.model.wire_index.ravel()] * np.asarray(self.spacing_mm)
                excess.append(rigid_excess_mm(points.reshape(self.model.n_layers, 3, 2), self.model))
        return float(np.median(excess)) if 2 * len(excess) > len(grays) else 0.0

    def describe(self) -> str:
        sx, sy = self.spacing_mm
        text = super().describe()
        if self.binning > 1:
            n = self.binning
            text += f" (frames binned {n} x {n}: {sx * n:.3f} x {sy * n:.3f})"
        overlay = f", overlay masked ({np.count_nonzero(self.keep == 0)} px)" if self.keep is not None else ""
        rigid = f", rigid fit within {self.tolerances.max_rigid_excess_mm:.2f} mm of the affine"
        return f"{text}: {_sizes_text(self.dot_attempts, self.sizes_from, self.roi)}{overlay}{rigid}"

    def _segment(self, gray: np.ndarray, index: int) -> FrameResult:
        if self.binning > 1:
            n = self.binning
            result = self._binned()(self._binned_frame(gray), index)
            markers = None
            if result.markers is not None:
                radius = REFINE_RADIUS_MM / np.asarray(self.spacing_mm)
                markers = refined_centroids(gray, (result.markers + 0.5) * n - 0.5, (radius[0], radius[1]))
            return replace(result, markers=markers, candidates=(result.candidates + 0.5) * n - 0.5)
        return super()._segment(gray, index)

    def _binned_frame(self, gray: np.ndarray) -> np.ndarray:
        """A frame binned ``binning`` x ``binning`` (each pixel the mean of a block, which keeps
        every echo's centroid; a last partial row or column of blocks is left out)."""
        n = self.binning
        height, width = (gray.shape[0] // n) * n, (gray.shape[1] // n) * n
        return cv2.resize(gray[:height, :width], (width // n, height // n), interpolation=cv2.INTER_AREA)

    def _binned(self) -> ProbecalSegmenter:
        """This segmenter for binned frames."""
        n = self.binning
        sx, sy = self.spacing_mm
        roi = None if self.roi is None else (self.roi[0] // n, self.roi[1] // n, self.roi[2] // n, self.roi[3] // n)
        fan = self.fan
        if fan is not None:  # in the binned pixels
            origin = ((fan.origin_px[0] + 0.5) / n - 0.5, (fan.origin_px[1] + 0.5) / n - 0.5)
            fan = Fan(fan.angles_deg, origin, fan.radius_start_px / n, fan.radius_stop_px / n)
        return replace(self, spacing_mm=(sx * n, sy * n), roi=roi, binning=1, fan=fan)

    def _dot_sets(self, gray: np.ndarray) -> Iterator[Dots]:
        if self.keep is not None and self.keep.shape == gray.shape:
            gray = cv2.bitwise_and(gray, self.keep)
        fan = self.fan
        if fan is not None:
            gray = fan_filled(gray, fan, PLUS_BAR_MM / float(np.sqrt(np.prod(self.spacing_mm))))
        return ((dots if fan is None else dots.within(fan)).without_faint(self.n_wires, FAINT)
                for dots in plus_dot_sets(gray, self.dot_attempts, self.roi))

    def _unlabelled(self, index: int, richest: Dots, failure: tuple[Dots, str]) -> FrameResult:
        if self.model.n_layers > 2:
            return self._incomplete_layer(index, richest, failure[1])
        return super()._unlabelled(index, richest, failure)

    def _incomplete_layer(self, index: int, dots: Dots, reason: str) -> FrameResult:
        """A pattern whose other layers are all seen: each dot of the remaining layer is the
        candidate nearest where the affine fit of those layers puts it (within
        :data:`NEAR_PREDICTION_MM`). All three there: the pattern is checked whole and kept;
        one missing: the frame is rejected naming that wire and where it should be."""
        scale = np.asarray(self.spacing_mm)
        q = dots.positions * scale
        for layer in range(self.model.n_layers):
            sub = self.model.without_layer(layer)
            labelling = label_dots(dots.positions, self.spacing_mm, sub, self.tolerances)
            if labelling.dots is None or labelling.ambiguous:
                continue
            predicted = predict_layer_mm(q[labelling.dots], sub, self.model, layer)
            distance = np.linalg.norm(q[None] - predicted[:, None], axis=-1)
            nearest = distance.argmin(axis=1)
            seen = distance[np.arange(3), nearest] <= NEAR_PREDICTION_MM
            if seen.sum() < 2 or len(set(nearest[seen])) < seen.sum():
                continue
            wires = self.model.wire_index[layer]
            if not seen.all():
                (k,) = np.flatnonzero(~seen)
                u, v = predicted[k] / scale
                return FrameResult(index, False, None, f"{self.n_wires - 1} of {self.n_wires} dots: wire "
                                   f"{wires[k] + 1} not seen near ({u:.0f}, {v:.0f}) px; frame left out",
                                   dots.positions)
            chosen = np.insert(labelling.dots, layer, nearest, axis=0)
            residual = float(affine_residual_mm(q[chosen][None], self.model)[0])
            if (residual <= self.tolerances.max_residual_mm and len(set(chosen.ravel())) == chosen.size
                    and rigid_excess_mm(q[chosen], self.model) <= self.tolerances.max_rigid_excess_mm):
                markers = np.empty((self.n_wires, 2))
                markers[self.model.wire_index.ravel()] = dots.positions[chosen.ravel()]
                return FrameResult(index, True, markers, "ok", dots.positions, residual)
        return FrameResult(index, False, None, reason, dots.positions)

@dataclass(frozen=True)
class ThesisSegmenter(_Labelled):
    """The thesis's dot finder (:func:`core.calibration.dots.find_dots`: a median filter, a disk
    opening, a threshold, blobs of a plausible size), retried with the parameter sets
    ``seed_attempts`` (dim dots, small dots, noisy frames), labelled with the twin's limits."""

    kind: ClassVar[str] = "thesis"
    seed_attempts: tuple[DotParams, ...] = ()

    @classmethod
    def made(cls, setup: _SetUp) -> Segmenter:
        pixel, (sx, sy) = setup.pixel_mm, setup.spacing_mm
        base = DotParams(
            median_px=max(odd(MEDIAN_MM / pixel), 3),
            disk_px=max(int(round(DISK_RADIUS_MM / pixel)), 1),
            threshold=THRESHOLD,
            min_area_px=MIN_AREA_MM2 / (sx * sy),
            max_area_px=MAX_AREA_MM2 / (sx * sy),
        )
        seeds = (
            base,
            replace(base, threshold=base.threshold / 2),  # dim dots
            replace(base, median_px=max(base.median_px - 2, 1)),  # small dots
            replace(base, median_px=base.median_px + 2, disk_px=base.disk_px + 1,  # noisy frames
                    threshold=min(2 * base.threshold, 0.6)),
        )
        return cls(**setup.common(), tolerances=Tolerances(), seed_attempts=tuple(dict.fromkeys(seeds)))

    def _dot_sets(self, gray: np.ndarray) -> Iterator[Dots]:
        return (find_dots(gray, p, self.roi).brightest(MAX_CANDIDATES) for p in self.seed_attempts)


@dataclass(frozen=True)
class PlusSegmenter(Segmenter):
    """PLUS's dot finder and labelling with PLUS's settings (``dot_attempts``: its one parameter
    set; ``plus_lines``: its line finder's limits), as a reference. A pattern whose dots an affine
    map cannot put on their wires (RMS beyond the residual limit) is rejected, which PLUS does
    not check."""

    kind: ClassVar[str] = "plus"
    dot_attempts: tuple[PlusDotParams, ...] = ()
    plus_lines: PlusLineModel | None = None

    @classmethod
    def made(cls, setup: _SetUp) -> Segmenter:
        return cls(**setup.common(), tolerances=Tolerances.from_plus_hints(setup.hints),
                   dot_attempts=(plus_dot_params(setup.hints, setup.pixel_mm),),
                   plus_lines=PlusLineModel.from_plus_hints(setup.phantom, setup.hints))

    def describe(self) -> str:
        return f"{super().describe()}: {_sizes_text(self.dot_attempts, 'PLUS', self.roi)}"

    def _segment(self, gray: np.ndarray, index: int) -> FrameResult:
        assert self.plus_lines is not None  # made() gives every plus segmenter PLUS's line model
        dots = find_plus_dots(gray, self.dot_attempts[0], self.roi)
        found, reason = plus_label_dots(dots.positions, dots.intensities, self.plus_lines)
        if found is None:
            if gray.max() - gray.min() < MIN_CONTRAST:
                reason = "no echoes: the frame is blank"
            return FrameResult(index, False, None, reason, dots.positions)
        markers = dots.positions[found]
        points_mm = markers[self.model.wire_index] * np.asarray(self.spacing_mm)
        residual = float(affine_residual_mm(points_mm[None], self.model)[0])
        if residual > self.tolerances.max_residual_mm:
            return FrameResult(index, False, None, f"dots off their wires by {residual:.2f} mm RMS", dots.positions)
        return FrameResult(index, True, markers, "ok", dots.positions, residual)


STRATEGIES: dict[str, type[Segmenter]] = {s.kind: s for s in (ProbecalSegmenter, ThesisSegmenter, PlusSegmenter)}


Progress = Callable[[int, int], None]
T = TypeVar("T")


@lru_cache(maxsize=4)
def _fan_inside(fan: Fan, width: int, height: int) -> np.ndarray:
    return fan.mask(width, height)


def fan_filled(gray: np.ndarray, fan: Fan, reach_px: float) -> np.ndarray:
    """A fan image with the black outside its fan replaced by the mean of the fan's pixels
    within about ``reach_px`` (Gaussian weights; 0 farther out): without it the step from echoes
    to black is an edge that a morphological top-hat lifts into dots."""
    inside = _fan_inside(fan, gray.shape[1], gray.shape[0])
    weight = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), reach_px)
    total = cv2.GaussianBlur(np.where(inside, gray, 0).astype(np.float32), (0, 0), reach_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(weight > 1e-3, total / weight, 0.0)
    return np.where(inside, gray, np.clip(np.round(mean), 0, 255)).astype(np.uint8)


def session_segmenter(session: Session, kind: str = "probecal", use_hints: bool = True,
                      work_spacing_mm: float = WORK_SPACING_MM, progress: Progress | None = None) -> Segmenter:
    """The session's segmenter (:meth:`Segmenter.for_session`), tuned on up to
    :data:`TUNE_FRAMES` valid frames spread evenly over the recording (``progress`` as
    :meth:`Segmenter.tune` tells it), once :func:`check_segmentation` finds that they fit the memory
    limit."""
    segmenter = Segmenter.for_session(session, kind=kind, use_hints=use_hints, work_spacing_mm=work_spacing_mm)
    valid = [i for i in range(len(session)) if session.records[i].extra.get("image_valid", True)]
    sample = tuning_sample(valid)
    if not sample:
        return segmenter
    size = check_segmentation(session, len(sample))
    return segmenter.tune(on_two_threads(lambda i: _frame_within(session, i, size), sample), progress)


HELD_BYTES_PER_PIXEL = 2
"""What each tuning frame holds while the tuning runs, per pixel: the frame and its copy with
the scanner's overlay masked."""
SEGMENT_BYTES_PER_PIXEL = 24
"""The working memory of segmenting frames on two threads, per pixel of a frame: measured 15
bytes (9 Mpx frames at 0.1 mm/px, which are not binned: morphology's float copies)."""


def check_segmentation(session: Session, tuning_frames: int) -> tuple[int, int]:
    """The (width, height) px of the session's frames (its manifest's, else its first frame's);
    InputError naming the session when segmenting them, with ``tuning_frames`` of them held to
    tune on (:data:`HELD_BYTES_PER_PIXEL`, :data:`SEGMENT_BYTES_PER_PIXEL`), would pass the
    memory limit. Checked before the frames are read."""
    width, height = session.image_size
    checked_bytes(session.path, f"segmenting frames of {width} x {height} px ({tuning_frames} held to tune on)",
                  (height, width), HELD_BYTES_PER_PIXEL * tuning_frames + SEGMENT_BYTES_PER_PIXEL)
    return width, height


def _frame_within(session: Session, index: int, size: tuple[int, int]) -> np.ndarray:
    """Frame ``index`` of the session, InputError naming it when it has more pixels than the
    session's frames (``size``, (width, height) px), which the memory was counted for."""
    image = session.image(index)
    height, width = image.shape[:2]
    if height * width > size[0] * size[1]:
        raise InputError(session.path / session.records[index].image,
                         f"frame {index} is {width} x {height} px, larger than the session's frames "
                         f"({size[0]} x {size[1]} px)")
    return image


def on_two_threads(function: Callable[[Any], T], items: Iterable[Any]) -> list[T]:
    """``function`` of each item, in order, on two threads (decoding frames and OpenCV's
    filters release the GIL)."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(function, items))


def tuning_sample(items: list) -> list:
    """Up to :data:`TUNE_FRAMES` of ``items`` spread evenly over them (a recording's frames)."""
    return items[:: max(1, -(-len(items) // TUNE_FRAMES))]


def segment_session(session: Session, progress: Progress | None = None,
                    segmenter: Segmenter | None = None) -> list[FrameResult]:
    """Segment every frame of a session (two threads: decoding and OpenCV release the GIL);
    by default with :func:`session_segmenter`. A found pattern keeps its echoes' peak rows, read
    from the frame while it is decoded (the calibration's echo-peak refit needs them)."""
    segmenter = segmenter or session_segmenter(session)

    def one(i: int) -> FrameResult:
        if not session.records[i].extra.get("image_valid", True):
            return FrameResult(i, False, None, "frame marked invalid in the recording", NO_DOTS.positions)
        image = session.image(i)
        result = segmenter(image, i)
        if result.markers is None:
            return result
        return replace(result, peak_rows=echo_peak_rows(image, result.markers, segmenter.spacing_mm))

    results = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        for result in pool.map(one, range(len(session))):
            results.append(result)
            if progress:
                progress(len(results), len(session))
    return results


def segmentation_json(results: list[FrameResult], session: Session) -> dict:
    """design §6 ``segment --out``: index is the source file's frame index for imported recordings."""
    frames = []
    for r in results:
        source = session.records[r.index].source_index
        frames.append({
            "index": int(source if source is not None else r.index),
            "found": bool(r.found),
            "markers": None if r.markers is None else np.round(r.markers, 3).tolist(),
            "reason": r.reason,
        })
    return {"frames": frames}


def write_segmentation(path: str | Path, results: list[FrameResult], session: Session) -> None:
    """Write :func:`segmentation_json` to ``path``, atomically (``probecal segment --out`` and the
    console's Save session)."""
    write_json(path, segmentation_json(results, session))
