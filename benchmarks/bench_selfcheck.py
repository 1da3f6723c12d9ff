"""The self-check (core.volume.selfcheck) on the twin at ``bench``: the test object swept with the
self-check's passes (``SELF_CHECK_PASSES``) from two wrist angles (``SELF_CHECK_VIEWS``: as
planned, and turned 180 deg about the beam).

Each figure is given for the two kinds of comparison the check makes: a pass against the same
pass from the other wrist angle (the views), and the tilted passes within a view.

a) The true calibration and the true arm (every frame reconstructed from where the flange really
   was, ``truth.json``'s ``frames``): the views must agree within 0.1 mm (offset).
b) The true calibration turned 1 deg about each image axis in turn, and shifted 1 mm along each,
   with the true arm: each must be flagged (the offsets printed, and the calibration change the
   check fits against the one induced).
c) The true calibration with the poses the arm reports (its kinematic error present, not
   identified): the offset the check reports against the arm's true effect, the offset between the
   views' noise-free surfaces under the arm error alone (the twin's surface at every frame's true
   pose, placed by its reported pose; each view fitted rigidly to the truth with its known
   correspondences), along the moves the compared surface pins: must match within 0.1 mm.

``--estimated``: instead, the calibration ``probecal calibrate`` estimates from the twin's default
sweep (60 poses, its arm fitted), checked on the reported poses: how often it is trusted, and each
kind's worst offset.

First, how far each way of placing a scan line's surface edge (``core.volume.surface.EDGES``)
moves with the incidence: a flat interface rendered by the twin at ``bench``, turned in the image
plane, its echo weaker the more it turns; the median edge against the interface (mm, along the
beam).

``--edge``: where each scan line's surface edge is placed (``core.volume.surface.EDGES``; the
check's own by default), to compare them on the same sweeps.

Run: .venv/bin/python benchmarks/bench_selfcheck.py [--seeds 10] [--frames-per-pass 90] [--views 0,180]
[--estimated] [--edge steepest]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from probecal.app.cli import wrist_angles
from probecal.core.acquisition.plan import SELF_CHECK_PASS_MM, SELF_CHECK_PASSES, SELF_CHECK_VIEWS, ProbeView
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.calibration.result import Calibration, load_calibration
from probecal.core.calibration.segment import segment_session
from probecal.core.calibration.solve import calibrate_session
from probecal.core.geometry.transforms import invert_transform, make_transform, transform_points
from probecal.core.io.session import Session
from probecal.core.twin.scanner import echo_onset_offset_px, twin_scanner
from probecal.core.volume.selfcheck import (
    COMPONENTS,
    CheckSettings,
    PassOffset,
    SelfCheck,
    frames_by_view,
    self_check,
)
from probecal.core.volume.surface import EDGES, SurfaceParams, extract_surface

AGREE_MM = 0.1
MATCH_MM = 0.1
CHANGES = {name: make_transform(Rotation.from_euler(axis, 1.0, degrees=True), np.zeros(3))
           for name, axis in (("turned 1 deg about x", "x"), ("turned 1 deg about y", "y"),
                              ("turned 1 deg about z", "z"))}
CHANGES |= {f"shifted 1 mm along {axis}": make_transform(np.eye(3), 1.0 * np.eye(3)[k])
            for k, axis in enumerate("xyz")}
COMPONENT_OF = dict(zip(CHANGES, (3, 4, 5, 0, 1, 2)))
"""Each change's component in :data:`COMPONENTS` order."""


def with_true_poses(session: Session) -> Session:
    """The session with every frame's pose where the flange really was (truth.json's frames)."""
    actual = {f["index"]: np.array(f["tool_to_base"]) for f in session.truth()["frames"]}
    return dataclasses.replace(session, records=[dataclasses.replace(r, tool_to_base=actual[r.index])
                                                 for r in session.records])


def changed(calibration: Calibration, change: np.ndarray) -> Calibration:
    """The calibration with its image moved by ``change`` in its own frame."""
    return dataclasses.replace(calibration, image_to_tool_rigid=calibration.image_to_tool_rigid @ change)


