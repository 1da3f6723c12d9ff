"""A token gate in front of the console (SPEC §7): the console moves a robot, so when it is exposed
beyond loopback every connection must present the shared token.

The viser server listens on loopback only; the gate listens on the public address and forwards
a connection only when its first request carries the token: as ``?token=...`` (the address
``probecal serve`` prints; the browser is then redirected to the bare page with the token in an
HttpOnly cookie) or in that cookie (the page's own requests and its websocket).
"""

from __future__ import annotations

import asyncio
import hmac
import threading
from http.cookies import SimpleCookie
from urllib.parse import parse_qs, urlsplit

COOKIE = "probecal_token"
MAX_HEADER_BYTES = 65536
HEADER_TIMEOUT_S = 10.0


def _request_token(head: bytes) -> tuple[str | None, str | None, str, bool]:
    """(query token, cookie token, path without the query, websocket upgrade) of a request head."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    target = parts[1] if len(parts) == 3 else "/"
    url = urlsplit(target)
    query = parse_qs(url.query).get("token", [None])[0]
    cookie, upgrade = None, False
    for line in lines[1:]:
        name, _, value = line.partition(":")
        name = name.strip().lower()
        if name == "cookie":
            jar = SimpleCookie()
            jar.load(value.strip())
            if COOKIE in jar:
                cookie = jar[COOKIE].value
        elif name == "upgrade" and value.strip().lower() == "websocket":
            upgrade = True
    return query, cookie, url.path or "/", upgrade


class TokenGate:
    """Forwards ``host:port`` to the console on ``127.0.0.1:backend_port`` for token holders."""

    def __init__(self, host: str, port: int, backend_port: int, token: str):
        self.host, self.port, self.backend_port, self.token = host, port, backend_port, token
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.base_events.Server | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, name="token-gate", daemon=True)

    def start(self) -> None:
        """Bind and serve in the background (raises OSError if the address is taken)."""
        self._server = self._loop.run_until_complete(asyncio.start_server(self._handle, self.host, self.port))
        self._thread.start()

    def stop(self) -> None:
        if self._server is None:
            return

        async def shutdown() -> None:
            self._server.close()
            await self._server.wait_closed()

        asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(5.0)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5.0)

    def _valid(self, token: str | None) -> bool:
        return token is not None and hmac.compare_digest(token.encode(), self.token.encode())

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEADER_TIMEOUT_S)
        except (asyncio.TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            writer.close()
            return
        query, cookie, path, upgrade = _request_token(head[:MAX_HEADER_BYTES])
        if self._valid(query) and not upgrade:
            await self._reply(writer, "302 Found", f"Location: {path}\r\nSet-Cookie: {COOKIE}={self.token}; "
                                                  "HttpOnly; SameSite=Strict; Path=/\r\n", "")
        elif self._valid(cookie) or self._valid(query):
            await self._forward(head, reader, writer)
        else:
            await self._reply(writer, "401 Unauthorized", "",
                              "probecal: this console needs its token; open the address probecal serve printed\n")

    @staticmethod
    async def _reply(writer: asyncio.StreamWriter, status: str, headers: str, body: str) -> None:
        data = body.encode()
        writer.write(f"HTTP/1.1 {status}\r\n{headers}Content-Type: text/plain; charset=utf-8\r\n"
                     f"Content-Length: {len(data)}\r\nConnection: close\r\n\r\n".encode() + data)
        try:
            await writer.drain()
        finally:
            writer.close()

    async def _forward(self, head: bytes, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            backend_reader, backend_writer = await asyncio.open_connection("127.0.0.1", self.backend_port)
        except OSError:
            await self._reply(writer, "502 Bad Gateway", "", "probecal: the console is not running\n")
            return
        backend_writer.write(head)

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            try:
                while data := await src.read(65536):
                    dst.write(data)
                    await dst.drain()
            except ConnectionError:
                pass
            finally:
                dst.close()

        await asyncio.gather(pipe(reader, backend_writer), pipe(backend_reader, writer))
