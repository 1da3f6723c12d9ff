"""The fuzzing harness's hostile trackers (``tests.support.peers.TRACKERS``), each a PLUS server a
tracked sweep records from, guided and continuous: one bad pose (NaN, mirrored, huge, timestamps
backwards), poses that compose past the readers' bound, floods of device names and of poses, a
TransformStatus of 5 MB, frames too small to guide; the bad poses also from the very first one."""

from __future__ import annotations

import sys
from pathlib import Path

from tests.support.fuzz import Case, Runner, command_line, read_back

TRACKED_SWEEP = ("sweep", "calibration", "{in}/sw", "--tracker", "igtl:127.0.0.1:{port}", "--phantom", "thesis-4layer")
MOTIONS = {"guided": (), "continuous": ("--frames", "60")}
"""How each hostile tracker is recorded: guided until its stream ends, or 60 frames (2 s)."""


def tracker_cases() -> list[Case]:
    from tests.support.peers import BAD_AT, SMALL_SPACING_MM, TRACKER_BAD_INPUT, TRACKER_SPACING_MM, TRACKERS

    cases = []
    for kind in TRACKERS:
        spacing = SMALL_SPACING_MM if kind == "small frames" else TRACKER_SPACING_MM
        starts = (BAD_AT, 0) if kind in TRACKER_BAD_INPUT else (BAD_AT,)
        for bad_at in starts:
            for motion, extra in MOTIONS.items():
                argv = (*TRACKED_SWEEP, "--spacing", str(spacing), "--motion", motion, *extra)
                first = " from the first pose" if bad_at == 0 else ""
                cases.append(Case(f"hostile tracker {kind}{first}: sweep {motion}", argv, (),
                                  run=from_tracker(kind, bad_at)))
    return cases


def from_tracker(kind: str, bad_at: int) -> Runner:
    """The command line on ``argv`` with ``{port}`` the port of the hostile tracker ``kind``
    (``tests.support.peers.start_tracker``), its images from the same server. A session the sweep's
    last line names is one it kept, which must read back whole; any other is left behind."""
    def run(argv: list[str], folder: Path) -> int:
        from tests.support.peers import start_tracker

        port = start_tracker(kind, bad_at)
        code = command_line([a.replace("{port}", str(port)) for a in argv], folder)
        sys.stderr.flush()
        lines = (folder.parent / f"{folder.name}.err").read_text(errors="replace").splitlines()
        session = folder / "sw"
        if session.exists() and (code == 0 or (lines and str(session) in lines[-1])):
            read_back(session)
        return code
    return run