def rigid_fit(seen: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The rigid move (4x4) that best lays ``seen`` on the corresponding ``true`` points."""
    seen_c, true_c = seen.mean(axis=0), true.mean(axis=0)
    rotation, _ = Rotation.align_vectors(true - true_c, seen - seen_c)
    return make_transform(rotation, true_c - rotation.apply(seen_c))


def arm_effect(session: Session, seed: int, calibration: Calibration) -> dict[tuple[int, int], np.ndarray]:
    """Per pass (view, pass), the move (4x4, base mm) that lays its noise-free surface, placed by
    the reported poses, on where the flange really put it: the arm error's true effect on it."""
    scanner = twin_scanner(seed, "bench")
    actual = {f["index"]: np.array(f["tool_to_base"]) for f in session.truth()["frames"]}
    to_truth = {}
    for k, passes in enumerate(frames_by_view(session)):
        for p, frames in enumerate(passes):
            seen, true = [], []
            for i in frames:
                record = session.records[i]
                in_image = scanner.surface_image_mm(actual[record.index])
                seen.append(transform_points(record.tool_to_base @ calibration.image_to_tool_rigid, in_image))
                true.append(transform_points(actual[record.index] @ calibration.image_to_tool_rigid, in_image))
            to_truth[k, p] = rigid_fit(np.concatenate(seen), np.concatenate(true))
    return to_truth


def true_offset(offset: PassOffset, to_truth: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
    """Where the arm error alone puts the pass's centroid from where the pass it is compared with
    puts it (base frame, mm), along the moves that pass's surface pins (no surface can show the
    others, such as a slide along an extruded object)."""
    against = to_truth[offset.against_view, offset.against_pass]
    return offset.pinned_offset_mm(invert_transform(against) @ to_truth[offset.view, offset.pass_index])


KINDS = ("views (a pass against the same pass turned)", "tilted passes within a view")


def kind_of(offset: PassOffset) -> str:
    """Which of :data:`KINDS` a comparison is."""
    return KINDS[offset.view == offset.against_view]


def compared(offset: PassOffset) -> str:
    """Which pass of which view the offset is of, and against which."""
    return f"view {offset.view} pass {offset.pass_index} against view {offset.against_view} pass {offset.against_pass}"


def offsets_text(check: SelfCheck) -> str:
    """Every comparison's offset (mm) and turn (deg), and the worst one's details."""
    worst = max(check.offsets, key=lambda o: o.offset_norm_mm)
    every = " ".join(f"{o.offset_norm_mm:.3f}/{o.rotation_deg:.2f}" for o in check.offsets)
    return (f"passes (mm/deg) {every}; worst {compared(worst)} "
            f"{np.round(worst.offset_mm, 3).tolist()}, median {worst.median_before_mm:.3f} -> "
            f"{worst.median_after_mm:.3f} mm, {len(worst.loose)} loose")


def verdict(ok: bool) -> str:
    return "ok" if ok else "OVER"


INCIDENCES_DEG = (0, 10, 20, 30, 40, 50)


def edge_drift(seed: int = 0) -> None:
    """Print, per edge and incidence, the median edge depth against the interface (mm)."""
    scanner = twin_scanner(seed, "bench")
    probe, render = scanner.twin.probe, scanner.renderer.render
    sx, sy = probe.true_spacing_mm
    columns = np.arange(probe.width_px)
    centred = columns - columns.mean()
    onset = echo_onset_offset_px(probe)
    print("the edge against the interface by incidence (median mm along the beam, + deeper; twin bench):")
    for edge in EDGES:
        cells = []
        for incidence in INCIDENCES_DEG:
            errors = []
            for k in range(6):
                rows = probe.height_px / 2 + np.tan(np.radians(incidence)) * sx / sy * centred + k / 6
                rows[(rows < 40) | (rows > probe.height_px - 40)] = np.nan
                image = render(np.empty((0, 2)), surface_rows=rows + onset, rng=np.random.default_rng(k))
                u, v = extract_surface(image, SurfaceParams(edge=edge))
                truth = rows[u.astype(int)]
                seen = np.isfinite(truth)
                errors.append((v[seen] - truth[seen]) * sy)
            error = np.concatenate(errors)
            cells.append(f"{incidence:2d} deg {np.median(error):+.3f}" if len(error) else f"{incidence:2d} deg none")
        print(f"  {edge:9s} " + "  ".join(cells))


def estimated(seeds: range, frames_per_pass: int, views: tuple[ProbeView, ...], settings: CheckSettings) -> None:
    """The self-check of the calibration probecal estimates, seed by seed, and how often it is
    trusted."""
    trusted = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            calibration_sweep = simulate_calibration(Path(tmp) / "cal", seed=seed, noise="bench")
            calibration = calibrate_session(calibration_sweep, segment_session(calibration_sweep)).calibration
            session = simulate_volume(Path(tmp) / "vol", seed=seed, noise="bench", n_frames=frames_per_pass,
                                      views=views, length_mm=SELF_CHECK_PASS_MM, passes=SELF_CHECK_PASSES)
            check = self_check(session, calibration, settings)
        trusted.append(check.trusted)
        worst = {kind: max(o.offset_norm_mm for o in check.offsets if kind_of(o) == kind) for kind in KINDS}
        fitted = np.concatenate([check.change.translation_mm, check.change.rotation_deg])
        print(f"seed {seed}: {'trusted' if check.trusted else 'NOT trusted'}; worst "
              f"{', '.join(f'{kind} {v:.3f} mm' for kind, v in worst.items())}; fitted change "
              f"{np.round(fitted, 2).tolist()} ({', '.join(COMPONENTS)})", flush=True)
    print(f"estimated calibration trusted on {sum(trusted)} of {len(trusted)} seeds")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--frames-per-pass", type=int, default=90)
    parser.add_argument("--estimated", action="store_true", help="check the estimated calibration instead")
    parser.add_argument("--views", type=wrist_angles, default=None, metavar="TURN[/TILT],...",
                        help="the wrist angles (deg), as probecal simulate volume --views takes them (default: "
                             "the self-check's own)")
    parser.add_argument("--edge", choices=EDGES, default=CheckSettings().surface.edge,
                        help="where a scan line's surface edge is placed (default: the check's own)")
    args = parser.parse_args()
    views = SELF_CHECK_VIEWS if args.views is None else tuple(ProbeView(turn, tilt) for turn, tilt in args.views)
    settings = CheckSettings(surface=dataclasses.replace(CheckSettings().surface, edge=args.edge))
    edge_drift()
    if args.estimated:
        estimated(range(args.first_seed, args.first_seed + args.seeds), args.frames_per_pass, views, settings)
        return
    rows_a: dict[str, list[float]] = {kind: [] for kind in KINDS}  # the worst offset per seed
    rows_c: dict[str, list[tuple[float, float, float]]] = {kind: [] for kind in KINDS}  # check, truth, apart
    rows_b: dict[str, list[tuple[bool, float, float]]] = {name: [] for name in CHANGES}  # flagged, offset, seen
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            session = simulate_volume(Path(tmp) / f"seed{seed}", seed=seed, noise="bench",
                                      n_frames=args.frames_per_pass, views=views,
                                      length_mm=SELF_CHECK_PASS_MM, passes=SELF_CHECK_PASSES)
            calibration = load_calibration(session.path / "truth.json")
            true_arm = with_true_poses(session)
            check = self_check(true_arm, calibration, settings)
            for kind in KINDS:
                rows_a[kind].append(max(o.offset_norm_mm for o in check.offsets if kind_of(o) == kind))
            worst = max(o.offset_norm_mm for o in check.offsets)
            print(f"seed {seed} a) true calibration, true arm: {offsets_text(check)} -> "
                  f"{verdict(worst <= AGREE_MM)} (trusted: {check.trusted})")
            for name, change in CHANGES.items():
                check = self_check(true_arm, changed(calibration, change), settings)
                fitted = np.concatenate([check.change.translation_mm, check.change.rotation_deg])
                rows_b[name].append((not check.trusted, max(o.offset_norm_mm for o in check.offsets),
                                     float(check.change.sensitivity[COMPONENT_OF[name]])))
                seen = ", ".join(c for c, v in zip(COMPONENTS, check.change.visible) if v)
                print(f"  b) {name}: {offsets_text(check)} -> {'flagged' if not check.trusted else 'NOT FLAGGED'}; "
                      f"fitted change {np.round(fitted, 2).tolist()} (seen: {seen}; "
                      f"unexplained {check.change.unexplained_mm:.3f} of {check.change.offsets_mm:.3f} mm)")
            check = self_check(session, calibration, settings)
            to_truth = arm_effect(session, seed, calibration)
            for offset in check.offsets:
                truth = true_offset(offset, to_truth)
                miss = float(np.linalg.norm(offset.offset_mm - truth))
                rows_c[kind_of(offset)].append((offset.offset_norm_mm, float(np.linalg.norm(truth)), miss))
                print(f"  c) reported poses, {compared(offset)}: check {offset.offset_norm_mm:.3f} mm "
                      f"{np.round(offset.offset_mm, 3).tolist()}, arm's true effect {np.linalg.norm(truth):.3f} mm "
                      f"{np.round(truth, 3).tolist()}, apart {miss:.3f} mm -> {verdict(miss <= MATCH_MM)}")
            print(f"     {check.cause}")
            print(f"  ({time.perf_counter() - started:.0f} s so far)", flush=True)
    print()
    for kind, rows in rows_a.items():
        print(f"a) true calibration and arm, {kind}: offset (mm; target <= {AGREE_MM}) mean {np.mean(rows):.3f}, "
              f"worst {np.max(rows):.3f} -> {verdict(max(rows) <= AGREE_MM)}")
    print("b) calibration changed, flagged (target: every seed); the worst pass's offset, smallest over the seeds; "
          "how far apart the change moves the views per unit, as the check reckons it (mean):")
    for name, rows in rows_b.items():
        flagged = [f for f, _, _ in rows]
        print(f"   {name:24s} {sum(flagged)}/{len(flagged)} -> {verdict(all(flagged))}; offset >= "
              f"{min(o for _, o, _ in rows):.3f} mm; {np.mean([v for _, _, v in rows]):.2f} mm per unit")
    for kind, c_rows in rows_c.items():
        misses = [m for _, _, m in c_rows]
        print(f"c) reported poses, {kind}: check's offset mean {np.mean([c for c, _, _ in c_rows]):.3f} mm, arm's "
              f"true effect mean {np.mean([t for _, t, _ in c_rows]):.3f} mm, apart mean {np.mean(misses):.3f}, "
              f"worst {np.max(misses):.3f} (target <= {MATCH_MM}) -> {verdict(max(misses) <= MATCH_MM)}")
    print(f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
