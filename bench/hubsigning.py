"""Signed hub endpoints: what signing costs a client, and what an attack gets through.

A signed vehicle (two simulated PX4 autopilots that require signing, an agent that signs
towards them) whose hub serves its default loopback endpoint (unsigned, everything) and
two signed ones: ``gcs`` (everything) and ``ro`` (read-only).

- ``hub.signing_added_latency_p99_ms``: a client's COMMAND_LONG (REQUEST_MESSAGE, not
  mirrored) timed from its send to the COMMAND_ACK arriving back at the same client; one
  client on the unsigned endpoint, one signing on ``gcs`` (the hub verifies its frame
  and signs the answer), taking turns at going first; the figure is the difference of
  the p99s. The note adds what signing costs inside the hub per frame, timed per call.
- ``hub.unauthorised_frames_forwarded``: the attack set (unsigned ARMs, ARMs signed with
  a wrong key, a genuine signed ARM replayed, a read-only client's signed ARMs, and a
  flood of unsigned COMMAND_LONGs from a separate process), each attacker with its own
  system id; counted where a frame would land, in the autopilots' command records.
- ``hub.real_msgs_lost_per_10k_under_attack``: sequence-number gaps in the vehicle's own
  stream at a signed client on ``gcs`` meanwhile, per 10 000 messages it received.
"""

from __future__ import annotations

import itertools
import multiprocessing
import os
import socket
import statistics
import time
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.agent import percentile
from bench.core import Figure
from roost_agent.hub_policy import Gate, Scope
from roost_api.autopilot import HubEndpoint, HubScope, HubSigning
from roost_mavlink.codec import Frame, scan
from roost_mavlink.signing import Signer, Timestamps, Verifier
from tests.support.hubclient import VEHICLE_SYSID, HubVehicle, hub_vehicle

COMMAND = "python -m bench hubsigning"
KEY = bytes.fromhex("3c" * 32)
WRONG_KEY = bytes.fromhex("c3" * 32)
LATENCY_SAMPLES = 2000
ATTACK_EACH = 200  # frames of each kind but the flood
FLOOD_S = 10.0
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
REQUEST = mavlink.MAV_CMD_REQUEST_MESSAGE
ATTACKERS = {"unsigned": 201, "wrong key": 202, "replayed": 203, "flood": 204, "read-only": 205}


def _command(sysid: int, command: int, param1: float = 0.0) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    msg = mav.command_long_encode(VEHICLE_SYSID, 1, command, 0, param1, 0, 0, 0, 0, 0, 0)
    return bytes(msg.pack(mav))


class _Client:
    """A raw UDP client of one endpoint: sends finished frames, reads what comes back."""

    def __init__(self, address: tuple[str, int], signer: Signer | None) -> None:
        self.address = address
        self.signer = signer
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)

    def prepare(self, frame: bytes) -> bytes:
        """``frame`` as this client sends it (signed when it signs)."""
        return frame if self.signer is None else self.signer.sign(frame)

    def send(self, frame: bytes) -> None:
        self.sock.sendto(self.prepare(frame), self.address)

    def until(self, found: Callable[[Frame], bool]) -> float:
        """Read until a frame satisfies ``found``; when it arrived (monotonic)."""
        while True:
            data = self.sock.recv(65535)
            at = time.monotonic()
            for msg in scan(data)[0]:
                if isinstance(msg, Frame) and found(msg):
                    return at

    def close(self) -> None:
        self.sock.close()


def _is_request_ack(msg: Frame) -> bool:
    return msg.get_type() == "COMMAND_ACK" and int(msg.command) == REQUEST


