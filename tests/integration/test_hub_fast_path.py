"""The hub's fast path (``roost_agent/_udpbatch.c``, :mod:`roost_agent.fastpath`) routes
exactly what the Python path routes, over real UDP on loopback.

An agent (in this process, a simulated bridge: the only stand-in) hubs two autopilots
played by test sockets that send real MAVLink 2 frames; a raw UDP client greets the
hub and keeps every datagram it gets. Each case runs twice: routed in Python (the fast
path off) and routed in C (skipped where the extension is not built, an install on a
machine without a C compiler; in `make test` the compiled build's run,
tests/integration/test_compiled_agent.py, which always has it, runs this file). Either
way the client must get the active autopilot's frames byte for byte, in the order sent,
one frame per datagram, and nothing else: not a forged copy from another
address (the source lock), not a frame of another system id, not an answer addressed to
the agent, not a frame of a corrupted datagram; and after a switch nothing more of the
old active autopilot, the new one's frames (its system id rewritten to the vehicle's)
and, switched back, the first one's again.
"""

from __future__ import annotations

import errno
import math
import resource
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from types import SimpleNamespace
from typing import Any, cast

import pytest
from pymavlink.dialects.v20 import common as mavlink

from roost_agent import Agent
from roost_agent import hub as hub_module
from roost_agent.bridge import SimulatedBridge
from roost_agent.fastpath import PUMP, RUN_FIELDS, FastRoute, _run_rules
from roost_agent.health import REBOOT_BACKSTEP_MS, TILT_WARN_DEG
from roost_agent.link import AutopilotLink
from roost_agent.transport import SO_TIMESTAMPNS, recent_realtime_offset
from roost_api.autopilot import (
    AutopilotCommand,
    CommandAction,
    FailoverPolicy,
    HubSpec,
)
from roost_sim.vehicle import free_udp_port
from tests.support.flight import SIM_THRESHOLDS, px4_pair_on_udp
from tests.support.waiting import wait_until

ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
LOCAL_POSITION = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK
PING = mavlink.MAVLINK_MSG_ID_PING
AGENT_COMPONENT = 191
POLL_S = 0.01

WAYS = [
    pytest.param(False, id="python"),
    pytest.param(
        True,
        id="c",
        marks=pytest.mark.skipif(PUMP is None, reason="the C extension is not built"),
    ),
]


class Autopilot:
    """A socket that speaks for autopilot ``sysid``: heartbeats at 10 Hz from a thread
    (it proves itself and stays healthy), frames on request, numbered in one sequence."""

    def __init__(self, sysid: int, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.to = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._beat, daemon=True)
        self.thread.start()

    def frame(self, msg: mavlink.MAVLink_message, mav: mavlink.MAVLink | None = None) -> bytes:
        with self.lock:
            return bytes(msg.pack(mav or self.mav))

    def attitude(self, boot_ms: int) -> bytes:
        return self.frame(mavlink.MAVLink_attitude_message(boot_ms, 0.1, 0.2, 0.3, 0, 0, 0))

    def send(self, *frames: bytes) -> None:
        self.sock.sendto(b"".join(frames), self.to)

    def stream(self, boot_ms: int, count: int) -> list[bytes]:
        """``count`` ATTITUDE frames, ``time_boot_ms`` from ``boot_ms`` up by 2 ms each,
        one datagram every 2 ms; the frames sent."""
        sent = []
        for n in range(1, count + 1):
            frame = self.attitude(boot_ms + 2 * n)
            self.send(frame)
            sent.append(frame)
            time.sleep(0.002)
        return sent

    def _beat(self) -> None:
        while not self.stopping.wait(0.1):
            # PX4, quadrotor, on the ground and disarmed, MAV_STATE STANDBY
            self.send(self.frame(mavlink.MAVLink_heartbeat_message(2, 12, 0x81, 0, 3, 3)))

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(2)
        self.sock.close()


