"""How real is the twin? Wire-dot and background statistics measured the same way on the real
PLUS recordings and on twin sessions, side by side (issue 15: the ``bench`` noise level must sit
inside the real spread).

Every dot of every frame where probecal's own segmenter finds the pattern (no PLUS hints but the
approximate spacing) is measured in the raw 8-bit frame around its marker:

- contrast: the peak gray level (3x3 mean) minus the local background (20th percentile of a
  5 x 3 mm window);
- lateral and axial FWHM (mm): the extent of the connected pixels above half the contrast that
  hold the peak; their area (mm^2) and elongation (lateral / axial);
- centroid below peak (mm): how far the segmented marker sits below the echo's peak row (the
  echo rings on below the wire; see ``core.calibration.dots.echo_peak_rows``);
- brightness spread: per frame, the coefficient of variation of its dots' contrasts;
- background: the mean gray level and its standard deviation around the pattern, dots left out
  (real frames are often black there, so a std / mean speckle contrast would mean nothing);
- wire fit residual: per frame, the RMS distance (mm) of the markers from their wires under the
  best affine map of the phantom's wire plane (the segmenter's own check): how far the dots stray
  from where the wires are, with no tracker involved; per recording, those offsets split into
  the part each wire keeps over the recording (a wire built off its definition, or a bias of its
  dots) and the part that changes from frame to frame (one value per recording).

Then the calibration's own statistics (issue 31), one value per recording, each recording
calibrated the robot's way (own segmenter, nominal spacing; the phantom pose as PLUS registered it
on a real recording, solved on the twin's robot sweep). The twin's columns per level: its robot
sweep, and, like for like with the real recordings, tracked freehand recordings of the fCal 2.0
phantom (``core.acquisition.simulate.simulate_freehand``: a hand's smooth path, an optical
tracker's noise and slow drift, the phantom pose known; ``--hand-seeds`` benches, each validated on a second path
over the same bench). ``--diagonal-tolerance``, ``--diagonal-shift``, ``--diagonal-turn`` and
``--layer-tolerance`` build every twin phantom's diagonal wires' ends, its diagonals as a whole or
turned about their middles, or its layers off instead of as each level does:

- objectives apart (mm): the farthest image corner between the all-wire and the middle-wire
  calibration;
- halves apart (mm): the farthest image corner between the default calibrations of the first
  and the second half of the recording;
- validation PRE3D all-wire / middle-wire: the ratio of the two objectives' PRE3D on the bench's
  validation recording (probecal's own markers; on the freehand twin, a second path over the
  same bench), for the recordings that have one, and middle-wire's PRE3D itself (mm): how far the tracked
  poses and the calibration together put the wires' points off, which bounds any tracker drift;
- wires vs tracker drift (mm): each frame's own image pose on the wires against its tracked pose
  through the all-wire calibration, out of plane at the image corners, averaged over
  nine frames in a row (the frames' jitter averages out), and its standard deviation
  along the recording (the largest corner's): how far the tracked pose wanders against the wires
  (``bench_objectives.single_frames``; the twin's freehand recordings get it from the level's
  ``tracker_drift``, ``--tracker-drift`` sets another);
- middle dot along diagonal (mm): per N layer, how the middle dot's lateral offset from where the
  all-wire calibration puts its crossing (less its outer dots' mean offset) changes from one end
  of the diagonal wire to the other (the slope against the crossing's fraction along it; the
  median over the layers): a diagonal built off its definition;
- wire offset, next frame's (corr): how much of the dots' changing offsets from their wires (as
  in the wire fit residual above) consecutive frames share, their correlation: a rough wire's
  echo changes only as its crossing moves along it, which a hand does slowly (the robot's sweep
  steps from pose to pose, so its column shows little);
- middle-wire layers apart (mm): per layer, the mean offset along the wires of each middle dot's
  point, as the all-wire calibration and the tracked poses put it, from its middle-wire point, as
  the dot ratio puts it (PRE3D's two points); how far apart the layers' offsets lie: a diagonal
  that sits (or echoes) off across itself as a whole;
- layer offsets middle-wire takes up (mm): the RMS over the layers of those offsets under the
  all-wire calibration less that under the middle-wire one: middle-wire fits PRE3D's points and
  tilts the image to put each layer's on its wires where the layers' places in the image let it,
  which is what it gains on a validation recording of the same phantom;
- probe along the wires, halves along the wires (mm), probe's turn (deg), turn with the sweep
  (corr): how the probe moved over the phantom: the image centre's standard deviation along the
  wires, the distance along them between the two halves' mean positions (a hand sweeps from one
  end to the other), the image's rotation about its mean (RMS per phantom axis, averaged over the
  axes), and how closely that rotation follows the position along the wires (the size of their
  correlation, averaged over the axes: a hand pivots as it slides the probe).

Printed: the median and the 10th-90th percentiles of each statistic per recording (the value, for
one per recording), then for each
twin level how many of its medians fall inside the real spread (issue 15: every one for `bench`;
issue 31: the calibration rows too, where a real spread is the lowest to the highest recording).

Run: .venv/bin/python benchmarks/bench_realism.py [--poses 60] [--levels realistic,bench] [--no-calibration]
     [--no-dots] [--hand-seeds 3] [--diagonal-tolerance MM] [--diagonal-shift MM] [--diagonal-turn MM]
     [--layer-tolerance MM,DEG] [--tracker-drift MM,DEG] [--phantom-registration MM,DEG] [--write-docs]

``--write-docs`` writes the calibration rows' medians, one column per recording or twin level
(``EVIDENCE_ROWS``), into docs/evidence.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from bench_calibration import FCAL_SETS, import_fcal, import_nwire
from bench_calibration_bound import HAND_POSES, drift_from, halves, per_axis_from
from bench_objectives import DRIFT_FRAMES, single_frames
from bench_real_segmentation import recordings, segmenter_for
from evidence import WRITE_DOCS, command_line, markdown_table, write_table
from scipy.spatial.transform import Rotation

from probecal.core.acquisition.pairing import paired_again
from probecal.core.acquisition.simulate import simulate_calibration, simulate_freehand
from probecal.core.calibration.dots import as_gray, echo_peak_rows
from probecal.core.calibration.frames import observations
from probecal.core.calibration.labelling import PatternModel, affine_offsets_mm
from probecal.core.calibration.metrics import middle_wire_points
from probecal.core.calibration.segment import Segmenter, segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.calibration.validate import validate_session
from probecal.core.geometry.transforms import invert_transform, transform_points
from probecal.core.io.phantomfile import load_phantom, phantom_path
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.io.sequence import read_sequence
from probecal.core.twin.levels import BENCH_SETUP, Level, level

WINDOW_MM = (2.5, 1.5)  # half width, half depth of the window measured around a dot
PEAK_REACH_MM = 0.5  # the peak is looked for this close to the marker
PATTERN_MARGIN_MM = 3.0  # background box around the pattern's dots
STATS = ("contrast (gray)", "lateral FWHM (mm)", "axial FWHM (mm)", "area (mm^2)", "elongation",
         "centroid below peak (mm)", "brightness spread (CV)", "background mean (gray)", "background std (gray)",
         "wire fit residual (mm)", "wire offset, per wire (mm)", "wire offset, per frame (mm)")
CALIBRATION_STATS = ("objectives apart (mm)", "halves apart (mm)", "val PRE3D all/middle", "val PRE3D middle (mm)",
                     "wires vs tracker drift (mm)", "middle dot along diagonal (mm)",
                     "wire offset, next frame's (corr)", "middle-wire layers apart (mm)",
                     "layer offsets middle-wire takes up (mm)", "probe along the wires (mm)",
                     "halves along the wires (mm)", "probe's turn (deg)", "turn with the sweep (corr)")
EVIDENCE_ROWS = {"objectives apart (mm)": "all-wire and middle-wire apart at the corners (mm)",
                 "halves apart (mm)": "default calibrations of the two halves apart (mm)",
                 "val PRE3D all/middle": "validation PRE3D, all-wire / middle-wire",
                 "val PRE3D middle (mm)": "validation PRE3D, middle-wire (mm)",
                 "wires vs tracker drift (mm)": "wires vs tracker drift (mm)",
                 "middle dot along diagonal (mm)": "middle dot along its diagonal (mm)",
                 "wire offset, next frame's (corr)": "dots' offsets, correlation with the next frame's",
                 "probe along the wires (mm)": "image centre along the wires, sd (mm)",
                 "probe's turn (deg)": "the image's turn (deg RMS per axis)"}


def dot_stats(gray: np.ndarray, marker: np.ndarray, spacing: tuple[float, float]) -> dict[str, float] | None:
    """One dot's statistics (see the module docstring); None if its window leaves the frame."""
    sx, sy = spacing
    hu, hv = int(round(WINDOW_MM[0] / sx)), int(round(WINDOW_MM[1] / sy))
    u, v = int(round(marker[0])), int(round(marker[1]))
    if u - hu < 0 or v - hv < 0 or u + hu >= gray.shape[1] or v + hv >= gray.shape[0]:
        return None
    window = gray[v - hv : v + hv + 1, u - hu : u + hu + 1].astype(np.float64)
    background = float(np.percentile(window, 20))
    smooth = cv2.blur(window, (3, 3))
    ru, rv = max(int(round(PEAK_REACH_MM / sx)), 1), max(int(round(PEAK_REACH_MM / sy)), 1)
    near = smooth[hv - rv : hv + rv + 1, hu - ru : hu + ru + 1]
    i, j = np.unravel_index(np.argmax(near), near.shape)
    peak_row, peak_col = hv - rv + i, hu - ru + j
    contrast = float(smooth[peak_row, peak_col]) - background
    if contrast <= 0:
        return None
    above = (window >= background + contrast / 2).astype(np.uint8)
    _, labels = cv2.connectedComponents(above, connectivity=8)
    blob = labels == labels[peak_row, peak_col]
    if not blob.any():
        return None
    rows, cols = np.nonzero(blob)
    lateral, axial = (np.ptp(cols) + 1) * sx, (np.ptp(rows) + 1) * sy
    return {"contrast (gray)": contrast, "lateral FWHM (mm)": lateral, "axial FWHM (mm)": axial,
            "area (mm^2)": blob.sum() * sx * sy, "elongation": lateral / axial}


