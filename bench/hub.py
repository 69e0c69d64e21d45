"""The agent's MAVLink hub: switch-to-client time, added latency, CPU per routed message.

Two simulated PX4 autopilots (real UDP MAVLink, onboard rates) behind an in-process agent
with the hub on a free port and a simulated bridge; a ground-station client on the hub.

- ``hub.switch_to_client_p99_ms``: a Switch command moves the bridge and the route; from
  the bridge write (the agent's own monotonic stamp) to the first message of the new
  autopilot arriving at the client. The client tells the autopilots apart by their boot
  clocks (``time_boot_ms``; the second sim starts seconds after the first), since both
  speak as the vehicle. Compare with ``cluster.switch_to_mavros_ms`` (re-pointing mavros
  by rolling its pod), which this replaces.
- ``hub.added_latency_p99_ms``: a client's COMMAND_LONG (REQUEST_MESSAGE, not mirrored)
  timed from the client's send to the sim's execution, through the hub and straight to
  the sim's socket, interleaved 2 ms apart (two commands sent back to back reach the sim
  together, and the second waits while it executes the first); the figure is the
  difference of the two p99s.
- ``hub.cpu_ms_per_10k_routed``: the process's CPU time with a client (a separate process
  streaming 50 Hz setpoints and draining telemetry unparsed) minus without, over equal
  windows, per 10 000 messages the hub routed (to the client, from it, mirrored).
"""

from __future__ import annotations

import math
import multiprocessing
import socket
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime

import psutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.core import Figure
from roost_agent import Agent
from roost_agent.bridge import SimulatedBridge
from roost_api.autopilot import (
    AutopilotCommand,
    CommandAction,
    HubSpec,
    RedundantAutopilotSpec,
)
from roost_sim import SimConfig, SimulatedAutopilot, autopilot_specs, start_vehicle_sims, stop_sims
from roost_sim.link import UdpLink
from tests.support.flight import take_off
from tests.support.hubclient import HubClient, Received

COMMAND = "python -m bench hub"
VEHICLE_SYSID = 42
SWITCHES = 40
LATENCY_SAMPLES = 1500
CPU_WINDOW_S = 10.0
BOOT_GAP_S = 3.0


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    index = min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))
    return ordered[index]


@contextmanager
def _vehicle() -> Iterator[tuple[list[SimulatedAutopilot], Agent]]:
    config = SimConfig.fast()
    first = start_vehicle_sims(["px4"], sysids=[1], config=config, name_prefix="a")
    time.sleep(BOOT_GAP_S)  # not a wait for a condition: the boot clocks must differ
    second = start_vehicle_sims(["px4"], sysids=[2], config=config, name_prefix="b")
    sims = first + second
    agent: Agent | None = None
    try:
        spec = RedundantAutopilotSpec(
            vehicle_name="bench",
            autopilots=autopilot_specs(sims),
            primary=sims[0].name,
            hub=HubSpec(sysid=VEHICLE_SYSID, udp="127.0.0.1:0"),
        )
        agent = Agent(spec, SimulatedBridge(range(len(sims))))
        agent.start()
        take_off(sims)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            a = agent.assessments()
            if all(s.name in a and a[s.name].level.value == "OK" for s in sims):
                break
            time.sleep(0.05)
        time.sleep(1.5)  # not a wait for a condition: T_off before switches are allowed
        yield sims, agent
    finally:
        if agent is not None:
            agent.stop()
        stop_sims(sims)


def _boot_at(sim: SimulatedAutopilot) -> float:
    snap = sim.snapshot()
    return time.monotonic() - snap.time_boot_ms / 1000


def _origin(item: Received, boots: dict[str, float]) -> str | None:
    boot_ms = getattr(item.msg, "time_boot_ms", None)
    if not isinstance(boot_ms, int) or boot_ms == 0:
        return None
    name, error = min(
        ((n, abs(item.at - (b + boot_ms / 1000))) for n, b in boots.items()), key=lambda x: x[1]
    )
    return name if error < BOOT_GAP_S / 3 else None


def _switch_to_client(sims: list[SimulatedAutopilot], agent: Agent) -> list[float]:
    assert agent.hub is not None
    boots = {s.name: _boot_at(s) for s in sims}
    samples: list[float] = []
    with HubClient(agent.hub.udp_address) as client:
        client.wait_for(lambda r: r.kind == "HEARTBEAT", 10)
        for i in range(SWITCHES):
            target = sims[(i + 1) % 2].name
            command = AutopilotCommand(
                id=f"bench-switch-{i}",
                action=CommandAction.SWITCH,
                target=target,
                issued_at=datetime.now(UTC),
            )
            result = agent.submit(command).result(timeout=5)
            if result.result != "Executed":
                raise RuntimeError(f"switch {i} to {target}: {result.message}")
            switched_at = agent.failovers()[-1].switched_at

            def from_target(r: Received, t: str = target) -> bool:
                return _origin(r, boots) == t

            first = client.wait_for(from_target, 5, since=switched_at)
            samples.append((first.at - switched_at) * 1000)
            time.sleep(0.3)
    return samples