class Client:
    """A hub client: greets the hub, keeps every datagram it gets."""

    def __init__(self, hub: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.hub = hub
        mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.sock.sendto(bytes(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav)), hub)
        self.datagrams: list[bytes] = []
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self.stopping.is_set():
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            with self.lock:
                self.datagrams.append(data)

    def frames(self, msg_id: int) -> list[bytes]:
        """The datagrams holding one frame of ``msg_id`` (every datagram is checked to
        hold exactly one frame)."""
        with self.lock:
            got = list(self.datagrams)
        for data in got:
            assert len(data) == 12 + data[1], data.hex()  # one unsigned MAVLink 2 frame
        return [d for d in got if d[7] | d[8] << 8 | d[9] << 16 == msg_id]

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(2)
        self.sock.close()


@dataclass
class Rig:
    agent: Agent
    fc1: Autopilot
    fc2: Autopilot
    client: Client


@pytest.fixture(params=WAYS)
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    """The agent and its autopilots, routing in C (param True) or in Python."""
    ports = [free_udp_port(), free_udp_port()]
    spec = px4_pair_on_udp(
        "fastpath",
        ports,
        HubSpec(udp="127.0.0.1:0", sysid=1),
        FailoverPolicy(thresholds=SIM_THRESHOLDS),
    )
    agent = Agent(spec, SimulatedBridge(range(2)))
    assert agent.hub is not None
    agent.hub.fast = request.param
    fc1, fc2 = Autopilot(1, ports[0]), Autopilot(2, ports[1])
    client = None
    try:
        agent.start()
        hub = agent.hub
        assert hub is not None
        links = agent.links
        wait_until(
            "both autopilots locked",
            lambda: all(link.locked_address for link in links.values()),
            10,
            POLL_S,
        )
        client = Client(hub.udp_address)
        wait_until("the client gets heartbeats", lambda: client.frames(0), 10, POLL_S)
        yield Rig(agent, fc1, fc2, client)
    finally:
        agent.stop()
        fc1.close()
        fc2.close()
        if client is not None:
            client.close()


def _switch(rig: Rig, target: str, n: int) -> None:
    command = AutopilotCommand(
        id=f"switch-{n}", action=CommandAction.SWITCH, target=target, issued_at=datetime.now(UTC)
    )
    result = rig.agent.submit(command).result(10)
    assert result.result == "Executed", result


def _arrived(rig: Rig, expected: list[bytes]) -> list[bytes]:
    wait_until(
        "the frames reach the client",
        lambda: len(rig.client.frames(ATTITUDE)) >= len(expected),
        10,
        POLL_S,
    )
    time.sleep(0.3)  # not a wait for a condition: anything that should not come would by now
    return rig.client.frames(ATTITUDE)


def test_the_active_autopilots_frames_arrive_byte_identical_and_in_order(rig: Rig) -> None:
    fc1 = rig.fc1
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    forger.bind(("127.0.0.1", 0))
    other = mavlink.MAVLink(None, srcSystem=9, srcComponent=1)
    expected: list[bytes] = []
    try:
        for i in range(300):
            boot_ms = 1000 + 2 * i  # time_boot_ms advances: a live autopilot
            frame = fc1.attitude(boot_ms)
            if i % 50 == 7:  # two frames in one datagram (as ArduPilot sends)
                second = fc1.attitude(boot_ms + 1)
                fc1.send(frame, second)
                expected += [frame, second]
            elif i % 50 == 13:  # a corrupted frame beside a good one: the good one is routed
                bad = bytearray(fc1.attitude(boot_ms))
                bad[-1] ^= 0xFF
                fc1.send(bytes(bad), frame)
                expected.append(frame)
            elif i % 50 == 21:  # another system's frame from the autopilot's address
                fc1.send(
                    fc1.frame(mavlink.MAVLink_attitude_message(boot_ms, 0, 0, 0, 0, 0, 0), other)
                )
                fc1.send(frame)
                expected.append(frame)
            elif i % 50 == 33:  # an answer addressed to the agent stays with the agent
                fc1.send(
                    fc1.frame(mavlink.MAVLink_command_ack_message(511, 0, 0, 0, 1, AGENT_COMPONENT))
                )
                fc1.send(frame)
                expected.append(frame)
            else:
                fc1.send(frame)
                expected.append(frame)
            # a forged copy of the autopilot's frame from another address
            forger.sendto(fc1.attitude(boot_ms), fc1.to)
            time.sleep(0.001)
        got = _arrived(rig, expected)
    finally:
        forger.close()
    assert got == expected
    with rig.client.lock:
        acks = [d for d in rig.client.datagrams if d[7] == COMMAND_ACK]
    assert acks == []
    hub = rig.agent.hub
    assert hub is not None
    assert (hub.counters.routed_in_c > 0) == hub.fast