def frame_stats(image: np.ndarray, markers: np.ndarray, spacing: tuple[float, float]) -> dict[str, list[float]]:
    """Every statistic of one frame's found pattern, as lists (a value per dot, or one per frame)."""
    gray = as_gray(image)
    out: dict[str, list[float]] = {name: [] for name in STATS}
    for marker in markers:
        stats = dot_stats(gray, marker, spacing)
        for name, value in (stats or {}).items():
            out[name].append(value)
    below = (markers[:, 1] - echo_peak_rows(gray, markers, spacing)) * spacing[1]
    out["centroid below peak (mm)"] = list(below[np.isfinite(below)])
    if len(out["contrast (gray)"]) > 1:
        contrasts = np.array(out["contrast (gray)"])
        out["brightness spread (CV)"].append(float(contrasts.std() / contrasts.mean()))
    margin = np.array([PATTERN_MARGIN_MM / spacing[0], PATTERN_MARGIN_MM / spacing[1]])
    (u0, v0), (u1, v1) = (np.maximum(markers.min(axis=0) - margin, 0).astype(int),
                          np.minimum(markers.max(axis=0) + margin, gray.shape[::-1]).astype(int))
    keep = np.ones(gray.shape, bool)
    hu, hv = int(round(WINDOW_MM[0] / spacing[0] / 2)), int(round(WINDOW_MM[1] / spacing[1]))
    for u, v in markers.astype(int):
        keep[max(v - hv, 0) : v + hv + 1, max(u - hu, 0) : u + hu + 1] = False
    values = gray[v0:v1, u0:u1][keep[v0:v1, u0:u1]].astype(np.float64)
    if values.size:
        out["background mean (gray)"].append(float(values.mean()))
        out["background std (gray)"].append(float(values.std()))
    return out


