"""The kernel steers a UDP link's datagrams: heartbeats and command answers to the urgent
socket, the bulk to the other (roost_agent.steering), and the link reads both in order.

Real sockets on 127.0.0.1 and the real kernel: the BPF program runs where it will run in
the agent. Skipped where the kernel cannot steer (not Linux).
"""

from __future__ import annotations

import errno
import select
import socket
import sys
import threading
import time
from collections.abc import Iterator

import pytest

from roost_agent import reader as reader_module
from roost_agent import transport
from roost_agent.reader import LinkReader, Session
from roost_agent.steering import (
    MAX_FRAMES,
    steered_sockets,
)
from roost_agent.transport import UdpListen, UdpOut
from roost_agent.trust import SourceLock
from roost_mavlink.codec import Encoder
from roost_mavlink.signing import sign_frame
from tests.support.kernelstamps import until_the_kernel_stamps_arrivals
from tests.support.waiting import wait_until

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="steering is Linux's")

ENCODER = Encoder(1, 1)
HEARTBEAT_FRAME = ENCODER.encode(
    "HEARTBEAT", type=2, autopilot=12, base_mode=0, custom_mode=0, system_status=4,
    mavlink_version=3,
)  # fmt: skip
ACK_FRAME = ENCODER.encode("COMMAND_ACK", command=400, result=0)
ATTITUDE_FRAME = ENCODER.encode(
    "ATTITUDE", time_boot_ms=1, roll=0, pitch=0, yaw=0, rollspeed=0, pitchspeed=0, yawspeed=0
)
# MAVLink 1: magic, length 9, seq, sysid, compid, id 0, then payload and CRC (not checked
# by the kernel: the link checks every frame after reading it).
V1_HEARTBEAT = bytes((0xFE, 9, 0, 1, 1, 0)) + bytes(11)
V1_ATTITUDE = bytes((0xFE, 28, 0, 1, 1, 30)) + bytes(30)


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket, socket.socket, int]]:
    bulk, urgent = steered_sockets(("127.0.0.1", 0))
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        yield bulk, urgent, sender, bulk.getsockname()[1]
    finally:
        for sock in (bulk, urgent, sender):
            sock.close()


def landed_on(pair: tuple[socket.socket, socket.socket, socket.socket, int], data: bytes) -> str:
    bulk, urgent, sender, port = pair
    sender.sendto(data, ("127.0.0.1", port))
    ready, _, _ = select.select([bulk, urgent], [], [], 5.0)
    assert len(ready) == 1, ready
    assert ready[0].recv(65535) == data
    return "urgent" if ready[0] is urgent else "bulk"


SIGNED_ATTITUDE = sign_frame(ATTITUDE_FRAME, bytes(32), 0, 1)


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        pytest.param(HEARTBEAT_FRAME, "urgent", id="heartbeat"),
        pytest.param(ACK_FRAME, "urgent", id="command-ack"),
        pytest.param(ATTITUDE_FRAME, "bulk", id="attitude"),
        pytest.param(V1_HEARTBEAT, "urgent", id="mavlink1-heartbeat"),
        pytest.param(V1_ATTITUDE, "bulk", id="mavlink1-attitude"),
        pytest.param(ATTITUDE_FRAME * 3 + HEARTBEAT_FRAME, "urgent", id="heartbeat-fourth"),
        pytest.param(V1_ATTITUDE + ACK_FRAME, "urgent", id="v1-then-v2-ack"),
        pytest.param(SIGNED_ATTITUDE + HEARTBEAT_FRAME, "urgent", id="after-a-signed-frame"),
        pytest.param(
            ATTITUDE_FRAME * (MAX_FRAMES - 1) + HEARTBEAT_FRAME, "urgent", id="last-frame-looked-at"
        ),
        pytest.param(ATTITUDE_FRAME * MAX_FRAMES + HEARTBEAT_FRAME, "bulk", id="beyond-max-frames"),
        pytest.param(b"\x00garbage" + HEARTBEAT_FRAME, "bulk", id="garbage-first"),
        pytest.param(HEARTBEAT_FRAME[:5], "bulk", id="truncated-header"),
        pytest.param(b"\xfd", "bulk", id="magic-only"),
        # An id whose low byte is a heartbeat's (256) is not a heartbeat.
        pytest.param(bytes((0xFD, 0, 0, 0, 0, 1, 1, 0, 1, 0, 0, 0)), "bulk", id="id-256"),
    ],
)
def test_the_kernel_steers_by_message_id(
    pair: tuple[socket.socket, socket.socket, socket.socket, int], data: bytes, expected: str
) -> None:
    assert landed_on(pair, data) == expected