def test_a_switch_re_points_the_route(rig: Rig) -> None:
    first = [rig.fc1.attitude(1000 + i) for i in range(20)]
    for frame in first:
        rig.fc1.send(frame)
        time.sleep(0.002)
    assert _arrived(rig, first) == first

    _switch(rig, "fc2", 1)
    for i in range(20):
        rig.fc1.send(rig.fc1.attitude(5000 + i))  # the standby's: kept from the client
        rig.fc2.send(rig.fc2.attitude(9000 + i))
        time.sleep(0.002)
    wait_until("fc2's frames arrive", lambda: len(rig.client.frames(ATTITUDE)) >= 40, 10, POLL_S)
    time.sleep(0.3)  # not a wait for a condition: anything that should not come would by now
    after = rig.client.frames(ATTITUDE)[20:]
    boot = [int.from_bytes(d[10:14], "little") for d in after]
    assert boot == [9000 + i for i in range(20)]
    assert {d[5] for d in after} == {1}  # fc2 (system 2) shown as the vehicle (1)

    _switch(rig, "fc1", 2)
    last = [rig.fc1.attitude(20_000 + i) for i in range(20)]
    for frame in last:
        rig.fc1.send(frame)
        time.sleep(0.002)
    wait_until("fc1's frames again", lambda: len(rig.client.frames(ATTITUDE)) >= 60, 10, POLL_S)
    time.sleep(0.3)  # not a wait for a condition: anything that should not come would by now
    assert rig.client.frames(ATTITUDE)[40:] == last
    hub = rig.agent.hub
    assert hub is not None
    assert (hub.counters.routed_in_c > 0) == hub.fast


def test_the_active_autopilot_falling_silent_is_judged_while_its_frames_are_routed(
    rig: Rig,
) -> None:
    """The reader sleeps in C while the stream flows; the silence deadline still wakes it."""
    fc1 = rig.fc1
    boot_ms = 1000
    end = time.monotonic() + 2.5  # over two rate windows: a fast stream, its threshold learnt
    while time.monotonic() < end:
        boot_ms += 5
        fc1.send(fc1.attitude(boot_ms))
        time.sleep(0.005)
    fc1.stopping.set()  # and its heartbeats stop too

    def silent() -> bool:
        judged = rig.agent.assessments().get("fc1")
        return judged is not None and "silent" in {f.code for f in judged.findings}

    wait_until("fc1 judged silent", silent, 10, POLL_S)
    hub = rig.agent.hub
    assert hub is not None
    assert (hub.counters.routed_in_c > 0) == hub.fast


def test_a_client_that_comes_while_the_stream_flows_gets_it_from_then_on(rig: Rig) -> None:
    """Routed in C, the stream's bulk reaches Python as runs, which Python cannot send
    again: a client the hub takes while C waits on a route made without it wakes the
    reader, and every frame sent once the hub counts the client reaches it."""
    fc1 = rig.fc1
    hub = rig.agent.hub
    assert hub is not None
    fc1.stream(5000, 100)  # the stream flows (in runs, in C)
    late = Client(hub.udp_address)
    try:
        address = late.sock.getsockname()
        wait_until("the hub takes the client", lambda: address in hub.clients(), 10, POLL_S)
        expected = fc1.stream(5200, 100)
        wait_until(
            "the frames reach the new client",
            lambda: len(late.frames(ATTITUDE)) >= len(expected),
            10,
            POLL_S,
        )
        assert late.frames(ATTITUDE)[-len(expected) :] == expected
    finally:
        late.close()


