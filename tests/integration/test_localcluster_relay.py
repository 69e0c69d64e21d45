"""The API relay real nodes reach the API server through: bytes both ways, a clean stop.

A real ``python -m roost_localcluster.relay`` process between a client and an echo
server, all on 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from roost_api.ports import free_port
from roost_localcluster.processes import ManagedProcess
from tests.support.waiting import wait_until


@pytest.fixture
def echo_server() -> Iterator[int]:
    """A TCP server on 127.0.0.1 answering every chunk with the same chunk."""
    server = socket.create_server(("127.0.0.1", 0))
    port = int(server.getsockname()[1])

    def serve() -> None:
        with contextlib.suppress(OSError):
            conn, _ = server.accept()
            with conn:
                while data := conn.recv(65536):
                    conn.sendall(data)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield port
    server.close()


def test_relay_carries_bytes_both_ways(echo_server: int, tmp_path: Path) -> None:
    listen = f"127.0.0.1:{free_port()}"
    process = ManagedProcess(
        "relay",
        [sys.executable, "-m", "roost_localcluster.relay", listen, f"127.0.0.1:{echo_server}"],
        tmp_path / "relay.log",
    )
    process.launch(die_with_parent=True)
    try:
        wait_until("the relay listening", lambda: "relaying" in process.log.read_text(), 10)
        payload = bytes(range(256)) * 1024
        host, port = listen.split(":")
        with socket.create_connection((host, int(port)), timeout=5) as conn:
            conn.sendall(payload)
            received = b""
            while len(received) < len(payload):
                received += conn.recv(65536)
        assert received == payload
    finally:
        process.stop()
    assert process.returncode == 0  # SIGTERM ends it cleanly
