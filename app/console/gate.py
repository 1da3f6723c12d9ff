"""The console's gate (design §7): the console moves a robot, so it answers only its own page.

Every HTTP request and websocket handshake reaches viser only through :meth:`Gate.check`:

- **Host** must name this console (a loopback name, or the bound address and the machine's own
  names when exposed) and its port: a DNS-rebinding page that resolves ``evil.example`` to
  127.0.0.1 sends ``Host: evil.example`` and is refused.
- **Origin**, when a browser sends one (always on a websocket, on every cross-site request), must
  be this console's own ``http://host:port``: another page open in the operator's browser cannot
  drive it. A websocket handshake without an Origin is refused.
- **Token** (required off loopback, optional on it): every request presents it, as ``?token=...``
  once (the address ``probecal serve`` prints; the browser is redirected to the bare page with the
  token in an HttpOnly, SameSite=Strict cookie) and then in that cookie. Wrong guesses from one
  address are refused for a time that doubles with each one.

The check runs inside viser's own server (its ``process_request``), so the console opens one
port, and nothing behind it is reachable without passing the gate.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import os
import secrets
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from http.cookies import CookieError, SimpleCookie
from pathlib import Path
from unittest import mock
from urllib.parse import parse_qs, urlsplit

import websockets.asyncio.server
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from probecal.core.errors import InputError
from probecal.core.io.files import read_bytes

COOKIE = "probecal_token"
TOKEN_ENV = "PROBECAL_TOKEN"
MIN_TOKEN_LENGTH = 16
FIRST_LOCKOUT_S = 0.5
MAX_LOCKOUT_S = 30.0
SINGLE_HEADERS = ("Upgrade", "Cookie")  # read as one value: websockets' Headers.get raises on a repeated one
MAX_GUESSERS = 4096  # addresses remembered; beyond, long-expired lockouts are forgotten
LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})


def new_token() -> str:
    """A fresh random token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def checked_token(token: str, source: str) -> str:
    """``token`` if it is long enough and URL-safe, else InputError naming where it came from."""
    if len(token) < MIN_TOKEN_LENGTH:
        raise InputError(None, f"the token from {source} has {len(token)} characters; at least "
                               f"{MIN_TOKEN_LENGTH} are needed")
    if not all(c.isalnum() or c in "-_.~" for c in token):
        raise InputError(None, f"the token from {source} may hold only letters, digits and - _ . ~")
    return token


def read_token(token_file: str | Path | None) -> str | None:
    """The token from ``token_file`` (its first line) or from ``$PROBECAL_TOKEN``; None if neither
    is given. Never from the command line, where every local user sees it in ``ps``."""
    if token_file is not None:
        path = Path(token_file)
        try:
            lines = read_bytes(path).decode("utf-8").splitlines()
        except UnicodeDecodeError as exc:
            raise InputError(path, f"the token file is not UTF-8 text ({exc.reason})") from None
        return checked_token(lines[0].strip() if lines else "", str(path))
    value = os.environ.get(TOKEN_ENV)
    return None if value is None else checked_token(value.strip(), TOKEN_ENV)


def host_names(bind: str) -> frozenset[str]:
    """The names a browser may use to reach a console bound to ``bind``: loopback names, the bound
    address and, for a wildcard bind, this machine's name and addresses."""
    names = set(LOOPBACK_NAMES) | {bind.lower()}
    if bind in ("0.0.0.0", "::", ""):
        hostname = socket.gethostname()
        names |= {hostname.lower(), socket.getfqdn().lower()}
        with contextlib.suppress(OSError):
            names |= {str(info[4][0]) for info in socket.getaddrinfo(hostname, None)}
    return frozenset(f"[{n}]" if ":" in n and not n.startswith("[") else n for n in names)


def _reply(status: http.HTTPStatus, text: str, headers: dict[str, str] | None = None) -> Response:
    body = f"probecal: {text}\n".encode()
    all_headers = Headers(**(headers or {}))
    all_headers["Content-Type"] = "text/plain; charset=utf-8"
    all_headers["Content-Length"] = str(len(body))
    all_headers["Connection"] = "close"
    return Response(status.value, status.phrase, all_headers, body)