def _has(client: Client, count: int) -> Callable[[], bool]:
    """Whether ``client`` has ``count`` ATTITUDE frames (a condition to wait for)."""
    return lambda: len(client.frames(ATTITUDE)) >= count


def test_every_client_the_hub_admits_gets_every_frame(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The hub alone limits its clients (``hub.MAX_CLIENTS``): routed in C, every client
    it admits gets every frame, however many there are. Raised past its default here, so
    a second limit of the C loop's own (it once had one, equal to the default, that
    silently left the clients past it out) would show."""
    monkeypatch.setattr(hub_module, "MAX_CLIENTS", hub_module.MAX_CLIENTS + 8)
    fc1 = rig.fc1
    hub = rig.agent.hub
    assert hub is not None
    more = [Client(hub.udp_address) for _ in range(hub_module.MAX_CLIENTS - 1)]
    clients = [rig.client, *more]
    try:
        wait_until(
            "the hub takes every client",
            lambda: len(hub.clients()) == len(clients),
            10,
            POLL_S,
        )
        expected = fc1.stream(7000, 50)
        for n, client in enumerate(clients):
            wait_until(f"the frames reach client {n}", _has(client, len(expected)), 10, POLL_S)
            assert client.frames(ATTITUDE)[-len(expected) :] == expected
    finally:
        for client in more:
            client.close()


def test_a_fault_in_the_fast_path_leaves_the_hub_routing_in_python(
    rig: Rig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A fault of the fast path itself (not its sockets': a bug) is reported once, and the
    reader goes on reading, routing in Python and deciding. The fault is a stand-in: the
    C call is replaced by one that raises, as no real input makes it fail."""
    hub = rig.agent.hub
    assert hub is not None
    if not hub.fast:
        pytest.skip("routed in Python: there is no fast path to fail")
    fc1 = rig.fc1
    calls = []

    def failing(*args: Any, **kwargs: Any) -> Any:
        calls.append(args)
        raise RuntimeError("a fault in the fast path")

    monkeypatch.setattr("roost_agent.reader.pump", failing)
    expected = []
    for i in range(100):
        frame = fc1.attitude(5000 + 4 * i)
        fc1.send(frame)
        expected.append(frame)
        time.sleep(0.002)
    got = _arrived(rig, expected)
    assert got[-len(expected) :] == expected
    assert len(calls) == 1
    assert caplog.text.count("the hub's fast path failed") == 1
    _switch(rig, "fc2", 1)  # and the agent still decides
    assert rig.agent.active == "fc2"


def _read_whole(link: AutopilotLink, kind: str) -> list[Any]:
    """The messages of ``kind`` the link's tap (the hub) gets whole from now on, as a
    list that grows; the tap still gets every message."""
    tap = link.tap
    assert tap is not None
    whole: list[Any] = []

    def watching(msg: Any, now: float) -> None:
        if msg.get_type() == kind:
            whole.append(msg)
        tap(msg, now)

    link.tap = watching
    return whole


