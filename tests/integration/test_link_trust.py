"""The agent trusts only its autopilots: real UDP, simulated autopilots, a hostile sender.

Everything runs on 127.0.0.1: simulated autopilots stream to an in-process agent, and a
hostile sender beside them sends to the same agent ports what an attacker would (garbage,
truncated and bad-CRC frames, frames spoofing the autopilot's ids from another address: a
low ``time_boot_ms`` ATTITUDE and 10/s EMERGENCY heartbeats).
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from roost_agent import Agent
from roost_agent.bridge import SimulatedBridge
from roost_agent.events import AgentEvent, EventKind
from roost_agent.health import HealthTracker
from roost_agent.link import AutopilotLink
from roost_agent.signing import LinkSigning, PersistentTimestamps
from roost_agent.state import STATE_FILE_NAME, StateFile
from roost_api.autopilot import (
    AutopilotSpec,
    FailoverPolicy,
    RedundantAutopilotSpec,
    SafetyRoutine,
    Thresholds,
)
from roost_api.meta import HealthLevel
from roost_sim import (
    FaultKind,
    SimConfig,
    SimulatedAutopilot,
    autopilot_specs,
    free_udp_port,
    start_vehicle_sims,
    stop_sims,
)
from roost_sim.hostile import HostileSender, Target
from roost_sim.link import UdpLink
from tests.support.flight import take_off
from tests.support.waiting import wait_until

# Sub-second start-up; ArduPilot streams as with its SRn_* parameters set, since this
# agent does not request streams itself.
SIM_CONFIG = SimConfig.fast(preset_streams=True)
KEY = bytes(range(32))
WRONG_KEY = bytes(range(100, 132))


class Events:
    """Every event of an agent, collected on its notifier thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.seen: list[AgentEvent] = []

    def __call__(self, event: AgentEvent) -> None:
        with self._lock:
            self.seen.append(event)

    def clear(self) -> None:
        with self._lock:
            self.seen.clear()

    def reasons(self, kind: EventKind | None = None) -> list[str]:
        with self._lock:
            return [e.reason for e in self.seen if kind is None or e.kind == kind]

    def errors_of(self, name: str) -> list[str]:
        with self._lock:
            return [
                e.message
                for e in self.seen
                if e.kind == EventKind.HEALTH
                and e.autopilot == name
                and e.health is not None
                and e.health.level in (HealthLevel.ERROR, HealthLevel.STALE)
            ]


def udp(sim: SimulatedAutopilot) -> UdpLink:
    assert isinstance(sim.link, UdpLink)
    return sim.link


def agent_port(sim: SimulatedAutopilot) -> int:
    """The port the sim streams to (where the agent listens)."""
    target = udp(sim).target
    assert target is not None
    return target[1]


def levels(agent: Agent) -> dict[str, HealthLevel]:
    return {name: a.level for name, a in agent.assessments().items()}


@contextmanager
def agent_for(
    sims: list[SimulatedAutopilot], state_dir: Path, signing: LinkSigning | None = None
) -> Iterator[tuple[Agent, Events]]:
    spec = RedundantAutopilotSpec(
        vehicle_name="v1",
        autopilots=autopilot_specs(sims),
        primary=sims[0].name,
        failover_policy=FailoverPolicy(safety_routine=SafetyRoutine(hold_seconds=1.0)),
    )
    agent = Agent(
        spec,
        SimulatedBridge(range(len(sims))),
        state_file=StateFile(state_dir / STATE_FILE_NAME),
        signing=signing,
    )
    events = Events()
    agent.subscribe(events)
    agent.start()
    try:
        yield agent, events
    finally:
        agent.stop()


def _quiet_counts(sim: SimulatedAutopilot, link: AutopilotLink) -> tuple[int, int]:
    """(frames the sim sent, frames the link accepted) with nothing in flight."""
    sim.inject(FaultKind.SILENCE)
    time.sleep(0.3)
    return sim.link.frames_sent, link.counters.accepted


