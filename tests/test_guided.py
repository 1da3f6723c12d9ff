"""Guided acquisition of a probe probecal does not move: the targets and their coverage
(core.acquisition.guidance), the hand (core.acquisition.hand), and the acquisition itself
(core.calibration.guided) on the freehand twin, run faster than real time."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from probecal.core.acquisition.freehand import FreehandTwin, Person, ScannerFrame, TrackerReport
from probecal.core.acquisition.guidance import (
    GUIDE_RANGES,
    MEASURES,
    TARGETS,
    Coverage,
    apart,
    frames_probe,
    guide_setup,
    guide_targets,
    measures,
    offsets_of,
    reach_of,
)
from probecal.core.acquisition.hand import Hand, HandParams, minimum_jerk
from probecal.core.acquisition.imagesource import SourceFrame
from probecal.core.acquisition.pairing import FramePairer
from probecal.core.acquisition.plan import crossings_in_view, perturbed, pivot_mm
from probecal.core.acquisition.tracker import PoseFeed, probe_to_reference
from probecal.core.calibration.guided import GUIDED_PHASE, GuidedAcquisition, GuideSettings, first_targets
from probecal.core.calibration.latency import TEMPORAL_PHASE
from probecal.core.calibration.register import refine_with_depth_scale, register_frame
from probecal.core.calibration.segment import Segmenter
from probecal.core.errors import InputError
from probecal.core.geometry.probe import image_mm_from_pixels
from probecal.core.io.manifest import CONTINUOUS, Manifest
from probecal.core.io.session import SessionWriter, load_session
from tests.support.cli import run_cli


@pytest.fixture(scope="module")
def twin() -> FreehandTwin:
    return FreehandTwin(seed=3)


def test_a_poses_offsets_are_read_back_as_the_plan_made_them(twin):
    setup = twin.setup
    offsets = np.array([0.0, 4.0, -1.5, 12.0, -20.0, 7.0])
    assert np.allclose(offsets_of(setup, perturbed(setup.image_to_phantom, pivot_mm(setup), offsets)), offsets)


def test_a_frame_is_read_at_its_tilt_though_the_nominal_spacing_is_off_in_depth(twin):
    """The twin's sound speed puts its true spacing a few per cent from the nominal one in depth; a
    rigid fit reads that as a tilt about the image's x, the fit with the depth scale does not."""
    truth = twin.scanner.twin
    nominal = truth.probe.nominal_spacing_mm
    ratio = truth.pixel_spacing_mm[1] / nominal[1]
    assert abs(ratio - 1) > 0.02
    setup = twin.setup
    for offsets in ([0.0, 0, 0, 1.0, 0, 0], [0.0, 3, -2, -6.0, 5, 2]):
        markers = truth.markers_px(twin.true_pose(np.array(offsets)))
        rigid = register_frame(setup.phantom, markers, nominal)
        wires = rigid.wire_indices
        scaled, scale = refine_with_depth_scale(setup.phantom, rigid.image_to_phantom,
                                                image_mm_from_pixels(markers, nominal)[wires], wires)
        rigid_off, scaled_off = (abs(offsets_of(setup, pose)[3] - offsets[3])
                                 for pose in (rigid.image_to_phantom, scaled))
        # the rest is the phantom as built, its wires up to 0.3 mm from the definition's
        assert rigid_off > 4.0 and scaled_off < 1.5, (rigid_off, scaled_off)
        assert scale == pytest.approx(ratio, abs=0.004)


def test_targets_spread_over_the_ranges_and_keep_every_wire_in_view(twin):
    setup = twin.setup
    targets = guide_targets(setup, 16, seed=1)
    assert targets.shape == (16, 6) and np.all(targets[:, 0] == 0)  # none across the wires
    for offsets in targets:
        assert crossings_in_view(setup, perturbed(setup.image_to_phantom, pivot_mm(setup), offsets))
    bounds = measures(np.array([*GUIDE_RANGES.translation_mm, *GUIDE_RANGES.rotation_deg]))
    spread = np.ptp(measures(targets), axis=0) / (2 * bounds)
    # a Latin hypercube spans every measure; turning in the image plane loses wires from view soonest
    assert np.all(spread > 0.3), dict(zip(MEASURES, spread))


def test_frames_too_small_for_the_phantom_are_refused_naming_their_size(twin):
    """64 x 48 px at 0.1 mm shows no N layer whole: an input error naming the frames' size, not a
    failure of the planner's."""
    phantom = twin.setup.phantom
    assert len(first_targets(guide_setup(phantom, frames_probe((64, 48), (1.0, 1.0))), GuideSettings())) == TARGETS
    with pytest.raises(InputError) as caught:
        first_targets(guide_setup(phantom, frames_probe((64, 48), (0.1, 0.1))), GuideSettings())
    assert str(caught.value) == ("frames of 64 x 48 px (6.4 x 4.8 mm) are too small to guide over the phantom: only "
                                 "0 of 16 targets keep every wire in view")


