"""The Vehicle controller: observe → :func:`~.plan.plan_vehicle` → apply → one status write.

Every trigger that concerns a Vehicle (its own events, its node's, its component
Pods', its RedundantAutopilot's reports and silences, its claim Lease, the
guard annotations, the optional fleet sweep) queues its name on the work queue
(:mod:`roost_operator.workqueue`), whose workers call :meth:`VehicleController.reconcile`,
so there is exactly one path from "what the cluster looks like" to "what it should look
like", and exactly one writer of ``Vehicle.status``. It does not import kopf.

Why it is safe to run at any time, any number of times, and to be killed half-way:

* **one lock per vehicle** serialises every path that writes for one vehicle in the
  process (:meth:`~VehicleController.reconcile` and
  :meth:`~VehicleController.release_if_gone`), beyond the work queue's own rule that a
  name is never reconciled twice at once;
* **read your own write**: a Vehicle with a RedundantAutopilot (whose reconcile may act
  on a failover) and the RedundantAutopilot are read fresh from the API on every run;
  other Vehicles, nodes, the claim and what Roost made for the vehicle come from watch
  caches that this controller's own writes update at once, and a retry after a conflict
  reads fresh (:class:`~roost_operator.cache.CachedView` says why that is safe);
* **a Vehicle that is gone is released**: when the Vehicle no longer exists (asked of
  the API server, never concluded from a cache) or is being deleted, the reconcile
  removes what Roost made for it (:meth:`VehicleController._release_gone`). Everything Roost
  makes for a vehicle can be found again by its label, so no finalizer is needed: the
  Vehicle's deletion event queues the release, and after a restart the node watcher's
  first listing queues every vehicle a node is still labelled for. Deletion never waits
  for the operator, nor for a node that cannot be reached: the pods of a gone Vehicle
  on such a node are removed at once (:func:`~.desired.release_step`);
* everything is computed from what was just read and written only where it differs
  (node patch planned by :func:`~roost_operator.vehicles.placement.plan_node`, objects
  through :meth:`~roost_kube.client.Kube.apply`, status compared before patching);
* writes that replace lists (node taints, status conditions) carry the
  ``resourceVersion`` they were computed from; a concurrent writer (a human, kopf's own
  annotations) causes a retry from a fresh read, never a lost update;
* failover Events carry deterministic names and are posted before the status write,
  condition transitions after it (see :mod:`roost_operator.autopilots.plan`);
* the fleet-wide cap on failover actions is race-free within the operator: counting
  other vehicles' actions and recording this one's happen under the ledger's lock.

Component pods are managed directly (no Deployment): :meth:`VehicleController._converge_pod`
takes the step :func:`~roost_operator.vehicles.desired.pod_step` decides — create a
missing pod, delete an outdated or ended one and create its successor only after the
deletion event of the old one has queued the next reconcile, never patch a live pod.

A release (a reconcile that finds the Vehicle gone, or
:meth:`VehicleController.release_if_gone`) removes what Roost made for the vehicle and
reports what it could not remove, once, in a Warning Event, instead of failing for ever.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta
from typing import Final

from roost_api.autopilot import RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.meta import now
from roost_api.vehicle import VehicleSpec, VehicleStatus
from roost_api.wellknown import (
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_NODE,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_kube.client import Kube
from roost_kube.errors import ApiError, ConflictError, PermanentApiError, TemporaryApiError
from roost_kube.patches import Obj, owner_reference
from roost_kube.resources import (
    CONFIGMAPS,
    LEASES,
    NODES,
    PODDISRUPTIONBUDGETS,
    PODS,
    REDUNDANT_AUTOPILOTS,
    VEHICLES,
)
from roost_operator import claims
from roost_operator.autopilots.conditions import DEFAULT_AGENT_STALE_AFTER
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.autopilots.plan import PlannedEvent, mavros_follows
from roost_operator.cache import Cached, CachedView
from roost_operator.vehicles import flight
from roost_operator.vehicles.config import config_map_name
from roost_operator.vehicles.desired import (
    DEFAULT_IMAGES,
    SIGNING_KEYS,
    PodStep,
    ReleaseStep,
    is_component_pod,
    pod_node,
    pod_step,
    release_step,
    workload_name,
)
from roost_operator.vehicles.placement import NodeClaim, NodeState, plan_node
from roost_operator.vehicles.plan import (
    EVENT_CONDITIONS,
    REFUSED_AUTOPILOT_LABEL,
    REFUSED_BUDGET,
    REFUSED_CONFIG,
    REFUSED_NODE,
    Context,
    Observed,
    VehiclePlan,
    acting,
    component_states,
    first_report_due,
    plan_vehicle,
    refusal_time,
    report,
)
from roost_operator.vehicles.status import write_vehicle_status

log = logging.getLogger(__name__)

CONFLICT_RETRIES: Final = 5
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
"""Every field of ``Vehicle.status``: this controller is its only writer."""


@dataclass(frozen=True)
class Peers:
    """What other objects say about a vehicle (kopf indexes in the operator).

    ``claims_on(node)``: every Vehicle naming ``node`` in its spec.
    ``autopilots_of(vehicle)``: name of the vehicle's RedundantAutopilot, if any.
    ``actions``: vehicles with a failover action running, as the index last saw them.
    """

    claims_on: Callable[[str], Sequence[NodeClaim]]
    autopilots_of: Callable[[str], str | None]
    actions: Callable[[], Iterable[str]] = lambda: ()


class ActionLedger:
    """Which vehicles have a cluster-side action running, for the fleet-wide cap.

    The kopf index of Vehicles lags this process's own writes by a watch round trip, so
    what this process wrote last for a vehicle overrides the index for that vehicle.
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self._written: dict[str, bool] = {}

    def others(self, vehicle: str, indexed: Iterable[str]) -> int:
        """Actions running on vehicles other than ``vehicle`` (call under :attr:`lock`)."""
        running = {name for name in indexed if self._written.get(name, True)}
        running |= {name for name, acting in self._written.items() if acting}
        running.discard(vehicle)
        return len(running)

    def record(self, vehicle: str, acting: bool) -> None:
        """What was (or is about to be) written for ``vehicle`` (call under :attr:`lock`)."""
        self._written[vehicle] = acting

    def forget(self, vehicle: str) -> None:
        """The vehicle is gone."""
        with self.lock:
            self._written.pop(vehicle, None)


