"""Reading OpenIGTLink as a client: connecting to a server (PLUS, 3D Slicer, a robot's bridge) and
reading whole, CRC-checked messages with a short time-out. The image source and the tracker both
read through it; each names its own error types, so that a fault says which device failed and
whether its data was bad or its connection was lost.

What a message quotes of the peer (a device name, a library's complaint about a body) is quoted
short (:func:`~probecal.core.errors.quoted`): a peer's text never makes a message long or two lines."""

from __future__ import annotations

import socket
import struct
import threading
import time
from typing import Any

import numpy as np
from pyigtl.messages import CRC64, MessageBase

from probecal.core.errors import DeviceError, InputError, quoted
from probecal.core.io.limits import checked_bytes

MAX_BODY_BYTES = 1 << 28  # larger OpenIGTLink bodies are taken as a corrupt stream
DECODED_COPIES = 3  # a body is held while its pixels are unpacked and made grey
READ_CHUNK_BYTES = 1 << 20  # most bytes read from the socket at once


class ReaderStopped(Exception):
    """The reader was asked to stop in the middle of a message."""


def connect_to(host: str, port: int, timeout_s: float, poll_s: float, name: str,
               error: type[DeviceError]) -> socket.socket:
    """A connected socket that times out every ``poll_s`` (s); ``error`` naming ``name`` when
    the server refuses, does not answer within ``timeout_s`` or cannot be reached."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except ConnectionRefusedError:
        raise error(f"{name}: connection refused (is the OpenIGTLink server running?)") from None
    except TimeoutError:
        raise error(f"{name}: no answer within {timeout_s:.1f} s") from None
    except OSError as exc:
        raise error(f"{name}: cannot connect ({exc.strerror or exc})") from None
    sock.settimeout(poll_s)
    return sock


def unpacked(fields: dict, body: bytearray, name: str, error: type[DeviceError]) -> Any:
    """The pyigtl message of a header's ``fields`` and its ``body``; ``error`` when the body is bad."""
    kind, device = fields["message_type"], fields["device_name"]
    message = MessageBase.create_message(kind)
    try:
        with np.errstate(all="ignore"):  # a hostile matrix is refused by the caller, not warned of
            message.unpack(fields, body)
    except Exception as exc:  # pyigtl raises anything from struct.error to TypeError on bad bodies
        raise error(f"{name}: bad {kind} message {quoted(device)} ({quoted(str(exc))})") from None
    return message


def message_time(fields: dict) -> float:
    """A message's timestamp (s), or the time it arrived when the sender left it 0."""
    return fields["timestamp"] or time.time()


class MessageReader:
    """Reads whole OpenIGTLink messages from a socket with a short time-out, keeping partial ones.

    Checks each body's CRC-64. Raises ``error`` when the data is not OpenIGTLink, ``lost`` (by
    default ``error`` too) when the connection closes or breaks, and ReaderStopped when ``stop`` is
    set mid-message.
    """

    def __init__(self, sock: socket.socket, name: str, stop: threading.Event, error: type[DeviceError],
                 lost: type[DeviceError] | None = None):
        self._sock = sock
        self._name = name
        self._stop = stop
        self._error = error
        self._lost = lost or error

    def read(self) -> tuple[dict, bytearray] | None:
        """(header fields, body) of the next message, or None when none started within the
        socket's time-out."""
        header = self._read(MessageBase.IGTL_HEADER_SIZE, idle_ok=True)
        if header is None:
            return None
        try:
            fields = MessageBase.parse_header(bytes(header))
        except (struct.error, UnicodeDecodeError) as exc:
            raise self._error(f"{self._name}: bad data, not an OpenIGTLink header ({exc})") from None
        if fields["body_size"] > MAX_BODY_BYTES:
            raise self._error(
                f"{self._name}: bad data, a {fields['message_type']!r} message of {fields['body_size']} bytes"
            )
        try:
            checked_bytes(None, f"a {fields['message_type']!r} message of {fields['body_size']} bytes",
                          (DECODED_COPIES, fields["body_size"]))
        except InputError as exc:
            raise self._error(f"{self._name}: {exc}") from None
        body = self._read(fields["body_size"])
        assert body is not None  # _read returns None only when idle_ok
        crc = struct.unpack_from(">Q", header, MessageBase.IGTL_HEADER_SIZE - 8)[0]
        if CRC64(body) != crc:
            kind, device = quoted(fields["message_type"]), quoted(fields["device_name"])
            raise self._error(f"{self._name}: bad data, CRC mismatch in {kind} {device}")
        return fields, body

    def _read(self, size: int, idle_ok: bool = False) -> bytearray | None:
        """``size`` bytes, held as they arrive (a header that claims a large body takes memory only
        as the body comes)."""
        buffer = bytearray()
        while len(buffer) < size:
            try:
                chunk = self._sock.recv(min(size - len(buffer), READ_CHUNK_BYTES))
            except TimeoutError:
                if self._stop.is_set():
                    raise ReaderStopped from None
                if idle_ok and not buffer:
                    return None
                continue
            except OSError as exc:
                raise self._lost(f"{self._name}: connection lost ({exc.strerror or exc})") from None
            if not chunk:
                raise self._lost(f"{self._name}: connection closed by the server")
            buffer += chunk
        return buffer