def test_routine_frames_are_routed_and_judged_without_being_read_whole(rig: Rig) -> None:
    """LOCAL_POSITION_NED, whose content the agent never reads: routed byte for byte and
    counted by the tracker either way; in C the hub's tap never gets one whole (C hands
    Python each datagram's summary: id, sequence number, time_boot_ms)."""
    link = rig.agent.links["fc1"]
    whole = _read_whole(link, "LOCAL_POSITION_NED")
    fc1 = rig.fc1
    before = link.tracker.stream_facts().counts.get("LOCAL_POSITION_NED", 0)
    expected = []
    for i in range(200):
        frame = fc1.frame(
            mavlink.MAVLink_local_position_ned_message(10_000 + 2 * i, i, 0, 0, 0, 0, 0)
        )
        fc1.send(frame)
        expected.append(frame)
        time.sleep(0.002)
    wait_until(
        "the frames reach the client",
        lambda: len(rig.client.frames(LOCAL_POSITION)) >= len(expected),
        10,
        POLL_S,
    )
    assert rig.client.frames(LOCAL_POSITION) == expected
    wait_until(
        "the tracker counted them",
        lambda: link.tracker.stream_facts().counts.get("LOCAL_POSITION_NED", 0) == before + 200,
        10,
        POLL_S,
    )
    hub = rig.agent.hub
    assert hub is not None
    assert len(whole) == (0 if hub.fast else 200)


def test_frames_with_a_target_are_routine_unless_addressed_to_the_agent(rig: Rig) -> None:
    """PING, which PX4 streams at 1 Hz, has a target. Addressed to everyone or to a
    ground station it is routed byte for byte and counted by the tracker, and in C the
    hub's tap never gets it whole (C read the target before routing it). Addressed to
    the agent it reaches no client and stays with the agent, either way. (The two kinds
    are sent one after the other: after a frame C does not forward, Python forwards
    what that read took after it, and reads it whole.)"""
    link = rig.agent.links["fc1"]
    pings = _read_whole(link, "PING")
    hub = rig.agent.hub
    assert hub is not None
    fc1 = rig.fc1
    kept_before = hub.counters.kept_for_agent
    to_agent = (1, AGENT_COMPONENT)  # the autopilot's system, the agent's component

    def send(targets: list[tuple[int, int]]) -> list[bytes]:
        before = link.tracker.stream_facts().counts.get("PING", 0)
        frames = []
        for i, target in enumerate(targets):
            frame = fc1.frame(mavlink.MAVLink_ping_message(1_000_000 + i, i, *target))
            fc1.send(frame)
            frames.append(frame)
            time.sleep(0.002)
        wait_until(
            "the tracker counted them",
            lambda: link.tracker.stream_facts().counts.get("PING", 0) == before + len(targets),
            10,
            POLL_S,
        )
        return frames

    expected = send([(0, 0) if i % 2 else (255, 190) for i in range(100)])
    wait_until(
        "the frames reach the client",
        lambda: len(rig.client.frames(PING)) >= len(expected),
        10,
        POLL_S,
    )
    whole = [(msg.target_system, msg.target_component) for msg in pings]
    assert whole == ([] if hub.fast else [(255, 190), (0, 0)] * 50)
    send([to_agent] * 20)
    time.sleep(0.3)  # not a wait for a condition: anything that should not come would by now
    assert rig.client.frames(PING) == expected
    assert hub.counters.kept_for_agent - kept_before == 20
    whole = [(msg.target_system, msg.target_component) for msg in pings]
    assert whole[-20:] == [to_agent] * 20


