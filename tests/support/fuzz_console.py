"""The fuzzing harness's console cases: every field of the console set to a hostile value over a
page's websocket (``tests.support.page``), then the job that uses it run, as an operator would
click it.

A case launches the console on the simulator in its child, with a sessions folder of its own
beside the case's folder, makes ready what the job needs (connected; a small sweep; a volume
reconstructed), sends the value, clicks the job's button and waits for the job to end. Its exit
code: 0 when the job ran through, 2 (and the status as one line) when it failed or stopped. A
traceback the console prints, a job that does not end, and what a failed job left in the sessions
folder (a session it kept must read back whole) are the harness's failures as for any command."""

from __future__ import annotations

import math
import shutil
import sys
from pathlib import Path

from tests.support.fuzz import Case, Runner, changed_entries, read_back, short, snapshot

NUMBERS: list[object] = [math.nan, math.inf, -math.inf, 0, -1, 1e-300, 1e300, 2**63, "", "x", None, True, [], {},
                         [1, 2, 3], "a" * 100_000, [[[[[[[[1]]]]]]]]]
VECTORS: list[object] = [[math.nan, 0.1], [0, 0], [-1, -1], [1e300, 1e300], [], [1, 2, 3, 4], "x", None, 5,
                         [[1], [1]], ["a", "b"], [True, False], [math.inf, -math.inf, math.nan]]
CHOICES: list[object] = ["bogus", "", None, 5, [], "a" * 100_000, "continuous ", "\x00"]
SWITCHES: list[object] = ["x", None, 5, [], {}, "", math.nan]
FOLDERS: list[object] = ["..", "../..", "/etc", "/", "", "a" * 100_000, "x\x00y", "vol/../../..", "vol/frames",
                         "vol/manifest.json", "~", None, 5, [], ".", "vol\n"]
FIELDS: dict[str, tuple[list[object], str]] = {
    "motion": (CHOICES, "start"), "speed": (NUMBERS, "start"), "latency_ms": (NUMBERS, "start"),
    "spacing": (VECTORS, "start"), "poses": (NUMBERS, "start"), "translation": (VECTORS, "start"),
    "rotation": (VECTORS, "start"), "resume": (SWITCHES, "start"), "tolerance": (NUMBERS, "start"),
    "frames_per_pass": (NUMBERS, "scan"), "cloud_colors": (CHOICES, "reload"),
    "window": (NUMBERS, "reload"), "level": (NUMBERS, "reload"), "session_path": (FOLDERS, "load"),
    **{f"slice_at.{axis}": (NUMBERS, "reload") for axis in "xyz"},
    **{f"layers.{layer}": (SWITCHES, "start") for layer in ("robot", "image plane", "markers")},
}
"""Each field, the values a page may send it, and the job that then uses it (by its button;
``reload``: Load session of the volume just reconstructed, which shows its cloud and slices)."""
JOB_S = 45.0  # the longest a case's job may run: under the harness's time limit


def console_cases() -> list[Case]:
    """Each field with each of its hostile values, and each field sent an update that is no value."""
    cases = [Case(f"console {name} = {short(value)}: {job}", ("console", name), _needs(job),
                  run=on_console(name, value, job)) for name, (values, job) in FIELDS.items() for value in values]
    cases += [Case(f"console {name} sent {{'bogus': 1}}: {job}", ("console", name), _needs(job),
                   run=on_console(name, 1, job, prop="bogus")) for name, (_, job) in FIELDS.items()]
    return cases


def _needs(job: str) -> tuple[str, ...]:
    return {"load": ("vol",), "reload": ("cal", "vol")}.get(job, ())



def on_console(name: str, value: object, job: str, prop: str = "value") -> Runner:
    """The console's field ``name`` set to ``value`` (``prop`` of it) by a page, then ``job``."""
    def run(_argv: list[str], folder: Path) -> int:
        from probecal.app.console.server import launch
        from tests.support.page import RawPage
        from tests.support.waiting import wait_until

        sessions = folder.parent / f"{folder.name}.sessions"
        sessions.mkdir()
        console = launch(port=0, sessions_dir=sessions, time_scale=0.0)
        try:
            _make_ready(console, job, folder)
            before = snapshot(sessions)
            runs = console.jobs.started
            with RawPage(console) as page:
                page.update(_handle(console, name), {prop: value})
                page.click(console.panel.load if job == "reload" else getattr(console.panel, job))
                wait_until(lambda: console.jobs.started > runs and not console.jobs.busy, "the job ended", JOB_S)
            status = console.panel.status.text
            failed = " failed: " in status or status.startswith("Stopped")
            if failed:
                _note_left(sessions, before, folder)
        finally:
            console.close()
            shutil.rmtree(sessions, ignore_errors=True)
        if failed:
            print(f"probecal: error: {status}", file=sys.stderr)
            return 2
        return 0
    return run


def _make_ready(console, job: str, folder: Path) -> None:
    """What ``job`` needs before it can run: the robot connected and small sweeps; a session to
    load; a calibration and a volume session loaded and reconstructed, to load again."""
    panel = console.panel
    panel.poses.value = 4
    panel.frames_per_pass.value = 4
    if job in ("start", "scan"):
        _job(console, console.connect)
    elif job == "load":
        shutil.copytree(folder / "vol", console.sessions_dir / "vol")
    elif job == "reload":
        for name in ("cal", "vol"):
            shutil.copytree(folder / name, console.sessions_dir / name)
        shutil.copy(folder / "cal" / "truth.json", console.sessions_dir / "cal" / "calibration.json")
        for name in ("cal", "vol"):
            panel.session_path.value = name
            _job(console, console.load_session)
        _job(console, console.reconstruct)


def _job(console, job) -> None:
    job()
    console.wait()
    status = console.panel.status.text
    if " failed: " in status:
        raise RuntimeError(f"the console could not be made ready: {status}")


def _handle(console, name: str):
    field, _, key = name.partition(".")
    handle = getattr(console.panel, field)
    return handle[key] if key else handle


def _note_left(sessions: Path, before: dict, folder: Path) -> None:
    """What a failed job changed in the sessions folder, written to ``{folder}.left`` for the
    harness; a session it kept (a sweep's frames) is read back whole and then set aside."""
    for entry in sorted(set(snapshot(sessions)) - set(before)):
        path = sessions / entry
        if "/" not in entry and path.is_dir() and (path / "manifest.json").is_file():
            read_back(path)
    left = changed_entries(before, snapshot(sessions))
    (folder.parent / f"{folder.name}.left").write_text("".join(f"{name}\n" for name in left))


def markup_cases() -> list[Case]:
    return []


def vanished_page_cases() -> list[Case]:
    return []
