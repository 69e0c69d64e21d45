"""The agent's autopilot links on real loopback sockets: UDP and TCP links, TCP listener
links, the source lock on what a listener answers, frames pymavlink's dialect lacks, and
the kernel's arrival time of a datagram read late.

The pure rules these links follow (source lock, signing, URLs) are in
``tests/unit/test_agent_trust.py``.
"""

from __future__ import annotations

import select
import socket
import time

import pytest

from roost_agent import link as link_module
from roost_agent.health import HealthTracker
from roost_agent.link import AutopilotLink
from roost_agent.transport import UdpListen, UdpOut, open_transport
from roost_api.autopilot import Thresholds
from roost_api.meta import Stack
from roost_mavlink import AGENT_COMPONENT_ID
from roost_sim import free_udp_port
from tests.support.agentspec import SPEC
from tests.support.kernelstamps import until_the_kernel_stamps_arrivals
from tests.support.waiting import wait_until


def test_udp_listener_replies_only_to_the_locked_autopilot_address() -> None:
    port = free_udp_port()
    listener = open_transport(f"udp://127.0.0.1:{port}")
    assert isinstance(listener, UdpListen)
    autopilot, spoofer = UdpOut("127.0.0.1", port), UdpOut("127.0.0.1", port)
    try:
        spoofer.send(b"spoof")
        autopilot.send(b"real")
        senders: list[tuple[bytes, object]] = []

        def both_arrived() -> bool:
            data, sender = listener.receive()
            if data:
                senders.append((data, sender))
            return len(senders) == 2

        wait_until("both datagrams", both_arrived, 5.0, 0.01)
        real = next(s for d, s in senders if d == b"real")
        listener.send(b"dropped: no locked peer yet")
        assert real is not None
        listener.lock_to(real)
        listener.send(b"reply")
        assert wait_until("the reply", lambda: autopilot.receive()[0], 5.0, 0.01) == b"reply"
        assert spoofer.receive()[0] == b""
    finally:
        for t in (listener, autopilot, spoofer):
            t.close()


def test_tcp_link_reads_only_its_autopilot_answers_as_191_and_reconnects() -> None:
    """A real TCP MAVLink peer (ArduPilot SITL serves TCP): frames from the autopilot
    count, a foreign sysid does not, the agent's own heartbeat goes out as component 191,
    and a closed connection is reopened."""
    from pymavlink.dialects.v20 import common  # noqa: PLC0415

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    spec = SPEC.autopilots[0].model_copy(update={"connection": f"tcp://127.0.0.1:{port}"})
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    link.start()
    try:
        conn, _ = server.accept()
        autopilot = common.MAVLink(None, srcSystem=1, srcComponent=1)
        foreign = common.MAVLink(None, srcSystem=99, srcComponent=1)
        for mav in (autopilot, foreign):
            conn.sendall(mav.heartbeat_encode(2, 12, 129, 0x03040000, 4).pack(mav))
        wait_until(
            "one accepted frame and one from another system",
            lambda: link.counters.accepted >= 1 and link.counters.other >= 1,
            5.0,
            0.01,
        )
        assert link.heartbeat() is not None and link.heartbeat()[0] == 0x03040000  # type: ignore[index]
        assert link.send_heartbeat()
        parser = common.MAVLink(None)
        conn.settimeout(5)
        msgs = parser.parse_buffer(conn.recv(1024)) or []
        assert [(m.get_type(), m.get_srcSystem(), m.get_srcComponent()) for m in msgs] == [
            ("HEARTBEAT", 1, AGENT_COMPONENT_ID)
        ]
        conn.close()
        again, _ = server.accept()  # the link noticed and connected again
        again.close()
        assert link.counters.reopened >= 1
    finally:
        link.stop()
        server.close()


def _px4_frames() -> tuple[bytes, bytes, bytes]:
    """(HEARTBEAT, CURRENT_MODE, a well-framed message of an id nobody defines) from
    system 1 component 1, as pymavlink's ``all`` dialect (which defines CURRENT_MODE)
    encodes them."""
    from pymavlink.dialects.v20 import all as everything  # noqa: PLC0415

    autopilot = everything.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = autopilot.heartbeat_encode(2, 12, 129, 0x03040000, 4).pack(autopilot)
    mode = autopilot.current_mode_encode(0, 0x03040000, 0x03040000).pack(autopilot)
    undefined = bytearray(beat)
    undefined[7:10] = (0xFFFF00).to_bytes(3, "little")
    return bytes(beat), bytes(mode), bytes(undefined)