def test_coverage_counts_reaches_gives_up_and_starts_a_new_round():
    targets = np.array([[0, 0, 0, 10.0, 0, 0], [0, 0, 0, -10.0, 0, 0]])
    coverage = Coverage(targets)
    reach = reach_of(GUIDE_RANGES)
    near = targets[0] + np.array([0, 0, 0, 0.9 * reach[0], 0, 0])
    assert apart(targets[0], near, GUIDE_RANGES) == pytest.approx(0.9)
    assert coverage.next_target(np.zeros(6)) in (0, 1)
    assert coverage.add(near) == [0] and coverage.add(near) == []
    assert coverage.counts.sum() == 2 * len(MEASURES)
    assert coverage.next_target(None) == 1 and coverage.fraction == 0.5
    coverage.give_up(1)
    assert coverage.next_target(None) is None
    coverage.extend(targets + 1.0)
    assert coverage.round == 1 and coverage.fraction == 0.0 and coverage.next_target(targets[1]) == 3


def test_the_hand_reaches_for_its_target_at_a_persons_pace_and_holds():
    hand = Hand(np.zeros(6), HandParams(tremor_mm=0, tremor_deg=0, sway_mm=0, sway_deg=0, aim_mm=0, aim_deg=0))
    target = np.array([0, 10.0, 0, 20.0, 0, 0])
    times = np.arange(0, 4, 0.02)
    path = np.array([hand.at(t, target) for t in times])
    assert np.allclose(path[times < 0.4], 0)  # it reacts first
    assert np.allclose(path[-1], target)  # and holds there once reached
    speed = np.linalg.norm(np.diff(path[:, :3], axis=0), axis=1) / 0.02
    assert 10 < speed.max() < 60  # mm/s: a person's reach, not a robot's
    assert minimum_jerk(0.5) == pytest.approx(0.5) and minimum_jerk(2.0) == 1.0


def test_guided_acquisition_on_the_freehand_twin(twin, tmp_path):
    """Faster than real time: the hand strokes until the latency is measured, then follows the
    targets; only frames held still are kept, and what is recorded is a session calibrate takes."""
    probe, phantom = twin.setup.probe, twin.setup.phantom
    manifest = Manifest(kind="calibration", source={"kind": "tracked"}, image_size=(probe.width_px, probe.height_px),
                        pixel_spacing_mm=probe.nominal_spacing_mm, motion=CONTINUOUS)
    writer = SessionWriter(tmp_path / "guided", manifest, phantom, probe)
    feed = PoseFeed()
    settings = GuideSettings(first_bound=15, bound_every=10_000, pose_wait_s=0.0)
    acquisition = GuidedAcquisition(writer, replace(twin.setup, phantom_to_base=np.eye(4)),
                                    Segmenter.create(phantom, probe.nominal_spacing_mm), FramePairer(feed), settings)

    def guide(offsets):
        return None if acquisition.phase != GUIDED_PHASE else acquisition.coverage.targets[acquisition.target(offsets)]

    person = Person(guide)
    for event in twin.events(person, frame_hz=10.0):
        if isinstance(event, TrackerReport):
            feed.push(probe_to_reference(event.probe_to_tracker, event.reference_to_tracker), event.t)
            if acquisition.kept >= 15 or event.t > 60:
                break
            continue
        assert isinstance(event, ScannerFrame)
        step = acquisition.take(SourceFrame(event.image, event.stamp, 0))
        if step.offsets is not None:
            person.seen(step.offsets, event.offsets)
    writer.close()
    assert acquisition.latency is not None
    assert acquisition.latency.image_latency_s == pytest.approx(twin.scanner.twin.image_latency_s, abs=0.008)
    assert acquisition.kept >= 15 and acquisition.coverage.reached.sum() >= 2
    session = load_session(tmp_path / "guided")
    phases = [r.extra["phase"] for r in session.records]
    assert phases[0] == TEMPORAL_PHASE and phases[-1] == GUIDED_PHASE and session.has_pose_stream
    bound = acquisition.measure_bound()
    assert bound is not None and np.isfinite(bound), acquisition.bound_problem
    # the session is a robot's continuous sweep to every command that takes one
    path = tmp_path / "guided"
    for args in (["calibrate", path], ["validate", "--calibration", path / "calibration.json", path],
                 ["phantom", "check", path], ["export-plus", path, tmp_path / "guided.igs.mha"],
                 ["reconstruct", "--calibration", path / "calibration.json", "--out", tmp_path / "volume", path]):
        done = run_cli(*args)
        assert done.returncode == 0, (args[0], done.stderr[-2000:])
    assert (tmp_path / "guided.igs.mha").is_file() and (tmp_path / "volume" / "report.json").is_file()
