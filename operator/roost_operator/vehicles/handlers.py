"""kopf triggers of the Vehicle controller: every one funnels into one reconcile.

Triggers, and why each exists:

* the Vehicle itself (resume on operator start, create, update) — kopf retries these
  with a backoff when a reconcile fails on a temporary error;
* a periodic resync (``Settings.resync_seconds``) — puts back hand edits and converges
  after anything missed; it writes nothing when nothing differs;
* its node (watch all Nodes) — a node appearing, turning Ready/NotReady or losing a
  Roost label re-reconciles the vehicles that claim it or that it is labelled for; node
  heartbeats that change nothing Roost looks at are filtered out by a fingerprint;
* its component Deployments — rollout progress updates ComponentsReady and ends a
  mavros re-point;
* its RedundantAutopilot — the agent reported. Reports that change nothing the
  controller reads (the periodic refresh of ``reportedAt``, heartbeat ages) are skipped
  by a fingerprint, except while the vehicle's ``AgentConnected`` is not True (a report
  is then exactly the news that the agent is back);
* a RedundantAutopilot timer that fires only once the object has been *idle* for the
  staleness window — the agent went silent: ``AgentConnected`` becomes Unknown;
* the Vehicle's guard annotations (pause, clear the latch), by watch event: kopf's
  update handlers do not see annotations under Roost's own prefix;
* a Vehicle timer while a failover action runs or a guard holds one back — timeouts,
  and the moment a guard lifts;
* its claim Lease — the mission claim mirrored into ``status.claimedBy``.

Deletion goes through the Roost finalizer (``roost.dev/cleanup``): labels, taint,
config and workloads are removed before the Vehicle disappears; what cannot be removed
is reported in an Event and the finalizer is released anyway. Other Vehicles waiting
for the freed node are reconciled next.

Handlers are registered by :func:`register` with the operator's settings (intervals
come from there); the :class:`~roost_operator.vehicles.controller.VehicleController`
and its per-process state live in the operator's memo (:mod:`roost_operator.runtime`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Hashable, Mapping
from typing import Any, Final

import kopf

from roost_api.meta import now
from roost_api.wellknown import (
    ANNOTATION_CLEAR_FAILOVER_LATCH,
    ANNOTATION_PAUSE_FAILOVER_ACTIONS,
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_kube import resources
from roost_kube.patches import content_hash
from roost_operator.claims import CLAIM_COMPONENT, claim_of
from roost_operator.edge import at_the_edge, handler_edge
from roost_operator.runtime import runtime
from roost_operator.settings import Settings
from roost_operator.vehicles.controller import Peers
from roost_operator.vehicles.placement import NodeClaim
from roost_operator.vehicles.plan import relevant_autopilot

VEHICLES: Final = resources.VEHICLES.kopf
AUTOPILOTS: Final = resources.REDUNDANT_AUTOPILOTS.kopf
LEASES: Final = resources.LEASES.kopf

NodeClaims = kopf.Index[str, NodeClaim]
AutopilotsByVehicle = kopf.Index[str, str]
FailoverActions = kopf.Index[str, bool]


class Fingerprints:
    """Remembers a digest per object to skip events that change nothing relevant."""

    def __init__(self) -> None:
        self._seen: dict[Hashable, str] = {}
        self._lock = threading.Lock()

    def changed(self, key: Hashable, relevant: Any) -> bool:
        digest = content_hash(relevant)
        with self._lock:
            if self._seen.get(key) == digest:
                return False
            self._seen[key] = digest
            return True

    def forget(self, key: Hashable) -> None:
        with self._lock:
            self._seen.pop(key, None)


log = logging.getLogger(__name__)
_node_prints = Fingerprints()
_autopilot_prints = Fingerprints()
_annotation_prints = Fingerprints()
_connected: dict[str, str | None] = {}


# -- indexes -------------------------------------------------------------------------


def vehicle_node_claims(
    *, name: str, spec: kopf.Spec, meta: kopf.Meta, **_: Any
) -> dict[str, NodeClaim]:
    """node name → the Vehicles naming it (a Vehicle being deleted claims nothing)."""
    if meta.get("deletionTimestamp") or not spec.get("nodeName"):
        return {}
    return {spec["nodeName"]: NodeClaim(name, str(meta["creationTimestamp"]))}


def autopilots_by_vehicle(*, name: str, spec: kopf.Spec, **_: Any) -> dict[str, str]:
    """vehicle name → its RedundantAutopilot's name."""
    vehicle = spec.get("vehicleName")
    return {vehicle: name} if vehicle else {}


