"""Guided freehand calibration on the freehand twin (``core.acquisition.freehand``) at ``bench``.

A hand holds the twin's probe over its phantom; an optical tracker reports the probe and the
reference with the level's noise and drift; the scanner's frames come as late as it runs. The
acquisition (``core.calibration.guided``) runs as the console runs it: the hand first moves the
probe up and down until the image latency is measured, then follows the targets the console
shows (the nearest target not yet reached) until the corner bound falls within the tolerance.
The bound is measured beside the stream: its result counts only once the calibration it took
would have finished, the hand moving on meanwhile (its wall time is the hand's time).

For each seed: the time to "enough" (s of the hand's time), the image corners of the calibration
that said enough against the truth (mean of four and farthest, mm), and whether its bound covers
the farthest corner. Then the same hand moving at random over the same ranges (a new random target
each time it has reached one), unguided, for the same time, every frame it kept calibrated at the
end. A seed not enough within ``--max-s`` is calibrated on every frame kept by then.

Run: .venv/bin/python benchmarks/bench_freehand.py [--seeds 10] [--tolerance 1.0] [--max-s 600] [--write-docs]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

from probecal.core.acquisition.freehand import FreehandTwin, Person, ScannerFrame, TrackerReport
from probecal.core.acquisition.guidance import REACH, apart
from probecal.core.acquisition.imagesource import SourceFrame
from probecal.core.acquisition.pairing import FramePairer
from probecal.core.acquisition.plan import PoseRanges, crossings_in_view, perturbed, pivot_mm
from probecal.core.acquisition.tracker import PoseFeed, probe_to_reference
from probecal.core.calibration.guided import GUIDED_PHASE, GuidedAcquisition, GuideSettings
from probecal.core.calibration.result import Calibration
from probecal.core.calibration.segment import Segmenter
from probecal.core.calibration.uncertainty import corner_distances_mm, image_corners_px
from probecal.core.io.manifest import CONTINUOUS, Manifest
from probecal.core.io.session import SessionWriter


@dataclass(frozen=True)
class Outcome:
    seed: int
    guided: bool
    seconds: float  # hand time to enough (or the time allowed)
    enough: bool
    kept: int
    reached: int
    targets: int
    bound_mm: float | None
    mean_mm: float | None
    farthest_mm: float | None
    wall_s: float
    problem: str = ""
    refused: tuple[tuple[str, int], ...] = ()  # guided frames not kept, by reason


class Guide:
    """The console's guidance as the bench's person reads it: the strokes while the latency is
    measured, then the acquisition's target (guided) or a random one over the same ranges, a new
    one once the probe reaches it (unguided)."""

    def __init__(self, acquisition: GuidedAcquisition, guided: bool, seed: int):
        self.acquisition, self.guided = acquisition, guided
        self.rng = np.random.default_rng([seed, 99])
        self._random: np.ndarray | None = None

    def __call__(self, offsets: np.ndarray | None) -> np.ndarray | None:
        if self.acquisition.phase != GUIDED_PHASE:
            return None
        if self.guided:
            k = self.acquisition.target(offsets)
            return self.acquisition.coverage.targets[k]
        if self._random is None or (offsets is not None and apart(self._random, offsets, self.ranges) <= 1.0):
            self._random = self._draw()
        return self._random

    @property
    def ranges(self) -> PoseRanges:
        return self.acquisition.settings.ranges

    def _draw(self) -> np.ndarray:
        bounds = np.array([0.0, *self.ranges.translation_mm[1:], *self.ranges.rotation_deg])
        setup = self.acquisition.setup
        while True:  # a random pose that keeps every wire in view, as the targets do
            offsets = self.rng.uniform(-1, 1, 6) * bounds
            if crossings_in_view(setup, perturbed(setup.image_to_phantom, pivot_mm(setup), offsets),
                                 self.ranges.margin_mm):
                return offsets


def run(seed: int, guided: bool, settings: GuideSettings, max_s: float, frame_hz: float) -> Outcome:
    started = time.monotonic()
    twin = FreehandTwin(seed, "bench")
    truth = twin.truth()
    true = Calibration(np.array(truth["image_to_tool_rigid"]), tuple(truth["pixel_spacing_mm"]))
    probe, phantom = twin.setup.probe, twin.setup.phantom
    manifest = Manifest(kind="calibration", source={"kind": "tracked", "tracker": "freehand twin"},
                        image_size=(probe.width_px, probe.height_px), pixel_spacing_mm=probe.nominal_spacing_mm,
                        motion=CONTINUOUS)
    with tempfile.TemporaryDirectory() as tmp:
        writer = SessionWriter(Path(tmp) / "guided", manifest, phantom, probe)
        feed = PoseFeed()
        segmenter = Segmenter.create(phantom, probe.nominal_spacing_mm)
        acquisition = GuidedAcquisition(writer, replace(twin.setup, phantom_to_base=np.eye(4)), segmenter,
                                        FramePairer(feed), replace(settings, pose_wait_s=0.0, seed=seed))
        person = Person(Guide(acquisition, guided, seed))
        pending: tuple[float, float | None] | None = None  # (when the bound being measured is known, its value)
        said: tuple[float, Calibration] | None = None
        refused: Counter[str] = Counter()
        index = 0
        for event in twin.events(person, frame_hz):
            if isinstance(event, TrackerReport):
                t = event.t
                feed.push(probe_to_reference(event.probe_to_tracker, event.reference_to_tracker), t)
                if pending is not None and t >= pending[0]:
                    if acquisition.enough:
                        assert acquisition.bound is not None
                        said = t, acquisition.bound.calibration
                        break
                    pending = None
                if pending is None and acquisition.bound_due():
                    wall = time.monotonic()
                    acquisition.measure_bound()
                    pending = (t + time.monotonic() - wall, acquisition.bound_mm)
                if t > max_s:
                    break
                continue
            assert isinstance(event, ScannerFrame)
            step = acquisition.take(SourceFrame(event.image, event.stamp, index))
            index += 1
            if step.index is None and acquisition.phase == GUIDED_PHASE:
                refused[step.why.split(" (")[0].split(":")[0]] += 1
            if step.offsets is not None:
                person.seen(step.offsets, event.offsets)
        if said is None:  # the time is up: every frame recorded calibrated, as the console's Calibrate does
            acquisition.measure_bound()
        writer.close()
    seconds = said[0] if said else max_s
    calibration = said[1] if said else (acquisition.bound.calibration if acquisition.bound else None)
    corners = (None if calibration is None else
               corner_distances_mm(calibration, true, image_corners_px((probe.width_px, probe.height_px))))
    return Outcome(seed, guided, seconds, said is not None, acquisition.kept, int(acquisition.coverage.reached.sum()),
                   len(acquisition.coverage.targets), acquisition.bound_mm,
                   None if corners is None else float(corners.mean()),
                   None if corners is None else float(corners.max()), time.monotonic() - started,
                   acquisition.bound_problem or acquisition.latency_problem, tuple(refused.most_common()))


def run_all(pool: ProcessPoolExecutor, seeds: list[int], guided: bool, settings: GuideSettings, max_s: list[float],
            frame_hz: float) -> list[Outcome]:
    """Every seed's outcome, each printed as it comes, in seed order."""
    futures = {pool.submit(run, seed, guided, settings, limit, frame_hz): seed for seed, limit in zip(seeds, max_s)}
    for future in as_completed(futures):
        print(describe(future.result()), flush=True)
    return sorted((f.result() for f in futures), key=lambda o: o.seed)