def test_runs_keep_what_the_health_model_and_the_hub_read(rig: Rig) -> None:
    """Routed in C, the bulk of the stream reaches Python as runs (``_udpbatch.c``):
    either way every frame reaches the client and is counted by the tracker, the hub's
    snapshot holds the last position, the time the attitude left its envelope is that
    of the first frame beyond it, and a step back in ``time_boot_ms`` is judged a
    reboot."""
    fc1 = rig.fc1
    link = rig.agent.links["fc1"]
    tracker = link.tracker
    hub = rig.agent.hub
    assert hub is not None
    before = dict(tracker.stream_facts().counts)
    boot_ms = 50_000
    sent: dict[str, int] = {}
    sent_at: list[float] = []  # the clock before each frame was made and sent

    def send(msg: mavlink.MAVLink_message) -> None:
        sent_at.append(time.monotonic())
        fc1.send(fc1.frame(msg))
        sent[msg.get_type()] = sent.get(msg.get_type(), 0) + 1
        time.sleep(0.002)

    for i in range(60):  # level flight: attitude, positions
        boot_ms += 4
        send(mavlink.MAVLink_attitude_message(boot_ms, 0.01, 0.02, 0, 0, 0, 0))
        send(mavlink.MAVLink_local_position_ned_message(boot_ms, i, 0, 0, 0, 0, 0))
        send(
            mavlink.MAVLink_global_position_int_message(
                boot_ms, 470_000_000 + i, 0, 0, 0, 0, 0, 0, 0
            )
        )

    def counted() -> bool:
        counts = tracker.stream_facts().counts
        return all(counts.get(kind, 0) - before.get(kind, 0) == n for kind, n in sent.items())

    wait_until("the tracker counted every frame", counted, 10, POLL_S)
    snapshot = hub.snapshot("fc1")
    assert snapshot is not None
    assert snapshot.lat_deg == pytest.approx((470_000_000 + 59) / 1e7)
    first = len(sent_at)
    for _ in range(20):  # beyond the envelope (70 degrees of roll)
        boot_ms += 4
        send(mavlink.MAVLink_attitude_message(boot_ms, 1.22, 0, 0, 0, 0, 0))
    wait_until("the tracker counted every frame", counted, 10, POLL_S)
    over_since = tracker._o.tilt_over_since
    assert over_since is not None
    # the first tilted frame's arrival: after it left, before the second did (the
    # sender's own delays, under load, move both)
    assert sent_at[first] <= over_since < sent_at[first + 1]
    for _ in range(20):
        boot_ms += 4
        send(mavlink.MAVLink_attitude_message(boot_ms, 0.01, 0, 0, 0, 0, 0))
    wait_until("the tracker counted every frame", counted, 10, POLL_S)
    assert tracker._o.tilt_over_since is None
    reboots = tracker.stream_facts().reboots
    boot_ms = 100  # a new timeline: the autopilot rebooted
    for i in range(20):
        boot_ms += 4
        send(mavlink.MAVLink_local_position_ned_message(boot_ms, i, 0, 0, 0, 0, 0))
    wait_until(
        "the reboot is judged", lambda: tracker.stream_facts().reboots == reboots + 1, 10, POLL_S
    )
    assert len(rig.client.frames(LOCAL_POSITION)) == sent["LOCAL_POSITION_NED"]
    assert (hub.counters.routed_in_c > 0) == hub.fast


# -- the C call itself: what ends it at once while runs are taken ---------------------

HELD_SENSORS = 0x2F  # enabled and healthy, as the tracker holds them in these rows
LANDED_IN_AIR = mavlink.MAV_LANDED_STATE_IN_AIR
GOOD_ESTIMATOR = mavlink.ESTIMATOR_ATTITUDE
CALL_TIMEOUT_S = 3.0


def _state_frames(mav: mavlink.MAVLink, health: int, landed: int, flags: int) -> list[bytes]:
    return [
        bytes(
            mavlink.MAVLink_sys_status_message(
                HELD_SENSORS, HELD_SENSORS, health, 500, 12000, 1000, 80, 0, 0, 0, 0, 0, 0
            ).pack(mav)
        ),
        bytes(mavlink.MAVLink_extended_sys_state_message(0, landed).pack(mav)),
        bytes(
            mavlink.MAVLink_estimator_status_message(5_000_000, flags, 0, 0, 0, 0, 0, 0, 0, 0).pack(
                mav
            )
        ),
    ]