def failover_actions(*, name: str, status: kopf.Status, **_: Any) -> dict[str, bool]:
    """Vehicles with a cluster-side failover action running (for the fleet-wide cap)."""
    action = (status.get("failover") or {}).get("action")
    return {name: True} if action else {}


def _autopilot_of(vehicle: str, indexes: Mapping[str, Any]) -> str | None:
    by_vehicle: AutopilotsByVehicle = indexes["autopilots_by_vehicle"]
    return next(iter(by_vehicle.get(vehicle, [])), None)


def peers_from(indexes: Mapping[str, Any]) -> Peers:
    """The :class:`Peers` view of the kopf indexes (a handler's ``**kwargs``)."""
    claims: NodeClaims = indexes["vehicle_node_claims"]
    actions: FailoverActions = indexes["failover_actions"]
    return Peers(
        claims_on=lambda node: list(claims.get(node, [])),
        autopilots_of=lambda vehicle: _autopilot_of(vehicle, indexes),
        actions=lambda: list(actions),
    )


def reconcile_now(memo: Any, vehicle: str, indexes: Mapping[str, Any]) -> None:
    """Reconcile one Vehicle (it may not exist: then nothing happens)."""
    rt = runtime(memo)
    with at_the_edge("Vehicle", vehicle):
        outcome = rt.vehicles.reconcile(vehicle, peers_from(indexes))
    if outcome is None:
        _connected.pop(vehicle, None)
    else:
        _connected[vehicle] = outcome.agent_connected


# -- the Vehicle's own triggers -----------------------------------------------------------


def vehicle_changed(*, name: str, memo: Any, **indexes: Any) -> None:
    """The Vehicle was created or its spec/labels changed (or the operator started)."""
    reconcile_now(memo, name, indexes)


def guard_annotations(
    *, type: str | None, name: str, meta: kopf.Meta, memo: Any, **indexes: Any
) -> None:
    """A human paused, resumed or cleared the latch of this vehicle's failover actions.

    A watch-event handler because kopf's update handlers do not see annotations under
    the operator's own ``roost.dev/`` prefix (its progress storage lives there).
    """
    if type == "DELETED":
        _annotation_prints.forget(name)
        return
    annotations = meta.get("annotations") or {}
    relevant = [
        annotations.get(ANNOTATION_PAUSE_FAILOVER_ACTIONS),
        annotations.get(ANNOTATION_CLEAR_FAILOVER_LATCH),
    ]
    if _annotation_prints.changed(name, relevant):
        reconcile_now(memo, name, indexes)


def vehicle_resync(*, name: str, memo: Any, **indexes: Any) -> None:
    """Periodic level-based resync (NFD practice: put hand edits back)."""
    reconcile_now(memo, name, indexes)


def failover_pending(*, name: str, memo: Any, **indexes: Any) -> None:
    """An action runs or waits for a guard: check for its end, timeout or the guard lifting."""
    reconcile_now(memo, name, indexes)


def _pending(status: kopf.Status, **_: Any) -> bool:
    failover = status.get("failover") or {}
    return bool(failover.get("action") or failover.get("blocked"))


def vehicle_deleted(
    *, name: str, spec: kopf.Spec, body: kopf.Body, memo: Any, **indexes: Any
) -> None:
    """Remove the vehicle's labels, taint, config and workloads; hand its node on.

    What cannot be removed is named in a Warning Event and the deletion goes on: a
    Vehicle that cannot be deleted is worse than a leftover a human can remove.
    """
    rt = runtime(memo)
    with at_the_edge("Vehicle", name):
        leftovers = rt.vehicles.release(name)
    if not leftovers.clean:
        log.warning("Vehicle %s: deleted, but left behind: %s", name, leftovers.problems)
        rt.kube.post_event(
            body,
            reason="CleanupIncomplete",
            message="deleted, but left behind: " + "; ".join(leftovers.problems),
            type="Warning",
            at=now().isoformat().replace("+00:00", "Z"),
        )
    _connected.pop(name, None)
    claims: NodeClaims = indexes["vehicle_node_claims"]
    for claim in claims.get(spec.get("nodeName", ""), []):
        if claim.vehicle != name:
            reconcile_now(memo, claim.vehicle, indexes)


# -- other objects' triggers ---------------------------------------------------------------


def _node_relevant(body: Mapping[str, Any]) -> Any:
    """What Roost reads from a node: existence, labels, annotations, taints, Ready."""
    meta = body.get("metadata", {})
    ready = [
        (c.get("status"), c.get("reason"), c.get("message"))
        for c in (body.get("status") or {}).get("conditions") or []
        if c.get("type") == "Ready"
    ]
    return [
        meta.get("labels"),
        meta.get("annotations"),
        (body.get("spec") or {}).get("taints"),
        ready,
    ]


