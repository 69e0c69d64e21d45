"""The agent's metric pieces without a link: every link counter exported, and the event
metrics (failover latency, safety routine, commands) fed by real events.

The registry is rendered with prometheus_client's exposition and read back with its
parser. Collectors on a real Agent and Publisher (bound sockets) are in
``tests/integration/test_agent_metrics_on_links.py``; the scraped agent in
``tests/integration/test_agent_metrics_endpoint.py``.
"""

from __future__ import annotations

from dataclasses import fields
from datetime import UTC, datetime

from prometheus_client import CollectorRegistry

from roost_agent.events import AgentEvent, EventKind, FailoverEvent
from roost_agent.link import LinkCounters
from roost_agent.metrics import (
    FRAME_RESULTS,
    LINK_EVENTS,
    LINK_TOTALS,
    EventMetrics,
)
from roost_api.autopilot import CommandResult, FailoverRecord
from tests.support.prometheus import samples

NOW = datetime(2026, 1, 1, tzinfo=UTC)


def test_every_link_counter_is_exported() -> None:
    named = set(FRAME_RESULTS) | set(LINK_EVENTS) | set(LINK_TOTALS)
    assert {f.name for f in fields(LinkCounters)} == named


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
