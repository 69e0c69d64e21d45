"""One Vehicle's whole decision as one pure function: :func:`plan_vehicle`.

The Vehicle controller (:mod:`.controller`) observes (:mod:`.observe`: everything read,
the live component Pods and the clock included), calls :func:`plan_vehicle` once,
carries the plan out (:mod:`.apply`) and writes the status once (:mod:`.status`) from the
plan and what the API server answered. The same observation always gives the same plan.

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
   of the vehicle's is taken away or replaced for it) or is not Ready; the node patches
   (the vehicle's labels and taint on its node, none on any other).
3. The vehicle's config values, its ConfigMap and its component Pods (none while
   the node is claimed by another Vehicle or the name is invalid), and the step for
   each live Pod (:func:`~.pods.pod_step`, held in the air by :func:`~.flight.hold_step`).
4. The mission claim mirrored into ``status.claimedBy`` (the claim itself is a Lease
   the mission controller writes, see :mod:`roost_operator.claims`).

The vehicle package uses the failover decision; the failover package
(:mod:`roost_operator.autopilots`) knows nothing of Vehicles' manifests: it is handed the
URL mavros would use for each autopilot and whether mavros has rolled out.
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
    VehicleSpec,
    VehicleStatus,
)
from roost_kube.patches import Obj
from roost_operator.autopilots.conditions import DEFAULT_AGENT_STALE_AFTER
from roost_operator.autopilots.guards import FleetGuards, vehicle_paused
from roost_operator.autopilots.plan import FailoverPlan, PlannedEvent
from roost_operator.autopilots.plan import plan as plan_failover
from roost_operator.vehicles import flight
from roost_operator.vehicles.conditions import FAILOVER_CONDITIONS, NodeBinding
from roost_operator.vehicles.config import vehicle_config, vehicle_config_map
from roost_operator.vehicles.manifests import (
    DEFAULT_FCU_URL,
    DEFAULT_IMAGES,
    SIGNING_KEYS,
    Autopilot,
    Workload,
    active_autopilot,
    autopilots_of,
    component_pod,
    component_workloads,
)
from roost_operator.vehicles.placement import (
    NodeClaim,
    NodeState,
    claim_winner,
    node_reachability,
    node_readiness,
    plan_node,
    vehicle_name_problem,
)
from roost_operator.vehicles.pods import PodStep, mavros_follows, pod_step


@dataclass(frozen=True)
class Context:
    """Settings the decision depends on (from the operator's settings)."""

    namespace: str
    guards: FleetGuards = field(default_factory=FleetGuards)
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER
    agent_image: str = DEFAULT_IMAGES[SIGNING_KEYS]
    """The key pod's image when the Vehicle names none."""
    first_report_hold: timedelta = timedelta(0)
    """See :func:`~.status.first_report_due`."""


@dataclass(frozen=True)
class Observed:
    """Everything one decision about a Vehicle reads, the clock included."""

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
    actions_elsewhere: int
    """Cluster-side failover actions running on other vehicles (the fleet's cap)."""
    now: datetime
    context: Context
    body: Obj = field(default_factory=dict)
    """The Vehicle as read (Events are about it; the status write carries its
    ``resourceVersion``)."""
    owners: Sequence[Obj] = ()
    """The owner reference every object made for the vehicle carries."""
    autopilot_name: str | None = None
    autopilot_node_label: str | None = None
    """The RedundantAutopilot's ``roost.dev/node`` label as read."""
    labelled_nodes: Sequence[Obj] = ()
    """Every node carrying the vehicle's label (its own node included)."""
    pods: Mapping[str, Obj] = field(default_factory=dict)
    """The vehicle's live component Pods, by component."""
    config_map: Obj | None = None
    """The vehicle's config ConfigMap as read."""


@dataclass(frozen=True)
class PodMove:
    """One component's Pod: the desired manifest, the live pod, and the step between."""

    component: str
    desired: Obj
    live: Obj | None
    step: PodStep


@dataclass(frozen=True)
class NodePatch:
    """A merge patch of one node (its ``resourceVersion`` inside); ``own``: the
    vehicle's node (a refusal shows in NodeBound) rather than one to release."""

    node: str
    patch: Obj
    own: bool


@dataclass(frozen=True)
class Plan:
    """What the vehicle should look like now; :mod:`.apply` carries it out in field order,
    :mod:`.status` writes :attr:`status` completed with what the API server answered."""

    name: str
    namespace: str
    body: Obj
    binding: NodeBinding
    node_state: NodeState | None
    """What to put on the target node; None: the vehicle labels no node."""
    node_patches: tuple[NodePatch, ...]
    autopilot_label: tuple[str, str] | None
    """(RedundantAutopilot, node) when its ``roost.dev/node`` label must change."""
    config_map: Obj
    disruption_budget: Obj | None
    """In the air: the PodDisruptionBudget refusing evictions; None on the ground."""
    delete_budget: str | None
    """On the ground after a flight: the PodDisruptionBudget to delete."""
    pods: dict[str, Obj]
    """Desired component Pods by component."""
    pod_moves: tuple[PodMove, ...]
    stray_pods: tuple[str, ...]
    """Live component Pods of components no longer wanted (deleted)."""
    failover: FailoverPlan | None
    events: tuple[PlannedEvent, ...]
    followed: Autopilot | None
    fcu_url: str
    status: VehicleStatus
    """The status before the component states are known (see :func:`~.status.report`)."""
    previous: VehicleStatus
    """The status as read (only what differs from it is written)."""
    generation: int | None
    now: datetime
    agent_expected: bool
    """The vehicle has a RedundantAutopilot: Ready waits for its agent."""
    first_report_until: datetime | None = None
    """A new Vehicle's first report may wait until then (:func:`~.status.first_report_due`)."""
    runs_workloads: bool = True
    holds_pods: bool = False
    """In the air: a differing pod is kept until the landing (:mod:`.flight`)."""

    @property
    def acting(self) -> bool:
        """Whether a cluster-side failover action runs after this plan (the fleet's cap)."""
        return self.failover is not None and self.failover.acting


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


def _failover(obs: Observed, autopilots: Sequence[Autopilot]) -> FailoverPlan | None:
    if obs.autopilot_spec is None:
        return None
    rollout_done = True
    book = obs.status.failover
    if book is not None and book.action is not None and obs.spec.components.mavros.enabled:
        rollout_done = mavros_follows(obs.status.fcu_url, obs.config_map, obs.pods.get("mavros"))
    ctx = obs.context
    return plan_failover(
        vehicle_name=obs.name,
        vehicle_spec=obs.spec,
        vehicle_status=obs.status,
        annotations=obs.annotations,
        autopilot_spec=obs.autopilot_spec,
        autopilot_status=obs.autopilot_status or RedundantAutopilotStatus(),
        fcu_urls={a.name: a.fcu_url for a in autopilots},
        guards=ctx.guards,
        paused_here=vehicle_paused(obs.annotations),
        actions_elsewhere=obs.actions_elsewhere,
        rollout_done=rollout_done,
        now=obs.now,
        stale_after=ctx.stale_after,
    )


def _conditions(obs: Observed, failover: FailoverPlan | None) -> list[Condition]:
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
            at=obs.now,
        )
    return conditions