def wire_offset_parts(results, model: PatternModel, spacing) -> tuple[float, float, float]:
    """The dots' offsets from their wires under each frame's best affine map, split into the part
    each wire keeps over the recording (its mean: where the wire was built, or a bias of its
    dots) and what changes from frame to frame: RMS per dot (mm) of each; and how much of what
    changes the next frame shares (the correlation of consecutive frames' changing parts)."""
    found = [r for r in results if r.found]
    offsets = np.array([affine_offsets_mm((r.markers[model.wire_index] * np.asarray(spacing))[None], model)[0]
                        for r in found])
    per_wire = offsets.mean(axis=0)
    changing = offsets - per_wire
    next_frame = np.diff([r.index for r in found]) == 1
    now, then = changing[:-1][next_frame], changing[1:][next_frame]
    return (float(np.sqrt((per_wire**2).sum(-1).mean())), float(np.sqrt((changing**2).sum(-1).mean())),
            float((now * then).sum() / np.sqrt((now**2).sum() * (then**2).sum())))


def collect(frames, results, segmenter: Segmenter) -> dict[str, np.ndarray]:
    """Every statistic pooled over the frames whose pattern was found."""
    spacing = segmenter.spacing_mm
    pooled: dict[str, list[float]] = {name: [] for name in STATS}
    for image, result in zip(frames, results):
        if not result.found:
            continue
        for name, values in frame_stats(image, np.asarray(result.markers, float), spacing).items():
            pooled[name].extend(values)
        pooled["wire fit residual (mm)"].append(result.residual_mm)
    per_wire, per_frame, _ = wire_offset_parts(results, segmenter.model, spacing)
    pooled["wire offset, per wire (mm)"].append(per_wire)
    pooled["wire offset, per frame (mm)"].append(per_frame)
    return {name: np.array(values) for name, values in pooled.items()}


