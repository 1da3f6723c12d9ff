"""PLUS's own fCal recordings played back through the PLUS-server stand-in and recorded live, against
the same recordings imported.

Each fCal bench's calibration and validation recordings are streamed over OpenIGTLink on loopback
as a PLUS server streams them (``core.acquisition.igtlstreamer.recording_batches``: the frames as
PLUS holds them, ProbeToTracker, ReferenceToTracker and StylusToTracker with their status, at the
recording's pace) and recorded by the tracked probe's source (``core.acquisition.tracked``: the
tracker's two devices composed, the images from the same server), with the phantom, its pose and
the segmentation settings of the bench's device set. Both the live recording and the import are
calibrated the robot's way (probecal's segmenter, no PLUS hints but the approximate spacing); the
figures are how far apart the two calibrations put the image corners (mm, farthest of four) and
each one's validation PRE3D on PLUS's own points of the validation recording.

Target: corners within 0.05 mm.

Run: PROBECAL_PLUS_DATA=... .venv/bin/python benchmarks/bench_playback.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from bench_calibration import FCAL_SETS, PLUS, import_fcal, plus_points_pre3d

from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.igtlstreamer import IgtlStreamer, recording_batches
from probecal.core.acquisition.tracked import TrackedRecording, setup_from_device_set
from probecal.core.acquisition.tracker import IgtlTracker, TrackerDevices
from probecal.core.calibration.segment import segment_session, session_segmenter
from probecal.core.calibration.solve import calibrate_session
from probecal.core.calibration.uncertainty import corner_distance_mm, image_corners_px
from probecal.core.io.plusresults import read_calibration_results
from probecal.core.io.sequence import read_sequence
from probecal.core.io.session import Session, load_session

TARGET_MM = 0.05


def played(sequence_file: Path, config: Path, out: Path) -> tuple[Session, float]:
    """The recording streamed by the stand-in and recorded live; and the wall time it took (s)."""
    sequence = read_sequence(sequence_file)
    started = time.monotonic()
    with IgtlStreamer() as streamer:
        streamer.play_batches(recording_batches(sequence, time.time()), wait_for_client_s=60.0, clients=2)
        tracker = IgtlTracker("127.0.0.1", streamer.port, TrackerDevices("ProbeToTracker", "ReferenceToTracker"),
                              device_clock=True)
        source = IgtlSource("127.0.0.1", streamer.port, transform_device=None)
        source.open()
        try:
            tracker.connect()
            recording = TrackedRecording(tracker, source, out, setup=setup_from_device_set(config))
            outcome = recording.run(frames=len(sequence), timeout_s=5.0)
        finally:
            tracker.disconnect()
            source.close()
    if outcome.error or outcome.refusals:
        raise SystemExit(f"{sequence_file.name}: {outcome.error or outcome.refusals[0]}")
    return load_session(out), time.monotonic() - started


def calibrated(session: Session):
    results = segment_session(session, segmenter=session_segmenter(session, use_hints=False))
    return calibrate_session(session, results).calibration


def main() -> None:
    print(f"PLUS recordings streamed through the stand-in vs imported; target: corners within {TARGET_MM} mm")
    for bench in FCAL_SETS:
        with tempfile.TemporaryDirectory() as tmp:
            imported_cal, imported_val = import_fcal(bench, Path(tmp))
            live = {}
            for part, stem in (("cal", bench.calibration), ("val", bench.validation)):
                sequence = PLUS / "TestImages" / f"{stem}.igs.mha"
                live[part], wall = played(sequence, bench.config, Path(tmp) / f"live-{part}")
                print(f"{bench.name} {part}: {len(live[part])} frames recorded live in {wall:.1f} s")
            baseline = read_calibration_results(bench.results)
            a, b = calibrated(imported_cal), calibrated(live["cal"])
            apart = corner_distance_mm(a, b, image_corners_px(imported_cal.image_size))
            pre_a = plus_points_pre3d(imported_val, a, baseline)[0]
            pre_b = plus_points_pre3d(live["val"], b, baseline)[0]
            print(f"{bench.name}: corners {apart:.4f} mm apart ({'within' if apart <= TARGET_MM else 'OVER'} "
                  f"{TARGET_MM}); validation PRE3D imported {pre_a:.3f} mm, streamed {pre_b:.3f} mm "
                  f"(PLUS {baseline.pre3d_validation_mm[0]})")


if __name__ == "__main__":
    main()
