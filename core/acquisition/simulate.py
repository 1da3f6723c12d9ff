"""Sessions recorded on the digital twin: a calibration sweep over the phantom or straight volume
sweeps over the test object, each with its ground truth in ``truth.json`` (SPEC §4)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from probecal.core.acquisition.plan import SweepPlan, calibration_plan, volume_plan
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.session import Session, SessionWriter, load_session
from probecal.core.robot.simulated import SimulatedRobot
from probecal.core.robot.ur3 import Unreachable
from probecal.core.twin.levels import Level, level
from probecal.core.twin.scanner import VOLUME_STANDOFF_MM, json_from_markers, twin_scanner
from probecal.core.twin.testobject import TEST_OBJECT_FILE
from probecal.core.twin.twin import Twin

Progress = Callable[[int, int], None]


def session_manifest(kind: str, twin: Twin, seed: int, noise: str | Level, plan: SweepPlan) -> dict:
    """The manifest of a session the twin's scanner images."""
    return {
        "kind": kind,
        "source": {"simulator": "probecal digital twin", "seed": seed, "noise": level(noise).name},
        "image_size": [twin.probe.width_px, twin.probe.height_px],
        "pixel_spacing_mm": list(twin.probe.nominal_spacing_mm),
        "phantom_to_base": None,
        "plan": plan.summary(),
    }


def simulate_calibration(
    out_dir: str | Path,
    n_poses: int = 60,
    seed: int = 0,
    noise: str | Level = "realistic",
    phantom: Phantom | None = None,
    progress: Progress | None = None,
) -> Session:
    """Run the calibration acquisition on the twin and record it as a session with truth.json.

    The session records the flange pose the robot reports; the image shows the phantom from
    where the flange actually is (``Twin.actual_tool_to_base``), and is stamped by the scanner's
    late clock. At ``harsh`` noise some frames are dropped by the "scanner" (not recorded) and
    some poses are shifted so that a wire leaves the field of view.
    """
    scanner = twin_scanner(seed, noise, phantom)
    twin, lvl = scanner.twin, scanner.level
    plan = calibration_plan(twin.nominal, n_poses, seed=seed)
    rng = np.random.default_rng(seed + 1)
    robot = SimulatedRobot(seed=seed, time_scale=0.0)
    robot.connect()
    truth_frames = []
    dropped = 0
    harsh = lvl.name == "harsh"
    manifest = session_manifest("calibration", twin, seed, lvl, SweepPlan.from_plans([plan]))
    with SessionWriter(out_dir, manifest, twin.phantom, twin.probe) as writer:
        for k, target in enumerate(plan.poses):
            if progress:
                progress(k + 1, len(plan.poses))
            if harsh and rng.random() < 0.05:
                target = target.copy()  # slide sideways so that an outer wire leaves the view
                target[:3, 3] += target[:3, 0] * rng.choice([-1.0, 1.0]) * 8.0
            try:
                robot.move_linear(target)
            except Unreachable:
                continue
            reported = robot.tool_to_base()
            actual = twin.actual_tool_to_base(reported, robot.joints())
            if harsh and rng.random() < 0.03:
                dropped += 1
                continue
            image, markers = scanner.calibration_frame(actual, rng)
            t = robot.elapsed_motion_s
            index = writer.append(image, reported, timestamp=t + scanner.image_delay_s(rng), pose_timestamp=t)
            truth_frames.append({"index": index, "markers_px": json_from_markers(markers),
                                 "tool_to_base": actual.tolist()})
        writer.write_truth({**twin.truth(), "frames": truth_frames})
        writer.update_manifest(dropped_frames=dropped, robot_time_s=round(robot.elapsed_motion_s, 1))
    return load_session(out_dir)


def simulate_volume(out_dir: str | Path, seed: int = 0, noise: str | Level = "realistic", n_frames: int = 120,
                    progress: Progress | None = None) -> Session:
    """Sweep the test object in straight passes and record a session with truth.json and the
    object's CAD mesh (``test_object.stl``) beside it; poses and stamps as in
    :func:`simulate_calibration`."""
    scanner = twin_scanner(seed, noise)
    twin, lvl = scanner.twin, scanner.level
    rng = np.random.default_rng(seed + 1)
    passes = volume_plan(scanner.region_to_base(), twin.nominal.image_to_tool_rigid, twin.probe, VOLUME_STANDOFF_MM,
                         n_frames=n_frames)
    total = sum(len(p.poses) for p in passes)
    manifest = session_manifest("volume", twin, seed, lvl, SweepPlan.from_plans(passes))
    manifest["cad_mesh"] = TEST_OBJECT_FILE.name
    robot = SimulatedRobot(seed=seed, time_scale=0.0)
    robot.connect()
    done = 0
    with SessionWriter(out_dir, manifest, probe=twin.probe) as writer:
        (Path(out_dir) / TEST_OBJECT_FILE.name).write_bytes(TEST_OBJECT_FILE.read_bytes())
        for pass_index, plan in enumerate(passes):
            for target in plan.poses:
                done += 1
                robot.move_linear(target)
                reported = robot.tool_to_base()
                image = scanner.volume_frame(twin.actual_tool_to_base(reported, robot.joints()), rng)
                t = robot.elapsed_motion_s
                writer.append(image, reported, timestamp=t + scanner.image_delay_s(rng), pose_timestamp=t,
                              sweep=pass_index)
                if progress:
                    progress(done, total)
        writer.write_truth(scanner.volume_truth())
        writer.update_manifest(robot_time_s=round(robot.elapsed_motion_s, 1))
    return load_session(out_dir)