def test_a_port_in_use_is_refused_as_a_single_socket_would_be() -> None:
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", 0))
    try:
        with pytest.raises(OSError) as refused:
            steered_sockets(holder.getsockname())
        assert refused.value.errno == errno.EADDRINUSE
    finally:
        holder.close()
    first = UdpListen("127.0.0.1", 0, steer=True)
    try:  # a second agent on the same port cannot join the first one's group
        with pytest.raises(OSError) as refused:
            UdpListen("127.0.0.1", first.local_address()[1], steer=True)
        assert refused.value.errno == errno.EADDRINUSE
    finally:
        first.close()


# serial: datagrams 5 ms apart must arrive in order
@pytest.mark.serial
def test_a_steered_link_reads_both_sockets_in_arrival_order() -> None:
    """Claims are settled by the sequence numbers of the frames after them, so a
    heartbeat read from the urgent socket must not jump the telemetry sent before it."""
    listener = UdpListen("127.0.0.1", 0, steer=True)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        urgent = listener.urgent_fileno()
        assert urgent is not None
        until_the_kernel_stamps_arrivals()  # before, a datagram is stamped when read
        port = listener.local_address()[1]
        sent = [ATTITUDE_FRAME, ATTITUDE_FRAME, HEARTBEAT_FRAME, ATTITUDE_FRAME, ACK_FRAME]
        sent = [frame + bytes((n,)) for n, frame in enumerate(sent)]  # tell them apart
        for data in sent:
            sender.sendto(data, ("127.0.0.1", port))
            # Loopback may deliver from another CPU's backlog: a gap keeps the arrival
            # order the sending order, which the stamps then record.
            time.sleep(0.005)
        select.select([listener.fileno()], [], [], 5.0)
        select.select([urgent], [], [], 5.0)
        time.sleep(0.1)  # every datagram delivered (the kernel may defer delivery)
        received = listener.receive_batch(256)
        assert [data for data, _, _ in received] == sent
        stamps = [stamp for _, _, stamp in received if stamp is not None]
        assert len(stamps) == len(sent)
        assert stamps == sorted(stamps)
    finally:
        listener.close()
        sender.close()


# serial: datagrams 5 ms apart must arrive in order
@pytest.mark.serial
def test_a_heartbeat_behind_a_bulk_read_only_in_part_waits_for_the_telemetry_before_it() -> None:
    """Signed frames are checked for replays in the order they are read, so a heartbeat
    that arrived after telemetry still queued (the bulk read stopped at its limit) must
    not be delivered first: it waits for a look after that telemetry's."""
    listener = UdpListen("127.0.0.1", 0, steer=True)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        urgent = listener.urgent_fileno()
        assert urgent is not None
        until_the_kernel_stamps_arrivals()
        port = listener.local_address()[1]
        sent = [ATTITUDE_FRAME + bytes((n,)) for n in range(6)] + [HEARTBEAT_FRAME]
        for data in sent:
            sender.sendto(data, ("127.0.0.1", port))
            time.sleep(0.005)  # arrival order = sending order (see above)
        select.select([urgent], [], [], 5.0)
        time.sleep(0.1)  # every datagram delivered
        received: list[bytes] = []
        for _ in range(len(sent)):  # reads of at most 4 a socket, until all are in
            received += [data for data, _, _ in listener.receive_batch(4)]
        assert received == sent
    finally:
        listener.close()
        sender.close()


def test_a_udpout_link_is_steered_on_the_address_its_peer_is_reached_from() -> None:
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    out = UdpOut("127.0.0.1", peer.getsockname()[1], steer=True)
    try:
        urgent = out.urgent_fileno()
        assert urgent is not None
        out.send(b"hello")
        _, source = peer.recvfrom(64)
        assert source[0] == "127.0.0.1"
        peer.sendto(HEARTBEAT_FRAME, source)
        ready, _, _ = select.select([out.fileno(), urgent], [], [], 5.0)
        assert ready == [urgent]
    finally:
        out.close()
        peer.close()