@dataclass
class Gate:
    """Host, Origin and token checks for one console (see the module docstring)."""

    names: frozenset[str]
    token: str | None = None
    port: int = 0  # set once bound
    _lockouts: dict[str, tuple[int, float]] = field(default_factory=dict)  # address -> (wrong guesses, until)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def _host_ok(self, host: str) -> bool:
        name, sep, port = host.lower().rpartition(":")
        return bool(sep) and name in self.names and port == str(self.port)

    def _origin_ok(self, origin: str, host: str) -> bool:
        url = urlsplit(origin)
        return url.scheme in ("http", "https") and url.netloc.lower() == host.lower() and not url.path

    @staticmethod
    def _token_ok(presented: str, token: str) -> bool:
        return hmac.compare_digest(presented.encode(), token.encode())

    def _locked_for(self, address: str) -> float:
        with self._lock:
            _, until = self._lockouts.get(address, (0, 0.0))
            return max(0.0, until - time.monotonic())

    def _guessed(self, address: str, right: bool) -> None:
        with self._lock:
            if right:
                self._lockouts.pop(address, None)
                return
            now = time.monotonic()
            if len(self._lockouts) >= MAX_GUESSERS:  # forget guessers whose lockout ran out long ago
                self._lockouts = {a: v for a, v in self._lockouts.items() if v[1] > now - MAX_LOCKOUT_S}
            count, _ = self._lockouts.get(address, (0, 0.0))
            self._lockouts[address] = (count + 1, now + min(FIRST_LOCKOUT_S * 2**count, MAX_LOCKOUT_S))

    def check(self, address: str, request: Request) -> Response | None:
        """None to let ``request`` (from ``address``) through to the console, else the refusal."""
        headers = request.headers
        hosts = headers.get_all("Host")
        host = hosts[0] if len(hosts) == 1 else None
        if not host or not self._host_ok(host):
            return _reply(http.HTTPStatus.MISDIRECTED_REQUEST, f"this console does not answer to Host {host!r}")
        repeated = next((name for name in SINGLE_HEADERS if len(headers.get_all(name)) > 1), None)
        if repeated is not None:
            return _reply(http.HTTPStatus.BAD_REQUEST, f"the {repeated} header is sent more than once")
        upgrade = headers.get("Upgrade", "").lower() == "websocket"
        origins = headers.get_all("Origin")
        origin = origins[0] if origins else None
        if (len(origins) > 1 or (origin is None and upgrade)
                or (origin is not None and not self._origin_ok(origin, host))):
            return _reply(http.HTTPStatus.FORBIDDEN,
                          f"requests from {origin or 'an unknown page'} may not drive this console")
        token = self.token
        if token is None:
            return None
        url = urlsplit(request.path)
        query = parse_qs(url.query).get("token", [None])[0]
        cookie = None
        with contextlib.suppress(CookieError):
            jar = SimpleCookie(headers.get("Cookie", ""))
            cookie = jar[COOKIE].value if COOKIE in jar else None
        presented = [t for t in (query, cookie) if t is not None]
        if not presented:
            return _reply(http.HTTPStatus.UNAUTHORIZED,
                          "this console needs its token; open the address probecal serve printed")
        wait = self._locked_for(address)
        if wait > 0:
            return _reply(http.HTTPStatus.TOO_MANY_REQUESTS, f"too many wrong tokens; try again in {wait:.1f} s",
                          {"Retry-After": str(int(wait) + 1)})
        right = any(self._token_ok(t, token) for t in presented)
        self._guessed(address, right)
        if not right:
            return _reply(http.HTTPStatus.UNAUTHORIZED, "wrong token; open the address probecal serve printed")
        if query is not None and not upgrade:
            return _reply(http.HTTPStatus.FOUND, "opening the console",
                          {"Location": url.path or "/",
                           "Set-Cookie": f"{COOKIE}={token}; HttpOnly; SameSite=Strict; Path=/"})
        return None

    def process_request(self, inner):
        """Wrap viser's ``process_request`` so that every request passes :meth:`check` first."""

        def process(connection, request: Request):
            refusal = self.check(str(connection.remote_address[0]), request)
            if refusal is not None:
                return refusal
            return inner(connection, request) if inner is not None else None

        return process


_install_lock = threading.Lock()


@contextlib.contextmanager
def gated(gate: Gate) -> Iterator[None]:
    """While active, websocket servers started by viser check every request with ``gate``.

    viser builds its server with ``websockets.asyncio.server.serve(..., process_request=...)`` in
    its own thread while ``viser.ViserServer(...)`` waits for it; wrapping ``serve`` for exactly
    that time puts the gate in front of the first request the console can receive."""
    original = websockets.asyncio.server.serve

    def serve(*args, **kwargs):
        kwargs["process_request"] = gate.process_request(kwargs.get("process_request"))
        return original(*args, **kwargs)

    with _install_lock, mock.patch.object(websockets.asyncio.server, "serve", serve):
        yield
