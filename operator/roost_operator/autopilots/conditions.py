"""The Vehicle conditions the operator derives from its RedundantAutopilot's status.

The node agent writes the RedundantAutopilot's conditions (``ActiveHealthy``,
``Redundant``, ``FailedOver``, ``Ready``); the operator turns them into two conditions
on the Vehicle, because users, ``kubectl get vehicles`` and mission preflight look at the
Vehicle:

``AgentConnected``
    ``True`` while the agent's ``status.reportedAt`` is recent. The agent re-reports at
    least every :data:`AGENT_REPORT_PERIOD` even when nothing changes, so a report older
    than the staleness window (default :data:`DEFAULT_AGENT_STALE_AFTER`, three missed
    reports, like a node lease's 10 s renewals against a 40 s grace period) means the
    agent, its node or the link to it is gone. The condition then becomes ``Unknown`` —
    never ``False``: a silent agent may still be flying the vehicle perfectly well.

``AutopilotsHealthy``
    Follows the RedundantAutopilot's ``Ready`` while the agent is connected, with the
    reason naming the first thing that is wrong (active autopilot unhealthy, failed over
    with no healthy standby left, no redundancy). ``Unknown`` when the agent is not
    connected: a stale report is not evidence of health.

Both compare the agent's timestamps with the operator's clock: vehicles and cluster are
assumed to keep time with NTP (their TLS certificates need it too). A report stamped in
the future counts as fresh rather than stale, so a fast drone clock never raises a false
alarm; a slow one shortens the window by its offset.

Pure functions: no API calls, ``now`` is a parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

from roost_api.autopilot import AutopilotConditionType, RedundantAutopilotStatus
from roost_api.meta import ConditionStatus, find_condition
from roost_api.vehicle import VehicleConditionReason, VehicleConditionType

AGENT_REPORT_PERIOD = timedelta(seconds=10)
"""How often the agent re-reports when nothing changes (its publisher's default)."""

DEFAULT_AGENT_STALE_AFTER = 3 * AGENT_REPORT_PERIOD
"""Age of the last report after which ``AgentConnected`` turns ``Unknown`` (the
operator's ``Settings.agent_stale_after`` defaults to it)."""


@dataclass(frozen=True)
class ConditionUpdate:
    """A condition the operator wants set; applied with ``roost_api.meta.set_condition``."""

    type: str
    status: ConditionStatus
    reason: str
    message: str


def _age_text(age: timedelta) -> str:
    return f"{age.total_seconds():.0f} s"


def agent_connected(
    status: RedundantAutopilotStatus,
    *,
    vehicle_node: str,
    now: datetime,
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER,
) -> ConditionUpdate:
    """``AgentConnected`` from the agent's last report on the RedundantAutopilot."""
    kind = VehicleConditionType.AGENT_CONNECTED.value
    if status.reported_at is None:
        return ConditionUpdate(
            kind,
            "Unknown",
            VehicleConditionReason.NEVER_REPORTED,
            f"no agent on node {vehicle_node} has reported yet",
        )
    if status.node_name and status.node_name != vehicle_node:
        return ConditionUpdate(
            kind,
            "Unknown",
            VehicleConditionReason.REPORT_FROM_OTHER_NODE,
            f"last report came from node {status.node_name}, but the vehicle is on node "
            f"{vehicle_node}; waiting for the agent there",
        )
    age = now - status.reported_at
    if age > stale_after:
        return ConditionUpdate(
            kind,
            "Unknown",
            VehicleConditionReason.REPORTS_STALE,
            f"agent on node {vehicle_node} last reported {_age_text(age)} ago "
            f"(stale after {_age_text(stale_after)})",
        )
    return ConditionUpdate(
        kind,
        "True",
        VehicleConditionReason.REPORTING,
        f"agent on node {vehicle_node} reports; active autopilot "
        f"{status.active_autopilot or 'not chosen yet'}",
    )


def autopilots_healthy(
    status: RedundantAutopilotStatus, connected: ConditionUpdate
) -> ConditionUpdate:
    """``AutopilotsHealthy`` from the agent's RedundantAutopilot conditions.

    ``connected`` is this vehicle's ``AgentConnected`` (from :func:`agent_connected`).
    """
    kind = VehicleConditionType.AUTOPILOTS_HEALTHY.value
    if connected.status != "True":
        return ConditionUpdate(
            kind,
            "Unknown",
            VehicleConditionReason.AGENT_NOT_CONNECTED,
            f"autopilot health unknown: {connected.message}",
        )
    conditions = status.conditions
    ready = find_condition(conditions, AutopilotConditionType.READY)
    active = find_condition(conditions, AutopilotConditionType.ACTIVE_HEALTHY)
    redundant = find_condition(conditions, AutopilotConditionType.REDUNDANT)
    failed_over = find_condition(conditions, AutopilotConditionType.FAILED_OVER)
    if ready is not None and ready.status == "True":
        return ConditionUpdate(kind, "True", VehicleConditionReason.REDUNDANT, ready.message)
    if active is None or active.status == "Unknown":
        message = active.message if active else "the agent has not judged the active autopilot"
        return ConditionUpdate(
            kind, "Unknown", VehicleConditionReason.ACTIVE_HEALTH_UNKNOWN, message
        )
    if active.status == "False":
        return ConditionUpdate(
            kind, "False", VehicleConditionReason.ACTIVE_UNHEALTHY, active.message
        )
    if redundant is not None and redundant.status == "False":
        if failed_over is not None and failed_over.status == "True":
            return ConditionUpdate(
                kind,
                "False",
                VehicleConditionReason.FAILED_OVER,
                f"{failed_over.message}; {redundant.message}",
            )
        return ConditionUpdate(
            kind, "False", VehicleConditionReason.NOT_REDUNDANT, redundant.message
        )
    if redundant is None or redundant.status == "Unknown":
        message = redundant.message if redundant else "the agent has not judged redundancy"
        return ConditionUpdate(kind, "Unknown", VehicleConditionReason.REDUNDANCY_UNKNOWN, message)
    if ready is None or ready.status == "Unknown":
        message = ready.message if ready else "the agent has not reported Ready"
        return ConditionUpdate(kind, "Unknown", VehicleConditionReason.READY_UNKNOWN, message)
    return ConditionUpdate(kind, "False", ready.reason, ready.message)