@dataclass(frozen=True)
class Outcome:
    """What a reconcile did, for the handlers."""

    agent_connected: str | None
    acting: bool
    blocked: str | None
    report_due: datetime | None = None
    """A held first report (:func:`~.plan.first_report_due`): reconcile again then."""


@dataclass(frozen=True)
class Leftovers:
    """What a release could not remove, and why (for the Event that says so)."""

    problems: tuple[str, ...] = ()

    @property
    def clean(self) -> bool:
        return not self.problems


@dataclass
class VehicleController:
    """The one writer of Vehicle status; see the module docstring."""

    kube: Kube
    namespace: str
    guards: FleetGuards = field(default_factory=FleetGuards)
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER
    first_report_hold: timedelta = timedelta(0)
    """See :func:`~roost_operator.vehicles.plan.first_report_due`."""
    agent_image: str = DEFAULT_IMAGES[SIGNING_KEYS]
    """The key pod's image when a Vehicle names none (the node agent's)."""
    ledger: ActionLedger = field(default_factory=ActionLedger)
    caches: Mapping[str, Cached] = field(default_factory=dict)
    """Watch caches (by kind) of nodes, claims and owned objects; others are read from
    the API."""
    cluster: CachedView = field(init=False, repr=False)
    """Reads of nodes, claims and owned objects, and the writes that keep them."""
    _locks: dict[str, threading.Lock] = field(default_factory=dict, repr=False)
    _guard: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __post_init__(self) -> None:
        self.cluster = CachedView(self.kube, self.caches)

    def lock(self, name: str) -> threading.Lock:
        """The lock of vehicle ``name`` (one per vehicle, for every path that writes)."""
        with self._guard:
            return self._locks.setdefault(name, threading.Lock())

    # -- reconcile -------------------------------------------------------------------

    def reconcile(self, name: str, peers: Peers) -> Outcome | None:
        """Converge everything Roost owns for Vehicle ``name``; None when it is gone."""
        with self.lock(name):
            for attempt in range(CONFLICT_RETRIES):
                try:
                    return self._reconcile_once(name, peers, fresh=attempt > 0)
                except ConflictError:
                    if attempt == CONFLICT_RETRIES - 1:
                        raise
                    log.info("Vehicle %s: concurrent write, reconciling again", name)
        return None

    def _observe(self, vehicle: Obj, peers: Peers) -> tuple[Observed, Obj | None]:
        kube = self.kube
        meta = vehicle["metadata"]
        name = meta["name"]
        spec = VehicleSpec.model_validate(vehicle["spec"])
        status = VehicleStatus.model_validate(vehicle.get("status") or {})
        autopilots_name = peers.autopilots_of(name)
        autopilot = kube.get(REDUNDANT_AUTOPILOTS, autopilots_name) if autopilots_name else None
        book = status.failover
        rollout_done = True
        if autopilot is not None and book is not None and book.action is not None:
            rollout_done = self._mavros_rolled_out(name, spec, status.fcu_url)
        cluster = self.cluster
        claim = claims.claim_of(cluster.get(LEASES, claims.lease_name(name), self.namespace) or {})
        observed = Observed(
            name=name,
            uid=meta.get("uid", ""),
            generation=meta.get("generation"),
            created=str(meta.get("creationTimestamp", "")),
            annotations=dict(meta.get("annotations") or {}),
            spec=spec,
            status=status,
            autopilot_spec=(
                RedundantAutopilotSpec.model_validate(autopilot["spec"]) if autopilot else None
            ),
            autopilot_status=(
                RedundantAutopilotStatus.model_validate(autopilot.get("status") or {})
                if autopilot
                else None
            ),
            node=cluster.get(NODES, spec.node_name),
            node_claims=[c for c in peers.claims_on(spec.node_name) if c.vehicle != name],
            claimed_by=claim.holder if claim else None,
            rollout_done=rollout_done,
            actions_elsewhere=0,  # counted under the ledger's lock, see _reconcile_once
            now=now(),
        )
        return observed, autopilot

    def _mavros_rolled_out(self, vehicle: str, spec: VehicleSpec, fcu_url: str | None) -> bool:
        if not spec.components.mavros.enabled:
            return True
        config_map = self.cluster.get(CONFIGMAPS, config_map_name(vehicle), self.namespace)
        mavros = self.cluster.get(PODS, workload_name(vehicle, "mavros"), self.namespace)
        return mavros_follows(fcu_url, config_map, mavros)

    def _reconcile_once(self, name: str, peers: Peers, *, fresh: bool) -> Outcome | None:
        kube = self.kube
        if fresh or peers.autopilots_of(name) is not None:
            vehicle = self.cluster.fresh(VEHICLES, name)
        else:
            vehicle = self.cluster.get(VEHICLES, name)
        if vehicle is None or vehicle["metadata"].get("deletionTimestamp"):
            self._release_gone(name, vehicle)
            return None
        obs, autopilot = self._observe(vehicle, peers)
        ctx = Context(
            namespace=self.namespace,
            owners=[owner_reference(vehicle)],
            guards=self.guards,
            stale_after=self.stale_after,
            agent_image=self.agent_image,
        )
        was_acting = obs.status.failover is not None and obs.status.failover.action is not None
        with self.ledger.lock:  # count the others and reserve this one in one step
            obs = replace(obs, actions_elsewhere=self.ledger.others(name, peers.actions()))
            plan = plan_vehicle(obs, ctx)
            self.ledger.record(name, acting(plan))
        try:
            live, refused = self._apply(obs, plan, autopilot)
            status = report(
                plan,
                live=live,
                refused=refused,
                generation=obs.generation,
                agent_expected=autopilot is not None,
            )
            self._post(vehicle, plan.events)
            states = component_states(plan, live=live, refused=refused)
            report_due = first_report_due(obs, status, states, self.first_report_hold)
            written = None
            if report_due is None:
                written = write_vehicle_status(
                    kube,
                    vehicle,
                    obs.status,
                    status,
                    fields=STATUS_FIELDS,
                    event_types=EVENT_CONDITIONS,
                )
            if written is not None:
                self.cluster.remember(written)
        except Exception:
            with self.ledger.lock:  # nothing was stored: the index/status stay the truth
                self.ledger.record(name, was_acting)
            raise
        if written is not None and refused:  # reported when the status shows it, never per retry
            summary = "; ".join(f"{what}: {error.message}" for what, error in refused.items())
            log.warning("Vehicle %s: the API server refused: %s", name, summary)
            kube.post_event(
                vehicle,
                reason="Refused",
                message=f"the API server refused what Roost built from the spec: {summary}",
                type="Warning",
                at=refusal_time(status, refused) or obs.now,
            )
        # Every refusal is in ComponentsReady; a temporary one is also raised so the
        # handler retries it, a permanent one waits for the user to change the spec.
        temporary = [error for error in refused.values() if isinstance(error, TemporaryApiError)]
        if temporary:
            raise temporary[0]
        failover = plan.failover
        return Outcome(
            agent_connected=failover.conditions[0].status if failover else None,
            acting=acting(plan),
            blocked=failover.failover.blocked if failover else None,
            report_due=report_due,
        )

    def _apply(
        self, obs: Observed, plan: VehiclePlan, autopilot: Obj | None
    ) -> tuple[dict[str, Obj | None], dict[str, ApiError]]:
        """Carry out ``plan``; the live component Pods and those the API server refused."""
        cluster = self.cluster
        refused: dict[str, ApiError] = {}

        def attempt(key: str, write: Callable[[], object]) -> None:
            try:
                write()
            except PermanentApiError as error:  # reported in the status, not retried
                refused[key] = error

        target = obs.spec.node_name if plan.node_state is not None else None
        for node in cluster.list_objects(NODES, labels={LABEL_VEHICLE: obs.name}):
            if node["metadata"]["name"] != target:
                self._converge_node(node, NodeState.released())
        bound, state = obs.node, plan.node_state
        if state is not None and bound is not None:
            attempt(REFUSED_NODE, lambda: self._converge_node(bound, state))
        if autopilot is not None:
            attempt(
                REFUSED_AUTOPILOT_LABEL,
                lambda: self._label_autopilot(autopilot, obs.spec.node_name),
            )
        attempt(REFUSED_CONFIG, lambda: cluster.apply(plan.config_map))
        self._hold_evictions(obs, plan, attempt)
        live: dict[str, Obj | None] = {}
        for component, manifest in plan.pods.items():
            try:
                live[component] = self._converge_pod(
                    manifest, node_exists=obs.node is not None, holding=plan.holds_pods
                )
            except ConflictError:
                raise
            except ApiError as err:
                refused[component] = err
        for pod in self._pods_of(obs.name):
            meta = pod["metadata"]
            if (meta.get("labels") or {}).get(LABEL_COMPONENT) not in plan.pods and not meta.get(
                "deletionTimestamp"
            ):
                cluster.delete(PODS, meta["name"], self.namespace)
        return live, refused

    def _pods_of(self, vehicle: str) -> list[Obj]:
        """The vehicle's component pods (not its Missions' onboard Job pods)."""
        owned = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: vehicle}
        listed = self.cluster.list_objects(PODS, namespace=self.namespace, labels=owned)
        return [pod for pod in listed if is_component_pod(pod)]

    def _hold_evictions(
        self, obs: Observed, plan: VehiclePlan, attempt: Callable[[str, Callable[[], object]], None]
    ) -> None:
        """In the air: the PodDisruptionBudget that refuses evictions; on the ground after a
        flight: delete it (roost_operator.vehicles.flight)."""
        budget = plan.disruption_budget
        if budget is not None:
            attempt(REFUSED_BUDGET, lambda: self.cluster.apply(budget))
        elif obs.status.flight_hold is not None:
            name = obs.status.flight_hold.disruption_budget
            self.cluster.delete(PODDISRUPTIONBUDGETS, name, self.namespace)

    def _converge_pod(
        self, desired: Obj, *, node_exists: bool, holding: bool = False
    ) -> Obj | None:
        """One step of a component's pod towards ``desired`` (see :func:`pod_step`; held in
        the air by :func:`flight.hold_step`); the pod as it is after the step (None: none
        yet)."""
        name, namespace = desired["metadata"]["name"], desired["metadata"]["namespace"]
        live = self.cluster.get(PODS, name, namespace)
        step = flight.hold_step(pod_step(live, desired, node_exists=node_exists), holding=holding)
        if step is PodStep.CREATE:
            try:
                return self.cluster.create(desired)
            except ConflictError as error:
                if not error.already_exists:
                    raise
                # The cache had not seen the old pod yet (or its deletion is not over):
                # judge the pod that exists; its events queue the next reconcile.
                return self.cluster.fresh(PODS, name, namespace)
        if step in (PodStep.REPLACE, PodStep.RESTART):
            log.info(
                "pod %s/%s: %s (deleting it; its successor follows)", namespace, name, step.value
            )
            self.cluster.delete(PODS, name, namespace)
        return live

    def _label_autopilot(self, autopilot: Obj, node_name: str) -> None:
        """Keep the RedundantAutopilot's ``roost.dev/node`` label on the vehicle's node:
        the chart's admission policy compares it with the node in the agent's token."""
        labels = autopilot["metadata"].get("labels") or {}
        if labels.get(LABEL_NODE) != node_name:
            self.kube.merge_patch(
                REDUNDANT_AUTOPILOTS,
                autopilot["metadata"]["name"],
                {"metadata": {"labels": {LABEL_NODE: node_name}}},
            )

    def _converge_node(self, node: Obj, want: NodeState) -> Obj:
        """Patch ``node`` until it carries ``want``; re-read and re-plan on conflicts."""
        name = node["metadata"]["name"]
        for _ in range(CONFLICT_RETRIES):
            patch = plan_node(node, want)
            if patch is None:
                return node
            try:
                return self.cluster.merge_patch(NODES, name, patch)
            except ConflictError:
                fresh = self.cluster.fresh(NODES, name)
                if fresh is None:
                    return node
                node = fresh
        raise ConflictError(409, "PATCH", f"nodes/{name}", "node kept changing under us")

    def _post(self, vehicle: Obj, events: Iterable[PlannedEvent]) -> None:
        """Post the plan's Events (deterministic names: a repeat is refused as a duplicate)."""
        for event in events:
            self.kube.post_event(
                vehicle,
                reason=event.reason,
                message=event.message,
                type=event.type,
                at=event.at,
            )

    # -- deletion ----------------------------------------------------------------------

    def release_if_gone(self, name: str) -> bool:
        """Release Vehicle ``name`` if the API server says it is gone or being deleted
        (for a vehicle queued before the controller can reconcile one that exists);
        whether it was."""
        with self.lock(name):
            vehicle = self.cluster.fresh(VEHICLES, name)
            if vehicle is not None and not vehicle["metadata"].get("deletionTimestamp"):
                return False
            self._release_gone(name, vehicle)
            return True

    def _release_gone(self, name: str, vehicle: Obj | None) -> None:
        """The Vehicle is gone (``None``) or being deleted: release what Roost made for
        it, and say once, in a Warning Event, what could not be removed."""
        leftovers = self._release_locked(name)
        if leftovers.clean:
            return
        log.warning("Vehicle %s: deleted, but left behind: %s", name, leftovers.problems)
        regarding = vehicle or {
            "apiVersion": VEHICLES.api_version,
            "kind": VEHICLES.kind,
            "metadata": {"name": name},
        }
        self.kube.post_event(
            regarding,
            reason="CleanupIncomplete",
            message="deleted, but left behind: " + "; ".join(leftovers.problems),
            type="Warning",
            at=now(),
        )

    def _release_locked(self, name: str) -> Leftovers:
        """Remove what Roost made for Vehicle ``name`` (labels, taint, config, workloads),
        under its lock.

        Every part is attempted even when another is refused for good; what could not be
        removed is returned, so the caller can say what was left. A temporary error is
        raised: the release is retried. Finding nothing to remove costs no request: the
        nodes, ConfigMaps and Pods are read from the watch caches.
        """
        problems: list[str] = []
        cluster = self.cluster
        for node in cluster.list_objects(NODES, labels={LABEL_VEHICLE: name}):
            try:
                self._converge_node(node, NodeState.released())
            except PermanentApiError as error:
                problems.append(f"node {node['metadata']['name']}: {error.message}")
        owned = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: name}
        for resource in (PODS, CONFIGMAPS):
            listed = cluster.list_objects(resource, namespace=self.namespace, labels=owned)
            # A Mission's onboard Job pods carry the vehicle's label too: not ours.
            for obj in [o for o in listed if resource is not PODS or is_component_pod(o)]:
                step = ReleaseStep.LEAVE if obj["metadata"].get("deletionTimestamp") else None
                if resource is PODS:
                    on = pod_node(obj)
                    step = release_step(obj, cluster.get(NODES, on) if on else None)
                if step is ReleaseStep.LEAVE:
                    continue
                try:
                    cluster.delete(
                        resource,
                        obj["metadata"]["name"],
                        self.namespace,
                        grace_period_s=0 if step is ReleaseStep.FORCE else None,
                    )
                except PermanentApiError as error:
                    problems.append(
                        f"{resource.kind} {self.namespace}/{obj['metadata']['name']}: "
                        f"{error.message}"
                    )
        self.ledger.forget(name)
        return Leftovers(tuple(problems))
