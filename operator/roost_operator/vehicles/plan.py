"""One Vehicle's whole decision, as pure functions: what it should look like, and its status.

The vehicle controller (:mod:`.controller`) is the only writer of ``Vehicle.status``.
It observes, calls :func:`plan_vehicle`, applies the plan, then calls :func:`report`
on what the apply left (the live component Pods) for the one status write. Both functions
take everything as arguments, ``now`` included, so the same observation always gives
the same plan.

What :func:`plan_vehicle` decides, in order:

1. The cluster side of failover when the vehicle has a RedundantAutopilot
   (:func:`roost_operator.autopilots.plan.plan`): ``AgentConnected``,
   ``AutopilotsHealthy``, the failover bookkeeping and its Events, and **which autopilot
   the vehicle's workloads follow**. That choice is made there and only there: a new
   active autopilot is followed unless a fleet guard holds the re-point back. Without a
   RedundantAutopilot the vehicle follows its primary autopilot (or the first, or a
   real vehicle's default serial link).
2. The node binding: the node named in the spec, unless the name cannot be a label
   value, an older Vehicle claims the node, the node does not exist, is unreachable
   (its link is lost: reported with the time the node controller noticed, and nothing
   of the vehicle's is taken away or replaced for it) or is not Ready.
3. The vehicle's config values, its ConfigMap and its component Pods (none while
   the node is claimed by another Vehicle or the name is invalid).
4. The mission claim mirrored into ``status.claimedBy`` (the claim itself is a Lease
   the mission controller writes, see :mod:`roost_operator.claims`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from roost_api.autopilot import RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.meta import Condition, ObjectReference, Stack, set_condition
from roost_api.vehicle import (
    FlightHold,
    VehicleConditionReason,
    VehicleConditionType,
    VehicleSpec,
    VehicleStatus,
)
from roost_api.wellknown import LABEL_NODE
from roost_kube.errors import ApiError
from roost_kube.patches import Obj
from roost_operator.autopilots.conditions import DEFAULT_AGENT_STALE_AFTER
from roost_operator.autopilots.guards import FleetGuards, vehicle_paused
from roost_operator.autopilots.plan import FailoverPlan, PlannedEvent
from roost_operator.autopilots.plan import plan as plan_failover
from roost_operator.vehicles import flight
from roost_operator.vehicles.config import vehicle_config, vehicle_config_map
from roost_operator.vehicles.desired import (
    DEFAULT_FCU_URL,
    DEFAULT_IMAGES,
    SIGNING_KEYS,
    Autopilot,
    ComponentState,
    NodeBinding,
    Workload,
    active_autopilot,
    autopilots_of,
    component_pod,
    component_workloads,
    components_condition,
    pod_hash,
    pod_state,
    vehicle_conditions,
)
from roost_operator.vehicles.placement import (
    NodeClaim,
    NodeState,
    claim_winner,
    node_reachability,
    node_readiness,
    vehicle_name_problem,
)

FAILOVER_CONDITIONS = (
    VehicleConditionType.AGENT_CONNECTED,
    VehicleConditionType.AUTOPILOTS_HEALTHY,
)
"""The conditions that exist only while the vehicle has a RedundantAutopilot."""

EVENT_CONDITIONS = (
    VehicleConditionType.READY,
    VehicleConditionType.NODE_BOUND,
    *FAILOVER_CONDITIONS,
)
"""Condition types whose transitions are recorded as Events. ComponentsReady is not:
its problems reach Ready's message, and a rollout would otherwise post one per step."""