def real_columns() -> dict[str, dict[str, np.ndarray]]:
    columns = {}
    for rec in recordings():
        if rec.name == "fCal 1.2 validation":
            continue  # the same bench and phantom as the calibration recording
        frames = list(rec.frames)
        segmenter = segmenter_for("probecal", rec, frames)
        results = [segmenter(frame, i) for i, frame in enumerate(frames)]
        columns[rec.name] = collect(frames, results, segmenter)
        print(f"  {rec.name}: {sum(r.found for r in results)} of {len(frames)} frames measured", flush=True)
    return columns


def twin_columns(levels: list[Level], poses: int, tmp: Path) -> dict[str, dict[str, np.ndarray]]:
    columns = {}
    for lvl in levels:
        name = lvl.name
        session = simulate_calibration(tmp / name, n_poses=poses, seed=0, noise=lvl)
        segmenter = session_segmenter(session)
        results = segment_session(session, segmenter=segmenter)
        frames = [session.image(r.index) for r in results]
        columns[f"twin {name}"] = collect(frames, results, segmenter)
        print(f"  twin {name}: {sum(r.found for r in results)} of {len(results)} frames measured", flush=True)
    return columns


def image_poses(obs, calibration) -> np.ndarray:
    """(F, 4, 4) ``image_to_phantom`` of every frame of ``obs``: its tracked pose through
    ``calibration`` (mm)."""
    return (invert_transform(calibration.phantom_to_base) @ np.asarray(obs.tool_to_base)
            @ calibration.image_to_tool_rigid)


