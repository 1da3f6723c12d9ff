"""Segmentation robustness on real frames: every real N-wire recording in the PLUS data, as
recorded and perturbed, segmented the robot's way (no PLUS settings but the approximate pixel
spacing), against PLUS's own points as truth.

Segmenters: probecal's own (default, tuned per recording on the frames it is given), the thesis's
(``thesis``, no hints) and the PLUS clone (``plus``, with PLUS's hand-tuned settings, as PLUS runs).
Perturbations: gain x0.5 and x1.5, gamma 0.7 and 1.4, multiplicative speckle, Gaussian blur
(sigma 1 px), 2 px horizontal motion blur, a 10 % crop from every side, one dot's whole echo
erased.
Printed per recording and perturbation: the share of PLUS's patterns found, points within 1 px
of PLUS's, and patterns found where PLUS found none, split into those PLUS's points on both
neighbouring frames confirm (frames PLUS missed in a smooth motion) and the rest (false finds).

Run: .venv/bin/python benchmarks/bench_real_segmentation.py [--stride 1] [--segmenters probecal,plus,thesis]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from probecal.core.calibration.labelling import plus_orientation
from probecal.core.calibration.segment import Segmenter, tuning_sample
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.io.plusresults import confirmed_by_neighbours, read_calibration_results, read_segmentation_baseline
from probecal.core.io.sequence import oriented_mf, read_sequence

PLUS = plus_data_dir()
IMAGES, CONFIGS = PLUS / "TestImages", PLUS / "ConfigFiles" / "Testing"


@dataclass
class Recording:
    name: str
    frames: np.ndarray  # (N, H, W) MF
    truth: list  # PLUS's points (W, 2) px per frame, None where PLUS found no pattern
    config: object


def _frames_mf(file: str) -> np.ndarray:
    """A recording's frames as PLUS holds them (MF), like ``probecal import-plus``."""
    seq = read_sequence(IMAGES / f"{file}.igs.mha")
    return oriented_mf(seq.frames, seq.fields.get("UltrasoundImageOrientation", "MF"))