@dataclass(frozen=True)
class Observed:
    """Everything one decision about a Vehicle reads (fresh from the API)."""

    name: str
    uid: str
    generation: int | None
    created: str
    annotations: Mapping[str, str]
    spec: VehicleSpec
    status: VehicleStatus
    autopilot_spec: RedundantAutopilotSpec | None
    autopilot_status: RedundantAutopilotStatus | None
    node: Obj | None
    """The node ``spec.nodeName`` names, as read (None when it does not exist)."""
    node_claims: Sequence[NodeClaim]
    """Every other Vehicle naming the same node."""
    claimed_by: ObjectReference | None
    """The Mission holding the vehicle's claim Lease, if any."""
    rollout_done: bool
    """Whether mavros runs with ``status.fcuUrl`` (ends a re-point; True without mavros)."""
    actions_elsewhere: int
    """Cluster-side failover actions running on other vehicles (the fleet's cap)."""
    now: datetime


@dataclass(frozen=True)
class VehiclePlan:
    """What the vehicle should look like now; the controller applies it in field order."""

    binding: NodeBinding
    node_state: NodeState | None
    """What to put on the target node; None: the vehicle labels no node."""
    config_map: Obj
    pods: dict[str, Obj]
    """Desired component Pods by component."""
    failover: FailoverPlan | None
    events: tuple[PlannedEvent, ...]
    followed: Autopilot | None
    fcu_url: str
    status: VehicleStatus
    """The status before the component states are known (see :func:`report`)."""
    runs_workloads: bool = field(default=True)
    holds_pods: bool = field(default=False)
    """In the air: a differing pod is kept until the landing (roost_operator.vehicles.flight)."""
    disruption_budget: Obj | None = field(default=None)
    """In the air: the PodDisruptionBudget refusing evictions; None on the ground."""


@dataclass(frozen=True)
class Context:
    """Settings the decision depends on (from the operator's settings)."""

    namespace: str
    owners: Sequence[Obj]
    guards: FleetGuards
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER
    agent_image: str = DEFAULT_IMAGES[SIGNING_KEYS]
    """The key pod's image when the Vehicle names none."""


def node_binding(obs: Observed) -> NodeBinding:
    """NodeBound from the name, the other claims on the node and the node as read."""
    node_name = obs.spec.node_name
    problem = vehicle_name_problem(obs.name)
    if problem is not None:
        return NodeBinding(False, VehicleConditionReason.INVALID_VEHICLE_NAME, problem)
    winner = claim_winner([*obs.node_claims, NodeClaim(obs.name, obs.created)])
    if winner is not None and winner.vehicle != obs.name:
        return NodeBinding(
            False,
            VehicleConditionReason.NODE_CLAIMED_BY_OTHER_VEHICLE,
            f"node {node_name} already belongs to Vehicle {winner.vehicle}, which was created "
            f"first; set spec.nodeName to a free node or delete Vehicle {winner.vehicle}",
        )
    if obs.node is None:
        return NodeBinding(
            False,
            VehicleConditionReason.NODE_NOT_FOUND,
            f"node {node_name} does not exist; join the vehicle's computer to the cluster "
            "as that node, or correct spec.nodeName",
        )
    lost = node_reachability(obs.node)
    if lost is not None:
        since = lost.since.isoformat().replace("+00:00", "Z") if lost.since else "an unknown time"
        return NodeBinding(
            False,
            VehicleConditionReason.NODE_UNREACHABLE,
            f"node {node_name} unreachable since {since} ({lost.detail}); the vehicle's pods "
            "are kept there and run on when its link is back (they tolerate the lost link)",
            since=lost.since,
        )
    ready, detail = node_readiness(obs.node)
    if not ready:
        return NodeBinding(
            False,
            VehicleConditionReason.NODE_NOT_READY,
            f"node {node_name} is labelled but not Ready ({detail}); check the vehicle's "
            "computer, its network and its kubelet",
        )
    return NodeBinding(
        True,
        VehicleConditionReason.NODE_LABELED,
        f"node {node_name} is labelled, tainted and Ready",
    )


def _failover(obs: Observed, ctx: Context) -> FailoverPlan | None:
    if obs.autopilot_spec is None:
        return None
    return plan_failover(
        vehicle_name=obs.name,
        vehicle_spec=obs.spec,
        vehicle_status=obs.status,
        annotations=obs.annotations,
        autopilot_spec=obs.autopilot_spec,
        autopilot_status=obs.autopilot_status or RedundantAutopilotStatus(),
        guards=ctx.guards,
        paused_here=vehicle_paused(obs.annotations),
        actions_elsewhere=obs.actions_elsewhere,
        rollout_done=obs.rollout_done,
        now=obs.now,
        stale_after=ctx.stale_after,
    )


