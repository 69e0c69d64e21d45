"""free_port against real sockets on 127.0.0.1: free for the kind asked, never twice, and
never a port the kernel hands out by itself."""

from __future__ import annotations

import socket

import pytest

from roost_api import ports
from roost_api.ports import PortPicker, free_port, port_free
from roost_sim import free_udp_port

KINDS = [socket.SOCK_DGRAM, socket.SOCK_STREAM]


@pytest.mark.parametrize("kind", KINDS, ids=["udp", "tcp"])
def test_ports_lie_below_the_ephemeral_range_and_differ(kind: socket.SocketKind) -> None:
    low, _ = ports.ephemeral_range()
    picked = [free_port(kind) for _ in range(20)]
    assert len(set(picked)) == len(picked)
    assert all(ports.PORT_FLOOR <= port < low for port in picked), picked
    for port in picked:
        with socket.socket(socket.AF_INET, kind) as sock:
            sock.bind(("127.0.0.1", port))


def test_free_udp_port_takes_its_ports_from_the_same_counter() -> None:
    tcp, udp = free_port(), free_udp_port()
    assert tcp != udp


@pytest.mark.parametrize("kind", KINDS, ids=["udp", "tcp"])
def test_a_bound_port_is_skipped(kind: socket.SocketKind) -> None:
    first, second = free_port(kind), free_port(kind)
    with socket.socket(socket.AF_INET, kind) as holder:
        holder.bind(("127.0.0.1", first))
        assert not port_free(first, kind)
        picker = PortPicker([first, second])
        assert picker.pick(lambda port: port_free(port, kind)) == second
    assert PortPicker([first, second]).pick(lambda port: port_free(port, kind)) == first