# serial: no failover under a flood, judged in real time
@pytest.mark.serial
def test_a_hostile_sender_costs_the_autopilots_nothing_and_hears_nothing(tmp_path: Path) -> None:
    """Partly a "nothing happens for N s" test: 6 s of hostile traffic (10 rounds/s of
    garbage, truncated, bad-CRC and spoofed frames per autopilot port) must cause no
    failover and no lost autopilot frame; then a real failover and its safety routine run
    with the hostile sender still there, and none of the agent's datagrams reach it."""
    sims = start_vehicle_sims(["px4", "ardupilot"], config=SIM_CONFIG)
    try:
        with agent_for(sims, tmp_path) as (agent, events):
            take_off(sims)
            wait_until("both OK", lambda: set(levels(agent).values()) == {HealthLevel.OK}, 15, 0.02)
            standby, link = sims[1], agent.links["fc2"]
            sent0, accepted0 = _quiet_counts(standby, link)
            standby.clear()
            wait_until("fc2 OK again", lambda: levels(agent)["fc2"] == HealthLevel.OK, 10, 0.02)
            targets = [Target(agent_port(s), s.sysid) for s in sims]
            events.clear()
            with HostileSender(targets, rounds_per_s=10.0, duration_s=60.0) as hostile:
                time.sleep(6.0)
                assert agent.failovers() == [] and agent.active == "fc1"
                assert events.errors_of("fc1") == []
                sent1, accepted1 = _quiet_counts(standby, link)
                assert accepted1 - accepted0 == sent1 - sent0 > 0  # not one frame lost
                for name, lnk in agent.links.items():
                    assert lnk.counters.foreign > 100, name
                    assert lnk.locked_address == udp(sims[int(name[-1]) - 1]).local_address
                assert "ForeignMavlinkTraffic" in events.reasons(EventKind.LINK)
                assert all(lnk.tracker.refuted == 0 for lnk in agent.links.values())
                # A real failover under attack: the safety routine's commands go to fc2.
                standby.clear()
                wait_until("fc2 OK", lambda: levels(agent)["fc2"] == HealthLevel.OK, 10, 0.02)
                time.sleep(1.2)  # T_off: fc2 is a failover target again
                sims[0].inject(FaultKind.SILENCE)
                wait_until("failover to fc2", lambda: agent.active == "fc2", 5, 0.02)
                wait_until("safety routine commands", lambda: len(standby.commands) > 0, 5, 0.02)
                time.sleep(0.5)
            assert hostile.sent > 500
            assert hostile.received == []  # no datagram of the agent reached the spoofer
    finally:
        stop_sims(sims)


def test_signing_required_hears_only_well_signed_autopilots(tmp_path: Path) -> None:
    sims = start_vehicle_sims(["px4", "px4", "px4"], config=SIM_CONFIG)
    good, wrong_key, _unsigned = sims
    good.link.enable_signing(KEY, link_id=1)
    wrong_key.link.enable_signing(WRONG_KEY, link_id=1)
    state = tmp_path / "state"
    try:
        clock = PersistentTimestamps(state / "signing-timestamp")
        signing = LinkSigning(key=KEY, require=True, clock=clock)
        with agent_for(sims, state, signing) as (agent, events):
            wait_until("fc1 OK", lambda: levels(agent).get("fc1") == HealthLevel.OK, 10, 0.02)
            counters = good.link.signing_counters
            assert counters is not None
            wait_until("the agent's signed heartbeat", lambda: counters.good > 0, 5, 0.02)
            assert counters.unsigned == counters.bad == 0
            wait_until("bad sigs", lambda: agent.links["fc2"].counters.bad_signature > 20, 5, 0.02)
            wait_until(
                "unsigned frames", lambda: agent.links["fc3"].counters.unsigned > 20, 5, 0.02
            )
            assert agent.links["fc2"].counters.accepted == 0
            assert agent.links["fc3"].counters.accepted == 0
            assert levels(agent)["fc2"] == levels(agent)["fc3"] == HealthLevel.STALE
            wait_until(
                "Event", lambda: "UnsignedMavlink" in events.reasons(EventKind.LINK), 15, 0.02
            )
            messages = " ".join(e.message for e in events.seen)
            assert KEY.hex() not in messages and WRONG_KEY.hex() not in messages
        first_run = counters.good
        # A restarted agent signs with timestamps beyond every one it used before: the
        # autopilot (which remembers the stream) keeps accepting it.
        restarted = LinkSigning(
            key=KEY, require=True, clock=PersistentTimestamps(state / "signing-timestamp")
        )
        assert restarted.clock.current() >= clock.current()
        with agent_for(sims, state, restarted) as (agent, _):
            wait_until("signed heartbeat after restart", lambda: counters.good > first_run, 5, 0.02)
            assert counters.bad == 0
    finally:
        stop_sims(sims)


