"""The pages' heartbeat, which the dead-man rule stands on: a page counts as open only while it
answers.

A page that closes cleanly says so, but a laptop that drops off the network, a tab frozen or a
client that stops reading says nothing: its connection stays open, and the sockets' buffers
fill. So every :data:`BEAT_S` the server pings each page's websocket (RFC 6455 ping; the
browser's network stack answers it once it has read everything sent before), and a page whose
answer has not come :data:`ANSWER_S` after the ping was due (sending included: a page that does
not read leaves no room to send it) is cut off. viser then sees the page go, and the console's
dead-man rule stops the motion. A page that closes (a close frame) is cut off as soon as the
next beat sees it closing, rather than after websockets' 10 s closing handshake.

Worst case, a page that vanishes is noticed ``BEAT_S + ANSWER_S`` (1.25 s) after its last
answer; a live page must keep up with what it is sent to within ``ANSWER_S``.
"""

from __future__ import annotations

import asyncio
import contextlib

import viser
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed
from websockets.protocol import State

BEAT_S = 0.25
"""How often each page is pinged (s)."""
ANSWER_S = 1.0
"""How long a page has to answer a ping, from when it was due (s)."""


class Heartbeat:
    """Pings every page of a viser server from :meth:`install` on, cutting off those that stop
    answering; :meth:`stop` before the server stops, so that no beat outlives its loop."""

    def __init__(self, server: viser.ViserServer):
        self._websock = server._websock_server
        self._beats: set[asyncio.Task] = set()
        self._websock.on_client_connect(self._watch)

    async def _watch(self, client: object) -> None:
        connection = self._websock._live_connections.get(client.client_id)  # type: ignore[attr-defined]
        if connection is not None:  # gone already
            beat = asyncio.get_running_loop().create_task(_beat(connection))
            self._beats.add(beat)
            beat.add_done_callback(self._beats.discard)

    def stop(self) -> None:
        loop = self._websock._background_event_loop
        if loop is None:  # never started
            return
        for beat in tuple(self._beats):
            with contextlib.suppress(RuntimeError):  # the loop closed already
                loop.call_soon_threadsafe(beat.cancel)


async def _beat(connection: ServerConnection) -> None:
    """Ping ``connection`` every :data:`BEAT_S` until it closes; cut it off once an answer is
    :data:`ANSWER_S` late or it is closing."""
    while connection.state is State.OPEN:
        try:
            await asyncio.wait_for(_answered(connection), ANSWER_S)
        except (asyncio.TimeoutError, ConnectionClosed):
            break
        await asyncio.sleep(BEAT_S)
    if connection.state is not State.CLOSED:
        with contextlib.suppress(AttributeError):  # no transport: never opened
            connection.transport.abort()


async def _answered(connection: ServerConnection) -> None:
    pong = await connection.ping()
    await pong