def _conditions(obs: Observed, failover: FailoverPlan | None, at: datetime) -> list[Condition]:
    """The failover conditions set (or removed without a RedundantAutopilot)."""
    if failover is None:
        return [c for c in obs.status.conditions if c.type not in FAILOVER_CONDITIONS]
    conditions = list(obs.status.conditions)
    for update in failover.conditions:
        conditions = set_condition(
            conditions,
            type=update.type,
            status=update.status,
            reason=update.reason,
            message=update.message,
            observed_generation=obs.generation,
            at=at,
        )
    return conditions


def plan_vehicle(obs: Observed, ctx: Context) -> VehiclePlan:
    """Decide the vehicle; see the module docstring."""
    failover = _failover(obs, ctx)
    autopilots = autopilots_of(obs.spec, obs.autopilot_spec)
    followed = active_autopilot(
        autopilots,
        reported_active=failover.failover.followed_autopilot if failover else None,
        primary=obs.autopilot_spec.primary if obs.autopilot_spec else None,
    )
    fcu_url = followed.fcu_url if followed else DEFAULT_FCU_URL
    values = vehicle_config(
        name=obs.name,
        spec=obs.spec,
        fcu_url=fcu_url,
        firmware=Stack(followed.stack) if followed else None,
        active_autopilot=followed.name if followed else None,
    )
    binding = node_binding(obs)
    labels_node = binding.bound or binding.reason in (
        VehicleConditionReason.NODE_NOT_FOUND,
        VehicleConditionReason.NODE_NOT_READY,
        VehicleConditionReason.NODE_UNREACHABLE,
    )
    wanted: list[Workload] = (
        component_workloads(
            obs.spec, autopilots, vehicle_name=obs.name, agent_image=ctx.agent_image
        )
        if labels_node
        else []
    )
    pods = {
        w.component: component_pod(
            obs.name,
            obs.spec.node_name,
            w,
            values,
            namespace=ctx.namespace,
            owners=list(ctx.owners),
        )
        for w in wanted
    }
    node_state = (
        NodeState.of_vehicle(obs.name, obs.spec) if labels_node and obs.node is not None else None
    )
    in_flight = flight.hold_reason(obs.autopilot_status) if labels_node else None
    hold = (
        None
        if in_flight is None
        else FlightHold(reason=in_flight, disruption_budget=flight.budget_name(obs.name))
    )
    status = obs.status.model_copy(
        update={
            "observed_generation": obs.generation,
            "conditions": _conditions(obs, failover, obs.now),
            "node_name": obs.spec.node_name if node_state is not None else None,
            "managed_labels": sorted(node_state.labels) if node_state is not None else [],
            "fcu_url": fcu_url,
            "active_autopilot": failover.active_autopilot if failover else None,
            "failover": failover.failover if failover else obs.status.failover,
            "claimed_by": obs.claimed_by,
            "flight_hold": hold,
        }
    )
    return VehiclePlan(
        binding=binding,
        node_state=node_state,
        config_map=vehicle_config_map(
            obs.name, values, namespace=ctx.namespace, owners=list(ctx.owners)
        ),
        pods=pods,
        failover=failover,
        events=failover.events if failover else (),
        followed=followed,
        fcu_url=fcu_url,
        status=status,
        runs_workloads=labels_node,
        # a failover consequence (mavros re-pointed) is the vehicle flying on: not held
        holds_pods=hold is not None and not (failover is not None and failover.acting),
        disruption_budget=None
        if hold is None
        else flight.disruption_budget(obs.name, namespace=ctx.namespace, owners=list(ctx.owners)),
    )


