"""A Vehicle's conditions, as pure functions: NodeBound, ComponentsReady, Ready, and
which transitions are worth an Event.

Every Vehicle condition is set here (the failover ones, AgentConnected and
AutopilotsHealthy, are decided by :mod:`roost_operator.autopilots.conditions` and set
by :mod:`.plan`). Times are always passed in: nothing here reads the clock.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Final

from roost_api.meta import Condition, ConditionStatus, set_condition
from roost_api.vehicle import VehicleConditionReason, VehicleConditionType
from roost_operator.vehicles.pods import ComponentState

FAILOVER_CONDITIONS: Final = (
    VehicleConditionType.AGENT_CONNECTED,
    VehicleConditionType.AUTOPILOTS_HEALTHY,
)
"""The conditions that exist only while the vehicle has a RedundantAutopilot."""

EVENT_CONDITIONS: Final = (
    VehicleConditionType.READY,
    VehicleConditionType.NODE_BOUND,
    *FAILOVER_CONDITIONS,
)
"""Condition types whose transitions are recorded as Events. ComponentsReady is not:
its problems reach Ready's message, and a rollout would otherwise post one per step."""


@dataclass(frozen=True)
class NodeBinding:
    """Outcome of binding the vehicle to its node, for the NodeBound condition."""

    bound: bool
    reason: str
    message: str
    since: datetime | None = None
    """When the problem began, if known (an unreachable node: when the node controller
    noticed); NodeBound's transition time when it changes."""


def components_condition(
    states: Sequence[ComponentState], *, blocked: str | None = None
) -> tuple[ConditionStatus, str, str]:
    """ComponentsReady from the states of all desired components.

    ``blocked`` says why no components run at all (the vehicle has no node to run on).
    """
    if blocked is not None:
        return "False", VehicleConditionReason.WAITING_FOR_NODE, f"no components run: {blocked}"
    if not states:
        return "True", VehicleConditionReason.NO_COMPONENTS, "no components are enabled"
    waiting = [s for s in states if not s.ready]
    if not waiting:
        names = ", ".join(s.component for s in states)
        return "True", VehicleConditionReason.ALL_COMPONENTS_READY, f"ready: {names}"
    message = "; ".join(f"component {s.component} not ready: {s.detail}" for s in waiting)
    return "False", VehicleConditionReason.COMPONENTS_NOT_READY, message


# The detail conditions Ready summarises, in the order their problems are reported.
READY_INPUTS: Final = (
    VehicleConditionType.NODE_BOUND,
    VehicleConditionType.COMPONENTS_READY,
    VehicleConditionType.AUTOPILOTS_HEALTHY,
    VehicleConditionType.AGENT_CONNECTED,
)


def ready_condition(
    conditions: Sequence[Condition], *, agent_expected: bool = False
) -> tuple[ConditionStatus, str, str]:
    """Ready from the detail conditions present: False on any False, else Unknown on any
    Unknown, else True. AutopilotsHealthy and AgentConnected count once they exist;
    ``agent_expected`` (the vehicle has a RedundantAutopilot) makes a missing
    AgentConnected count as Unknown, so Ready is never True before the failover side
    has heard from the vehicle's agent.
    """
    present = {c.type: c for c in conditions}
    inputs = [
        (c.type, c.status, c.reason, c.message)
        for c in (present.get(t) for t in READY_INPUTS)
        if c is not None
    ]
    if agent_expected and VehicleConditionType.AGENT_CONNECTED not in present:
        inputs.append(
            (
                VehicleConditionType.AGENT_CONNECTED.value,
                "Unknown",
                VehicleConditionReason.AGENT_NOT_HEARD_YET,
                "the vehicle's node agent has not been heard from yet",
            )
        )
    for wanted in ("False", "Unknown"):
        failing = [i for i in inputs if i[1] == wanted]
        if failing:
            message = "; ".join(f"{kind}: {text}" for kind, _, _, text in failing)
            return wanted, failing[0][2], message
    return "True", VehicleConditionReason.VEHICLE_READY, "node bound, components ready"


def vehicle_conditions(
    previous: Sequence[Condition],
    *,
    binding: NodeBinding,
    components: tuple[ConditionStatus, str, str],
    generation: int | None,
    at: datetime,
    agent_expected: bool = False,
) -> list[Condition]:
    """The Vehicle's conditions after this reconcile (others' condition types kept);
    ``at`` stamps a transition (NodeBound's own time when the binding knows it).

    ``agent_expected``: see :func:`ready_condition`.
    """
    conditions = set_condition(
        previous,
        type=VehicleConditionType.NODE_BOUND,
        status="True" if binding.bound else "False",
        reason=binding.reason,
        message=binding.message,
        observed_generation=generation,
        at=binding.since or at,
    )
    status, reason, message = components
    conditions = set_condition(
        conditions,
        type=VehicleConditionType.COMPONENTS_READY,
        status=status,
        reason=reason,
        message=message,
        observed_generation=generation,
        at=at,
    )
    return with_ready(conditions, generation=generation, at=at, agent_expected=agent_expected)


def with_ready(
    conditions: Sequence[Condition],
    *,
    generation: int | None,
    at: datetime | None = None,
    agent_expected: bool = False,
) -> list[Condition]:
    """``conditions`` with Ready recomputed from the detail conditions (see
    :func:`ready_condition`); the one place every Vehicle condition writer summarises."""
    status, reason, message = ready_condition(conditions, agent_expected=agent_expected)
    return set_condition(
        conditions,
        type=VehicleConditionType.READY,
        status=status,
        reason=reason,
        message=message,
        observed_generation=generation,
        at=at,
    )


def transitions(
    before: Sequence[Condition], after: Sequence[Condition], types: Iterable[str]
) -> list[Condition]:
    """Conditions of ``types`` worth an Event: those whose status changed, and a detail
    condition that appears False (a problem from the start, such as a missing node).

    Other first appearances are no news: a condition that appears True or Unknown is the
    vehicle starting as it should, and Ready's first False says that its components are
    still rolling out or repeats a detail condition's own Event. Ready turning True is
    news; a Vehicle whose first status is already Ready (its "starting" report was held
    until its pods were Ready, see :func:`~.status.first_report_due`) posts no Event.
    """
    wanted = set(types)
    old = {c.type: c.status for c in before}
    return [
        c
        for c in after
        if c.type in wanted
        and (
            old[c.type] != c.status
            if c.type in old
            else c.status == "False" and c.type != VehicleConditionType.READY
        )
    ]
