"""The console's tracked probe (``serve --tracker``): Connect opens the tracker and its images,
Start sweep runs the guided acquisition (``core.calibration.guided``), showing what is still
missing: the coverage of each measure and the corner bound in the status column, the targets and
the live image in 3D, in the phantom's frame."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from probecal.app.console.draw import image_outline
from probecal.app.console.panel import GREEN, GREY, RED
from probecal.app.console.text import Markup, html
from probecal.app.console.view import ConsoleView
from probecal.app.tracked import (
    TrackedSpec,
    TrackedStreams,
    guide_of,
    guided_acquisition,
    open_streams,
)
from probecal.core.acquisition.guidance import MEASURES, UNITS, measures
from probecal.core.acquisition.plan import perturbed, pivot_mm
from probecal.core.acquisition.sweep import LiveFrame
from probecal.core.acquisition.tracked import TrackedSetup
from probecal.core.calibration.guided import (
    GUIDED_PHASE,
    GuidedAcquisition,
    GuidedOutcome,
    GuidedRun,
    GuideSettings,
    GuideStep,
)
from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.robot.contract import HOME_JOINTS

SHOW_HZ = 8.0
"""How often a guided frame is drawn (the stream may come faster)."""
COVERED = ("#e9ecef", "#b2f2bb", "#40c057")
"""A coverage bin's colour: no frame kept there, one or two, three or more."""


def coverage_html(acquisition: GuidedAcquisition, paused: str | None) -> Markup:
    """What is still missing, for the status column: the phase, each measure's bins over its
    range (filled where frames were kept), the targets reached and the bound against the
    tolerance; a pause's reason in red."""
    rows = []
    span = measures(np.array([*acquisition.settings.ranges.translation_mm, *acquisition.settings.ranges.rotation_deg]))
    for name, unit, counts, half in zip(MEASURES, UNITS, acquisition.coverage.counts, span):
        cells = Markup("").join(html('<td style="background:{};width:18px"></td>',
                                     COVERED[0 if c == 0 else 1 if c < 3 else 2]) for c in counts)
        rows.append(html('<tr><td style="padding-right:4px;white-space:nowrap">{} ±{:g} {}</td>{}</tr>', name, half,
                         unit, cells))
    coverage = acquisition.coverage
    current = coverage.rounds == coverage.round
    reached = f"targets reached: {int(coverage.reached[current].sum())} / {int(current.sum())}"
    if coverage.round:
        reached += f" (round {coverage.round + 1}; {int(coverage.reached.sum())} in all)"
    bound = acquisition.bound_mm
    tolerance = acquisition.settings.tolerance_mm
    bound_text = ("corner bound: measured after "
                  f"{acquisition.settings.first_bound} frames held still" if bound is None else
                  f"corner bound: ±{bound:.2f} mm (tolerance {tolerance:g} mm)")
    if acquisition.phase != GUIDED_PHASE:
        latency = (f" (latency so far {acquisition.latency.image_latency_s * 1000:.0f} ± "
                   f"{acquisition.latency.std_error_s * 1000:.0f} ms)" if acquisition.latency else "")
        phase = f"Move the probe slowly up and down over the wires{latency}."
    elif acquisition.enough:
        phase = "Enough: the bound is within your tolerance."
    else:
        phase = f"Hold the image on the orange target. {acquisition.kept} frames held still."
    lines = [html('<div style="font-weight:600">{}</div>', phase)]
    if paused is not None:
        lines.append(html('<div style="color:{};font-weight:600">Paused: {}</div>', RED, paused))
    lines += [html('<table style="border-spacing:1px;font-size:12px">{}</table>', Markup("").join(rows)),
              html("<div>{}</div>", reached),
              html('<div style="color:{};font-weight:600">{}</div>', GREEN if acquisition.enough else GREY, bound_text)]
    return html('<div class="probecal-guide" style="font-size:13px;line-height:1.25">{}</div>', Markup("").join(lines))


