"""The console's token gate (SPEC §7): with a token, only browsers that present it get the console."""

from __future__ import annotations

import http.client

import pytest

from app.console import launch
from app.headless import CHROMIUM, chromium, click, open_console, wait_text
from core.errors import InputError

TOKEN = "correct-horse-battery"


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    console = launch(port=0, sessions_dir=tmp_path_factory.mktemp("sessions"), time_scale=0.0, token=TOKEN)
    yield console
    console.close()


def _get(console, path: str, cookie: str | None = None) -> http.client.HTTPResponse:
    connection = http.client.HTTPConnection(console.gate.host, console.gate.port, timeout=10)
    connection.request("GET", path, headers={"Cookie": cookie} if cookie else {})
    return connection.getresponse()


def test_requests_without_the_token_are_refused(console):
    for path, cookie in (("/", None), ("/?token=wrong", None), ("/index.html", "probecal_token=wrong")):
        response = _get(console, path, cookie)
        assert response.status == 401
        assert b"needs its token" in response.read()


def test_the_token_sets_a_cookie_that_opens_the_page(console):
    response = _get(console, f"/?token={TOKEN}")
    assert response.status == 302 and response.getheader("Location") == "/"
    cookie = response.getheader("Set-Cookie")
    assert cookie.startswith(f"probecal_token={TOKEN};") and "HttpOnly" in cookie
    page = _get(console, "/", f"probecal_token={TOKEN}")
    assert page.status == 200 and b"<html" in page.read().lower()
    assert console.url == f"http://127.0.0.1:{console.gate.port}/?token={TOKEN}"


def test_a_browser_with_the_token_drives_the_console(console):
    if not CHROMIUM.is_file():
        pytest.skip("Debian chromium is not installed")
    with chromium() as browser:
        page = open_console(browser, console.gate.port, token=TOKEN)
        click(page, "Connect")
        wait_text(page, "Connected to the simulated UR3")


def test_an_open_address_needs_a_token(tmp_path):
    with pytest.raises(InputError, match="without --token"):
        launch(host="0.0.0.0", port=0, sessions_dir=tmp_path)