def _added_latency(
    sims: list[SimulatedAutopilot], agent: Agent, samples: int = LATENCY_SAMPLES
) -> tuple[list[float], list[float]]:
    assert agent.hub is not None
    active = next(s for s in sims if s.name == agent.active)
    hub_mav = mavlink.MAVLink(None, 255, 190)
    direct_mav = mavlink.MAVLink(None, 250, 190)
    hub_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    direct_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    hub_sock.bind(("127.0.0.1", 0))
    direct_sock.bind(("127.0.0.1", 0))
    link = active.link
    assert isinstance(link, UdpLink)
    sim_address = link.local_address
    sent: dict[tuple[int, int], float] = {}
    since = time.monotonic()
    try:
        for i in range(samples):
            for via_hub, mav, sock, target, address in (
                (1, hub_mav, hub_sock, VEHICLE_SYSID, agent.hub.udp_address),
                (0, direct_mav, direct_sock, active.sysid, sim_address),
            ):
                frame = mav.command_long_encode(
                    target, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 1, 0, 0, 0, 0, 0, float(i)
                ).pack(mav)
                sent[(via_hub, i)] = time.monotonic()
                sock.sendto(frame, address)
                # half a period apart: a command sent straight behind the other would
                # reach the sim while it still executes that one, and wait for it
                time.sleep(0.002)
        time.sleep(0.5)  # not a wait for a condition: the last commands drain
    finally:
        hub_sock.close()
        direct_sock.close()
    via: list[float] = []
    direct: list[float] = []
    for record in active.commands:
        if record.at < since or record.command != mavlink.MAV_CMD_REQUEST_MESSAGE:
            continue
        key = (1 if record.source[0] == 255 else 0, int(record.params[6]))
        start = sent.get(key)
        if start is not None and record.source[0] in (255, 250):
            (via if key[0] else direct).append((record.at - start) * 1000)
    return via, direct


def _client_process(address: tuple[str, int], seconds: float) -> None:
    mav = mavlink.MAVLink(None, 255, 190)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    end = time.monotonic() + seconds
    beat = 0.0
    while time.monotonic() < end:
        now = time.monotonic()
        if now >= beat:
            beat = now + 1.0
            hb = mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            sock.sendto(hb.pack(mav), address)
        setpoint = mav.set_position_target_local_ned_encode(
            0, VEHICLE_SYSID, 1, 1, 0xFF8, 0, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0
        )
        sock.sendto(setpoint.pack(mav), address)
        try:
            while sock.recv(65535):
                pass
        except BlockingIOError:
            pass
        time.sleep(0.02)
    sock.close()


def _cpu_per_10k(agent: Agent) -> tuple[float, int, float]:
    hub = agent.hub
    assert hub is not None
    me = psutil.Process()

    def cpu_s() -> float:
        times = me.cpu_times()
        return float(times.user + times.system)

    start = cpu_s()
    time.sleep(CPU_WINDOW_S)  # not a wait for a condition: the idle measurement window
    idle = cpu_s() - start
    c = hub.counters
    ctx = multiprocessing.get_context("spawn")
    client = ctx.Process(target=_client_process, args=(hub.udp_address, CPU_WINDOW_S + 1.0))
    client.start()
    time.sleep(0.5)  # not a wait for a condition: the client's first datagrams arrive
    start = cpu_s()
    mark = c.to_clients + c.from_clients + c.mirrored
    time.sleep(CPU_WINDOW_S)  # not a wait for a condition: the routed measurement window
    busy = cpu_s() - start
    routed = c.to_clients + c.from_clients + c.mirrored - mark
    client.join(timeout=5)
    extra_ms = max(0.0, busy - idle) * 1000
    return (extra_ms * 10_000 / routed if routed else float("nan")), routed, idle


def run() -> list[Figure]:
    with _vehicle() as (sims, agent):
        switches = _switch_to_client(sims, agent)
        via, direct = _added_latency(sims, agent)
        cpu, routed, idle = _cpu_per_10k(agent)
    switch_p99 = _percentile(switches, 0.99)
    added = _percentile(via, 0.99) - _percentile(direct, 0.99)
    return [
        Figure(
            "hub.switch_to_client_p99_ms",
            round(switch_p99, 3),
            "ms",
            "<= 20",
            COMMAND,
            f"{len(switches)} commanded switches between two PX4 sims (onboard rates) in "
            f"flight: bridge write to the new autopilot's first message at a UDP client of "
            f"the hub; median {statistics.median(switches):.2f} ms, max {max(switches):.2f} ms "
            "(the mavros re-point it replaces: cluster.switch_to_mavros_ms)",
        ),
        Figure(
            "hub.added_latency_p99_ms",
            round(added, 3),
            "ms",
            "<= 1",
            COMMAND,
            f"{len(via)}/{len(direct)} COMMAND_LONGs client->sim via the hub / straight to "
            f"the sim, interleaved 2 ms apart: p99 {_percentile(via, 0.99):.3f} vs "
            f"{_percentile(direct, 0.99):.3f} ms, median "
            f"{statistics.median(via):.3f} vs {statistics.median(direct):.3f} ms",
        ),
        Figure(
            "hub.cpu_ms_per_10k_routed",
            round(cpu, 2),
            "ms",
            "informational",
            COMMAND,
            f"process CPU with a client (50 Hz setpoints mirrored to the standby, all "
            f"telemetry to the client) minus without, {CPU_WINDOW_S:.0f} s each; {routed} "
            f"messages routed; idle process CPU {idle * 1000 / CPU_WINDOW_S:.0f} ms/s "
            "(two sims and the agent in one process)",
        ),
    ]