NEWS: list[tuple[str, Callable[[mavlink.MAVLink, int], bytes] | None]] = [
    ("nothing new: the states repeated", None),
    (
        "a sensor unhealthy",
        lambda mav, _: _state_frames(mav, HELD_SENSORS & ~1, LANDED_IN_AIR, GOOD_ESTIMATOR)[0],
    ),
    (
        "the landed state",
        lambda mav, _: _state_frames(
            mav, HELD_SENSORS, mavlink.MAV_LANDED_STATE_ON_GROUND, GOOD_ESTIMATOR
        )[1],
    ),
    (
        "the estimator's flags",
        lambda mav, _: _state_frames(mav, HELD_SENSORS, LANDED_IN_AIR, 0)[2],
    ),
    (
        "a tilt past the envelope",
        lambda mav, boot: bytes(
            mavlink.MAVLink_attitude_message(boot, 1.22, 0, 0, 0, 0, 0).pack(mav)
        ),
    ),
    (
        "a kind read whole (PARAM_VALUE)",
        lambda mav, _: bytes(
            mavlink.MAVLink_param_value_message(b"MPC_XY_VEL_MAX", 12.0, 9, 900, 3).pack(mav)
        ),
    ),
    (
        "a HEARTBEAT",
        lambda mav, _: bytes(mavlink.MAVLink_heartbeat_message(2, 12, 0x81, 0, 4, 3).pack(mav)),
    ),
]


Sender = Callable[[Callable[[bytes], None], mavlink.MAVLink, Callable[[], bool]], None]


def _call_c(send: Sender, frozen: tuple[float, float] = (math.inf, -1.0)) -> tuple[float, Any]:
    """One C call (``CALL_TIMEOUT_S``) on a link socket over real UDP, taking runs with
    the states above held, while ``send`` sends from the locked autopilot (given a way to
    send a frame, the autopilot's encoder, and whether the call still runs); frozen
    telemetry's deadline and age as the reader hands them over. How long the call took,
    and what it returned."""
    assert PUMP is not None
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # also the hub's client
    link = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sockets = (autopilot, link)
    for s in sockets:
        s.bind(("127.0.0.1", 0))
    link.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    held = {
        "SYS_STATUS": (HELD_SENSORS, HELD_SENSORS),
        "EXTENDED_SYS_STATE": (LANDED_IN_AIR,),
        "ESTIMATOR_STATUS": (GOOD_ESTIMATOR,),
        "EKF_STATUS_REPORT": (-1,),
    }
    state = (TILT_WARN_DEG, 60.0, 0, 0.5, time.monotonic() + 100, 1000, REBOOT_BACKSTEP_MS, held)
    route = cast(
        FastRoute, SimpleNamespace(run_kinds=hub_module.RUN_KINDS, kept_ids=hub_module.KEPT_IDS)
    )
    result: list[tuple[float, Any]] = []

    def call() -> None:
        started = time.monotonic()
        items, _, _ = PUMP(
            link.fileno(),
            -1,
            [],
            (CALL_TIMEOUT_S, math.inf, -1.0, recent_realtime_offset(), *frozen),
            [(link.fileno(), autopilot.getsockname())],
            autopilot.getsockname(),
            1,
            1,
            AGENT_COMPONENT,
            False,
            True,
            [],
            256,
            hub_module.ROUTINE,
            _run_rules(route, state),
        )
        result.append((time.monotonic() - started, items))

    thread = threading.Thread(target=call)
    thread.start()
    try:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        send(lambda frame: autopilot.sendto(frame, link.getsockname()), mav, thread.is_alive)
        thread.join(CALL_TIMEOUT_S + 5)
    finally:
        for s in sockets:
            s.close()
    [outcome] = result
    return outcome


