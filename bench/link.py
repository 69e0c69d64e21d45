"""Link-trust benchmarks: what a hostile sender on the agent's ports costs.

How it measures: two simulated PX4 autopilots stream at PX4 onboard-like rates (about
470 messages/s each) to a ``roost-agent`` process (standalone, simulated bridge,
failover mode Manual so that the counting pauses below cannot switch anything). A
:class:`roost_sim.hostile.HostileSender` beside them sends to the same agent ports,
first at the rate of the tests (10 rounds/s: garbage, truncated, bad-CRC and spoofed
frames, 10/s EMERGENCY heartbeats), then as a flood. Both phases are bounded in time and
go to 127.0.0.1 only.

- ``link.real_msgs_lost_per_10k_hostile``: the autopilots' frames sent during both
  phases minus the frames the agent accepted from them, per 10,000 sent. The sims are
  silenced for a moment before and after, so no frame is in flight when counted.
- ``link.agent_cpu_pct_hostile_flood``: the agent process's user+system CPU, in percent
  of one core, while the flood runs (target rate :data:`FLOOD_PER_S` datagrams/s; the
  achieved rate is in the note).

Knobs (environment): ``ROOST_BENCH_HOSTILE_S`` (default 20), ``ROOST_BENCH_FLOOD_S``
(default 10).
"""

from __future__ import annotations

import os
import time

import psutil

from bench.agent import PX4_ONBOARD_RATES, vehicle
from bench.core import Figure
from roost_api.autopilot import FailoverMode, Thresholds
from roost_sim import FaultKind, SimulatedAutopilot
from roost_sim.hostile import HostileSender, Target
from roost_sim.link import UdpLink
from tests.support.agent import AgentProcess

HOSTILE_S = float(os.environ.get("ROOST_BENCH_HOSTILE_S", "20"))
FLOOD_S = float(os.environ.get("ROOST_BENCH_FLOOD_S", "10"))
FLOOD_PER_S = 20_000
DATAGRAMS_PER_ROUND = 7
COMMAND = "python -m bench link"


def _agent_port(sim: SimulatedAutopilot) -> int:
    link = sim.link
    assert isinstance(link, UdpLink) and link.target is not None
    return link.target[1]


def _quiet_totals(sims: list[SimulatedAutopilot], agent: AgentProcess) -> tuple[int, int]:
    """(frames the sims sent, frames the agent accepted), nothing in flight."""
    for sim in sims:
        sim.inject(FaultKind.SILENCE)
    time.sleep(0.3)
    agent.read()
    agent.wait_for(lambda d: "status" in d, 5)  # a status line printed after the silence began
    sent = sum(s.link.frames_sent for s in sims)
    accepted = sum(c["accepted"] for c in agent.links.values())
    for sim in sims:
        sim.clear()
    return sent, accepted


def measure() -> tuple[int, int, float, float, int, dict[str, int]]:
    """(real frames sent, lost, agent CPU % in the flood, achieved flood datagrams/s,
    hostile datagrams in all, link counters summed)."""
    with vehicle(Thresholds(), PX4_ONBOARD_RATES, mode=FailoverMode.MANUAL) as (sims, agent):
        targets = [Target(_agent_port(s), s.sysid) for s in sims]
        sent0, accepted0 = _quiet_totals(sims, agent)
        with HostileSender(targets, rounds_per_s=10.0, duration_s=HOSTILE_S) as steady:
            time.sleep(HOSTILE_S)
        rounds = FLOOD_PER_S / (DATAGRAMS_PER_ROUND * len(targets))
        proc = psutil.Process(agent.pid)
        with HostileSender(targets, rounds_per_s=rounds, duration_s=FLOOD_S) as flood:
            cpu0, t0 = sum(proc.cpu_times()[:2]), time.monotonic()
            time.sleep(FLOOD_S)
            cpu1, t1 = sum(proc.cpu_times()[:2]), time.monotonic()
            flooded = flood.sent
        sent1, accepted1 = _quiet_totals(sims, agent)
        totals: dict[str, int] = {}
        for counters in agent.links.values():
            for key, value in counters.items():
                totals[key] = totals.get(key, 0) + int(value)
        sent = sent1 - sent0
        lost = sent - (accepted1 - accepted0)
        cpu_pct = (cpu1 - cpu0) / (t1 - t0) * 100
        return sent, lost, cpu_pct, flooded / (t1 - t0), steady.sent + flood.sent, totals


def run() -> list[Figure]:
    sent, lost, cpu_pct, flood_rate, hostile, totals = measure()
    counted = ", ".join(
        f"{k} {totals.get(k, 0)}"
        for k in ("foreign", "bad", "unknown", "truncated", "other", "errors")
    )
    return [
        Figure(
            "link.real_msgs_lost_per_10k_hostile",
            round(lost * 10_000 / sent, 3) if sent else float("nan"),
            "msgs",
            "== 0",
            COMMAND,
            f"{lost} of {sent} autopilot frames lost over {HOSTILE_S:.0f} s of hostile traffic "
            f"at 10 rounds/s and {FLOOD_S:.0f} s of flood ({hostile} hostile datagrams: "
            "garbage, truncated, bad CRC, spoofed sysid, low time_boot_ms ATTITUDE, EMERGENCY "
            f"heartbeats) beside two PX4 sims at onboard rates; agent counters: {counted}",
        ),
        Figure(
            "link.agent_cpu_pct_hostile_flood",
            round(cpu_pct, 1),
            "%",
            "",
            COMMAND,
            f"roost-agent user+system CPU (percent of one core) during a {FLOOD_S:.0f} s flood "
            f"of {flood_rate:.0f} hostile datagrams/s (asked {FLOOD_PER_S}/s) on loopback, "
            "two PX4 sims streaming beside it; foreign datagrams are counted, never parsed",
        ),
    ]
