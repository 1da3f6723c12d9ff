"""OpenIGTLink output: pyigtl messages over our own TCP server, for 3D Slicer.

``IgtlPublisher`` sends the calibration as TRANSFORM "ImageToProbe" (``image_to_tool``, 4x4 mm with
  the pixel spacing inside, as PLUS sends it) and live tracked frames: IMAGE "Image" placed in the
  reference frame by its ijk-to-world matrix (``tool_to_base @ image_to_tool``) and TRANSFORM
  "ProbeToReference" (``tool_to_base``). It never blocks the caller. ``IgtlServer`` serves any
number of clients, each with its own bounded outbox (the tests' PLUS stand-in streams through it).

Our ``base`` frame (PLUS's Reference) is sent as Slicer's world (RAS) unchanged, as PLUS does.
pyigtl's own server is not used: it installs SIGINT/SIGTERM handlers (main thread only), serves
one client at a time and silently keeps only the newest 100 queued messages.
"""

from __future__ import annotations

import select
import socket
import threading
from collections import deque
from collections.abc import Callable

import numpy as np
from pyigtl.messages import ImageMessage, MessageBase, TransformMessage

IMAGE_DEVICE = "Image"
TOOL_DEVICE = "ProbeToReference"
CALIBRATION_DEVICE = "ImageToProbe"
POLL_S = 0.05  # how often server threads look at their stop flags
SEND_TIMEOUT_S = 5.0  # a client that takes no data for this long is dropped
PUBLISH_OUTBOX = 4  # frames queued per client for a live viewer; older ones are dropped
MAX_CLIENTS = 8  # connections served at once; more are closed at once


def image_message(
    image: np.ndarray, ijk_to_world: np.ndarray, timestamp: float | None, device: str
) -> ImageMessage:
    """An IMAGE message of a uint8 (rows, cols) frame, sent as one slice (1, rows, cols) as PLUS
    does: i = column, j = row. ``ijk_to_world`` maps voxel indices to mm (RAS = our frames as-is)."""
    return ImageMessage(
        np.ascontiguousarray(image)[np.newaxis],
        ijk_to_world_matrix=ijk_to_world,
        world_coordinate_system="ras",
        timestamp=timestamp,
        device_name=device,
    )


def transform_message(a_to_b: np.ndarray, timestamp: float | None, device: str,
                      status: str | None = None) -> TransformMessage:
    """A TRANSFORM message of a 4x4 (mm); OpenIGTLink carries it as float32. With a ``status``
    it carries PLUS's TransformStatus ("OK", "MISSING", ...) in its metadata (header version 2)."""
    message = TransformMessage(np.asarray(a_to_b, dtype=float), timestamp=timestamp, device_name=device)
    if status is not None:
        message.header_version = 2
        message.metadata = {"TransformStatus": status}
    return message


class _Client:
    """One connected client: a bounded outbox drained by a daemon sender thread.

    Whatever the client sends is read and discarded; its closing the connection, or taking no
    data for SEND_TIMEOUT_S, ends it.
    """

    def __init__(self, sock: socket.socket, capacity: int, on_close: Callable[[_Client], None]):
        self._sock = sock
        self._capacity = capacity
        self._on_close = on_close
        self._outbox: deque[tuple[bytes, bool]] = deque()  # (packed messages, is a state message)
        self._cond = threading.Condition()
        self.closed = False
        sock.settimeout(SEND_TIMEOUT_S)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def start(self) -> None:
        threading.Thread(target=self._run, name="igtl-client", daemon=True).start()

    def put(self, data: bytes, block: bool, state: bool = False) -> None:
        """Queue ``data``; when the outbox is full, wait for room (``block``, at most SEND_TIMEOUT_S)
        or drop the oldest queued item that is not a state message."""
        with self._cond:
            if block:
                self._cond.wait_for(lambda: len(self._outbox) < self._capacity or self.closed, SEND_TIMEOUT_S)
            if self.closed:
                return
            if len(self._outbox) >= self._capacity:
                droppable = [i for i, (_, is_state) in enumerate(self._outbox) if not is_state]
                if droppable:
                    del self._outbox[droppable[0]]
            self._outbox.append((data, state))
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    self._cond.wait_for(lambda: self._outbox or self.closed, POLL_S)
                    if self.closed:
                        return
                    data = self._outbox.popleft()[0] if self._outbox else None
                    self._cond.notify_all()
                if data is not None:
                    self._sock.sendall(data)
                self._discard_input()
        except (OSError, ValueError):  # the connection broke, or close() closed the socket (fd -1)
            return
        finally:
            self.close()
            self._on_close(self)

    def _discard_input(self) -> None:
        while select.select([self._sock], [], [], 0)[0]:
            if not self._sock.recv(65536):
                raise ConnectionResetError("client closed the connection")


