"""The console answers only its own page (design §7, issue 13): Host, Origin and token are checked on
every HTTP request and websocket handshake, in both modes, and the console opens no other port."""

from __future__ import annotations

import http.client
import os
import shutil
import socket
import subprocess
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from probecal.app.console.gate import COOKIE, TOKEN_ENV, read_token
from probecal.app.console.panel import session_html, surface_html
from probecal.app.console.server import launch
from probecal.app.headless import CHROMIUM, chromium, click, new_tab, open_console, wait_text
from probecal.app.report import Verdict
from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
from probecal.core.errors import InputError
from tests.support.cli import PROBECAL, run_cli
from tests.support.refusals import assert_one_line_error
from tests.support.waiting import wait_until

TOKEN = "correct-horse-battery-staple"
SHARE_ICON = "svg.tabler-icon-share"


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening_ports() -> set[int]:
    """TCP ports this process listens on (from /proc: its socket inodes in LISTEN state)."""
    inodes = set()
    for fd in Path("/proc/self/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # 0A: LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


@pytest.fixture(scope="module")
def open_console_server(tmp_path_factory):
    console = launch(port=0, sessions_dir=tmp_path_factory.mktemp("sessions"), time_scale=0.0)
    yield console
    console.close()


@pytest.fixture(scope="module")
def token_console(tmp_path_factory):
    before = _listening_ports()
    console = launch(port=0, sessions_dir=tmp_path_factory.mktemp("sessions"), time_scale=0.0, token=TOKEN)
    console.opened_ports = _listening_ports() - before
    yield console
    console.close()


def _get(port: int, path: str = "/", **headers: str) -> tuple[int, http.client.HTTPResponse]:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    connection.request("GET", path, headers={"Host": f"127.0.0.1:{port}", **headers})
    response = connection.getresponse()
    response.read()
    return response.status, response


def _handshake(port: int, origin: str | None, host: str | None = None, cookie: str | None = None) -> int:
    """The HTTP status of a websocket handshake with the console (101: accepted)."""
    headers = {"Cookie": cookie} if cookie else {}
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    try:
        with connect(f"ws://{host or f'127.0.0.1:{port}'}/", sock=sock, origin=origin, additional_headers=headers,
                     open_timeout=10, subprotocols=["viser-v0"]):
            return 101
    except InvalidStatus as exc:
        return exc.response.status_code


@pytest.mark.parametrize("mode", ["open", "token"])
def test_a_foreign_origin_websocket_is_refused_in_both_modes(mode, open_console_server, token_console):
    console = open_console_server if mode == "open" else token_console
    port, cookie = console.server.get_port(), f"{COOKIE}={TOKEN}" if mode == "token" else None
    own = f"http://127.0.0.1:{port}"
    assert _handshake(port, own, cookie=cookie) == 101
    for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", "null", f"{own}.evil.example",
                   f"https://evil.example:{port}", "file://"):
        assert _handshake(port, origin, cookie=cookie) == 403, origin
    assert _handshake(port, None, cookie=cookie) == 403  # browsers always send an Origin


@pytest.mark.parametrize("mode", ["open", "token"])
def test_a_repeated_header_is_a_bad_request_in_both_modes(mode, open_console_server, token_console):
    """Two Upgrade (or Cookie) headers made the gate's own reading of them fail: HTTP 500."""
    port = (open_console_server if mode == "open" else token_console).server.get_port()
    for name, values in (("Upgrade", ["websocket", "websocket"]), ("Cookie", [f"{COOKIE}={TOKEN}", "a=b"])):
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        connection.putrequest("GET", "/", skip_host=True)
        connection.putheader("Host", f"127.0.0.1:{port}")
        for value in values:
            connection.putheader(name, value)
        connection.endheaders()
        response = connection.getresponse()
        assert response.status == 400 and name.encode() in response.read(), name
        connection.close()


@pytest.mark.parametrize("mode", ["open", "token"])
def test_a_foreign_host_is_refused_in_both_modes(mode, open_console_server, token_console):
    """DNS rebinding: a page at evil.example resolved to 127.0.0.1 sends Host: evil.example."""
    console = open_console_server if mode == "open" else token_console
    port = console.server.get_port()
    cookie = {"Cookie": f"{COOKIE}={TOKEN}"} if mode == "token" else {}
    assert _get(port, **cookie)[0] == 200
    assert _get(port, Host=f"localhost:{port}", **cookie)[0] == 200
    for host in (f"evil.example:{port}", "evil.example", f"127.0.0.1:{port + 1}", "", f"127.0.0.1.evil.example:{port}"):
        assert _get(port, Host=host, **cookie)[0] == 421, host
        if host:
            assert _handshake(port, f"http://{host}", host=host, cookie=cookie.get("Cookie")) == 421, host
    assert _get(port, Origin="http://evil.example", **cookie)[0] == 403