def describe(o: Outcome) -> str:
    bound = "-" if o.bound_mm is None else f"{o.bound_mm:.3f}"
    corners = "-" if o.mean_mm is None else f"{o.mean_mm:.3f} / {o.farthest_mm:.3f}"
    covered = "" if o.bound_mm is None or o.farthest_mm is None else ("yes" if covers(o) else "NO")
    return (f"seed {o.seed:2d} {'guided  ' if o.guided else 'unguided'}: {o.seconds:6.1f} s "
            f"{'enough' if o.enough else 'not enough':10s} kept {o.kept:4d}, targets {o.reached}/{o.targets}, "
            f"bound {bound} mm, corners mean / farthest {corners} mm, covered {covered} "
            f"({o.wall_s:.0f} s wall; not kept: {', '.join(f'{why} {n}' for why, n in o.refused) or 'none'})"
            f"{' ' + o.problem if o.problem else ''}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--tolerance", type=float, default=GuideSettings.tolerance_mm,
                        help="enough when the corner bound is within this (mm)")
    parser.add_argument("--max-s", type=float, default=600.0, help="hand time allowed per seed (s)")
    parser.add_argument("--frame-hz", type=float, default=10.0, help="the scanner's frame rate")
    parser.add_argument("--rotation", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="the targets' turns about the phantom's axes, either way (deg; default the guide's)")
    parser.add_argument("--no-unguided", action="store_true")
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    settings = GuideSettings(tolerance_mm=args.tolerance)
    if args.rotation:
        settings = replace(settings, ranges=replace(settings.ranges, rotation_deg=tuple(args.rotation)))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    turns = "/".join(f"{v:g}" for v in settings.ranges.rotation_deg)
    print(f"freehand twin at bench, {len(seeds)} seeds, tolerance {args.tolerance:g} mm, frames at "
          f"{args.frame_hz:g} Hz, targets turned up to {turns} deg, reached within {REACH:g} of each range", flush=True)
    with ProcessPoolExecutor(max_workers=2) as pool:
        guided = run_all(pool, seeds, True, settings, [args.max_s] * len(seeds), args.frame_hz)
        unguided = [] if args.no_unguided else run_all(pool, seeds, False, replace(settings, first_bound=10**9),
                                                       [o.seconds for o in guided], args.frame_hz)
    summarize("guided", guided)
    if unguided:
        summarize("unguided, same time", unguided)
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, table_rows(guided, unguided)))}")