def recordings() -> list[Recording]:
    fcal = read_device_set(CONFIGS / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml")
    results = read_calibration_results(IMAGES / "FreehandCalibration3NWires.results.xml")
    out = []
    for name, file, section in (("fCal 1.2 calibration", "fCal_Test_Calibration_3NWires", results.calibration),
                                ("fCal 1.2 validation", "fCal_Test_Validation_3NWires", results.validation)):
        out.append(Recording(name, _frames_mf(file), [f.points for f in section], fcal))
    for name, file, config in (("VLCUS", "SegmentationTest_VLCUS_RandomStepperMotionData2",
                                "PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber"),
                               ("USTC", "USTC_FrameGrabber_ProbeRotationData",
                                "PlusDeviceSet_iCal_CalibrationOnly_FrameGrabber")):
        baseline = read_segmentation_baseline(IMAGES / f"{file}_Segmentation_baseline.xml")
        out.append(Recording(name, _frames_mf(file), [c.points for c in baseline],
                             read_device_set(CONFIGS / f"{config}.xml")))
    return out


Perturb = Callable[[np.ndarray, np.ndarray | None, np.random.Generator], tuple[np.ndarray, np.ndarray | None]]


def _gray(values: np.ndarray) -> np.ndarray:
    return np.clip(values, 0, 255).astype(np.uint8)


def _erase(image, truth, rng):
    """One of PLUS's dots gone: its whole echo (the blob of pixels above 10 % of the frame's
    maximum that holds it, grown by 4 px) set to black, so no fragment of it stays behind."""
    if truth is None:
        return image, truth
    u, v = truth[rng.integers(len(truth))]
    bright = (image >= 0.1 * image.max()).astype(np.uint8)
    _, labels = cv2.connectedComponents(bright, connectivity=8)
    c, r = int(round(u)), int(round(v))
    near = labels[max(r - 3, 0) : r + 4, max(c - 3, 0) : c + 4]
    if not near.any():
        return image, truth
    blob = labels == np.bincount(near[near > 0]).argmax()
    out = image.copy()
    out[cv2.dilate(blob.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0] = 0
    return out, truth


def _crop(image, truth, rng):
    h, w = image.shape
    y, x = h // 10, w // 10
    return np.ascontiguousarray(image[y : h - y, x : w - x]), None if truth is None else truth - (x, y)


PERTURBATIONS: dict[str, Perturb] = {
    "as recorded": lambda im, t, rng: (im, t),
    "gain x0.5": lambda im, t, rng: (_gray(im * 0.5), t),
    "gain x1.5": lambda im, t, rng: (_gray(im * 1.5), t),
    "gamma 0.7": lambda im, t, rng: (_gray(255 * (im / 255.0) ** 0.7), t),
    "gamma 1.4": lambda im, t, rng: (_gray(255 * (im / 255.0) ** 1.4), t),
    "speckle": lambda im, t, rng: (_gray(im * rng.rayleigh(0.8, im.shape) + rng.normal(0, 3, im.shape)), t),
    "blur 1 px": lambda im, t, rng: (cv2.GaussianBlur(im, (0, 0), 1.0), t),
    "motion 2 px": lambda im, t, rng: (cv2.filter2D(im, -1, np.full((1, 3), 1 / 3)), t),
    "crop 10 %": _crop,
    "one dot erased": _erase,
}


def segmenter_for(kind: str, rec: Recording, frames: list[np.ndarray]) -> Segmenter:
    phantom = rec.config.phantom
    hints = rec.config.segmentation.attributes
    spacing = (float(hints["ApproximateSpacingMmPerPixel"]),) * 2
    if kind == "plus":
        return Segmenter.create(phantom, spacing, plus_orientation(phantom), hints, kind="plus")
    segmenter = Segmenter.create(phantom, spacing, plus_orientation(phantom), kind=kind)
    return segmenter.tune(tuning_sample(frames))


def score(segmenter: Segmenter, frames: list[np.ndarray], truth: list) -> tuple[int, int, int, int, np.ndarray]:
    """(PLUS's patterns, of those found, found where PLUS found none but its neighbouring frames
    confirm, found where PLUS found none unconfirmed, distances px)."""
    theirs = both = missed = extra = 0
    distances = []
    for i, (frame, points) in enumerate(zip(frames, truth)):
        result = segmenter(frame, i)
        theirs += points is not None
        both += result.found and points is not None
        if result.found and points is None:
            confirmed = confirmed_by_neighbours(result.markers, i, truth)
            missed += confirmed
            extra += not confirmed
        if result.found and points is not None:
            distances.append(np.linalg.norm(result.markers - points, axis=1))
    return theirs, both, missed, extra, np.concatenate(distances) if distances else np.empty(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stride", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--segmenters", default="probecal,plus,thesis")
    args = parser.parse_args()
    if not PLUS.is_dir():
        print(f"PLUS data not found at {PLUS}")
        return
    kinds = args.segmenters.split(",")
    totals = {k: np.zeros(4, int) for k in kinds}
    within = {k: [] for k in kinds}
    print(f"{'recording':22s} {'perturbation':15s} " + " ".join(f"{k:>30s}" for k in kinds))
    print(f"{'':38s} " + " ".join(f"{'found / 1px / PLUS missed / false':>36s}" for _ in kinds))
    for rec in recordings():
        rng = np.random.default_rng(0)
        for name, perturb in PERTURBATIONS.items():
            pairs = [perturb(f, t, rng) for f, t in zip(rec.frames[:: args.stride], rec.truth[:: args.stride])]
            frames, truth = [p[0] for p in pairs], [p[1] for p in pairs]
            cells = []
            for kind in kinds:
                theirs, both, missed, extra, d = score(segmenter_for(kind, rec, frames), frames, truth)
                totals[kind] += (theirs, both, missed, extra)
                within[kind].append(d)
                near = f"{np.mean(d < 1):6.1%}" if len(d) else "   -  "
                cells.append(f"{both:4d}/{theirs:<4d} {both / max(theirs, 1):6.1%} {near} {missed:3d} {extra:3d}")
            print(f"{rec.name:22s} {name:15s} " + " ".join(f"{c:>36s}" for c in cells), flush=True)
    for kind in kinds:
        theirs, both, missed, extra = totals[kind]
        d = np.concatenate(within[kind])
        print(f"all {kind:9s}: found {both}/{theirs} ({both / theirs:.1%}) of PLUS's patterns, points within 1 px "
              f"{np.mean(d < 1):.1%}; where PLUS found none: {missed} confirmed by its neighbouring frames, "
              f"{extra} false")
    rec = recordings()[0]
    segmenter = segmenter_for("probecal", rec, list(rec.frames))
    frames = list(rec.frames)
    rates = []
    for _ in range(3):  # the median of three passes: one pass is at the mercy of a noisy neighbour
        start = time.perf_counter()
        for i, frame in enumerate(frames):
            segmenter(frame, i)
        rates.append(len(frames) / (time.perf_counter() - start))
    print(f"speed probecal on 820x616 fCal, no ROI: {np.median(rates):.0f} frames/s on one thread, median of 3 passes "
          f"({segmenter.describe()})")


if __name__ == "__main__":
    main()
