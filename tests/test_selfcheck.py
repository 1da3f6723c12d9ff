"""The self-check: a twin sweep from two wrist angles, its views against each other, bad input."""

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from probecal.core.acquisition.plan import AS_PLANNED, DEFAULT_PASSES, SELF_CHECK_VIEWS, ProbeView
from probecal.core.acquisition.simulate import simulate_volume
from probecal.core.calibration.result import load_calibration
from probecal.core.geometry.transforms import make_transform
from probecal.core.io.session import RECORDS, Session, load_session
from probecal.core.volume.pointcloud import read_ply
from probecal.core.volume.saved import load_self_check
from probecal.core.volume.selfcheck import frames_by_view, self_check
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error, assert_refused

FRAMES = 50
"""Frames per pass: 30 mm passes, frames 0.6 mm apart, as close as a self-check needs them."""


@pytest.fixture(scope="module")
def two_views(tmp_path_factory):
    """The test object's steps swept in two short passes, from as planned and turned 180 deg."""
    return simulate_volume(tmp_path_factory.mktemp("selfcheck") / "s", seed=3, noise="realistic", n_frames=FRAMES,
                           views=SELF_CHECK_VIEWS, length_mm=30.0, passes=DEFAULT_PASSES[:2])


def test_every_frame_records_its_view_and_the_views_sweep_the_same_passes(two_views):
    views = [r.extra["view"] for r in two_views.records]
    sweeps = [r.extra["sweep"] for r in two_views.records]
    assert views == [0] * 2 * FRAMES + [1] * 2 * FRAMES and sweeps == [k // FRAMES for k in range(4 * FRAMES)]
    truth = two_views.truth()
    assert [f["index"] for f in truth["frames"]] == list(range(4 * FRAMES))
    first, turned = two_views.records[0].tool_to_base, two_views.records[2 * FRAMES].tool_to_base
    turn = turned[:3, :3] @ first[:3, :3].T
    assert np.degrees(np.arccos((np.trace(turn) - 1) / 2)) == pytest.approx(180.0, abs=0.5)


def test_the_check_finds_an_offset_induced_in_the_calibration(two_views):
    calibration = load_calibration(two_views.path / "truth.json")
    right = self_check(two_views, calibration)
    assert right.trusted, right.cause
    shifted = dataclasses.replace(calibration, image_to_tool_rigid=calibration.image_to_tool_rigid
                                  @ make_transform(np.eye(3), [1.5, 0.0, 0.0]))
    wrong = self_check(two_views, shifted)
    assert not wrong.trusted
    # Along the image x, the turned view's image runs the other way: its passes sit 3 mm from the first's.
    assert [o.offset_norm_mm for o in wrong.offsets] == pytest.approx([3.0, 3.0], abs=0.3)
    assert wrong.change.visible[0] and wrong.change.translation_mm[0] == pytest.approx(1.5, abs=0.3)
    assert "calibration error" in wrong.cause


@pytest.fixture(scope="module")
def checked(two_views, tmp_path_factory):
    """A self-check's folder as ``probecal selfcheck`` writes it, and what the command printed."""
    out = tmp_path_factory.mktemp("checked") / "check"
    result = run_cli("selfcheck", two_views.path, "--calibration", two_views.path / "truth.json", "--out", out)
    assert result.returncode == 0, result.stderr
    return out, result.stdout


def test_selfcheck_writes_its_report_and_each_view_in_its_colour(checked):
    out, printed = checked
    assert printed.startswith("Trust the volumes: the views agree within"), printed
    report = json.loads((out / "report.json").read_text())
    assert report["trusted"] and report["views"] == ["view_0.ply", "view_1.ply"]
    assert len(report["passes"]) == 2 and all(p["offset_norm_mm"] <= 0.3 for p in report["passes"])
    colours = []
    for name in report["views"]:
        points, colors = read_ply(out / name)
        assert len(points) > 1000 and colors is not None and len(np.unique(colors, axis=0)) == 1
        colours.append(tuple(colors[0]))
    assert colours[0] != colours[1]
    saved = load_self_check(out)
    assert saved.report == report
    assert [len(v) for v in saved.views] == [len(read_ply(out / name)[0]) for name in report["views"]]


@pytest.mark.parametrize(("change", "fragments"), [
    (lambda r: r.update(views=["../../calibration.json"]), ("views must be view_0.ply",)),
    (lambda r: r.update(views=[f"view_{k}.ply" for k in range(100)]), ("1 to 36",)),
    (lambda r: r["passes"][0].pop("rotation_deg"), ("passes[0].rotation_deg is missing",)),
    (lambda r: r["passes"][0].update(view=-1), ("passes[0].view must be a whole number of at least 0",)),
    (lambda r: r.update(passes=[]), ("passes is empty",)),
    (lambda r: r.update(trusted="yes"), ("trusted must be true or false",)),
    (lambda r: r.pop("max_offset_mm"), ("max_offset_mm is missing",)),
])
def test_a_saved_self_check_that_is_not_whole_is_refused(checked, tmp_path, change, fragments):
    out = Path(shutil.copytree(checked[0], tmp_path / "check"))
    report = json.loads((out / "report.json").read_text())
    change(report)
    (out / "report.json").write_text(json.dumps(report))
    assert_refused(lambda: load_self_check(out), out / "report.json", *fragments)


def test_a_saved_self_check_view_cut_short_is_refused(checked, tmp_path):
    out = Path(shutil.copytree(checked[0], tmp_path / "check"))
    data = (out / "view_1.ply").read_bytes()
    (out / "view_1.ply").write_bytes(data[:-7])
    assert_refused(lambda: load_self_check(out), out / "view_1.ply", "not the")


def test_selfcheck_refuses_frames_too_far_apart(tmp_path):
    sparse = tmp_path / "sparse"
    result = run_cli("simulate", "volume", sparse, "--views", "0,180", "--frames-per-pass", "2", "--noise", "none")
    assert result.returncode == 0, result.stderr
    result = run_cli("selfcheck", sparse, "--calibration", sparse / "truth.json")
    assert_one_line_error(result, str(sparse), "frames of pass 0 of view 0 lie", "at most 0.7 mm apart")


def test_selfcheck_refuses_a_session_of_one_view(tmp_path):
    session = simulate_volume(tmp_path / "one", seed=1, noise="none", n_frames=2, views=(AS_PLANNED,))
    result = run_cli("selfcheck", session.path, "--calibration", session.path / "truth.json")
    assert_one_line_error(result, str(session.path), "all of view 0", "two or more views")
    plain = simulate_volume(tmp_path / "plain", seed=1, noise="none", n_frames=2, passes=DEFAULT_PASSES[:2])
    result = run_cli("selfcheck", plain.path, "--calibration", plain.path / "truth.json")
    assert_one_line_error(result, str(plain.path), "state no view", "one wrist angle")
    assert not (plain.path / "selfcheck").exists()


def without_views(session: Session, out: Path) -> Session:
    """A copy of ``session`` whose records state neither view nor pass, as a recording made
    elsewhere."""
    shutil.copytree(session.path, out)
    records = [json.loads(line) for line in (out / RECORDS).read_text().splitlines()]
    (out / RECORDS).write_text("".join(json.dumps({k: v for k, v in r.items() if k not in ("view", "sweep")}) + "\n"
                                       for r in records))
    return load_session(out)


def test_a_recording_that_states_no_views_is_grouped_by_the_wrist_angle_held(two_views, tmp_path):
    plain = without_views(two_views, tmp_path / "plain")
    assert frames_by_view(plain) == [[list(range(2 * FRAMES))], [list(range(2 * FRAMES, 4 * FRAMES))]]
    calibration = load_calibration(two_views.path / "truth.json")
    assert self_check(plain, calibration).trusted
    shifted = dataclasses.replace(calibration, image_to_tool_rigid=calibration.image_to_tool_rigid
                                  @ make_transform(np.eye(3), [1.5, 0.0, 0.0]))
    wrong = self_check(plain, shifted)
    assert not wrong.trusted and wrong.offsets[0].offset_norm_mm == pytest.approx(3.0, abs=0.3)


def test_frames_farther_apart_than_the_check_holds_for_are_cautioned(tmp_path):
    sparse = simulate_volume(tmp_path / "sparse", seed=2, noise="none", n_frames=30, views=SELF_CHECK_VIEWS,
                             length_mm=30.0, passes=DEFAULT_PASSES[:1])
    result = run_cli("selfcheck", sparse.path, "--calibration", sparse.path / "truth.json")
    assert result.returncode == 0, result.stderr
    report = json.loads((sparse.path / "selfcheck" / "report.json").read_text())
    assert len(report["cautions"]) == 2 and " lie 1.0" in report["cautions"][0]
    assert result.stderr.count("caution: the frames of pass 0 of view") == 2, result.stderr


def test_selfcheck_refuses_an_unreadable_calibration(two_views, tmp_path):
    bad = tmp_path / "calibration.json"
    bad.write_text("{not json")
    result = run_cli("selfcheck", two_views.path, "--calibration", bad, "--out", tmp_path / "out")
    assert_one_line_error(result, str(bad))
    assert not (tmp_path / "out").exists()


def test_sessions_of_one_wrist_angle_each_are_checked_as_views(tmp_path):
    sessions = [simulate_volume(tmp_path / f"view{k}", seed=3, noise="realistic", n_frames=FRAMES,
                                views=(view,), length_mm=30.0, passes=DEFAULT_PASSES[:2])
                for k, view in enumerate(SELF_CHECK_VIEWS)]
    out = tmp_path / "check"
    result = run_cli("selfcheck", *(s.path for s in sessions), "--calibration", sessions[0].path / "truth.json",
                     "--out", out)
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["trusted"] and report["sessions"] == [str(s.path) for s in sessions]
    assert [(p["view"], p["pass_index"]) for p in report["passes"]] == [(1, 0), (1, 1)]
    one_pass = simulate_volume(tmp_path / "one", seed=3, noise="none", n_frames=2, views=(ProbeView(90.0),),
                               passes=DEFAULT_PASSES[:1])
    result = run_cli("selfcheck", sessions[0].path, one_pass.path, "--calibration", sessions[0].path / "truth.json",
                     "--out", tmp_path / "mismatched")
    assert_one_line_error(result, str(one_pass.path), "have 2, 1 passes")
    assert not (tmp_path / "mismatched").exists()


def test_a_sweep_given_twice_or_copied_is_refused(tmp_path):
    """One sweep agrees with itself whatever the calibration: given twice (or as a copy of its
    folder), it would say to trust the volumes."""
    session = simulate_volume(tmp_path / "view", seed=3, noise="none", n_frames=4, views=SELF_CHECK_VIEWS[:1],
                              passes=DEFAULT_PASSES[:1])
    shutil.copytree(session.path, tmp_path / "copy")
    for again in (session.path, tmp_path / "view" / ".." / "view", tmp_path / "copy"):
        result = run_cli("selfcheck", session.path, again, "--calibration", session.path / "truth.json",
                         "--out", tmp_path / "out")
        assert_one_line_error(result, str(again), "a self-check compares different sweeps of one object")
        assert not (tmp_path / "out").exists()


def test_tilted_passes_show_a_shift_along_the_beam_that_the_turn_does_not(tmp_path):
    tilted = simulate_volume(tmp_path / "tilted", seed=4, noise="realistic", n_frames=FRAMES, views=SELF_CHECK_VIEWS,
                             length_mm=30.0, passes=DEFAULT_PASSES[3:5])
    calibration = load_calibration(tilted.path / "truth.json")
    right = self_check(tilted, calibration)
    assert right.trusted, right.cause
    assert [(o.view, o.pass_index, o.against_view, o.against_pass) for o in right.offsets] == [
        (1, 0, 0, 0), (1, 1, 0, 1), (0, 1, 0, 0), (1, 1, 1, 0)]
    shifted = dataclasses.replace(calibration, image_to_tool_rigid=calibration.image_to_tool_rigid
                                  @ make_transform(np.eye(3), [0.0, 1.0, 0.0]))
    wrong = self_check(tilted, shifted)
    # The turned view sees the shift as the first does; the passes tilted 40 deg apart see it 0.68 mm apart.
    assert [o.offset_norm_mm for o in wrong.offsets[:2]] == pytest.approx([0.0, 0.0], abs=0.1)
    assert [o.offset_norm_mm for o in wrong.offsets[2:]] == pytest.approx([0.68, 0.68], abs=0.12)
    assert not wrong.trusted and wrong.change.visible[1]
    assert wrong.change.translation_mm[1] == pytest.approx(1.0, abs=0.2)