@dataclass
class GuidedMode:
    """A console's tracked probe: its streams once connected, and the guided run in progress."""

    spec: TrackedSpec
    view: ConsoleView
    setup: TrackedSetup
    settings: GuideSettings = GuideSettings()
    streams: TrackedStreams | None = field(init=False, default=None)
    acquisition: GuidedAcquisition | None = field(init=False, default=None)
    _run: GuidedRun | None = field(init=False, default=None)
    _shown_at: float = field(init=False, default=0.0)
    _lock: threading.Lock = field(init=False, default_factory=threading.Lock)

    @property
    def connected(self) -> bool:
        return self.streams is not None and self.streams.tracker.connected

    @property
    def phantom(self) -> Phantom:
        assert self.setup.phantom is not None  # a tracked console is made for a phantom (tracked_setup)
        return self.setup.phantom

    @property
    def name(self) -> str:
        return "the tracked probe" if self.streams is None else self.streams.tracker.name

    def connect(self) -> None:
        """Open the tracker and its images (again, when open), and show the first frame."""
        self.close()
        self.streams = open_streams(self.spec, self._guide)
        frame = self.streams.source.latest(5.0)
        self.view.show_frame(LiveFrame(frame.image, self.streams.tracker.tool_to_base(), HOME_JOINTS, None, 0, 0),
                             None)

    def _guide(self, offsets: np.ndarray | None) -> np.ndarray | None:
        """What the freehand twin's hand is shown: the run's guidance."""
        return guide_of([self.acquisition] if self.acquisition is not None else [], offsets)

    def run(self, path: Path, tolerance_mm: float, created: Callable[[], None]) -> GuidedOutcome:
        """A guided acquisition into a new session at ``path`` until enough or stopped;
        ``created`` is called once the session is."""
        if self.streams is None:
            raise InputError(None, "the tracked probe is not connected: click Connect first")
        streams = self.streams
        writer, self.acquisition = guided_acquisition(streams, self.setup, path, tolerance_mm, self.settings)
        created()
        self.view.panel.guide.visible = True
        self.view.show_step("guiding")
        self._run = GuidedRun(self.acquisition, streams.source, lambda: streams.tracker.paused, self._show)
        try:
            return self._run.run()
        finally:
            self._run = None
            if streams.server is not None:
                writer.write_truth(streams.server.twin.truth())
            writer.close()
            self._draw_guide(None)

    def stop(self) -> bool:
        """End the guided run (its frames stay recorded); False when none runs."""
        run = self._run
        if run is None:
            return False
        run.stop()
        return True

    def close(self) -> None:
        if self.streams is not None:
            self.streams.close()
            self.streams = None

    def _show(self, step: GuideStep | str) -> None:
        """A frame (or a pause's reason) on every tab, at most ``SHOW_HZ`` times a second."""
        paused = step if isinstance(step, str) else None
        now = time.monotonic()
        if paused is None and now - self._shown_at < 1.0 / SHOW_HZ:
            return
        self._shown_at = now
        if isinstance(step, GuideStep):
            pose = step.tool_to_base if step.tool_to_base is not None else np.eye(4)
            self.view.show_frame(LiveFrame(step.frame.image, pose, HOME_JOINTS, None, 0, 0), step.result)
        self._draw_guide(step.offsets if isinstance(step, GuideStep) else None, paused=paused)
        self._count()

    def _count(self) -> None:
        """The strip's counter: frames recorded and kept; its bar, the targets of this round reached."""
        acquisition = self.acquisition
        assert acquisition is not None
        recorded = len(acquisition.results)
        if acquisition.phase != GUIDED_PHASE:
            self.view.working(f"Guided acquisition: {recorded} frames recorded while the latency is measured")
        else:
            self.view.counter(f"Guided acquisition: {recorded} frames recorded, {acquisition.kept} kept",
                              100.0 * acquisition.coverage.fraction)

    def _draw_guide(self, offsets: np.ndarray | None, paused: str | None = None) -> None:
        acquisition = self.acquisition
        if acquisition is None:
            return
        content = coverage_html(acquisition, paused)
        self.view.panel.guide.show(content)
        setup = acquisition.centre
        left = np.flatnonzero(~acquisition.coverage.reached & ~acquisition.coverage.given_up)
        outlines = np.array([self._outline(perturbed(setup.image_to_phantom, pivot_mm(setup), t))
                             for t in acquisition.coverage.targets[left]]).reshape(-1, 2, 3)
        k = acquisition.coverage.next_target(offsets)
        nearest = None if k is None else self._outline(perturbed(setup.image_to_phantom, pivot_mm(setup),
                                                                 acquisition.coverage.targets[k]))
        live = None if offsets is None else self._outline(perturbed(setup.image_to_phantom, pivot_mm(setup), offsets))
        self.view.scene.set_guide(outlines, nearest, live)

    def _outline(self, image_to_phantom: np.ndarray) -> np.ndarray:
        """(4, 2, 3) edges of the image at ``image_to_phantom`` (image mm), phantom mm."""
        probe = self.acquisition.setup.probe  # type: ignore[union-attr]
        return image_outline(image_to_phantom @ probe.scale_matrix(probe.nominal_spacing_mm), probe.width_px,
                             probe.height_px)