class IgtlServer:
    """An OpenIGTLink TCP server that sends messages to every connected client.

    ``port=0`` takes a free port (see ``port``). ``send(..., block=False)`` never waits: a slow
    client loses its oldest queued items. ``block=True`` waits for room instead (lossless
    streaming). A state message (``set_state``) is never dropped, and is also sent to every client
    that connects later. At most MAX_CLIENTS are served at once; each one's outbox is bounded and
    whatever it sends is discarded, so no client can make the server hold more memory.
    """

    def __init__(self, port: int = 0, host: str = "127.0.0.1", outbox: int = PUBLISH_OUTBOX):
        try:
            self._listener = socket.create_server((host, port))
        except OSError as exc:
            raise OSError(exc.errno, f"cannot listen for OpenIGTLink on {host}:{port}: {exc.strerror}") from None
        self._listener.settimeout(POLL_S)
        self.host = host
        self.port: int = self._listener.getsockname()[1]
        self._outbox = outbox
        self._clients: list[_Client] = []
        self._state: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self._joined = threading.Condition(self._lock)
        self._closed = threading.Event()
        self._accepter = threading.Thread(target=self._accept, name="igtl-accept", daemon=True)
        self._accepter.start()

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def wait_for_client(self, timeout_s: float, count: int = 1) -> bool:
        """True once ``count`` clients are connected, False after ``timeout_s`` without them."""
        with self._joined:
            self._joined.wait_for(lambda: len(self._clients) >= count or self._closed.is_set(), timeout_s)
            return len(self._clients) >= count

    def send(self, *messages: MessageBase, block: bool = False) -> int:
        """Send ``messages`` together to every client; returns how many clients there were."""
        with self._lock:
            clients = list(self._clients)
        if clients:
            data = b"".join(m.pack() for m in messages)
            for client in clients:
                client.put(data, block)
        return len(clients)

    def set_state(self, message: MessageBase) -> None:
        """Send ``message`` now and to every client that connects later (newest per device)."""
        data = message.pack()
        with self._lock:
            self._state[message.device_name] = data
            clients = list(self._clients)
        for client in clients:
            client.put(data, block=False, state=True)

    def close(self) -> None:
        """Close the listening socket and every connection at once."""
        self._closed.set()
        self._listener.close()
        with self._joined:
            clients, self._clients = self._clients, []
            self._joined.notify_all()
        for client in clients:
            client.close()
        self._accepter.join(POLL_S * 4)

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            client = _Client(sock, self._outbox, self._forget)
            with self._joined:
                if self._closed.is_set():
                    client.close()
                    return
                if len(self._clients) >= MAX_CLIENTS:
                    client.close()
                    continue
                self._clients.append(client)
                for data in self._state.values():
                    client.put(data, block=False, state=True)
                self._joined.notify_all()
            client.start()

    def _forget(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)


class IgtlPublisher:
    """Live OpenIGTLink output for 3D Slicer: the calibration and tracked frames.

    Nothing here waits for the network: with no client a frame is not even packed, and a slow
    client loses its oldest frames. The calibration is re-sent to every client that connects.
    """

    def __init__(self, port: int = 18944, host: str = "127.0.0.1"):
        self._server = IgtlServer(port, host, PUBLISH_OUTBOX)
        self._image_to_tool: np.ndarray | None = None

    @property
    def port(self) -> int:
        return self._server.port

    @property
    def clients(self) -> int:
        return self._server.clients

    def wait_for_client(self, timeout_s: float) -> bool:
        return self._server.wait_for_client(timeout_s)

    def publish_calibration(self, image_to_tool: np.ndarray, timestamp: float | None = None) -> None:
        """TRANSFORM ImageToProbe = ``image_to_tool`` (4x4 mm, pixel spacing included)."""
        self._image_to_tool = np.array(image_to_tool, dtype=float)
        self._server.set_state(transform_message(self._image_to_tool, timestamp, CALIBRATION_DEVICE))

    def publish_frame(
        self,
        image: np.ndarray,
        tool_to_base: np.ndarray | None,
        timestamp: float,
        pose_timestamp: float | None = None,
    ) -> int:
        """IMAGE "Image" (uint8 rows x cols) and TRANSFORM ProbeToReference (``tool_to_base``, mm).

        With a pose and a published calibration the IMAGE's ijk-to-world matrix is
        ``tool_to_base @ image_to_tool``, so Slicer shows it in place in the reference frame;
        otherwise it is the identity (pixels). Returns the number of clients it went to.
        """
        if not self._server.clients:
            return 0
        if tool_to_base is not None and self._image_to_tool is not None:
            ijk_to_world = tool_to_base @ self._image_to_tool
        else:
            ijk_to_world = np.eye(4)
        messages: list[MessageBase] = [image_message(image, ijk_to_world, timestamp, IMAGE_DEVICE)]
        if tool_to_base is not None:
            pose_time = pose_timestamp if pose_timestamp is not None else timestamp
            messages.append(transform_message(tool_to_base, pose_time, TOOL_DEVICE))
        return self._server.send(*messages)

    def close(self) -> None:
        self._server.close()

    def __enter__(self) -> IgtlPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