def test_the_token_console_opens_one_port_and_it_needs_the_token(token_console):
    port = token_console.server.get_port()
    assert token_console.opened_ports == {port}
    assert _get(port)[0] == 401
    assert _handshake(port, f"http://127.0.0.1:{port}") == 401
    status, response = _get(port, f"/?token={TOKEN}")
    assert status == 302 and response.getheader("Location") == "/"
    cookie = response.getheader("Set-Cookie")
    assert cookie.startswith(f"{COOKIE}={TOKEN};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    assert _get(port, Cookie=f"{COOKIE}={TOKEN}")[0] == 200
    assert token_console.url == f"http://127.0.0.1:{port}/?token={TOKEN}"


def test_wrong_tokens_lock_the_guesser_out_for_longer_each_time(token_console):
    port = token_console.server.get_port()
    assert _get(port, "/?token=wrong-guess-number-1")[0] == 401
    status, response = _get(port, f"/?token={TOKEN}")  # even the right token waits out the lockout
    assert status == 429 and int(response.getheader("Retry-After")) >= 1
    gate = token_console.gate
    count, until = gate._lockouts["127.0.0.1"]
    gate._lockouts["127.0.0.1"] = (count, 0.0)  # the lockout has passed
    assert _get(port, "/?token=wrong-guess-number-2")[0] == 401
    assert gate._lockouts["127.0.0.1"][0] == count + 1
    gate._lockouts["127.0.0.1"] = (count + 1, 0.0)
    assert _get(port, f"/?token={TOKEN}")[0] == 302
    assert "127.0.0.1" not in gate._lockouts


def test_tokens_come_from_a_file_or_the_environment_and_must_be_long(tmp_path, monkeypatch):
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    assert read_token(None) is None
    monkeypatch.setenv(TOKEN_ENV, TOKEN)
    assert read_token(None) == TOKEN
    (tmp_path / "token").write_text(f"{TOKEN}x\n")
    assert read_token(tmp_path / "token") == TOKEN + "x"
    for bad, problem in (("short", "at least 16"), ("x" * 20 + "<script>", "only letters"), ("", "at least 16")):
        (tmp_path / "token").write_text(bad)
        with pytest.raises(InputError, match=problem):
            read_token(tmp_path / "token")
    with pytest.raises(InputError, match="not found"):
        read_token(tmp_path / "missing")
    with pytest.raises(InputError, match="at least 16"):
        launch(port=0, sessions_dir=tmp_path, token="short")


@pytest.mark.slow
def test_serve_refuses_a_short_token_and_a_port_in_use_and_makes_a_token_off_loopback(tmp_path):
    env = {**os.environ, TOKEN_ENV: "short"}
    result = subprocess.run([str(PROBECAL), "serve", "--port", "0"], capture_output=True, text=True, env=env,
                            timeout=120)
    assert_one_line_error(result, TOKEN_ENV, "at least 16")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert_one_line_error(run_cli("serve", "--port", port, "--sessions", tmp_path), f"port {port}", "in use")
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
    proc = subprocess.Popen([str(PROBECAL), "serve", "--host", "0.0.0.0", "--port", "0", "--sessions", tmp_path],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert "probecal console on http://0.0.0.0:" in line, (line, proc.stderr.read() if proc.poll() else "")
        token = line.split("?token=")[1].split()[0]
        assert len(token) >= 16
    finally:
        proc.terminate()
        proc.wait(timeout=30)


class _EvilPage(BaseHTTPRequestHandler):
    """A page on another origin that tries to drive the console over its websocket."""

    console_port = 0

    def do_GET(self):
        body = f"""<html><body><script>
            const ws = new WebSocket("ws://127.0.0.1:{self.console_port}", ["viser-v0"]);
            ws.onopen = () => {{ document.title = "opened"; }};
            ws.onerror = () => {{ document.title = "refused"; }};
        </script></body></html>""".encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.mark.slow
@pytest.mark.browser  # Chromium of its own, not the browser fixture
def test_a_page_from_another_origin_cannot_drive_the_console_in_a_browser(open_console_server):
    if not CHROMIUM.is_file():
        pytest.skip("Debian chromium is not installed")
    console = open_console_server
    _EvilPage.console_port = console.server.get_port()
    evil = ThreadingHTTPServer(("127.0.0.2", 0), _EvilPage)
    threading.Thread(target=evil.serve_forever, daemon=True).start()
    try:
        with chromium() as browser:
            page = new_tab(browser)
            page.goto(f"http://127.0.0.2:{evil.server_address[1]}/")
            page.wait_for_function("document.title !== ''", timeout=30_000)
            assert page.title() == "refused"
            assert not console.server.get_clients()  # the foreign page never became a client
            own = open_console(browser, console.server.get_port())
            click(own, "Connect")
            wait_text(own, "Connected to the simulated UR3")
    finally:
        evil.shutdown()
        evil.server_close()


HOSTILE_NAME = '<img src=x onerror="document.title=1">'


def _load(console, folder: str) -> str:
    console.panel.session_path.value = folder
    assert console.load_session()
    console.wait()
    return console.panel.status.text


def test_the_folder_field_opens_only_sessions_inside_the_sessions_folder(tmp_path):
    sessions, outside = tmp_path / "sessions", tmp_path / "outside"
    simulate_calibration(outside, n_poses=3, seed=5, noise="none")
    simulate_calibration(sessions / HOSTILE_NAME, n_poses=3, seed=5, noise="none")
    (sessions / "link").symlink_to(outside)
    console = launch(port=0, sessions_dir=sessions, time_scale=0.0)
    try:
        for folder in (str(outside), "../outside", "link", f"{sessions}/../outside", "/etc", ""):
            status = _load(console, folder)
            assert "Load session failed" in status and console.calibration_session is None, (folder, status)
        status = _load(console, HOSTILE_NAME)
        assert "Loaded calibration session" in status and HOSTILE_NAME in status  # shown as typed
        assert "<img" not in console.panel.status.content and "&lt;img" in console.panel.status.content
        assert console.calibration_session == sessions / HOSTILE_NAME
        assert _load(console, str(sessions / HOSTILE_NAME)).startswith(status[:40])
    finally:
        console.close()


def test_load_refuses_saved_results_that_link_out_of_the_session(tmp_path):
    """A calibration.json, a reconstruction folder or a file of it that is a link out of the
    session is refused in one line, as the command line refuses links out; nothing is read
    through it, and the link stays as it was."""
    sessions, outside = tmp_path / "sessions", tmp_path / "outside"
    cal = simulate_calibration(sessions / "cal", n_poses=3, seed=5, noise="none")
    vol = simulate_volume(sessions / "vol", seed=5, noise="none", n_frames=4)
    outside.mkdir()
    shutil.copy(cal.path / "truth.json", outside / "calibration.json")
    (cal.path / "calibration.json").symlink_to(outside / "calibration.json")
    (vol.path / "reconstruction").symlink_to(outside, target_is_directory=True)
    (outside / "report.json").write_text('{"frames": 1, "surface_points": 1}')
    console = launch(port=0, sessions_dir=sessions, time_scale=0.0)
    try:
        for folder, link in (("cal", "calibration.json"), ("vol", "reconstruction")):
            status = _load(console, folder)
            assert f"Load session failed: {sessions / folder}: '{link}' leads outside" in status, status
            assert (sessions / folder / link).is_symlink()
        assert console.calibration is None and console.view.reconstruction is None
    finally:
        console.close()


def test_text_from_files_is_escaped_in_the_console_panels():
    hostile = Path(f"/tmp/{HOSTILE_NAME}/{HOSTILE_NAME}")
    verdict = Verdict(None, HOSTILE_NAME, 1.0)
    for shown in (session_html(hostile), surface_html({"surface_points": 1, "frames": 1}, verdict, hostile)):
        assert "<img" not in shown and "&lt;img" in shown


@pytest.mark.slow
@pytest.mark.browser  # Chromium of its own, not the browser fixture
def test_a_browser_with_the_token_drives_the_console(token_console):
    if not CHROMIUM.is_file():
        pytest.skip("Debian chromium is not installed")
    with chromium() as browser:
        page = open_console(browser, token_console.server.get_port(), token=TOKEN)
        assert "token" not in page.url  # redirected to the bare page, the token kept in a cookie
        click(page, "Connect")
        wait_text(page, "Connected to the simulated UR3")


@pytest.mark.browser  # Chromium of its own, not the browser fixture
def test_no_page_can_open_a_public_share_tunnel(open_console_server):
    """viser opens a public tunnel to the server on a share request from any connected page; the
    console has no Share button and refuses the request."""
    import msgspec.msgpack

    console = open_console_server
    port = console.server.get_port()
    refused = console.server.share_requests_refused
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    with connect(f"ws://127.0.0.1:{port}/", sock=sock, origin=f"http://127.0.0.1:{port}", open_timeout=10,
                 subprotocols=[f"viser-v{viser.__version__}"]) as ws:  # an admitted page's client
        ws.send(msgspec.msgpack.encode({"type": "ShareUrlRequest"}))
        wait_until(lambda: console.server.share_requests_refused > refused, "the share request refused")
    assert console.server._share_tunnel is None  # viser's tunnel slot stays empty
    plain = viser.ViserServer(host="127.0.0.1", port=_free_loopback_port(), verbose=False)  # viser's own page
    try:
        with chromium() as browser:
            page = browser.new_page()
            page.goto(f"http://127.0.0.1:{plain.get_port()}/")
            page.locator(SHARE_ICON).first.wait_for(timeout=60_000)  # how viser shows its Share button
            page = open_console(browser, port)
            wait_text(page, "Connect")
            assert page.locator(SHARE_ICON).count() == 0
    finally:
        plain.stop()