TABLE = ("seed", "guided: time to enough", "corners, mean / farthest (mm)", "bound (mm)", "covers",
         "unguided, same time: corners (mm)", "bound (mm)", "covers")


def _cells(o: Outcome | None) -> list[str]:
    """An outcome's corners, bound and whether the bound covers the farthest corner."""
    if o is None:
        return ["-", "-", "-"]
    corners = "-" if o.mean_mm is None else f"{o.mean_mm:.3f} / {o.farthest_mm:.3f}"
    bound = "-" if o.bound_mm is None else f"{o.bound_mm:.2f}"
    return [corners, bound, "yes" if covers(o) else "no"]


def covers(o: Outcome) -> bool:
    return o.farthest_mm is not None and o.bound_mm is not None and o.farthest_mm <= o.bound_mm


def table_rows(guided: list[Outcome], unguided: list[Outcome]) -> list[list[str]]:
    """A row per seed, then the seeds together (median time, mean corners, seeds covered)."""
    beside = {o.seed: o for o in unguided}
    rows = [[str(o.seed), f"{o.seconds:.0f} s" if o.enough else f"not in {o.seconds:.0f} s", *_cells(o),
             *_cells(beside.get(o.seed))] for o in guided]

    def together(outcomes: list[Outcome]) -> list[str]:
        means = [o.mean_mm for o in outcomes if o.mean_mm is not None]
        return [f"**{np.mean(means):.3f}** (mean)" if means else "-", "",
                f"**{sum(covers(o) for o in outcomes)} of {len(outcomes)}**"]

    rows.append([f"**{len(guided)} seeds**", f"**{np.median([o.seconds for o in guided]):.0f} s** (median; "
                 f"{sum(o.enough for o in guided)} enough)", *together(guided),
                 *(together(unguided) if unguided else ["-", "-", "-"])])
    return rows


def summarize(label: str, rows: list[Outcome]) -> None:
    done = [o for o in rows if o.mean_mm is not None]
    covered = sum(covers(o) for o in rows)
    means = [o.mean_mm for o in done if o.mean_mm is not None]
    mean, worst = (np.mean(means), max(means)) if means else (float("nan"), float("nan"))
    print(f"{label}: enough in {sum(o.enough for o in rows)}/{len(rows)}, median time "
          f"{np.median([o.seconds for o in rows]):.0f} s, corners mean {mean:.3f} mm (worst seed {worst:.3f}), "
          f"bound covers {covered}/{len(rows)}")


if __name__ == "__main__":
    main()
