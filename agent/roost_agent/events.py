"""What the agent tells its subscribers: failovers, health changes, safety-routine
progress, command results.

Why this module exists apart from the agent: the publisher (:mod:`roost_agent.publisher`),
the metrics (:mod:`roost_agent.metrics`), the flight recorder and the standalone JSON
printer read these events without needing the agent's loop, and the agent's actions
(:mod:`roost_agent.actions`) and spec handling (:mod:`roost_agent.spec_changes`) emit
them. :meth:`roost_agent.agent.Agent.subscribe` delivers them on a notifier thread, so
a slow subscriber cannot stall a switch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import Any

from roost_api.plain import AutopilotHealth, CommandResult, FailoverRecord


class EventKind(StrEnum):
    """What an :class:`AgentEvent` is about."""

    STARTED = "Started"
    FAILOVER = "Failover"
    HEALTH = "HealthChanged"
    SAFETY = "SafetyRoutine"
    COMMAND = "Command"
    LAND_ORDERED = "LandOrdered"
    NO_HEALTHY_STANDBY = "NoHealthyStandby"
    EMERGENCY_STOP = "EmergencyStop"
    SPEC = "Spec"
    BRIDGE_ERROR = "BridgeError"
    LINK = "Link"
    PARAMETERS = "Parameters"
    FENCE = "Fence"


@dataclass(frozen=True)
class FailoverEvent:
    """One bridge switch with its timing (monotonic seconds)."""

    record: FailoverRecord
    detected_at: float
    switched_at: float
    onset_at: float | None

    @property
    def latency_ms(self) -> float:
        """Detection to bridge switched."""
        return (self.switched_at - self.detected_at) * 1000

    @property
    def onset_to_switch_ms(self) -> float | None:
        """Start of the failure (as the findings know it) to bridge switched."""
        return None if self.onset_at is None else (self.switched_at - self.onset_at) * 1000


@dataclass(frozen=True)
class AgentEvent:
    """Something a publisher reports; ``reason``/``message``/``warning`` map onto a
    Kubernetes Event, the optional payloads onto status fields."""

    kind: EventKind
    reason: str
    message: str
    warning: bool
    time: datetime
    autopilot: str | None = None
    failover: FailoverEvent | None = None
    health: AutopilotHealth | None = None
    command: CommandResult | None = None

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (the standalone agent prints these, one per line)."""
        doc: dict[str, Any] = {
            "event": self.kind.value,
            "reason": self.reason,
            "message": self.message,
            "warning": self.warning,
            "time": self.time.isoformat(),
        }
        if self.autopilot is not None:
            doc["autopilot"] = self.autopilot
        if self.failover is not None:
            doc["failover"] = self.failover.record.to_api()
            doc["latencyMs"] = self.failover.latency_ms
            doc["onsetToSwitchMs"] = self.failover.onset_to_switch_ms
            # CLOCK_MONOTONIC seconds, comparable with time.monotonic() in any process
            # on the same host (benchmarks measure fault onset -> switch with them).
            doc["monotonic"] = {
                "detectedAt": self.failover.detected_at,
                "switchedAt": self.failover.switched_at,
                "onsetAt": self.failover.onset_at,
            }
        if self.health is not None:
            doc["health"] = self.health.to_api()
        if self.command is not None:
            doc["command"] = self.command.to_api()
        return doc


Listener = Callable[[AgentEvent], None]