REFUSED_NODE = "node"
REFUSED_AUTOPILOT_LABEL = "autopilot-label"
REFUSED_CONFIG = "config"
REFUSED_BUDGET = "disruption-budget"
"""Keys of :func:`report`'s ``refused`` for writes other than component Pods."""


def _binding_after(plan: VehiclePlan, refused: Mapping[str, ApiError]) -> NodeBinding:
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


def report(
    plan: VehiclePlan,
    *,
    live: Mapping[str, Obj | None],
    refused: Mapping[str, ApiError],
    generation: int | None,
    agent_expected: bool,
) -> VehicleStatus:
    """The status to write once the plan is applied: NodeBound, ComponentsReady, Ready.

    ``live`` maps each desired component to its Pod as the apply left it,
    ``refused`` the writes the API server refused, by component or by one of the
    ``REFUSED_*`` keys, with its answer: each shows in a condition with what to change.
    """
    states = component_states(plan, live=live, refused=refused)
    components = components_condition(
        states, blocked=None if plan.runs_workloads else plan.binding.message
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
        generation=generation,
        agent_expected=agent_expected,
    )
    update: dict[str, object] = {"conditions": conditions}
    hold = plan.status.flight_hold
    if hold is not None and plan.holds_pods:
        update["flight_hold"] = hold.model_copy(
            update={"deferred": flight.deferred(plan.pods, live)}
        )
    return plan.status.model_copy(update=update)


def component_states(
    plan: VehiclePlan, *, live: Mapping[str, Obj | None], refused: Mapping[str, ApiError]
) -> list[ComponentState]:
    """Each desired component's state once the plan is applied (see :func:`report`)."""
    return [
        ComponentState(c, False, f"its Pod was refused: {refused[c].message}")
        if c in refused
        # in the air an outdated pod is kept on purpose: it counts as it runs
        else pod_state(c, live.get(c), None if plan.holds_pods else pod_hash(desired))
        for c, desired in plan.pods.items()
    ]


HELD_CONDITIONS = (VehicleConditionType.READY, VehicleConditionType.COMPONENTS_READY)
"""The conditions a held first report may have False: its components are still starting."""


def first_report_due(
    obs: Observed,
    status: VehicleStatus,
    states: Sequence[ComponentState],
    hold: timedelta,
) -> datetime | None:
    """When to write the first status of a new Vehicle whose components are only
    starting, or None to write ``status`` now.

    A new Vehicle's components are usually Ready moments after its pods are created, and
    a status saying "starting" written in between is the most expensive request of its
    rollout (a write of the whole custom object, sent to every watcher of Vehicles), so
    that report waits until ``hold`` after the Vehicle's creation. Any other news is
    written at once: an existing status, a condition other than Ready and
    ComponentsReady that is not True, a component that is not merely starting (refused,
    ended, waiting for a reason such as an image pull), anything of failover or claims,
    a Vehicle with a RedundantAutopilot, or a Vehicle older than ``hold``.
    """
    if hold <= timedelta(0) or obs.status.conditions or obs.autopilot_spec is not None:
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
    try:
        due = datetime.fromisoformat(obs.created) + hold
    except ValueError:
        return None
    return due if obs.now < due else None


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


def acting(plan: VehiclePlan) -> bool:
    """Whether a cluster-side failover action runs after this plan (counts for the cap)."""
    return plan.failover is not None and plan.failover.acting


def relevant_autopilot(body: Mapping[str, Any] | None) -> Any:
    """What the vehicle decision reads from its RedundantAutopilot, minus the numbers
    that tick with every report (``reportedAt``, heartbeat ages): a fingerprint of this
    changes only when a decision may change."""
    if body is None:
        return None
    status = dict(body.get("status") or {})
    status.pop("reportedAt", None)
    healths = status.pop("autopilots", None) or []
    return [
        body.get("spec"),
        (body.get("metadata") or {}).get("labels"),
        status,
        [(h.get("name"), h.get("level"), h.get("landedState"), h.get("armed")) for h in healths],
    ]
