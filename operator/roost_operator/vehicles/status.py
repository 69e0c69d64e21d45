"""The Vehicle's status, written once per reconcile from the plan and what apply returned.

:func:`report` completes the plan's status with what the API server answered (the live
component Pods after the apply, the writes it refused): NodeBound, ComponentsReady,
Ready and the in-flight deferrals. :func:`write_status` sends a JSON merge patch of the
fields that changed, carrying the ``resourceVersion`` the status was computed from: a
write in between (a human, kopf's own annotations) causes a 409 and a decision from a
fresh read, never a lost update of a list written whole (the conditions). Nothing is
sent when nothing changed, which keeps idle reconciles free of writes. Condition
transitions and refusals are recorded as Events after the write, stamped with times
from the observation, never from the clock.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Final

from roost_api.vehicle import VehicleConditionReason, VehicleConditionType, VehicleStatus
from roost_api.wellknown import LABEL_NODE
from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.patches import Obj, merge_patch_fields
from roost_kube.resources import VEHICLES
from roost_operator.vehicles import flight
from roost_operator.vehicles.conditions import (
    EVENT_CONDITIONS,
    NodeBinding,
    components_condition,
    transitions,
    vehicle_conditions,
)
from roost_operator.vehicles.manifests import pod_hash
from roost_operator.vehicles.plan import Plan
from roost_operator.vehicles.pods import ComponentState, pod_state

log = logging.getLogger(__name__)

STATUS_FIELDS: Final = (
    "observedGeneration",
    "conditions",
    "nodeName",
    "managedLabels",
    "fcuUrl",
    "activeAutopilot",
    "failover",
    "claimedBy",
    "flightHold",
)
"""Every field of ``Vehicle.status``: the Vehicle controller is its only writer."""

REFUSED_NODE: Final = "node"
REFUSED_AUTOPILOT_LABEL: Final = "autopilot-label"
REFUSED_CONFIG: Final = "config"
REFUSED_BUDGET: Final = "disruption-budget"
"""Keys of :attr:`Applied.refused` for writes other than component Pods."""

HELD_CONDITIONS: Final = (VehicleConditionType.READY, VehicleConditionType.COMPONENTS_READY)
"""The conditions a held first report may have False: its components are still starting."""


@dataclass(frozen=True)
class Applied:
    """What the apply left: each desired component's Pod as the API server answered
    (None: none yet), and the writes it refused for good, by component or ``REFUSED_*``."""

    live: Mapping[str, Obj | None] = field(default_factory=dict)
    refused: Mapping[str, ApiError] = field(default_factory=dict)


@dataclass(frozen=True)
class Written:
    """What the status step did: the Vehicle as written (None: nothing was written) and,
    for a held first report, when to reconcile again."""

    vehicle: Obj | None
    report_due: datetime | None


def _binding_after(plan: Plan, refused: Mapping[str, ApiError]) -> NodeBinding:
    """NodeBound, unless the API server refused a write the binding needs."""
    if REFUSED_NODE in refused:
        return NodeBinding(
            False,
            VehicleConditionReason.NODE_REFUSED,
            f"labelling node {plan.status.node_name or '?'} was refused: "
            f"{refused[REFUSED_NODE].message}; check spec.nodeName and spec.labels",
        )
    if REFUSED_AUTOPILOT_LABEL in refused:
        return NodeBinding(
            False,
            VehicleConditionReason.AUTOPILOT_LABEL_REFUSED,
            f"the RedundantAutopilot's {LABEL_NODE} label was refused: "
            f"{refused[REFUSED_AUTOPILOT_LABEL].message}; with a RedundantAutopilot "
            "spec.nodeName must also be a label value (at most 63 characters)",
        )
    return plan.binding


def component_states(plan: Plan, applied: Applied) -> list[ComponentState]:
    """Each desired component's state once the plan is applied."""
    refused, live = applied.refused, applied.live
    return [
        ComponentState(c, False, f"its Pod was refused: {refused[c].message}")
        if c in refused
        # in the air an outdated pod is kept on purpose: it counts as it runs
        else pod_state(c, live.get(c), None if plan.holds_pods else pod_hash(desired))
        for c, desired in plan.pods.items()
    ]


def report(plan: Plan, applied: Applied) -> VehicleStatus:
    """The status to write once the plan is applied: NodeBound, ComponentsReady, Ready;
    each refusal shows in a condition with what to change."""
    refused = applied.refused
    components = components_condition(
        component_states(plan, applied),
        blocked=None if plan.runs_workloads else plan.binding.message,
    )
    if REFUSED_CONFIG in refused:
        components = (
            "False",
            VehicleConditionReason.CONFIG_REFUSED,
            f"the vehicle's config ConfigMap was refused: {refused[REFUSED_CONFIG].message}; "
            "make spec.config smaller",
        )
    conditions = vehicle_conditions(
        plan.status.conditions,
        binding=_binding_after(plan, refused),
        components=components,
        generation=plan.generation,
        at=plan.now,
        agent_expected=plan.agent_expected,
    )
    update: dict[str, object] = {"conditions": conditions}
    hold = plan.status.flight_hold
    if hold is not None and plan.holds_pods:
        update["flight_hold"] = hold.model_copy(
            update={"deferred": flight.deferred(plan.pods, applied.live)}
        )
    return plan.status.model_copy(update=update)