@pytest.mark.skipif(PUMP is None, reason="the C extension is not built")
@pytest.mark.parametrize(("what", "news"), NEWS, ids=[row[0] for row in NEWS])
def test_while_runs_are_taken_news_ends_the_c_call_at_once(
    what: str, news: Callable[[mavlink.MAVLink, int], bytes] | None
) -> None:
    """Decision table, one C call per row over real UDP: while runs are taken the read
    interval is long (``agent.ROUTED_TICK_S``), so whatever Python reads whole must end
    the call when it arrives. Attitude and the state kinds repeating the states held
    join one run and wait for the call's timeout; a state that changed, a tilt class
    that changed, a kind read whole or a HEARTBEAT ends the call at once, read whole
    after the run before it."""
    sent: list[bytes] = []

    def send(out: Callable[[bytes], None], mav: mavlink.MAVLink, _: Callable[[], bool]) -> None:
        boot = 2000
        for _ in range(3):
            for frame in [
                bytes(mavlink.MAVLink_attitude_message(boot, 0.01, 0, 0, 0, 0, 0).pack(mav)),
                *_state_frames(mav, HELD_SENSORS, LANDED_IN_AIR, GOOD_ESTIMATOR),
            ]:
                out(frame)
                boot += 4
                time.sleep(0.002)
        if news is not None:
            sent.append(news(mav, boot))
            out(sent[0])

    took, items = _call_c(send)
    assert len(items[0]) == RUN_FIELDS, what  # the twelve frames before, one run
    assert items[0][3] == 12, what
    if not sent:
        assert len(items) == 1, what
        assert took >= CALL_TIMEOUT_S * 0.9, what  # nothing ended it: the timeout did
    else:
        data, _, _, routed, summary = items[1]
        assert (data, routed, summary) == (sent[0], True, None), what  # read whole, routed
        assert took < CALL_TIMEOUT_S / 2, what  # it ended when the news came


FROZEN_S = 0.6  # longer than any stall of the sending thread under load
FROZEN = [("time_boot_ms advancing: moved past the call", 4, False), ("stuck: it falls", 0, True)]


@pytest.mark.skipif(PUMP is None, reason="the C extension is not built")
@pytest.mark.parametrize(("what", "step_ms", "falls"), FROZEN, ids=[row[0] for row in FROZEN])
def test_while_runs_are_taken_c_moves_frozen_telemetrys_deadline(
    what: str, step_ms: int, falls: bool
) -> None:
    """Decision table over real UDP: handed frozen telemetry's deadline (600 ms after the
    last ``time_boot_ms`` advance), C moves it with each frame whose ``time_boot_ms``
    advances, so a stream that advances keeps the call to its timeout; frames stuck at
    one ``time_boot_ms`` keep coming but do not move it, and the call ends when it falls."""

    def send(
        out: Callable[[bytes], None], mav: mavlink.MAVLink, running: Callable[[], bool]
    ) -> None:
        boot = 2000
        deadline = time.monotonic() + CALL_TIMEOUT_S + 1
        while running() and time.monotonic() < deadline:  # ATTITUDE at 100 Hz
            boot += step_ms
            out(bytes(mavlink.MAVLink_attitude_message(boot, 0.01, 0, 0, 0, 0, 0).pack(mav)))
            time.sleep(0.01)

    took, _ = _call_c(send, (FROZEN_S, FROZEN_S))
    if falls:
        assert FROZEN_S * 0.9 <= took < CALL_TIMEOUT_S * 0.8, what
    else:
        assert took >= CALL_TIMEOUT_S * 0.9, what


def _plain_call(
    bulk_fd: int, wake: list[int], timeout_s: float
) -> tuple[list[Any], list[Any], bool]:
    """One C call without clients, source lock or runs: a link that only waits."""
    assert PUMP is not None
    return PUMP(
        bulk_fd,
        -1,
        wake,
        (timeout_s, math.inf, -1.0, recent_realtime_offset(), math.inf, -1.0),
        [],
        None,
        1,
        1,
        AGENT_COMPONENT,
        False,
        True,
        [],
        256,
        hub_module.ROUTINE,
        None,
    )


@pytest.mark.skipif(PUMP is None, reason="the C extension is not built")
def test_a_descriptor_that_is_not_open_is_an_os_error_from_c() -> None:
    """A link socket closed under the call is not waited on: the read that follows
    reports it (EBADF), raised with the interpreter's lock held again; the reader then
    lets the link's own read report the failure (ReadLink.failed)."""
    not_open = resource.getrlimit(resource.RLIMIT_NOFILE)[0] - 1
    with pytest.raises(OSError) as raised:
        _plain_call(not_open, [], CALL_TIMEOUT_S)
    assert raised.value.errno == errno.EBADF
