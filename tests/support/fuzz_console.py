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

import json
import math
import shutil
import sys
from html.parser import HTMLParser
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


MARKUP: list[str] = [
    "<img src=x onerror=window.__pwned=1>", "<iframe srcdoc=\"<script>top.document.title='PWNED'<&#47;script>\">",
    "<script>window.__pwned=1</script>", "<a href=javascript:alert(1)>x</a>", "[x](javascript:alert(1))",
    "<style>*{display:none}</style>", "\"><svg onload=alert(1)>", "&lt;b&gt;&amp;", "{0}{1}%s", "</div></table><b>",
    "<!--", "\u202ebidi", "<img src onerror=X>",
]
"""Texts that run, restyle or break a page when a page takes them as HTML or markdown."""
MARKUP_SOURCES = ("calibration folder", "volume folder", "manifest kind", "frame file", "wire name")
"""Where text from outside reaches the console: a session folder's name, a manifest's field, a file
name an error quotes, a phantom's wire name in Check phantom's table."""
PAGE_TAGS = {"div", "span", "p", "table", "thead", "tbody", "tr", "td", "th"}
PAGE_ATTRIBUTES = {"style", "class", "title"}
"""The tags and attributes the console's own templates write (``app/console``): any other in a
box came from outside."""


def markup_cases() -> list[Case]:
    """Each markup text through each outside source into the console, every box it shows then
    parsed: only the console's own tags and attributes."""
    return [Case(f"console markup via {source}: {short(text)}", ("console", source), ("cal", "vol"),
                 run=markup_shown(source, text)) for source in MARKUP_SOURCES for text in MARKUP]


def markup_shown(source: str, text: str) -> Runner:
    """``text`` put in ``source`` of a session, the session loaded (and, for a wire name,
    calibrated and checked); AssertionError (a traceback: the harness's failure) when a box of the
    page holds a tag or attribute the console does not write."""
    def run(_argv: list[str], folder: Path) -> int:
        from probecal.app.console.server import launch

        sessions = folder.parent / f"{folder.name}.sessions"
        sessions.mkdir()
        name = _hostile_session(source, text, folder, sessions)
        console = launch(port=0, sessions_dir=sessions, time_scale=0.0)
        try:
            console.panel.session_path.value = name
            _ran(console, console.load_session)
            if source == "wire name" and console.calibration is not None:
                _ran(console, console.check_phantom)
            status = console.panel.status.text
            for box, content in _boxes(console):
                _only_page_markup(box, content)
        finally:
            console.close()
            shutil.rmtree(sessions, ignore_errors=True)
        if " failed: " in status:
            print(f"probecal: error: {status}", file=sys.stderr)
            return 2
        return 0
    return run


def _hostile_session(source: str, text: str, folder: Path, sessions: Path) -> str:
    """A session in ``sessions`` carrying ``text`` in ``source``; its folder's name."""
    name = text.replace("/", "\u2215").replace("\x00", "") if source.endswith("folder") else "s"
    if source == "volume folder":
        shutil.copytree(folder / "vol", sessions / name)
        return name
    shutil.copytree(folder / "cal", sessions / name)
    shutil.copy(sessions / name / "truth.json", sessions / name / "calibration.json")
    if source == "manifest kind":
        _edit_json(sessions / name / "manifest.json", lambda m: m.update(kind=text))
    elif source == "frame file":
        records = sessions / name / "records.jsonl"
        records.write_text(records.read_text().replace('"frames/000000.png"', json.dumps(f"frames/{text}.png"), 1))
    elif source == "wire name":
        _edit_json(sessions / name / "phantom.json", lambda p: p["layers"][0]["wires"][0].update(name=text))
    return name


def _edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _ran(console, job) -> None:
    job()
    console.wait(JOB_S)


def _boxes(console):
    """Every text box of the console's panel, by name, with the HTML it holds."""
    from probecal.app.console.text import TextBox

    return [(name, value.content) for name, value in vars(console.panel).items() if isinstance(value, TextBox)]


class _PageMarkup(HTMLParser):
    def __init__(self, box: str):
        super().__init__(convert_charrefs=True)
        self.box = box

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        foreign = {name for name, _ in attrs} - PAGE_ATTRIBUTES
        if tag not in PAGE_TAGS or foreign:
            raise AssertionError(f"the console's {self.box} box holds <{tag} {' '.join(sorted(foreign))}>: "
                                 "markup from outside")

    def handle_comment(self, data: str) -> None:
        raise AssertionError(f"the console's {self.box} box holds a comment: markup from outside")


def _only_page_markup(box: str, content: str) -> None:
    parser = _PageMarkup(box)
    parser.feed(content)
    parser.close()


VANISHINGS = ("frozen", "silent after its close", "not reading")
"""How a page goes without a word: its network frozen (``vanishing.FreezingRelay``), a close frame
and then nothing, or a page that stops reading what it is sent (and goes on sending)."""
SWEEPS = {"start": ("stop at every pose", "continuous"), "scan": ("stop at every pose",)}
NOTICED_S = 15.0
"""The most a case waits for the console to notice its page gone: the heartbeat takes 1.25 s; the
rest is a busy machine."""


def vanished_page_cases() -> list[Case]:
    """A sweep started from a page that then vanishes, every way, for every sweep the console runs."""
    return [Case(f"console page {how}: {job} ({motion})", ("console", job), (), run=page_vanished(how, job, motion))
            for how in VANISHINGS for job, motions in SWEEPS.items() for motion in motions]


def page_vanished(how: str, job: str, motion: str) -> Runner:
    """``job`` clicked from a page that vanishes ``how`` once 2 frames are recorded: the sweep must
    stop (exit 2, its status as the one line) long before its plan's end, and what it kept must
    read back; AssertionError (a traceback) when it runs on."""
    def run(_argv: list[str], folder: Path) -> int:
        from probecal.app.console.server import launch
        from tests.support.page import RawPage
        from tests.support.vanishing import FreezingRelay
        from tests.support.waiting import recorded_frames, wait_until

        sessions = folder.parent / f"{folder.name}.sessions"
        sessions.mkdir()
        console = launch(port=0, sessions_dir=sessions, time_scale=0.25)
        panel = console.panel
        panel.poses.value, panel.frames_per_pass.value, panel.speed.value = 40, 40, 0.3
        panel.motion.value = motion
        try:
            with FreezingRelay(("127.0.0.1", console.server.get_port())) as relay, \
                    RawPage(console, via=relay.address) as page:
                page.click(panel.connect)
                wait_until(lambda: console.rig.robot.connected and not console.busy, "connected", JOB_S)
                page.click(getattr(panel, job))
                session = wait_until(lambda: next(sessions.glob("*/records.jsonl"), None), "a session", JOB_S).parent
                wait_until(lambda: recorded_frames(session) >= 2, "frames recorded", JOB_S)
                if how == "silent after its close":
                    page.send_close_frame()
                relay.deafen() if how == "not reading" else relay.freeze()
                wait_until(lambda: not console.busy, "the sweep stopped", NOTICED_S)
                relay.close()
            status = panel.status.text
            if "Stopped: no console page was open" not in status:
                raise AssertionError(f"the sweep ran on with no page to watch it: {status}")
            read_back(session)
        finally:
            console.close()
            shutil.rmtree(sessions, ignore_errors=True)
        print(f"probecal: error: {status}", file=sys.stderr)
        return 2
    return run
