"""A page of the console without a browser: its websocket, sending what a page sends (a field's
new value, a click) with any value at all, as a buggy or hostile page could."""

from __future__ import annotations

import socket
from typing import Any

import msgspec.msgpack
import viser
from websockets.sync.client import ClientConnection, connect

from probecal.app.console.controller import Console
from tests.support.waiting import wait_until

CAMERA = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, 1.0), "fov": 1.0,
          "near": 0.01, "far": 100.0, "image_height": 800, "image_width": 1280, "look_at": (0.0, 0.0, 0.0),
          "up_direction": (0.0, 0.0, 1.0)}


class RawPage:
    """A page admitted by the console (its first message, the camera, makes viser take it as a
    client); closing it waits until the console has seen it go. It reads all it is sent, as a
    live page does (the console cuts off a page that stops reading: ``heartbeat``), through
    ``via`` (an address relaying to the console, ``vanishing.FreezingRelay``) when given."""

    def __init__(self, console: Console, via: tuple[str, int] | None = None):
        self.console = console
        self.via = via
        self._ws: ClientConnection | None = None
        self._id: int | None = None  # the console's client id for this page

    def __enter__(self) -> RawPage:
        port = self.console.server.get_port()
        before = set(self.console.server.get_clients())
        sock = socket.create_connection(self.via or ("127.0.0.1", port), timeout=10)
        self._ws = connect(f"ws://127.0.0.1:{port}/", sock=sock, origin=f"http://127.0.0.1:{port}",
                           open_timeout=10, close_timeout=2, subprotocols=[f"viser-v{viser.__version__}"],
                           max_queue=None)
        self.send(CAMERA)
        new = wait_until(lambda: set(self.console.server.get_clients()) - before, "the page connected")
        self._id = min(new)
        return self

    def __exit__(self, *exc) -> None:
        assert self._ws is not None
        self._ws.close()
        wait_until(lambda: self._id not in self.console.server.get_clients(), "the page gone")

    def send_close_frame(self) -> None:
        """A close frame, without waiting for the console's: a page whose close is its last word."""
        assert self._ws is not None
        with self._ws.protocol_mutex:
            self._ws.protocol.send_close()
            self._ws.send_data()

    def send(self, message: dict[str, Any]) -> None:
        assert self._ws is not None
        self._ws.send(msgspec.msgpack.encode(message))

    def update(self, handle: viser.GuiInputHandle, updates: dict[str, Any]) -> None:
        """What a page sends when a field changes (or, with ``{"value": True}``, a button is clicked)."""
        self.send({"type": "GuiUpdateMessage", "uuid": handle._impl.uuid, "updates": updates})

    def set(self, handle: viser.GuiInputHandle, value: Any) -> None:
        """Send ``value`` for the field ``handle`` and wait until the console took it."""
        before = handle._impl.update_timestamp
        self.update(handle, {"value": value})
        wait_until(lambda: handle._impl.update_timestamp != before, "the update taken")

    def click(self, button: viser.GuiButtonHandle) -> None:
        self.update(button, {"value": True})
