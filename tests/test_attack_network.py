"""Network streams hold bounded memory whatever a client sends (issue 13): URSim's dashboard and
script ports, the OpenIGTLink publisher, and the OpenIGTLink image input."""

from __future__ import annotations

import socket

import pytest

from core.igtl import MAX_CLIENTS, IgtlServer
from core.ursim import DASHBOARD_GREETING, DASHBOARD_PORT, MAX_LINE_BYTES, MAX_SCRIPT_BYTES, SCRIPT_PORTS, URSim
from tests.conftest import assert_one_line_error, loopback, run_cli, wait_until
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
