"""Signed, scoped hub endpoints against real clients and attacks over real UDP.

A signed vehicle: two simulated PX4 autopilots that require signing, an agent that signs
towards them, and a hub with two more endpoints for ground stations: ``gcs`` (signed,
everything) and ``ro`` (signed, read-only). Clients are pymavlink (MAVProxy's MAVLink
layer) with and without the key. What an attacker sends is judged where it would land:
each attacker has its own system id, and the simulated autopilots record every command
with its sender, so "nothing got through" is read at the autopilots, not from the hub's
own counters. The bridge is simulated (no GPIO hardware here).
"""

from __future__ import annotations

import itertools
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent.events import AgentEvent
from roost_agent.hub import Hub
from roost_agent.hub_policy import (
    BAD_SIGNATURE,
    NOT_ALLOWED,
    REPLAYED,
    UNSIGNED,
)
from roost_api.autopilot import HubEndpoint, HubScope, HubSigning, HubTransport
from roost_mavlink.signing import Signer, Timestamps, Verdict, Verifier, split_frames
from tests.support.agent import run_agent_once
from tests.support.hubclient import VEHICLE_SYSID, HubClient, HubVehicle, hub_vehicle
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow

KEY = bytes.fromhex("5f" * 32)
WRONG_KEY = bytes.fromhex("a0" * 32)
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM

# One system id per attack: an autopilot's command record names who got through.
UNSIGNED_SYSID = 201
WRONG_KEY_SYSID = 202
REPLAY_SYSID = 203
FLOOD_SYSID = 204
READ_ONLY_SYSID = 205
ATTACKERS = (UNSIGNED_SYSID, WRONG_KEY_SYSID, REPLAY_SYSID, FLOOD_SYSID, READ_ONLY_SYSID)


def endpoints() -> list[HubEndpoint]:
    return [
        HubEndpoint(name="gcs", address="127.0.0.1:0", signing=HubSigning.REQUIRED),
        HubEndpoint(
            name="gcs-tcp",
            address="127.0.0.1:0",
            transport=HubTransport.TCP,
            signing=HubSigning.REQUIRED,
        ),
        HubEndpoint(
            name="ro",
            address="127.0.0.1:0",
            scope=HubScope.READ_ONLY,
            signing=HubSigning.REQUIRED,
        ),
    ]


EVENTS: list[AgentEvent] = []  # everything the module's vehicle reported
STARTED: list[float] = []


@pytest.fixture(scope="module")
def vehicle() -> Iterator[HubVehicle]:
    with hub_vehicle(["px4", "px4"], endpoints=endpoints(), key=KEY) as v:
        STARTED.append(time.monotonic())
        unsubscribe = v.agent.subscribe(EVENTS.append)
        yield v
        unsubscribe()


def hub_of(v: HubVehicle) -> Hub:
    hub = v.agent.hub
    assert hub is not None
    return hub