def _node_patches(obs: Observed, node_state: NodeState | None) -> tuple[NodePatch, ...]:
    """Release every other node labelled for the vehicle; put ``node_state`` on its own."""
    target = obs.spec.node_name if node_state is not None else None
    patches = [
        NodePatch(node["metadata"]["name"], patch, own=False)
        for node in obs.labelled_nodes
        if node["metadata"]["name"] != target
        and (patch := plan_node(node, NodeState.released())) is not None
    ]
    if node_state is not None and obs.node is not None:
        own = plan_node(obs.node, node_state)
        if own is not None:
            patches.append(NodePatch(obs.spec.node_name, own, own=True))
    return tuple(patches)


def _pod_moves(obs: Observed, pods: Mapping[str, Obj], *, holding: bool) -> tuple[PodMove, ...]:
    moves = []
    for component, desired in pods.items():
        live = obs.pods.get(component)
        step = pod_step(live, desired, node_exists=obs.node is not None)
        moves.append(PodMove(component, desired, live, flight.hold_step(step, holding=holding)))
    return tuple(moves)


def _first_report_until(obs: Observed) -> datetime | None:
    """When a new Vehicle's first report is due at the latest (None: no hold applies)."""
    hold = obs.context.first_report_hold
    if hold <= timedelta(0) or obs.status.conditions or obs.autopilot_spec is not None:
        return None
    try:
        due = datetime.fromisoformat(obs.created) + hold
    except ValueError:
        return None
    return due if obs.now < due else None


def plan_vehicle(obs: Observed) -> Plan:
    """Decide the vehicle; see the module docstring."""
    ctx = obs.context
    owners = list(obs.owners)
    autopilots = autopilots_of(obs.spec, obs.autopilot_spec)
    failover = _failover(obs, autopilots)
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
            obs.name, obs.spec.node_name, w, values, namespace=ctx.namespace, owners=owners
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
    # a failover consequence (mavros re-pointed) is the vehicle flying on: not held
    holding = hold is not None and not (failover is not None and failover.acting)
    status = obs.status.model_copy(
        update={
            "observed_generation": obs.generation,
            "conditions": _conditions(obs, failover),
            "node_name": obs.spec.node_name if node_state is not None else None,
            "managed_labels": sorted(node_state.labels) if node_state is not None else [],
            "fcu_url": fcu_url,
            "active_autopilot": failover.active_autopilot if failover else None,
            "failover": failover.failover if failover else obs.status.failover,
            "claimed_by": obs.claimed_by,
            "flight_hold": hold,
        }
    )
    relabel = (
        (obs.autopilot_name, obs.spec.node_name)
        if obs.autopilot_name is not None and obs.autopilot_node_label != obs.spec.node_name
        else None
    )
    return Plan(
        name=obs.name,
        namespace=ctx.namespace,
        body=obs.body,
        binding=binding,
        node_state=node_state,
        node_patches=_node_patches(obs, node_state),
        autopilot_label=relabel,
        config_map=vehicle_config_map(obs.name, values, namespace=ctx.namespace, owners=owners),
        disruption_budget=None
        if hold is None
        else flight.disruption_budget(obs.name, namespace=ctx.namespace, owners=owners),
        delete_budget=obs.status.flight_hold.disruption_budget
        if hold is None and obs.status.flight_hold is not None
        else None,
        pods=pods,
        pod_moves=_pod_moves(obs, pods, holding=holding),
        stray_pods=tuple(
            sorted(
                pod["metadata"]["name"]
                for component, pod in obs.pods.items()
                if component not in pods and not pod["metadata"].get("deletionTimestamp")
            )
        ),
        failover=failover,
        events=failover.events if failover else (),
        followed=followed,
        fcu_url=fcu_url,
        status=status,
        previous=obs.status,
        generation=obs.generation,
        now=obs.now,
        agent_expected=obs.autopilot_spec is not None,
        first_report_until=_first_report_until(obs),
        runs_workloads=labels_node,
        holds_pods=holding,
    )


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