def test_where_the_kernel_refuses_to_steer_a_link_keeps_one_socket(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(bind: tuple[str, int]) -> tuple[socket.socket, socket.socket]:
        raise OSError(errno.ENOPROTOOPT, "Protocol not available")

    monkeypatch.setattr(transport, "steered_sockets", refuse)
    monkeypatch.setattr(transport, "_STEERING_WORKS", [True])
    listener = UdpListen("127.0.0.1", 0, steer=True)
    try:
        assert listener.urgent_fileno() is None
        assert "does not steer" in caplog.text
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sender.sendto(HEARTBEAT_FRAME, listener.local_address())
        select.select([listener.fileno()], [], [], 5.0)
        assert [data for data, _, _ in listener.receive_batch(8)] == [HEARTBEAT_FRAME]
        sender.close()
    finally:
        listener.close()
    assert transport._STEERING_WORKS == [False]  # asked once per process, not per link


def test_the_reader_reads_rarely_only_while_every_link_is_steered() -> None:
    reader = LinkReader()
    reader.drive(lambda: None, 0.02, 0.1)
    steered = UdpListen("127.0.0.1", 0, steer=True)
    plain = UdpListen("127.0.0.1", 0)
    first = Session(steered, SourceLock(relock_after_s=1.0), None)
    second = Session(plain, SourceLock(relock_after_s=1.0), None)
    try:
        assert reader.tick_s == 0.02  # nothing to read yet
        reader.attach(first)
        assert reader.tick_s == 0.1
        reader.attach(second)  # a link nothing wakes the reader for
        assert reader.tick_s == 0.02
        reader.detach(second)
        assert reader.tick_s == 0.1
        reader.detach(first)
        assert (first.urgent_fd, reader.tick_s) == (None, 0.02)
    finally:
        steered.close()
        plain.close()


# serial: a read within 50 ms
@pytest.mark.serial
def test_health_judged_between_reads_stands_for_the_last_read() -> None:
    """Status and metrics judge at any time; what arrived since the last read is not read
    yet, so the judgement is as of that read, but never more than half a second back."""
    reader = LinkReader()
    assert reader.as_of(100.0) == 100.0  # not reading: now is now
    reader.drive(lambda: None, 0.02, 0.1)
    reader.start()
    try:
        wait_until("a read", lambda: time.monotonic() - reader.as_of(time.monotonic()) < 0.05)
        now = time.monotonic()
        assert now - reader_module.READ_WAIT_S <= reader.as_of(now) <= now
        stalled = now + 60.0 - reader_module.READ_WAIT_S
        assert reader.as_of(now + 60.0) == stalled  # a stalled reader
    finally:
        reader.stop()


class _CountingLink:
    """Stands in for an AutopilotLink: counts the reader's drains and empties the socket."""

    def __init__(self) -> None:
        self.drains = 0

    def drain(self, session: Session) -> None:
        self.drains += 1
        session.transport.receive_batch(1 << 16)


# serial: wake-ups per 20 ms interval counted
@pytest.mark.serial
@pytest.mark.interpreted_only  # the link that counts drains stands in for an AutopilotLink
def test_a_flood_of_forged_heartbeats_wakes_the_reader_no_more_than_the_short_interval() -> None:
    """Heartbeats are easy to forge, and each one lands on the urgent socket: the reader
    still wakes at most about twice per short interval (the urgent wake, and the read at
    the end of the quiet time after it), not once per datagram."""
    reader = LinkReader()
    short_s = 0.02
    reader.drive(lambda: None, short_s, 60.0)
    listener = UdpListen("127.0.0.1", 0, steer=True)
    link = _CountingLink()
    session = Session(listener, SourceLock(relock_after_s=1.0), None)
    session.link = link  # type: ignore[assignment]
    flooding = threading.Event()
    sent = [0]

    def flood() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            while not flooding.is_set():
                sender.sendto(HEARTBEAT_FRAME, listener.local_address())
                sent[0] += 1
                time.sleep(0.0002)

    flooder = threading.Thread(target=flood)
    reader.start()
    try:
        reader.call(lambda: reader.attach(session))
        started, before = time.monotonic(), link.drains
        flooder.start()
        time.sleep(0.5)
        flooding.set()
        flooder.join()
        elapsed, drains = time.monotonic() - started, link.drains - before
    finally:
        reader.stop()
        listener.close()
    assert sent[0] > 4 * elapsed / short_s  # many more datagrams than short intervals
    assert drains <= 2 * elapsed / short_s + 5, (drains, sent[0])


def test_steered_pairs_on_port_zero_never_join_another_group() -> None:
    """Autobinding a reuseport socket may pick a port another group of the same user
    holds (and join that group); two links would then share one pair's datagrams."""
    pairs = [steered_sockets(("127.0.0.1", 0)) for _ in range(200)]
    try:
        ports = [bulk.getsockname()[1] for bulk, _ in pairs]
        assert len(set(ports)) == len(ports)
        assert all(urgent.getsockname()[1] == bulk.getsockname()[1] for bulk, urgent in pairs)
    finally:
        for bulk, urgent in pairs:
            bulk.close()
            urgent.close()