def _round_trips(v: HubVehicle) -> tuple[list[float], list[float]]:
    hub = v.agent.hub
    assert hub is not None
    plain = _Client(hub.udp_address, None)
    signed = _Client(hub.endpoint_address("gcs"), Signer(KEY, 5, Timestamps()))
    frame = _command(250, REQUEST, float(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION))
    out: tuple[list[float], list[float]] = ([], [])
    try:
        for i in range(LATENCY_SAMPLES + 20):
            order = ((0, plain), (1, signed)) if i % 2 else ((1, signed), (0, plain))
            for which, client in order:
                ready = client.prepare(frame)  # the client's own signing is not timed
                start = time.monotonic()
                client.sock.sendto(ready, client.address)
                arrived = client.until(_is_request_ack)
                if i >= 20:  # the first ones warm up both paths
                    out[which].append((arrived - start) * 1000)
            time.sleep(0.002)
    finally:
        plain.close()
        signed.close()
    return out


def _in_process_cost() -> tuple[float, float]:
    """p99 (ms) of the per-frame work signing adds inside the hub, timed per call: the
    gate's verdict on a signed client frame and the signature on a frame to clients."""
    clock = Timestamps()
    gate = Gate(Scope(HubScope.EVERYTHING), Verifier(KEY, clock))
    client = Signer(KEY, 3, Timestamps())
    hub_signer = Signer(KEY, 0xF0, clock)
    frames = [client.sign(_command(250, REQUEST)) for _ in range(20_000)]
    outgoing = _command(VEHICLE_SYSID, REQUEST)
    verify: list[float] = []
    sign: list[float] = []
    for frame in frames:
        t0 = time.perf_counter_ns()
        gate.judge(frame, 76, REQUEST)
        t1 = time.perf_counter_ns()
        hub_signer.sign(outgoing)
        t2 = time.perf_counter_ns()
        verify.append((t1 - t0) / 1e6)
        sign.append((t2 - t1) / 1e6)
    return percentile(verify, 99), percentile(sign, 99)


def _flood(address: tuple[str, int], seconds: float, sysid: int) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    frame = _command(sysid, ARM, 1.0)
    end = time.monotonic() + seconds
    sent = 0
    while time.monotonic() < end:
        sock.sendto(frame, address)
        sent += 1
        if sent % 64 == 0:
            time.sleep(0.001)  # ~40 000 frames/s: a flood the hub thread must keep up with
    sock.close()


def _attack(v: HubVehicle) -> tuple[int, int, int, int, int]:
    """(unauthorised commands that reached an autopilot, vehicle messages received by
    the signed client, sequence numbers missing among them, frames the hub dropped,
    answers to the agent kept from clients meanwhile)."""
    hub = v.agent.hub
    assert hub is not None
    gcs_at, ro_at = hub.endpoint_address("gcs"), hub.endpoint_address("ro")
    pilot = _Client(gcs_at, Signer(KEY, 1, Timestamps()))
    wrong = Signer(WRONG_KEY, 1, Timestamps())
    reader = Signer(KEY, 2, Timestamps())
    genuine = Signer(KEY, 9, Timestamps()).sign(_command(ATTACKERS["replayed"], REQUEST))
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    attacker.bind(("127.0.0.1", 0))
    dropped_before = hub.counters.dropped_from_clients
    for_agent = hub.counters.kept_for_agent
    seqs: list[int] = []
    try:
        pilot.send(_command(250, REQUEST, float(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)))
        pilot.until(_is_request_ack)
        attacker.sendto(genuine, gcs_at)  # recorded, then replayed below
        ctx = multiprocessing.get_context("spawn")
        flood = ctx.Process(target=_flood, args=(gcs_at, FLOOD_S, ATTACKERS["flood"]))
        flood.start()
        end = time.monotonic() + FLOOD_S
        step = 0
        while time.monotonic() < end or flood.is_alive():
            if step < ATTACK_EACH:
                attacker.sendto(_command(ATTACKERS["unsigned"], ARM, 1.0), gcs_at)
                attacker.sendto(wrong.sign(_command(ATTACKERS["wrong key"], ARM, 1.0)), gcs_at)
                attacker.sendto(genuine, gcs_at)
                attacker.sendto(reader.sign(_command(ATTACKERS["read-only"], ARM, 1.0)), ro_at)
                step += 1
            try:
                data = pilot.sock.recv(65535)
            except TimeoutError:
                continue
            for msg in scan(data)[0]:
                if isinstance(msg, Frame) and msg.get_srcSystem() == VEHICLE_SYSID:
                    seqs.append(msg.get_seq())
        flood.join(timeout=5)
        # drain: a last signed request behind every attack frame on the same socket
        pilot.send(_command(250, REQUEST, float(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)))
        pilot.until(_is_request_ack)
    finally:
        pilot.close()
        attacker.close()
    # answers to the agent's own requests take sequence numbers but stay with the agent
    gaps = sum((b - a - 1) % 256 for a, b in itertools.pairwise(seqs))
    kept = hub.counters.kept_for_agent - for_agent
    lost = max(0, gaps - kept)
    # Every attacker's ARM that reached an autopilot, and every replay of the genuine
    # request beyond its one legitimate delivery (to the active autopilot).
    arms = sum(
        1
        for sim in v.sims
        for c in sim.commands
        if c.source[0] in ATTACKERS.values() and c.command == ARM
    )
    replayed = sum(
        1 for sim in v.sims for c in sim.commands if c.source[0] == ATTACKERS["replayed"]
    )
    unauthorised = arms + max(0, replayed - 1)
    dropped = hub.counters.dropped_from_clients - dropped_before
    return unauthorised, len(seqs), lost, dropped, kept