def test_the_link_relocks_when_the_autopilot_comes_back_on_another_port() -> None:
    first = SimulatedAutopilot.udp(
        "px4", 1, target_port=free_udp_port(), name="fc1", config=SIM_CONFIG
    ).start()
    port = agent_port(first)
    spec = AutopilotSpec(
        name="fc1", stack="px4", connection=f"udp://127.0.0.1:{port}", sysid=1, bridge_channel=0
    )
    seen: list[tuple[str, str]] = []
    thresholds = Thresholds(heartbeat_warn_ms=500, heartbeat_error_ms=1000)
    link = AutopilotLink(
        spec,
        HealthTracker("fc1", spec.stack, thresholds),
        on_event=lambda reason, message, warning: seen.append((reason, message)),
    )
    second: SimulatedAutopilot | None = None
    link.start()
    try:
        wait_until("first lock", lambda: link.locked_address == udp(first).local_address, 5, 0.02)
        first.stop()  # the autopilot reboots; it comes back sending from another port
        second = SimulatedAutopilot.udp(
            "px4", 1, target_port=port, name="fc1", config=SIM_CONFIG
        ).start()
        wait_until("relock", lambda: link.locked_address == udp(second).local_address, 10, 0.02)
        locks = [r for r, _ in seen if r.startswith("Autopilot")]
        assert locks == ["AutopilotLocked", "AutopilotAddressChanged"]
        assert link.counters.relocked == 1
        accepted = link.counters.accepted
        wait_until(
            "messages from the new port", lambda: link.counters.accepted > accepted + 10, 5, 0.02
        )
    finally:
        link.stop()
        first.stop()
        if second is not None:
            second.stop()


def test_a_link_that_cannot_open_reports_retries_and_recovers(tmp_path: Path) -> None:
    """The agent's port is taken by another socket: the link reports the error (Event and
    status), keeps retrying, and works once the port is free."""
    blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    blocker.bind(("127.0.0.1", 0))
    port = blocker.getsockname()[1]
    sims = [
        SimulatedAutopilot.udp("px4", 1, target_port=port, name="fc1", config=SIM_CONFIG).start(),
        SimulatedAutopilot.udp(
            "px4", 2, target_port=free_udp_port(), name="fc2", config=SIM_CONFIG
        ).start(),
    ]
    try:
        with agent_for(sims, tmp_path) as (agent, events):
            wait_until("LinkError", lambda: "LinkError" in events.reasons(EventKind.LINK), 5, 0.02)
            reasons = wait_until(
                "fc1 status",
                lambda: [a.reasons for a in agent.status().autopilots if a.name == "fc1"],
                5,
                0.02,
            )
            assert any("link error: OSError" in r for r in reasons[0]), reasons
            wait_until("retries", lambda: agent.links["fc1"].counters.reopened >= 2, 5, 0.02)
            assert agent.links["fc1"].error is not None
            assert events.reasons(EventKind.LINK).count("LinkError") == 1  # no Event storm
            blocker.close()
            wait_until("fc1 OK", lambda: levels(agent).get("fc1") == HealthLevel.OK, 20, 0.02)
            assert agent.links["fc1"].error is None
            # the Event is emitted on the agent's event thread, after the health turned OK
            wait_until(
                "LinkRecovered", lambda: "LinkRecovered" in events.reasons(EventKind.LINK), 5, 0.02
            )
    finally:
        blocker.close()
        stop_sims(sims)


@pytest.mark.parametrize(
    ("connection", "why"),
    [
        ("udp://127.0.0.1:0", "port 0 is not 1-65535"),
        ("udp://127.0.0.1:70000", "port 70000 is not 1-65535"),
        ("udpout://:14550", "lacks a host"),
        ("serial:///home/fc:57600", "a path under /dev/"),
        ("serial:///dev/ttyUSB0:fast", "baud 'fast' is not a positive number"),
    ],
)
def test_a_bad_connection_is_refused_at_start_in_one_line(
    tmp_path: Path, connection: str, why: str
) -> None:
    exe = Path(sys.executable).with_name("roost-agent")
    bad = f"name=fc1,stack=px4,connection={connection},sysid=1,channel=0"
    good = f"name=fc2,stack=px4,connection=udp://127.0.0.1:{free_udp_port()},sysid=2,channel=1"
    flags = ["--autopilot", bad, "--autopilot", good, "--state-dir", str(tmp_path)]
    done = subprocess.run(
        [str(exe), *flags, "--cluster", "off"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and why in lines[0] and "fc1" in lines[0], done.stderr
    assert "Traceback" not in done.stderr and done.stdout == ""