def node_event(*, type: str | None, name: str, body: kopf.Body, memo: Any, **indexes: Any) -> None:
    """A node changed: reconcile the vehicles that claim it or that it carries."""
    if type == "DELETED":
        _node_prints.forget(name)
    elif not _node_prints.changed(name, _node_relevant(body)):
        return
    claims: NodeClaims = indexes["vehicle_node_claims"]
    vehicles = {claim.vehicle for claim in claims.get(name, [])}
    labelled = body.get("metadata", {}).get("labels", {}).get(LABEL_VEHICLE)
    if labelled:
        vehicles.add(labelled)
    for vehicle in sorted(vehicles):
        reconcile_now(memo, vehicle, indexes)


def component_event(*, labels: kopf.Labels, memo: Any, **indexes: Any) -> None:
    """A component Deployment changed (rollout progress, deletion): update the vehicle."""
    reconcile_now(memo, labels[LABEL_VEHICLE], indexes)


def autopilot_reported(
    *, type: str | None, name: str, body: kopf.Body, memo: Any, **indexes: Any
) -> None:
    """The agent wrote a report (or someone changed the spec): act on what is new."""
    vehicle = (body.get("spec") or {}).get("vehicleName")
    if not vehicle:
        return
    if type == "DELETED":
        _autopilot_prints.forget(name)
        reconcile_now(memo, vehicle, indexes)
        return
    changed = _autopilot_prints.changed(name, relevant_autopilot(body))
    if changed or _connected.get(vehicle) != "True":
        reconcile_now(memo, vehicle, indexes)


def autopilot_silent(*, spec: kopf.Spec, memo: Any, **indexes: Any) -> None:
    """No report for the whole staleness window: AgentConnected turns Unknown."""
    vehicle = spec.get("vehicleName")
    if vehicle:
        reconcile_now(memo, vehicle, indexes)


def claim_changed(*, body: kopf.Body, memo: Any, **indexes: Any) -> None:
    """A mission claimed or released the vehicle: mirror it into ``status.claimedBy``."""
    claim = claim_of(body)
    if claim is not None:
        reconcile_now(memo, claim.vehicle, indexes)


# -- registration ------------------------------------------------------------------------


def register(registry: kopf.OperatorRegistry, settings: Settings) -> None:
    """Register the Vehicle controller's handlers with the operator's settings."""
    backoff = settings.retry_backoff_seconds
    stale = settings.agent_stale_after.total_seconds()
    kopf.index(*VEHICLES, registry=registry)(vehicle_node_claims)
    kopf.index(*VEHICLES, registry=registry)(failover_actions)
    kopf.index(*AUTOPILOTS, registry=registry)(autopilots_by_vehicle)
    for trigger in (kopf.on.resume, kopf.on.create, kopf.on.update):
        trigger(*VEHICLES, backoff=backoff, registry=registry)(handler_edge(vehicle_changed))
    kopf.timer(
        *VEHICLES,
        interval=settings.resync_seconds,
        initial_delay=settings.resync_seconds,
        registry=registry,
    )(handler_edge(vehicle_resync))
    kopf.timer(
        *VEHICLES,
        interval=settings.failover_poll_seconds,
        when=_pending,
        backoff=backoff,
        registry=registry,
    )(handler_edge(failover_pending))
    kopf.on.event(*VEHICLES, registry=registry)(handler_edge(guard_annotations))
    kopf.on.delete(*VEHICLES, backoff=backoff, registry=registry)(handler_edge(vehicle_deleted))
    kopf.on.event("", "v1", "nodes", registry=registry)(handler_edge(node_event))
    kopf.on.event(
        "apps",
        "v1",
        "deployments",
        labels={
            LABEL_MANAGED_BY: MANAGED_BY,
            LABEL_VEHICLE: kopf.PRESENT,
            LABEL_COMPONENT: kopf.PRESENT,
        },
        registry=registry,
    )(handler_edge(component_event))
    kopf.on.event(*AUTOPILOTS, registry=registry)(handler_edge(autopilot_reported))
    kopf.timer(*AUTOPILOTS, interval=stale / 3, idle=stale, backoff=backoff, registry=registry)(
        handler_edge(autopilot_silent)
    )
    kopf.on.event(
        *LEASES,
        labels={LABEL_MANAGED_BY: MANAGED_BY, LABEL_COMPONENT: CLAIM_COMPONENT},
        registry=registry,
    )(handler_edge(claim_changed))