def run() -> list[Figure]:
    endpoints = [
        HubEndpoint(name="gcs", address="127.0.0.1:0", signing=HubSigning.REQUIRED),
        HubEndpoint(
            name="ro", address="127.0.0.1:0", scope=HubScope.READ_ONLY, signing=HubSigning.REQUIRED
        ),
    ]
    with hub_vehicle(["px4", "px4"], endpoints=endpoints, key=KEY) as v:
        plain, signed = _round_trips(v)
    verify_p99, sign_p99 = _in_process_cost()
    with hub_vehicle(["px4", "px4"], endpoints=endpoints, key=KEY) as v:
        unauthorised, received, lost, dropped, kept = _attack(v)
    added = percentile(signed, 99) - percentile(plain, 99)
    return [
        Figure(
            "hub.signing_added_latency_p99_ms",
            round(added, 3),
            "ms",
            "<= 0.2",
            COMMAND,
            f"{len(plain)}/{len(signed)} COMMAND_LONG -> COMMAND_ACK round trips through the "
            f"hub, unsigned endpoint / signed endpoint (verify in, sign out), alternating: "
            f"p99 {percentile(signed, 99):.3f} vs {percentile(plain, 99):.3f} ms, "
            f"median {statistics.median(signed):.3f} vs {statistics.median(plain):.3f} ms; "
            f"inside the hub, per frame: verify p99 {verify_p99:.4f} ms, sign p99 "
            f"{sign_p99:.4f} ms (20 000 calls each); 1-min load average "
            f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores",
        ),
        Figure(
            "hub.unauthorised_frames_forwarded",
            unauthorised,
            "frames",
            "== 0",
            COMMAND,
            f"{ATTACK_EACH} each of unsigned ARMs, wrong-key ARMs, a replayed genuine frame "
            f"and a read-only client's signed ARMs, plus {FLOOD_S:.0f} s of unsigned "
            f"COMMAND_LONG flood from another process; {dropped} frames dropped by the hub "
            "(the rest of the flood by the kernel's socket buffer); counted at the autopilots",
        ),
        Figure(
            "hub.real_msgs_lost_per_10k_under_attack",
            round(lost * 10_000 / received, 2) if received else float("nan"),
            "msgs",
            "== 0",
            COMMAND,
            f"sequence gaps in the vehicle's stream at a signed client during the attack: "
            f"{lost} missing of {received + lost} (sequence gaps less the {kept} answers to "
            "the agent's own requests the hub keeps from clients)",
        ),
    ]