def middle_dot_along_diagonal(phantom, obs, calibration, image_to_phantom: np.ndarray) -> float:
    """How far each N's middle dot strays with where it crosses its diagonal wire: per layer, the
    slope (mm per whole diagonal) of its lateral offset, less its outer dots' mean offset, from
    where ``calibration`` and the tracked poses (``image_to_phantom``, :func:`image_poses`) put the
    crossings, against the crossing's fraction along the diagonal; the median over the layers. A
    diagonal built off its definition, or an echo that shifts along it, gives a slope; a bench
    where it sits true, none."""
    spacing = np.asarray(calibration.pixel_spacing_mm)
    along: dict[int, list[tuple[float, float]]] = {}
    for markers, pose in zip(obs.markers_px, image_to_phantom):
        crossings = {c.index: c for c in phantom.crossings(pose)}
        for layer in range(len(phantom.layers)):
            n = [3 * layer + w for w in range(3)]
            if not all(i in crossings and np.isfinite(markers[i]).all() for i in n):
                continue
            lateral = [markers[i][0] * spacing[0] - crossings[i].point_image[0] for i in n]
            along.setdefault(layer, []).append((crossings[n[1]].t, lateral[1] - (lateral[0] + lateral[2]) / 2))
    slopes = [abs(np.polyfit(*np.array(pairs).T, 1)[0]) for pairs in along.values() if len(pairs) > 2]
    return float(np.median(slopes))


