"""A network that drops a page without a word: a TCP relay between a page (a browser, a raw
websocket) and the console that, once frozen, neither reads, writes nor closes, as a laptop
that falls off the network leaves its connections. The console's sockets stay open; what it
sends piles up in the relay's buffers and nothing answers. Deafened, it passes only what the
page sends: a page that stopped reading."""

from __future__ import annotations

import contextlib
import select
import socket
import threading

POLL_S = 0.05  # how often a waiting pump looks at the freeze flag


class FreezingRelay:
    """Relays connections made to ``listen`` (host, port; port 0: a free one) to ``target``
    until :meth:`freeze` (or, what the console sends, :meth:`deafen`)."""

    def __init__(self, target: tuple[str, int], listen: tuple[str, int] = ("127.0.0.1", 0)):
        self.target = target
        self._listener = socket.create_server(listen)
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self.frozen = threading.Event()
        self.deaf = threading.Event()  # nothing more reaches the page
        self._closed = threading.Event()
        self._sockets: list[socket.socket] = [self._listener]
        threading.Thread(target=self._accept, name="relay-accept", daemon=True).start()

    def __enter__(self) -> FreezingRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def freeze(self) -> None:
        """From now on nothing passes either way, and nothing closes."""
        self.deaf.set()
        self.frozen.set()

    def deafen(self) -> None:
        """From now on what the console sends no longer reaches the page, as when the page stops
        reading; what the page sends still passes."""
        self.deaf.set()

    def close(self) -> None:
        self._closed.set()
        for sock in self._sockets:
            with contextlib.suppress(OSError):
                sock.close()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                page, _ = self._listener.accept()
            except OSError:
                return
            console = socket.create_connection(self.target)
            self._sockets += [page, console]
            for source, sink, stopped in ((page, console, self.frozen), (console, page, self.deaf)):
                threading.Thread(target=self._pump, args=(source, sink, stopped), name="relay-pump",
                                 daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket, stopped: threading.Event) -> None:
        while not stopped.is_set() and not self._closed.is_set():
            try:
                if not select.select([source], [], [], POLL_S)[0]:
                    continue
                data = source.recv(1 << 16)
            except (OSError, ValueError):  # ValueError: closed meanwhile
                break
            if not data or stopped.is_set():
                break
            try:
                sink.sendall(data)
            except OSError:
                break
        if not stopped.is_set():  # a side closed before: so does the other
            with contextlib.suppress(OSError):
                sink.shutdown(socket.SHUT_WR)
        self._closed.wait()  # stopped: hold both sockets open, unread