def arm_frame(sysid: int, *, seq: int = 0) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    mav.seq = seq
    msg = mav.command_long_encode(VEHICLE_SYSID, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
    return bytes(msg.pack(mav, force_mavlink1=False))


def commands_from(v: HubVehicle, sysid: int, command: int = ARM) -> int:
    """ARM_DISARM commands (by default) from ``sysid`` that reached an autopilot."""
    return sum(
        1 for sim in v.sims for c in sim.commands if c.source[0] == sysid and c.command == command
    )


def send(address: tuple[str, int], frames: list[bytes]) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(("127.0.0.1", 0))
        for frame in frames:
            sock.sendto(frame, address)
    finally:
        sock.close()


def test_a_signed_client_flies_the_vehicle_and_sees_it_signed(vehicle: HubVehicle) -> None:
    v = vehicle
    hub = hub_of(v)
    with HubClient(hub.endpoint_address("gcs"), sysid=250, key=KEY) as gcs:
        # pymavlink here takes only frames signed with the key: a heartbeat means signed
        gcs.wait_for(lambda r: r.kind == "HEARTBEAT" and r.sysid == VEHICLE_SYSID, 10)
        assert gcs.command(VEHICLE_SYSID, ARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        wait_until("armed on both", lambda: all(s.snapshot().armed for s in v.sims), 10, 0.05)
        assert gcs.command(VEHICLE_SYSID, ARM, 0) == mavlink.MAV_RESULT_ACCEPTED
        wait_until("disarmed", lambda: not any(s.snapshot().armed for s in v.sims), 10, 0.05)
    assert commands_from(v, 250) >= 2


def test_the_hub_signs_what_it_sends_with_the_vehicle_key(vehicle: HubVehicle) -> None:
    hub = hub_of(vehicle)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(5)
    clock = Timestamps()
    try:
        hello = Signer(KEY, 3, clock).sign(_heartbeat(251))
        sock.sendto(hello, hub.endpoint_address("gcs"))
        data = sock.recv(65535)
    finally:
        sock.close()
    verifier = Verifier(KEY, Timestamps())
    frames = split_frames(data)
    assert frames and all(verifier.check(f) is Verdict.GOOD for f in frames)


def _heartbeat(sysid: int) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    msg = mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return bytes(msg.pack(mav))


# serial: the legitimate client must keep up with the vehicle's stream, losing nothing,
# through a 3000-datagram flood (its reader is a thread of this process); beside a second
# worker at load 8-9 it lost 9 frames
@pytest.mark.serial
def test_attacks_get_nothing_through_and_the_legitimate_client_loses_nothing(
    vehicle: HubVehicle,
) -> None:
    v = vehicle
    hub = hub_of(v)
    gcs_at, ro_at = hub.endpoint_address("gcs"), hub.endpoint_address("ro")
    with HubClient(gcs_at, sysid=250, key=KEY) as gcs:
        gcs.wait_for(lambda r: r.kind == "HEARTBEAT" and r.sysid == VEHICLE_SYSID, 10)
        since = time.monotonic()
        for_agent = hub.counters.kept_for_agent
        # a genuine signed ARM, recorded on the air and replayed below
        genuine = Signer(KEY, 9, Timestamps()).sign(arm_frame(REPLAY_SYSID))
        send(gcs_at, [genuine])
        wait_until("the genuine ARM arms", lambda: commands_from(v, REPLAY_SYSID) > 0, 10, 0.05)
        assert gcs.command(VEHICLE_SYSID, ARM, 0) == mavlink.MAV_RESULT_ACCEPTED
        wait_until("disarmed", lambda: not any(s.snapshot().armed for s in v.sims), 10, 0.05)
        through_before = commands_from(v, REPLAY_SYSID)

        gcs_drops = next(e for e in hub.endpoints if e.name == "gcs").drops
        wrong = Signer(WRONG_KEY, 1, Timestamps())

        def attack(reason: int, frames: list[bytes]) -> None:
            """Send ``frames``, then repeat the last until one more is counted as
            ``reason`` (the kernel may drop datagrams of a flood before the hub reads)."""
            before = gcs_drops.by_reason[reason]
            send(gcs_at, frames)
            deadline = time.monotonic() + 10
            while gcs_drops.by_reason[reason] <= before and time.monotonic() < deadline:
                send(gcs_at, frames[-1:])
                time.sleep(0.05)
            assert gcs_drops.by_reason[reason] > before

        attack(UNSIGNED, [arm_frame(UNSIGNED_SYSID, seq=i) for i in range(5)])
        attack(BAD_SIGNATURE, [wrong.sign(arm_frame(WRONG_KEY_SYSID, seq=i)) for i in range(5)])
        attack(REPLAYED, [genuine] * 5)
        attack(UNSIGNED, [arm_frame(FLOOD_SYSID, seq=i % 256) for i in range(3000)])
        with HubClient(ro_at, sysid=READ_ONLY_SYSID, key=KEY) as ro:
            ro.wait_for(lambda r: r.kind == "HEARTBEAT" and r.sysid == VEHICLE_SYSID, 10)
            ro_drops = next(e for e in hub.endpoints if e.name == "ro").drops
            ro.mav.command_long_send(VEHICLE_SYSID, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
            wait_until("the read-only ARM dropped", lambda: ro_drops.by_reason[NOT_ALLOWED], 10)
            # a read the scope allows still works on the read-only endpoint
            version = mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
            request = mavlink.MAV_CMD_REQUEST_MESSAGE
            assert ro.command(VEHICLE_SYSID, request, version) == mavlink.MAV_RESULT_ACCEPTED
        # the legitimate client still flies after the flood
        assert gcs.command(VEHICLE_SYSID, ARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(VEHICLE_SYSID, ARM, 0) == mavlink.MAV_RESULT_ACCEPTED
        received = gcs.messages(since=since)
        for_agent = hub.counters.kept_for_agent - for_agent

    assert not any(s.snapshot().armed for s in v.sims)
    for sysid in (UNSIGNED_SYSID, WRONG_KEY_SYSID, FLOOD_SYSID, READ_ONLY_SYSID):
        assert commands_from(v, sysid) == 0, sysid
    assert commands_from(v, REPLAY_SYSID) == through_before
    request = mavlink.MAV_CMD_REQUEST_MESSAGE
    assert commands_from(v, READ_ONLY_SYSID, request) > 0  # what its scope allows
    # the vehicle's own stream to the signed client lost nothing (sequence numbers are
    # the active autopilot's, kept by the hub)
    # (read from the frame: pymavlink leaves the header of ids it lacks undecoded)
    seqs = [bytes(r.msg.get_msgbuf())[4] for r in received if r.sysid == VEHICLE_SYSID]
    gaps = sum((b - a - 1) % 256 for a, b in itertools.pairwise(seqs))
    # (answers to the agent's own requests use sequence numbers but stay with the agent)
    assert len(seqs) > 100 and gaps <= for_agent, (gaps, for_agent)
    drops = {e.name: e.dropped for e in hub.endpoint_status()}
    assert drops["gcs"] >= 5 + 5 + 5 and drops["ro"] >= 1

    # thousands of drops, reported in at most one Event a minute per endpoint
    def about_gcs() -> list[AgentEvent]:
        return [e for e in reported() if e.message.startswith("endpoint gcs:")]

    def reported() -> list[AgentEvent]:
        return [e for e in list(EVENTS) if e.reason == "HubFramesDropped"]

    wait_until("a HubFramesDropped Event", about_gcs, 10, 0.05)  # delivered by a thread
    minutes = (time.monotonic() - STARTED[0]) / 60
    assert len(about_gcs()) <= 1 + minutes
    assert all(e.warning for e in reported())


def test_a_tcp_client_gets_nothing_until_it_signs_and_then_only_signed_frames(
    vehicle: HubVehicle,
) -> None:
    hub = hub_of(vehicle)
    drops = next(e for e in hub.endpoints if e.name == "gcs-tcp").drops
    before = drops.by_reason[UNSIGNED]
    with socket.create_connection(hub.endpoint_address("gcs-tcp"), timeout=5) as conn:
        me = conn.getsockname()[:2]
        conn.sendall(_heartbeat(243))
        wait_until("the unsigned frame dropped", lambda: drops.by_reason[UNSIGNED] > before, 10)
        assert me not in hub.clients()
        conn.sendall(Signer(KEY, 4, Timestamps()).sign(_heartbeat(243)))
        wait_until("signed in", lambda: me in hub.clients(), 10, 0.02)
        data = b""
        while len(split_frames(data)) < 20:
            data += conn.recv(65535)
    verifier = Verifier(KEY, Timestamps())
    assert all(verifier.check(f) is Verdict.GOOD for f in split_frames(data))


def test_the_status_says_which_endpoints_sign(vehicle: HubVehicle) -> None:
    status = vehicle.agent.status()
    shown = {e.name: (e.scope, e.signed) for e in status.hub_endpoints}
    assert shown == {
        "udp": (HubScope.EVERYTHING, False),
        "gcs": (HubScope.EVERYTHING, True),
        "gcs-tcp": (HubScope.EVERYTHING, True),
        "ro": (HubScope.READ_ONLY, True),
    }


def test_an_agent_with_an_endpoint_beyond_loopback_and_no_key_refuses_in_one_line(
    tmp_path: Path,
) -> None:
    """Refused before any socket is bound (nothing listens beyond loopback)."""
    done = run_agent_once(tmp_path, {"endpoints": [{"name": "gcs", "address": "0.0.0.0:14560"}]})
    assert done.returncode == 2
    refusals = [line for line in done.stderr.splitlines() if line.startswith("roost-agent: ")]
    assert len(refusals) == 1, done.stderr
    assert "hub endpoint gcs" in refusals[0] and "signing: Unauthenticated" in refusals[0]
    assert "Traceback" not in done.stderr


NEW_KEY = bytes.fromhex("6e" * 32)


def test_a_rotated_key_is_taken_without_a_restart_and_nothing_breaks_meanwhile() -> None:
    """The agent gets the new key with the old one as ``previous`` (what ``roost keys
    rotate`` writes): the autopilots, still on the old key, keep being answered with it;
    a ground station with either key flies; once an autopilot is provisioned with the new
    key the agent answers it with that one."""
    with hub_vehicle(["px4", "px4"], endpoints=endpoints(), key=KEY) as v:
        hub = hub_of(v)
        signing = v.agent.links["fc1"].signing
        assert signing is not None
        v.agent.rekey(signing.rotated(NEW_KEY, KEY))
        for name in ("fc1", "fc2"):
            heard = v.agent.links[name].counters.accepted
            wait_until(
                f"{name} still heard on the old key",
                lambda n=name, h=heard: v.agent.links[n].counters.accepted > h + 50,
                10,
                0.05,
            )
        for key, sysid in ((KEY, 240), (NEW_KEY, 241)):
            with HubClient(hub.endpoint_address("gcs"), sysid=sysid, key=key) as gcs:
                gcs.wait_for(lambda r: r.kind == "HEARTBEAT" and r.sysid == VEHICLE_SYSID, 10)
                assert gcs.command(VEHICLE_SYSID, ARM, 1) == mavlink.MAV_RESULT_ACCEPTED
                assert gcs.command(VEHICLE_SYSID, ARM, 0) == mavlink.MAV_RESULT_ACCEPTED
        for sim in v.sims:  # provisioned with the new key
            sim.link.enable_signing(NEW_KEY, link_id=7)
        for name in ("fc1", "fc2"):
            link = v.agent.links[name]
            heard = link.counters.accepted
            wait_until(
                f"{name} heard on the new key",
                lambda lk=link, h=heard: lk.counters.accepted > h + 50,
                10,
                0.05,
            )
        assert all(link.counters.bad_signature == 0 for link in v.agent.links.values())
        # the autopilots take what the agent forwards, now signed with the new key
        assert v.client.command(VEHICLE_SYSID, ARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        wait_until("armed on both", lambda: all(s.snapshot().armed for s in v.sims), 10, 0.05)
        assert v.client.command(VEHICLE_SYSID, ARM, 0) == mavlink.MAV_RESULT_ACCEPTED
        with HubClient(hub.endpoint_address("gcs"), sysid=242, key=WRONG_KEY) as stranger:
            stranger.mav.command_long_send(VEHICLE_SYSID, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
            gcs_drops = next(e for e in hub.endpoints if e.name == "gcs").drops
            wait_until("the stranger dropped", lambda: gcs_drops.by_reason[BAD_SIGNATURE], 10)
        assert commands_from(v, 242) == 0
