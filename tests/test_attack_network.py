"""Network streams hold bounded memory whatever the other end sends (issue 13): URSim's dashboard
and script ports, the OpenIGTLink publisher, and the OpenIGTLink image input, which ends a hostile
stream with one clear line."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from pyigtl.messages import CRC64, MessageBase

from probecal.core.acquisition.igtl import MAX_CLIENTS, IgtlServer, image_message
from probecal.core.acquisition.igtlreader import MAX_BODY_BYTES
from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.imagesource import ImageSourceError
from probecal.core.robot.urscript import MAX_SCRIPT_BYTES
from probecal.core.robot.ursim import DASHBOARD_GREETING, DASHBOARD_PORT, MAX_LINE_BYTES, SCRIPT_PORTS, URSim
from tests.support.cli import HANG_TIMEOUT_S, run_cli
from tests.support.loopback import loopback
from tests.support.refusals import assert_one_line_error
from tests.support.waiting import wait_until
from tests.test_ursim import dashboard, dropped

HOST = loopback(9, 1)


@pytest.fixture(scope="module")
def sim():
    log: list[str] = []
    sim = URSim(HOST, time_scale=0.0, log=log.append).start()
    sim.log_lines = log
    yield sim
    sim.stop()


def _flood(sock: socket.socket, total: int, chunk: bytes) -> None:
    """Send ``total`` bytes of ``chunk`` until done or the peer hangs up."""
    sent = 0
    try:
        while sent < total:
            sock.sendall(chunk)
            sent += len(chunk)
    except (BrokenPipeError, ConnectionResetError):
        pass


def test_a_dashboard_line_without_end_is_cut_off(sim):
    sock = socket.create_connection((HOST, DASHBOARD_PORT), timeout=10)
    assert sock.recv(200).decode().startswith(DASHBOARD_GREETING)
    _flood(sock, 4 * MAX_LINE_BYTES, b"x" * 1024)
    reply = b""
    while chunk := sock.recv(200):
        reply += chunk
    assert f"line longer than {MAX_LINE_BYTES} bytes".encode() in reply
    sock.close()
    assert dashboard(HOST, "robotmode")[1].startswith("Robotmode:")  # the server still answers others


def test_a_script_port_flood_is_dropped(sim):
    sock = socket.create_connection((HOST, SCRIPT_PORTS[-1]), timeout=10)
    _flood(sock, 2 * MAX_SCRIPT_BYTES, b"def flood():\n" + b"  x = 1\n" * 8000)
    assert dropped(sock)
    wait_until(lambda: any("script client dropped" in line for line in sim.log_lines), "the drop in URSim's log")
    sock.close()


def test_ursim_refuses_an_address_beyond_loopback():
    with pytest.raises(ValueError, match="not a loopback address"):
        URSim("10.1.2.3")
    assert_one_line_error(run_cli("ursim", "--host", "10.1.2.3"), "10.1.2.3", "loopback")


def test_the_igtl_publisher_serves_a_bounded_number_of_clients():
    server = IgtlServer(0)
    socks = []
    try:
        for _ in range(MAX_CLIENTS):
            socks.append(socket.create_connection(("127.0.0.1", server.port), timeout=10))
        wait_until(lambda: server.clients == MAX_CLIENTS, f"{MAX_CLIENTS} clients")
        extra = socket.create_connection(("127.0.0.1", server.port), timeout=10)
        assert dropped(extra)
        extra.close()
        assert server.clients == MAX_CLIENTS
        _flood(socks[0], 8 << 20, b"\xff" * 65536)  # input is read and thrown away
        assert server.clients in (MAX_CLIENTS, MAX_CLIENTS - 1)
    finally:
        for sock in socks:
            sock.close()
        server.close()


def _valid_image_message() -> bytes:
    image = np.arange(48 * 64, dtype=np.uint32).astype(np.uint8).reshape(48, 64)
    return image_message(image, np.eye(4), 1.0, "Image").pack()


def _recrc(data: bytearray) -> bytearray:
    """``data`` with its header's body CRC-64 made right again (so the body itself is parsed)."""
    body = bytes(data[MessageBase.IGTL_HEADER_SIZE:])
    data[MessageBase.IGTL_HEADER_SIZE - 8:MessageBase.IGTL_HEADER_SIZE] = CRC64(body).to_bytes(8, "big")
    return data


def _hostile_streams() -> list[tuple[str, bytes]]:
    good = _valid_image_message()
    rng = np.random.default_rng(13)
    streams = [("garbage", rng.integers(0, 256, 300, dtype=np.uint8).tobytes()),
               ("header only", good[:MessageBase.IGTL_HEADER_SIZE]),
               ("short header", good[:20])]
    for cut in (60, 80, 200, len(good) - 1):
        streams.append((f"cut at {cut}", good[:cut]))
    huge = bytearray(good)
    huge[42:50] = (MAX_BODY_BYTES - 1).to_bytes(8, "big")  # claims 256 MB, sends 3 kB, then hangs up
    streams.append(("claims a huge body", bytes(huge)))
    for i in range(12):  # bodies spoilt with a right CRC: the image parser itself meets them
        spoilt = bytearray(good)
        for at in rng.integers(MessageBase.IGTL_HEADER_SIZE, MessageBase.IGTL_HEADER_SIZE + 80, 4):
            spoilt[at] = int(rng.integers(0, 256))
        streams.append((f"spoilt body {i}", bytes(_recrc(spoilt))))
    return streams


@pytest.mark.parametrize("name, data", _hostile_streams(), ids=[name for name, _ in _hostile_streams()])
def test_a_hostile_igtl_server_ends_the_stream_with_a_clear_error(name, data):
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(10)
        with IgtlSource("127.0.0.1", listener.getsockname()[1]) as source:
            connection, _ = listener.accept()
            with connection:
                connection.sendall(data)
            frames = []
            with pytest.raises(ImageSourceError, match=r"igtl:127\.0\.0\.1:\d+: ") as caught:
                while True:  # whatever frames it makes of the bytes, the stream then ends
                    frames.append(source.latest(timeout_s=10.0))
            assert "\n" not in str(caught.value)
            for frame in frames:
                assert frame.image.dtype == np.uint8 and frame.image.ndim == 2 and frame.image.size <= 48 * 64


@pytest.mark.parametrize("args, fragments", [
    (("--port", "99999"), ("--port", "99999", "not within 0 to 65535")),
    (("--port", "-1"), ("--port", "not within 0 to 65535")),
    (("--publish", "99999"), ("--publish", "not within 0 to 65535")),
    (("--host", "192.0.2.1", "--port", "0"), ("--host 192.0.2.1", "cannot listen")),
    (("--host", "%%%", "--port", "0"), ("--host %%%", "resolves")),
])
def test_serve_refuses_a_port_or_host_it_cannot_listen_on_at_once(tmp_path, args, fragments):
    """viser would fail in its own thread and leave the console waiting for ever."""
    result = run_cli("serve", *args, "--sessions", tmp_path / "sessions", timeout_s=HANG_TIMEOUT_S)
    assert_one_line_error(result, *fragments)
    assert not (tmp_path / "sessions").exists()


def test_serve_refuses_a_publish_port_in_use_before_starting(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = run_cli("serve", "--port", "0", "--publish", port, "--sessions", tmp_path, timeout_s=HANG_TIMEOUT_S)
    assert_one_line_error(result, f"--publish {port}", "in use")
    assert result.stdout == ""