@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_a_message_the_pymavlink_dialect_lacks_is_counted_as_the_autopilots(
    transport: str,
) -> None:
    """PX4 v1.16's CURRENT_MODE (which pymavlink's dialect lacks) is accepted like any
    message of the autopilot, in UDP datagrams and in a TCP stream; a frame of an id
    nobody defines is counted ``unknown`` and costs nothing after it."""
    beat, mode, undefined = _px4_frames()
    peer = socket.socket(
        socket.AF_INET, socket.SOCK_DGRAM if transport == "udp" else socket.SOCK_STREAM
    )
    peer.bind(("127.0.0.1", 0))
    if transport == "udp":
        port = free_udp_port()
        connection = f"udp://127.0.0.1:{port}@127.0.0.1:{peer.getsockname()[1]}"
    else:
        peer.listen()
        connection = f"tcp://127.0.0.1:{peer.getsockname()[1]}"
    spec = SPEC.autopilots[0].model_copy(update={"connection": connection})
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    link.start()
    try:
        if transport == "udp":  # bound (and locked to the peer) once the link opened
            wait_until("the link open", lambda: link.locked_address is not None, 5.0, 0.01)
            for datagram in (beat, mode, undefined, mode + beat):
                peer.sendto(datagram, ("127.0.0.1", port))
        else:
            conn, _ = peer.accept()
            conn.sendall(beat + mode + undefined + mode + beat)
        wait_until(
            "five frames read",
            lambda: link.counters.accepted + link.counters.unknown >= 5,
            5.0,
            0.01,
        )
        c = link.counters
        assert (c.accepted, c.unknown, c.bad, c.errors) == (4, 1, 0, 0)
        assert link.tracker.stream_facts().counts["CURRENT_MODE"] == 2
    finally:
        link.stop()
        peer.close()


def test_tcp_listener_link_reads_the_autopilot_that_connects_to_it() -> None:
    """``tcpin://``: the link listens, an autopilot connects; the reader follows the
    accepted connection (its descriptor is not the listening one) and reads its frames,
    also after the autopilot reconnects."""
    from pymavlink.dialects.v20 import common  # noqa: PLC0415

    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    spec = SPEC.autopilots[0].model_copy(update={"connection": f"tcpin://127.0.0.1:{port}"})
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    link.start()
    autopilot = common.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        for connection in (1, 2):
            client = wait_until(
                "the link listening",
                lambda: _connected(port),
                5.0,
                0.02,
            )
            with client:
                before = link.counters.accepted
                for _ in range(3):
                    client.sendall(autopilot.heartbeat_encode(2, 12, 129, 0, 4).pack(autopilot))
                wait_until(
                    f"frames of connection {connection}",
                    lambda before=before: link.counters.accepted >= before + 3,  # type: ignore[misc]
                    5.0,
                    0.01,
                )
    finally:
        link.stop()


def _connected(port: int) -> socket.socket | None:
    try:
        return socket.create_connection(("127.0.0.1", port), timeout=1.0)
    except OSError:
        return None


# serial: reads 50 ms late judged against a slack
@pytest.mark.serial
@pytest.mark.parametrize("later_than_slack", [False, True])
def test_a_datagram_read_late_keeps_its_kernel_arrival_time(
    monkeypatch: pytest.MonkeyPatch, later_than_slack: bool
) -> None:
    """The reader reads once per tick; the health tracker must see when a message arrived
    (the kernel's receive timestamp), not when it was read. Read 50 ms late with the
    slack widened (a loaded machine may oversleep the 50 ms): its arrival. Read 300 ms
    late, beyond the slack: the slack before the read, never the read time (which would
    delay a silence by the whole wait)."""
    if not later_than_slack:
        monkeypatch.setattr(link_module, "STAMP_SLACK_S", 10.0)
    from pymavlink.dialects.v20 import common  # noqa: PLC0415

    autopilot_socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot_socket.bind(("127.0.0.1", 0))
    sender = autopilot_socket.getsockname()
    port = free_udp_port()
    spec = SPEC.autopilots[0].model_copy(
        update={"connection": f"udp://127.0.0.1:{port}@{sender[0]}:{sender[1]}"}
    )
    link = AutopilotLink(spec, HealthTracker("fc1", Stack.PX4, Thresholds()))
    session = link._open()
    try:
        until_the_kernel_stamps_arrivals()
        mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
        sent_at = time.monotonic()
        autopilot_socket.sendto(
            mav.heartbeat_encode(2, 12, 129, 0, 4).pack(mav), ("127.0.0.1", port)
        )
        # Loopback usually delivers inside sendto, but the kernel may defer it (to
        # ksoftirqd); the stamp is taken on delivery, so wait for the socket to hold it.
        # (A heartbeat goes to the link's urgent socket where the kernel steers.)
        urgent = session.transport.urgent_fileno()
        descriptors = [session.transport.fileno(), *([] if urgent is None else [urgent])]
        assert select.select(descriptors, [], [], 5.0)[0]
        delivered = time.monotonic()
        time.sleep(0.3 if later_than_slack else 0.05)
        read_from = time.monotonic()
        link.drain(session)
        read_until = time.monotonic()
        beat = link.heartbeat()
        assert beat is not None
        if later_than_slack:
            slack = link_module.STAMP_SLACK_S
            assert read_from - slack - 0.001 <= beat[2] <= read_until - slack + 0.001
        else:  # arrival (within the clock conversion's rounding), not the read 50 ms later
            assert sent_at - 0.001 <= beat[2] <= delivered + 0.001
    finally:
        link._close()
        autopilot_socket.close()
