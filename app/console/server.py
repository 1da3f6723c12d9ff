"""Starting the console: a viser server behind the gate (``gate``) on the address asked for, the
rig the command line names, and the console on both (``probecal serve``)."""

from __future__ import annotations

import contextlib
import errno
import io
import ipaddress
import socket
import time
from pathlib import Path

import viser

from probecal.app.console import heartbeat, wakeup
from probecal.app.console.controller import Console
from probecal.app.console.gate import Gate, checked_token, gated, host_names, new_token
from probecal.app.console.updates import guard_updates
from probecal.app.rigspec import make_rig
from probecal.app.tracked import TrackedSpec
from probecal.core.acquisition.igtl import IgtlPublisher
from probecal.core.errors import InputError
from probecal.core.geometry.probe import Probe
from probecal.core.robot.safety import Workspace

PUBLISH_HOST = "127.0.0.1"  # OpenIGTLink has no authentication: it is served on loopback only


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
    except (OSError, ValueError):
        return False


def _in_use(host: str, port: int, option: str = "--port") -> InputError:
    return InputError(None, f"{option} {port}: the port is in use on {host} (another console?); choose another")


def _check_listenable(host: str, port: int, option: str = "--port") -> None:
    """InputError naming ``--host`` or the port's ``option`` unless a server can listen on
    ``host:port`` now: viser, given a name that does not resolve, an address of another machine or
    a port in use, fails in its own thread and leaves the console waiting for ever."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (OSError, UnicodeError) as exc:
        raise InputError(None, f"--host {host}: not an address nor a name that resolves ({exc})") from None
    with socket.socket(family, kind, proto) as trial:
        trial.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as viser's own server does
        try:
            trial.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise _in_use(host, port, option) from None
            raise InputError(None, f"--host {host}: cannot listen on {address[0]} ({exc.strerror})") from None


class ConsoleServer(viser.ViserServer):
    """viser's server without its share tunnel, with a heartbeat: a console drives a robot, so no
    page may open a public address to it (viser serves a share request from any connected page,
    its button only hidden: this server refuses every one and counts them), and a page that stops
    answering counts as gone (``heartbeat``)."""

    share_requests_refused = 0

    def __init__(self, host: str, port: int) -> None:
        super().__init__(host=host, port=port, label="probecal", verbose=False)
        self.heartbeat = heartbeat.Heartbeat(self)  # a page that stops answering is a page gone (dead-man rule)

    def request_share_url(self, verbose: bool = True) -> str | None:
        self.share_requests_refused += 1
        return None

    def stop(self) -> None:
        self.heartbeat.stop()
        super().stop()


def _gated_server(host: str, port: int, gate: Gate) -> ConsoleServer:
    """A viser server on ``host:port`` (0: a free port) whose every request passes ``gate``.
    InputError if ``host`` cannot be listened on or ``port`` is taken (viser would silently move
    to the next one)."""
    _check_listenable(host, port)
    gate.port = port or _free_port(host)
    wakeup.install()  # the console's job threads update the page
    with gated(gate), contextlib.redirect_stdout(io.StringIO()):  # viser's banner would print a tokenless address
        server = ConsoleServer(host, gate.port)
    if server.get_port() != gate.port:
        if port:
            server.stop()
            raise _in_use(host, port)
        gate.port = server.get_port()  # the free port was taken meanwhile; requests so far were refused
    guard_updates(server)
    return server


def launch(host: str = "127.0.0.1", port: int = 8080, robot: str = "sim", image: str = "sim",
           sessions_dir: str | Path = "sessions", time_scale: float = 0.25, seed: int = 0,
           token: str | None = None, workspace: Workspace | None = None, publish: int | None = None,
           latency_s: float = 0.0, spacing_mm: tuple[float, float] | None = None,
           start_depth_mm: float | None = None, probe: Probe | None = None, unattended: bool = False,
           tracked: TrackedSpec | None = None) -> Console:
    """Start the console without blocking (port 0 picks a free port). ``time_scale`` is wall
    seconds per robot second for the simulated robot (0.25: four times faster than real).
    ``publish`` is an OpenIGTLink port on loopback on which 3D Slicer receives the calibration
    (ImageToProbe) and every frame shown, placed by ProbeToReference.

    The console moves a robot, so it answers only its own page (``app.console.gate``); off loopback it
    needs a ``token`` (one is made when none is given) that browsers present once in the printed
    address and then in a cookie. A sweep stops at its next pose when the last page closes, unless
    ``unattended`` (the dead-man rule, ``Console``). ``tracked``: a probe probecal does not move,
    guided instead of swept (``app.console.guided``)."""
    exposed = not _is_loopback(host)
    if token is None and exposed:
        token = new_token()
    gate = Gate(host_names(host), None if token is None else checked_token(token, "the command line"))
    if publish is not None:
        _check_listenable(PUBLISH_HOST, publish, "--publish")
    server = _gated_server(host, port, gate)
    try:
        rig = make_rig(robot, image, seed, time_scale, workspace, latency_s, spacing_mm, start_depth_mm, probe)
        console = Console(server, rig, Path(sessions_dir), gate, unattended, tracked)
    except BaseException:
        server.stop()
        raise
    if publish is not None:
        try:
            console.publisher = IgtlPublisher(publish, PUBLISH_HOST)
        except OSError as exc:
            console.close()
            raise InputError(None, f"--publish {publish}: {exc.strerror}") from None
    return console


def serve(host: str = "127.0.0.1", port: int = 8080, robot: str = "sim", image: str = "sim",
          sessions_dir: str | Path = "sessions", time_scale: float = 0.25, token: str | None = None,
          workspace: Workspace | None = None, publish: int | None = None, latency_s: float = 0.0,
          spacing_mm: tuple[float, float] | None = None, start_depth_mm: float | None = None,
          probe: Probe | None = None, unattended: bool = False, tracked: TrackedSpec | None = None) -> None:
    """Start the console and block until interrupted."""
    console = launch(host, port, robot, image, sessions_dir, time_scale, token=token, workspace=workspace,
                     publish=publish, latency_s=latency_s, spacing_mm=spacing_mm, start_depth_mm=start_depth_mm,
                     probe=probe, unattended=unattended, tracked=tracked)
    print(f"probecal console on {console.url} (Ctrl+C to stop)", flush=True)
    if console.publisher is not None:
        print(f"OpenIGTLink for 3D Slicer on port {console.publisher.port}: ImageToProbe, Image, ProbeToReference",
              flush=True)
    try:
        while True:
            time.sleep(1.0)
    finally:
        console.close()
