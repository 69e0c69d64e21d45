"""Pieces of the agent's publisher that need no API server: transition times carried
across agent restarts, deterministic Event names, and which agent events are posted."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from roost_agent.events import AgentEvent, EventKind
from roost_agent.publisher import POSTED_KINDS, carry_transitions, merge_patch_body, posted
from roost_api.autopilot import AutopilotHealth, FailoverRecord, RedundantAutopilotStatus
from roost_api.meta import HealthLevel
from tests.support.conditions import cond

T0 = datetime(2026, 5, 1, 12, 0, 0, tzinfo=UTC)
LATER = T0 + timedelta(minutes=5)


def test_a_restarted_agent_keeps_the_transition_times_already_in_the_api() -> None:
    written = [cond("Ready", at=T0), cond("Redundant", at=T0), cond("Old", at=T0)]
    current = [
        cond("Ready", "True", "Ready", at=LATER),  # unchanged status: keeps T0
        cond("Redundant", "False", "NoHealthyStandby", at=LATER),  # changed: LATER
    ]
    merged = {c.type: c for c in carry_transitions(written, current)}
    assert set(merged) == {"Ready", "Redundant"}  # types the agent no longer sets go
    assert merged["Ready"].last_transition_time == T0 and merged["Ready"].reason == "Ready"
    assert merged["Redundant"].last_transition_time == LATER


def test_health_changes_are_never_posted_as_events() -> None:
    """Under a flapping link they would be a storm; conditions carry them instead."""
    assert EventKind.HEALTH not in POSTED_KINDS
    assert EventKind.FAILOVER in POSTED_KINDS and EventKind.COMMAND in POSTED_KINDS
    # Link failures, foreign senders and bad signatures are posted; the links rate-limit
    # them at the source (one per error text, one per alarm quiet time).
    assert EventKind.LINK in POSTED_KINDS


def test_a_parameter_drift_is_posted_and_the_conditions_steps_are_not() -> None:
    def event(kind: EventKind, reason: str) -> AgentEvent:
        return AgentEvent(kind, reason, "fc1: ...", warning=True, time=T0)

    assert posted(event(EventKind.PARAMETERS, "ParameterDrifted"))
    assert not posted(event(EventKind.PARAMETERS, "ParametersWriting"))
    assert posted(event(EventKind.SPEC, "SpecRejected"))
    assert not posted(event(EventKind.SPEC, "SpecApplied"))


def test_the_status_patch_removes_what_the_agent_no_longer_reports() -> None:
    status = RedundantAutopilotStatus(
        active_autopilot="fc2",
        autopilots=[AutopilotHealth(name="fc1", level=HealthLevel.STALE)],
        last_failover=FailoverRecord.model_validate(
            {
                "time": T0,
                "from": "fc1",
                "to": "fc2",
                "reason": "r",
                "latencyMs": 1.0,
                "trigger": "Automatic",
            }
        ),
    )
    body = merge_patch_body(status)
    assert body["lastCommand"] is None  # top-level: null deletes it
    assert body["lastFailover"]["safetyRoutine"] is None  # object member: null deletes it
    assert body["autopilots"] == [
        {"name": "fc1", "level": "STALE", "reasons": [], "unhealthySensors": [], "conditions": []}
    ]  # list items: no nulls
