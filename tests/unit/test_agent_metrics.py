"""The agent's metric collectors on a real Agent, real link counters and real events.

No HTTP here (tests/integration/test_agent_metrics_endpoint.py scrapes a running agent): the
registry is rendered with prometheus_client's exposition and read back with its parser.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from dataclasses import fields
from datetime import UTC, datetime

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families

from roost_agent.agent import Agent, AgentEvent, EventKind, FailoverEvent
from roost_agent.bridge import SimulatedBridge
from roost_agent.hub_policy import NOT_ALLOWED
from roost_agent.kube import AgentKube
from roost_agent.links import LinkCounters
from roost_agent.metrics import (
    FRAME_RESULTS,
    LINK_EVENTS,
    LINK_TOTALS,
    EventMetrics,
    build_registry,
)
from roost_agent.publisher import Publisher, PublisherSettings
from roost_api.autopilot import CommandResult, FailoverRecord, HubEndpoint, HubSpec
from roost_kube.client import Kube
from roost_kube.transport import Credentials, DirectTransport
from tests.support.feed import two_px4_spec
from tests.support.waiting import wait_until

NOW = datetime(2026, 1, 1, tzinfo=UTC)


def make_agent() -> Agent:
    """An agent (not started: no threads) on two UDP links nobody sends to."""
    spec = two_px4_spec(15000)
    return Agent(spec, SimulatedBridge([0, 1]))


def samples(registry: object) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    text = generate_latest(registry).decode()  # type: ignore[arg-type]
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def test_every_link_counter_is_exported() -> None:
    named = set(FRAME_RESULTS) | set(LINK_EVENTS) | set(LINK_TOTALS)
    assert {f.name for f in fields(LinkCounters)} == named


def test_collector_reads_health_active_and_link_counters() -> None:
    agent = make_agent()
    agent.tick()  # assess: nothing heard yet
    link = agent.links["fc2"]
    link.counters.accepted = 120
    link.counters.bad_signature = 3
    link.counters.bytes = 9000
    link.counters.errors = 1
    link.counters.relocked = 2
    registry, unsubscribe = build_registry(agent)
    got = samples(registry)
    unsubscribe()
    assert got[("roost_agent_active_autopilot", (("autopilot", "fc1"),))] == 1
    assert got[("roost_agent_active_autopilot", (("autopilot", "fc2"),))] == 0
    assert got[("roost_agent_latched", ())] == 0
    # silent since start: STALE (4), and the state-set agrees
    assert got[("roost_agent_autopilot_health_level", (("autopilot", "fc2"),))] == 4
    assert got[("roost_agent_autopilot_health", (("autopilot", "fc2"), ("level", "STALE")))] == 1
    assert got[("roost_agent_autopilot_health", (("autopilot", "fc2"), ("level", "OK")))] == 0
    frames = "roost_agent_link_frames_total"
    assert got[(frames, (("autopilot", "fc2"), ("result", "accepted")))] == 120
    assert got[(frames, (("autopilot", "fc2"), ("result", "bad_signature")))] == 3
    assert got[(frames, (("autopilot", "fc1"), ("result", "accepted")))] == 0
    assert got[("roost_agent_link_received_bytes_total", (("autopilot", "fc2"),))] == 9000
    assert got[("roost_agent_link_errors_total", (("autopilot", "fc2"),))] == 1
    events = "roost_agent_link_events_total"
    assert got[(events, (("autopilot", "fc2"), ("event", "relocked")))] == 2
    assert ("roost_agent_publisher_pending_events", ()) not in got  # standalone: no publisher


def test_hub_drops_are_exported_per_endpoint_and_reason() -> None:
    spec = two_px4_spec(15010).model_copy(
        update={
            "hub": HubSpec(
                udp="127.0.0.1:0",
                endpoints=[HubEndpoint(name="ro", address="127.0.0.1:0", scope="ReadOnly")],
            )
        }
    )
    agent = Agent(spec, SimulatedBridge([0, 1]))
    try:
        hub = agent.hub
        assert hub is not None
        ro = next(e for e in hub.endpoints if e.name == "ro")
        ro.drops.note(("127.0.0.1", 40000), NOT_ALLOWED, 0.0)
        ro.drops.note(("127.0.0.1", 40001), NOT_ALLOWED, 1.0)
        registry, unsubscribe = build_registry(agent)
        got = samples(registry)
        unsubscribe()
    finally:
        hub = agent.hub
        if hub is not None:
            hub.close()
    dropped = "roost_agent_hub_dropped_frames_total"
    assert got[(dropped, (("endpoint", "ro"), ("reason", "not_allowed")))] == 2
    assert got[(dropped, (("endpoint", "udp"), ("reason", "unsigned")))] == 0
    assert (dropped, (("endpoint", "ro"), ("reason", "accepted"))) not in got


def event(kind: EventKind, reason: str, **payload: object) -> AgentEvent:
    return AgentEvent(kind, reason, "message", False, NOW, **payload)  # type: ignore[arg-type]


def test_events_feed_failover_latency_safety_and_command_metrics() -> None:
    registry = CollectorRegistry()
    observe = EventMetrics(registry).observe  # what the agent's notifier thread calls
    record = FailoverRecord(
        time=NOW,
        from_autopilot="fc1",
        to_autopilot="fc2",
        reason="fc1: silent",
        latency_ms=0.4,
        trigger="Automatic",
    )
    # detected at 10.0, switched 0.4 ms later; the silence began 520 ms before the switch
    switch = FailoverEvent(record, detected_at=10.0, switched_at=10.0004, onset_at=9.4804)
    observe(event(EventKind.FAILOVER, "FailedOver", autopilot="fc2", failover=switch))
    observe(event(EventKind.SAFETY, "SafetyRoutineHolding", autopilot="fc2"))
    observe(event(EventKind.SAFETY, "SafetyRoutineLanded", autopilot="fc2"))
    command = CommandResult(id="c1", result="Rejected", message="no", time=NOW)
    observe(event(EventKind.COMMAND, "CommandRejected", command=command))
    got = samples(registry)
    key = (("from_autopilot", "fc1"), ("reason", "FailedOver"), ("to_autopilot", "fc2"))
    assert got[("roost_agent_failovers_total", key)] == 1
    det = "roost_agent_failover_detection_to_switch_seconds"
    assert got[(f"{det}_count", ())] == 1
    assert abs(got[(f"{det}_sum", ())] - 0.0004) < 1e-9
    assert got[(f"{det}_bucket", (("le", "0.00025"),))] == 0
    assert got[(f"{det}_bucket", (("le", "0.0005"),))] == 1
    onset = "roost_agent_failover_onset_to_switch_seconds"
    assert got[(f"{onset}_bucket", (("le", "0.5"),))] == 0
    assert got[(f"{onset}_bucket", (("le", "1.0"),))] == 1
    phases = "roost_agent_safety_routine_phases_total"
    assert got[(phases, (("autopilot", "fc2"), ("phase", "Landed")))] == 1
    assert got[("roost_agent_commands_total", (("result", "Rejected"),))] == 1
    assert got[("roost_agent_events_total", (("kind", "Failover"), ("reason", "FailedOver")))] == 1


def test_agent_without_metrics_does_not_import_prometheus_client() -> None:
    code = "import sys, roost_agent.main; print('prometheus_client' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_publisher_queue_and_api_errors_while_the_api_is_unreachable() -> None:
    """A real Publisher whose API server refuses connections (a closed loopback port)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again when the block ends: connections refused
    transport = DirectTransport(Credentials(host=f"http://127.0.0.1:{port}"), retries=0)
    kube = AgentKube(Kube(transport, "roost-agent", (1.0, 1.0)))
    agent = make_agent()
    publisher = Publisher(
        agent,
        kube,
        node_name="n1",
        settings=PublisherSettings(retry_min_s=0.05, retry_max_s=0.1),
    )
    registry, unsubscribe = build_registry(agent, publisher)
    publisher.start()
    agent.start()  # posts AgentStarted: queued, since nothing can be delivered
    try:
        wait_until(
            "discovery failed twice and the Started Event waits",
            lambda: publisher.api_errors >= 2 and publisher.pending_events >= 1,
            10,
        )
        got = samples(registry)
        assert got[("roost_agent_publisher_api_errors_total", ())] >= 2
        assert got[("roost_agent_publisher_pending_events", ())] >= 1
    finally:
        unsubscribe()
        agent.stop()
        publisher.stop()
