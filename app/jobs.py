"""Long work that the command line and the console both run, run the same way by both."""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

from probecal.core.calibration.segment import Segmenter
from probecal.core.calibration.solve import CalibrationReport, segment_and_calibrate
from probecal.core.io.session import Session

WORKERS = min(2, os.cpu_count() or 1)
"""Worker processes for a calibration's fits, refits and registrations."""


def run_calibration(session: Session, segmenter: Segmenter | None = None, method: str = "auto",
                    solve_phantom_pose: bool = False, frame_progress: Callable[[int, int], None] | None = None,
                    progress: Callable[[str], None] | None = None) -> CalibrationReport:
    """``probecal calibrate`` and the console's Calibrate: segment every frame of ``session``
    here, then solve image_to_tool with the fits, refits and registrations in :data:`WORKERS`
    processes (``core.calibration.solve.segment_and_calibrate``). ``frame_progress(done, total)``
    and ``progress(step)`` are called here between steps; what they raise (the console's Stop)
    ends the work, and the workers drop what they have not started."""
    # The workers fork from a fresh server process: forking this one, whose segmentation has
    # started OpenCV's threads (and, in the console, the web server's), hung once in a busy suite.
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["probecal.core.calibration.solve"])
    pool = ProcessPoolExecutor(max_workers=WORKERS, mp_context=context)
    try:
        return segment_and_calibrate(session, segmenter, method, solve_phantom_pose, frame_progress=frame_progress,
                                     progress=progress, mapper=pool.map)
    finally:
        pool.shutdown(cancel_futures=True)