def first_report_due(
    plan: Plan, status: VehicleStatus, states: Sequence[ComponentState]
) -> datetime | None:
    """When to write the first status of a new Vehicle whose components are only
    starting, or None to write ``status`` now.

    A new Vehicle's components are usually Ready moments after its pods are created, and
    a status saying "starting" written in between is the most expensive request of its
    rollout (a write of the whole custom object, sent to every watcher of Vehicles), so
    that report waits until the plan's :attr:`~.plan.Plan.first_report_until` (the
    operator's hold after the Vehicle's creation). Any other news is written at once: a
    condition other than Ready and ComponentsReady that is not True, a component that is
    not merely starting (refused, ended, waiting for a reason such as an image pull),
    anything of failover or claims. The plan sets no hold for a Vehicle with a status
    already, with a RedundantAutopilot, or older than the hold.
    """
    if plan.first_report_until is None:
        return None
    if status.failover is not None or status.claimed_by is not None:
        return None
    if any(c.status != "True" for c in status.conditions if c.type not in HELD_CONDITIONS):
        return None
    components = next(
        (c for c in status.conditions if c.type == VehicleConditionType.COMPONENTS_READY), None
    )
    if components is None or components.reason != VehicleConditionReason.COMPONENTS_NOT_READY:
        return None  # ready, or its config was refused: news
    if not any(not s.ready for s in states) or not all(s.ready or s.starting for s in states):
        return None
    return plan.first_report_until


def refusal_time(status: VehicleStatus, refused: Mapping[str, ApiError]) -> datetime | None:
    """When the conditions that report ``refused`` last changed (None: no such condition).

    The refusal's Event is stamped with it, never with the clock: the same refusal seen
    again by a later reconcile names the same Event and the API refuses the repeat.
    """
    on_node = REFUSED_NODE in refused or REFUSED_AUTOPILOT_LABEL in refused
    kinds = [VehicleConditionType.NODE_BOUND] if on_node else []
    if any(key not in (REFUSED_NODE, REFUSED_AUTOPILOT_LABEL) for key in refused):
        kinds.append(VehicleConditionType.COMPONENTS_READY)
    times = [c.last_transition_time for c in status.conditions if c.type in kinds]
    return min(times, default=None)


def status_patch(
    old: VehicleStatus, new: VehicleStatus, fields: Iterable[str] = STATUS_FIELDS
) -> dict[str, Any] | None:
    """Merge patch of ``fields`` (camelCase) that differ, or None when none do.

    In a merge patch a missing key means "keep", so a field that became empty is sent as
    an explicit null, and an object field carries nulls for its emptied members (objects
    merge recursively). Lists are replaced whole and sent without nulls, which the
    schema would reject inside list items.
    """
    return merge_patch_fields(new, old=old, fields=fields) or None


def write_status(kube: Kube, plan: Plan, applied: Applied) -> Written:
    """Write the status :func:`report` makes of ``plan`` and ``applied`` (unless a first
    report is held), then its condition transitions and refusals as Events.

    Raises :class:`~roost_kube.errors.ConflictError` when the Vehicle changed since it
    was read: the controller decides again from a fresh read.
    """
    old = plan.previous
    status = report(plan, applied)
    due = first_report_due(plan, status, component_states(plan, applied))
    patch = None if due is not None else status_patch(old, status)
    if patch is None:
        return Written(None, due)
    vehicle = plan.body
    written = kube.merge_patch(
        VEHICLES,
        plan.name,
        {"metadata": {"resourceVersion": vehicle["metadata"]["resourceVersion"]}, "status": patch},
        subresource="status",
    )
    for cond in transitions(old.conditions, status.conditions, EVENT_CONDITIONS):
        kube.post_event(
            vehicle,
            reason=cond.reason,
            message=f"{cond.type} is {cond.status}: {cond.message}",
            type="Normal" if cond.status == "True" else "Warning",
            at=plan.now,
        )
    refused = applied.refused
    if refused:  # reported when the status shows it, never per retry
        summary = "; ".join(f"{what}: {error.message}" for what, error in refused.items())
        log.warning("Vehicle %s: the API server refused: %s", plan.name, summary)
        kube.post_event(
            vehicle,
            reason="Refused",
            message=f"the API server refused what Roost built from the spec: {summary}",
            type="Warning",
            at=refusal_time(status, refused) or plan.now,
        )
    return Written(written, None)
