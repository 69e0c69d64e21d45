"""The links' batch reception: the C extension (``roost_agent/_udpbatch.c``, one recvmmsg
for the queue) and its Python fallback give the same datagrams, senders and arrival
stamps, over real UDP sockets on loopback.

The C half skips where the extension is not built (an install on a machine without a C
compiler); in `make test` this file runs in the compiled build's run
(tests/integration/test_compiled_agent.py), which always has it.
"""

from __future__ import annotations

import errno
import os
import select
import socket
from collections.abc import Callable, Iterator

import pytest

from roost_agent.transport import (
    BATCH_RECEIVE,
    DATAGRAM_SEND,
    SO_TIMESTAMPNS,
    Received,
    UdpListen,
    receive_each,
)
from tests.support.kernelstamps import until_the_kernel_stamps_arrivals

Receive = Callable[[socket.socket, int], list[Received]]


def _compiled(sock: socket.socket, limit: int) -> list[Received]:
    assert BATCH_RECEIVE is not None
    return BATCH_RECEIVE(sock.fileno(), limit)


def _python_and_c(python: object, c: object, c_id: str, built: bool) -> list[object]:
    """Both ways as test parameters, the C one skipped where the extension is not built."""
    return [
        pytest.param(python, id="python"),
        pytest.param(
            c, id=c_id, marks=pytest.mark.skipif(not built, reason="the C extension is not built")
        ),
    ]


WAYS = _python_and_c(receive_each, _compiled, "recvmmsg", BATCH_RECEIVE is not None)


Send = Callable[[socket.socket, bytes, tuple[str, int]], None]


def _send_python(sock: socket.socket, data: bytes, address: tuple[str, int]) -> None:
    sock.sendto(data, address)


def _send_compiled(sock: socket.socket, data: bytes, address: tuple[str, int]) -> None:
    assert DATAGRAM_SEND is not None
    DATAGRAM_SEND(sock.fileno(), data, address)


SENDS = _python_and_c(_send_python, _send_compiled, "c", DATAGRAM_SEND is not None)


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    """A stamped, non-blocking receiver (as a link's) and a sender, on loopback."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    tx.bind(("127.0.0.1", 0))
    # before, a datagram is stamped when read: later than the ones stamped after it
    until_the_kernel_stamps_arrivals()
    yield rx, tx
    rx.close()
    tx.close()


def _queued(rx: socket.socket, tx: socket.socket, payloads: list[bytes]) -> None:
    for payload in payloads:
        tx.sendto(payload, rx.getsockname())
    assert select.select([rx], [], [], 5)[0]


@pytest.mark.parametrize("receive", WAYS)
def test_every_queued_datagram_comes_in_order_with_its_sender_and_stamp(
    pair: tuple[socket.socket, socket.socket], receive: Receive
) -> None:
    rx, tx = pair
    # more than one recvmmsg batch (16), and the largest datagram UDP carries
    payloads = [bytes([i]) * (1 + i * 7) for i in range(40)] + [os.urandom(65507)]
    _queued(rx, tx, payloads)
    got: list[Received] = []
    while len(got) < len(payloads):  # loopback delivers at once; a read never waits
        batch = receive(rx, 256)
        assert batch, f"{len(got)} of {len(payloads)} came"
        got += batch
    assert [data for data, _, _ in got] == payloads
    assert {sender for _, sender, _ in got} == {tx.getsockname()}
    stamps = [stamp for _, _, stamp in got]
    assert all(stamp is not None for stamp in stamps)
    assert stamps == sorted(stamps)  # type: ignore[type-var]
    assert receive(rx, 256) == []  # an empty queue is an empty batch, no error


@pytest.mark.parametrize("receive", WAYS)
def test_a_batch_stops_at_its_limit_and_the_rest_waits(
    pair: tuple[socket.socket, socket.socket], receive: Receive
) -> None:
    rx, tx = pair
    payloads = [b"%d" % i for i in range(30)]
    _queued(rx, tx, payloads)
    first = receive(rx, 20)
    assert [data for data, _, _ in first] == payloads[:20]
    rest = receive(rx, 256)
    assert [data for data, _, _ in rest] == payloads[20:]


@pytest.mark.parametrize("receive", WAYS)
def test_an_unstamped_socket_gives_no_stamp(receive: Receive) -> None:
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx,
    ):
        rx.bind(("127.0.0.1", 0))
        rx.setblocking(False)
        tx.bind(("127.0.0.1", 0))
        _queued(rx, tx, [b"x"])
        assert receive(rx, 4) == [(b"x", tx.getsockname(), None)]


def test_a_link_reads_its_queue_the_same_either_way() -> None:
    """A listening UDP link's whole read (steered or not, as the kernel allows) gives
    what was sent, in order, from its sender."""
    link = UdpListen("127.0.0.1", 0, steer=True)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.bind(("127.0.0.1", 0))
            payloads = [b"\xfd" + bytes([i]) * 20 for i in range(50)]
            for payload in payloads:
                tx.sendto(payload, link.local_address())
            got: list[Received] = []
            while len(got) < len(payloads):
                assert select.select([link.fileno()], [], [], 5)[0]
                got += link.receive_batch(256)
            source = tx.getsockname()
        assert [data for data, _, _ in got] == payloads
        assert {sender for _, sender, _ in got} == {source}
    finally:
        link.close()


@pytest.mark.parametrize("send", SENDS)
def test_a_datagram_sent_either_way_arrives_whole_from_the_senders_port(
    pair: tuple[socket.socket, socket.socket], send: Send
) -> None:
    rx, tx = pair
    sizes = [1, 280, 1500, 9000]
    for size in sizes:
        send(tx, bytes(range(256)) * (size // 256) + bytes(size % 256), rx.getsockname())
    assert select.select([rx], [], [], 2.0)[0]
    got = receive_each(rx, 10)
    assert [len(data) for data, _, _ in got] == sizes
    assert {sender for _, sender, _ in got} == {tx.getsockname()}


@pytest.mark.skipif(DATAGRAM_SEND is None, reason="the C extension is not built")
def test_the_c_send_refuses_what_it_cannot_send_with_an_error_a_link_catches(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    """A link's write catches OSError and ValueError (``AutopilotLink._send``)."""
    rx, tx = pair
    closed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closed.close()
    with pytest.raises(OSError):
        _send_compiled(closed, b"x", rx.getsockname())
    with pytest.raises(ValueError, match="not an IPv4 address"):
        _send_compiled(tx, b"x", ("::1", rx.getsockname()[1]))
    with pytest.raises(OSError) as too_long:  # past the largest UDP datagram, as sendto
        _send_compiled(tx, bytes(70_000), rx.getsockname())
    assert too_long.value.errno == errno.EMSGSIZE
