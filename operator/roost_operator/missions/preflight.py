"""Preflight: the checks every assigned vehicle passes before anything starts on it.

Each check reads one writer's verdict rather than re-deriving it: ``NodeBound``,
``ComponentsReady`` and ``AgentConnected`` are the operator's conditions on the Vehicle,
``ActiveHealthy`` and ``Redundant`` are the node agent's on the RedundantAutopilot. A
condition that is absent counts as failing: before the agent has ever reported, nobody
knows the vehicle is fit to fly. Which checks apply is the mission's ``spec.preflight``;
the vehicle-side checks (node bound, components ready) always do, and so does the
firmware check of a RedundantAutopilot that requires a firmware (``spec.firmware``):
the agent's ``FirmwareAcceptable`` condition, whose message names the autopilot that
breaks the requirement. The Vehicle's summary
``Ready`` is not used: it also requires redundancy, which a mission may waive.
"""

from __future__ import annotations

from dataclasses import dataclass

from roost_api.autopilot import AutopilotConditionType
from roost_api.meta import Condition, find_condition
from roost_api.mission import MissionVehicleReason, Preflight
from roost_api.vehicle import VehicleConditionType
from roost_operator.missions.observed import AutopilotView, VehicleView
from roost_operator.missions.selection import is_claimable, unfit_reason


@dataclass(frozen=True)
class PreflightFailure:
    """One failed check: a CamelCase reason and a sentence for people."""

    reason: str
    message: str


def _condition_text(condition: Condition | None, missing: str) -> str:
    if condition is None:
        return missing
    detail = f": {condition.message}" if condition.message else ""
    return f"{condition.status} ({condition.reason}{detail})"


def preflight_failures(
    vehicle: VehicleView | None, autopilots: AutopilotView | None, checks: Preflight
) -> list[PreflightFailure]:
    """Every check ``vehicle`` fails, in a fixed order; empty when it may start."""
    if vehicle is None:
        return [
            PreflightFailure(MissionVehicleReason.VEHICLE_MISSING, "the Vehicle no longer exists")
        ]
    failures: list[PreflightFailure] = []
    if not is_claimable(vehicle):
        failures.append(
            PreflightFailure(
                MissionVehicleReason.VEHICLE_NOT_READY,
                f"vehicle not ready: {unfit_reason(vehicle)}",
            )
        )
    if checks.require_agent_connected:
        agent = find_condition(vehicle.status.conditions, VehicleConditionType.AGENT_CONNECTED)
        if agent is None or agent.status != "True":
            failures.append(
                PreflightFailure(
                    MissionVehicleReason.AGENT_NOT_CONNECTED,
                    "node agent not connected: "
                    + _condition_text(agent, "no AgentConnected condition yet"),
                )
            )
    autopilot_checks = [
        (
            checks.require_active_healthy,
            AutopilotConditionType.ACTIVE_HEALTHY,
            MissionVehicleReason.ACTIVE_AUTOPILOT_UNHEALTHY,
            "active autopilot not healthy",
        ),
        (
            checks.require_redundancy,
            AutopilotConditionType.REDUNDANT,
            MissionVehicleReason.NOT_REDUNDANT,
            "no healthy standby autopilot",
        ),
    ]
    for required, condition_type, reason, summary in autopilot_checks:
        if not required:
            continue
        if autopilots is None:
            failures.append(
                PreflightFailure(reason, f"{summary}: no RedundantAutopilot for this vehicle")
            )
            continue
        condition = find_condition(autopilots.status.conditions, condition_type)
        if condition is None or condition.status != "True":
            missing = f"no {condition_type} condition from the agent yet"
            failures.append(
                PreflightFailure(reason, f"{summary}: {_condition_text(condition, missing)}")
            )
    if autopilots is not None and autopilots.spec.firmware is not None:
        condition = find_condition(
            autopilots.status.conditions, AutopilotConditionType.FIRMWARE_ACCEPTABLE
        )
        if condition is None or condition.status != "True":
            missing = "no FirmwareAcceptable condition from the agent yet"
            failures.append(
                PreflightFailure(
                    MissionVehicleReason.FIRMWARE_UNACCEPTABLE,
                    f"firmware requirement not met: {_condition_text(condition, missing)}",
                )
            )
    return failures