def layer_offsets(phantom, obs, calibration, image_to_phantom: np.ndarray) -> np.ndarray:
    """(L,) each layer's mean offset (mm) along the wires of a middle dot's point as
    ``calibration`` and the tracked poses (``image_to_phantom``) put it from its middle-wire point
    as the dot ratio puts it (PRE3D's two points, in the phantom frame): a diagonal that sits (or
    echoes) off across itself moves its layer's ratio, and so its point, along the wires."""
    spacing = np.asarray(calibration.pixel_spacing_mm)
    offsets = []
    for markers, pose in zip(obs.markers_px, image_to_phantom):
        middles = np.column_stack([markers[1::3] * spacing, np.zeros(len(markers) // 3)])
        offsets.append((transform_points(pose, middles) - middle_wire_points(phantom, markers))[:, 1])
    return np.nanmean(np.array(offsets), axis=0)


def hand_motion(image_to_phantom: np.ndarray, spacing_mm, image_size) -> tuple[float, float, float, float]:
    """How the probe moved over the phantom: the image centre's standard deviation along the
    wires (phantom y, mm), how far apart the two halves of the recording hold it on average along
    them (mm), the image's turn (deg: its rotation from its mean, RMS per phantom axis, averaged
    over the axes) and how closely that turn follows the sweep along the wires (the correlation of
    each axis's turn with the position along them, its size averaged over the axes: a hand that
    pivots at the wrist or elbow tilts and turns the probe as it slides it), from every frame's
    ``image_to_phantom`` (:func:`image_poses`)."""
    centre = np.append(np.asarray(image_size) * np.asarray(spacing_mm) / 2, [0.0, 1.0])
    along = (image_to_phantom @ centre)[:, 1]
    half = len(along) // 2
    rotation = Rotation.from_matrix(image_to_phantom[:, :3, :3])
    turn = (rotation * rotation.mean().inv()).as_rotvec(degrees=True)
    halves_apart = abs(along[:half].mean() - along[half:].mean())
    with_sweep = np.mean([abs(np.corrcoef(along, axis)[0, 1]) for axis in turn.T])
    return float(along.std()), float(halves_apart), float(np.sqrt((turn ** 2).mean(0)).mean()), float(with_sweep)


def calibration_stats(session, validation=None) -> dict[str, np.ndarray]:
    """The calibration rows (see the module docstring) of one recording, the robot's way; a
    validation session adds the objectives' PRE3D ratio on it."""
    segmenter = session_segmenter(session, use_hints=False)
    results = segment_session(session, segmenter=segmenter)
    fitted = {method: calibrate_session(session, results, method, with_validation=False).calibration
              for method in ("all-wire", "middle-wire")}
    stats = {"objectives apart (mm)": [corner_distance_mm(fitted["all-wire"], fitted["middle-wire"],
                                                          image_corners_px(session.image_size))],
             "halves apart (mm)": [halves(session, results)[0]], "val PRE3D all/middle": [],
             "val PRE3D middle (mm)": []}
    all_wire = fitted["all-wire"]
    paired = session if all_wire.image_latency_s is None else paired_again(session, all_wire.image_latency_s)
    obs = observations(paired, results)[0]  # the tracked poses at the latency the calibration measured
    stats["wires vs tracker drift (mm)"] = [single_frames(session.phantom, all_wire.phantom_to_base, obs, all_wire,
                                                          image_corners_px(session.image_size))[2]]
    poses = image_poses(obs, all_wire)
    stats["middle dot along diagonal (mm)"] = [middle_dot_along_diagonal(session.phantom, obs, all_wire, poses)]
    stats["wire offset, next frame's (corr)"] = [wire_offset_parts(results, segmenter.model, segmenter.spacing_mm)[2]]
    layers = {method: layer_offsets(session.phantom, obs, c, poses if c is all_wire else image_poses(obs, c))
              for method, c in fitted.items()}
    stats["middle-wire layers apart (mm)"] = [float(np.ptp(layers["all-wire"]))]
    # What middle-wire, fitted to PRE3D's points, takes up of them by tilting the image.
    rms = {method: float(np.sqrt(np.mean(offsets ** 2))) for method, offsets in layers.items()}
    stats["layer offsets middle-wire takes up (mm)"] = [rms["all-wire"] - rms["middle-wire"]]
    motion = hand_motion(poses, all_wire.pixel_spacing_mm, session.image_size)
    for stat, value in zip(CALIBRATION_STATS[-4:], motion):
        stats[stat] = [value]
    if validation is not None:
        held = segment_session(validation, segmenter=session_segmenter(validation, use_hints=False))
        pre3d = {m: validate_session(validation, c, held)["pre3d_mm"] for m, c in fitted.items()}
        stats["val PRE3D all/middle"] = [pre3d["all-wire"] / pre3d["middle-wire"]]
        stats["val PRE3D middle (mm)"] = [pre3d["middle-wire"]]
    return {name: np.array(values) for name, values in stats.items()}


def real_calibration_columns(tmp: Path) -> dict[str, dict[str, np.ndarray]]:
    columns = {}
    for bench in FCAL_SETS:
        calibration, validation = import_fcal(bench, tmp)
        columns[f"{bench.name} calibration"] = calibration_stats(calibration, validation)
        print(f"  {bench.name}: calibrated", flush=True)
    nwire = import_nwire(tmp)
    columns["NwirePhantomFreehand"] = calibration_stats(nwire)
    print("  NwirePhantomFreehand: calibrated", flush=True)
    return columns


WANDER_MARKERS = ("ReferenceToTracker", "StylusToTracker")


def marker_wander() -> None:
    """Print, per real recording, how far its markers that stay with the bench wander: the
    reference (fixed to the phantom) and the stylus (lying still), in the tracker's frame, as the
    standard deviation of their means over nine frames in a row (RMS over the axes: mm, and deg
    about each axis), then the median over the recordings of the reference's. The ``bench``
    level's ``tracker_drift`` is half of it: the size at which the freehand twin's validation PRE3D
    meets the real recordings' (the whole of it gives about twice the real)."""
    wander = []
    for name in [f for bench in FCAL_SETS for f in (bench.calibration, bench.validation)] + ["NwirePhantomFreehand"]:
        seq = read_sequence(plus_data_dir() / "TestImages" / f"{name}.igs.mha", images=False)
        cells = []
        for marker in WANDER_MARKERS:
            tracked = seq.statuses.get(marker, np.ones(len(seq), bool))
            if tracked.sum() < 2 * DRIFT_FRAMES:
                cells.append(f"{marker}: not tracked")
                continue
            poses = seq.transforms[marker][tracked]
            rotation = Rotation.from_matrix(poses[:, :3, :3])
            offsets = np.column_stack([poses[:, :3, 3], (rotation * rotation.mean().inv()).as_rotvec(degrees=True)])
            window = np.ones(DRIFT_FRAMES) / DRIFT_FRAMES
            sd = np.array([np.convolve(axis, window, mode="valid").std() for axis in offsets.T])
            rms = (float(np.sqrt(np.mean(sd[:3] ** 2))), float(np.sqrt(np.mean(sd[3:] ** 2))))
            cells.append(f"{marker} {rms[0]:.2f} mm {rms[1]:.3f} deg")
            if marker == WANDER_MARKERS[0]:
                wander.append(rms)
        print(f"  {name:40s} " + "; ".join(cells))
    median = np.median(np.array(wander), axis=0)
    print(f"  median reference wander {median[0]:.2f} mm {median[1]:.2f} deg; twin bench tracker_drift "
          f"{BENCH_SETUP.tracker_drift[0]:.2f} mm {BENCH_SETUP.tracker_drift[1]:.2f} deg")


def twin_levels(names: list[str], **errors) -> list[Level]:
    """The twin's levels, with their set-up errors named in ``errors`` (``SetupErrors`` fields; None:
    the level's own) replaced."""
    given = {name: value for name, value in errors.items() if value is not None}
    return [replace(lvl, setup=replace(lvl.setup, **given)) for lvl in (level(name) for name in names)]


def twin_calibration_columns(levels: list[Level], poses: int, hand_seeds: int,
                             tmp: Path) -> dict[str, dict[str, np.ndarray]]:
    """Per level, the robot's sweep (seed 0; another seed is another bench and probe mount, so it
    is not validated) and, like for like with the real recordings, tracked freehand recordings of
    the fCal 2.0 phantom (``hand_seeds`` benches, each a calibration path validated on a second
    path over the same bench)."""
    columns = {}
    fcal = load_phantom(phantom_path("fcal-2.0"))
    for lvl in levels:
        name = lvl.name
        session = simulate_calibration(tmp / f"{name}-cal", n_poses=poses, seed=0, noise=lvl)
        columns[f"twin {name}"] = calibration_stats(session)
        print(f"  twin {name}: calibrated", flush=True)
        benches = []
        for seed in range(hand_seeds):
            recordings = [simulate_freehand(tmp / f"{name}-hand{seed}-{path}", n_poses=HAND_POSES, seed=seed,
                                            noise=lvl, phantom=fcal, path=path) for path in (0, 1)]
            benches.append(calibration_stats(*recordings))
        columns[f"twin {name} freehand"] = {stat: np.concatenate([b[stat] for b in benches])
                                            for stat in CALIBRATION_STATS}
        print(f"  twin {name} freehand: {hand_seeds} benches calibrated", flush=True)
    return columns


def print_table(columns: dict[str, dict[str, np.ndarray]], stats: tuple[str, ...]) -> None:
    """The statistics of every column side by side, then how many of each twin level's medians
    lie within the real spread."""
    names = list(columns)
    print("median [10th, 90th percentile]")
    print(f"{'statistic':26s}" + "".join(f"{name:>26s}" for name in names))
    for stat in stats:
        cells = []
        for name in names:
            values = columns[name][stat]
            if len(values) > 1:
                cells.append(f"{np.median(values):.3g} "
                             f"[{np.percentile(values, 10):.3g}, {np.percentile(values, 90):.3g}]")
            else:
                cells.append(f"{values[0]:.3g}" if len(values) else "-")
        print(f"{stat:26s}" + "".join(f"{c:>26s}" for c in cells))
    real = [n for n in names if not n.startswith("twin")]
    if not real:
        return
    print("within the real spread (a twin median between the lowest 10th and the highest 90th percentile "
          "of the real recordings):")
    for name in (n for n in names if n.startswith("twin")):
        outside, measured = [], [stat for stat in stats if len(columns[name][stat])]
        for stat in measured:
            lo = min(np.percentile(columns[r][stat], 10) for r in real if len(columns[r][stat]))
            hi = max(np.percentile(columns[r][stat], 90) for r in real if len(columns[r][stat]))
            if not lo <= np.median(columns[name][stat]) <= hi:
                outside.append(stat)
        print(f"  {name}: {len(measured) - len(outside)} of {len(measured)} statistics"
              + (f"; outside: {', '.join(outside)}" if outside else ""))


def column_label(name: str) -> str:
    """A column's name as the evidence table heads it: ``twin bench freehand`` as
    ``twin `bench`, freehand``, ``fCal 1.2 calibration`` as ``fCal 1.2``."""
    if not name.startswith("twin "):
        return name.removesuffix(" calibration")
    lvl, _, freehand = name.removeprefix("twin ").partition(" ")
    return f"twin `{lvl}`" + (", freehand" if freehand else "")


def evidence_table(columns: dict[str, dict[str, np.ndarray]]) -> list[str]:
    """The ``EVIDENCE_ROWS`` of the calibration columns as a markdown table: each column's
    median (its one value, for one per recording), – where it has none."""
    header = ["", *(column_label(name) for name in columns)]
    rows = [[label, *(f"{np.median(c[stat]):.2f}".replace("-", "−") if len(c[stat]) else "–"
                      for c in columns.values())]
            for stat, label in EVIDENCE_ROWS.items()]
    return markdown_table(header, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--levels", default="realistic,bench")
    parser.add_argument("--no-calibration", action="store_true", help="only the dot and background statistics")
    parser.add_argument("--no-dots", action="store_true", help="only the calibration statistics")
    parser.add_argument("--hand-seeds", type=int, default=3, help="tracked freehand twin benches per level")
    parser.add_argument("--diagonal-tolerance", type=float, metavar="MM",
                        help="the twin's diagonal wires' ends built off across them instead of as each level does")
    parser.add_argument("--diagonal-shift", type=float, metavar="MM",
                        help="the twin's diagonal wires built off across themselves as a whole instead of as each "
                             "level does")
    parser.add_argument("--diagonal-turn", type=float, metavar="MM",
                        help="the twin's diagonal wires turned about their middles within their layers (each end "
                             "across by up to MM) instead of as each level does")
    parser.add_argument("--layer-tolerance", type=per_axis_from, metavar="MM,DEG",
                        help="the twin's phantom layers built off as a whole instead of as each level does "
                             "(every axis, or six values: x, y, z mm, then deg about them)")
    parser.add_argument("--tracker-drift", type=drift_from, metavar="MM,DEG",
                        help="the freehand twin's slow tracker error (RMS per axis) instead of each level's")
    parser.add_argument("--phantom-registration", type=per_axis_from, metavar="MM,DEG",
                        help="the freehand twin's error in the registered phantom pose (sd per axis, every axis or "
                             "six values: x, y, z mm, then deg about them) instead of each level's")
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    levels = twin_levels(args.levels.split(","), diagonal_tolerance_mm=args.diagonal_tolerance,
                         diagonal_shift_mm=args.diagonal_shift, diagonal_turn_mm=args.diagonal_turn,
                         layer_tolerance=args.layer_tolerance,
                         tracker_drift=args.tracker_drift, phantom_registration=args.phantom_registration)
    if not args.no_dots:
        print("measuring (own segmenter, no hints)")
        columns = real_columns() if plus_data_dir().is_dir() else {}
        with tempfile.TemporaryDirectory() as tmp:
            columns.update(twin_columns(levels, args.poses, Path(tmp)))
        print_table(columns, STATS)
    if args.no_calibration:
        return
    if plus_data_dir().is_dir():
        print("markers that stay with the bench, wandering along each real recording (tracker frame)")
        marker_wander()
    print("calibrating (the robot's way: own segmenter, nominal spacing)")
    with tempfile.TemporaryDirectory() as tmp:
        calibration = real_calibration_columns(Path(tmp)) if plus_data_dir().is_dir() else {}
        calibration.update(twin_calibration_columns(levels, args.poses, args.hand_seeds, Path(tmp)))
    print_table(calibration, CALIBRATION_STATS)
    if args.write_docs:
        print(f"written: {write_table(command_line(), evidence_table(calibration))}")


if __name__ == "__main__":
    main()
