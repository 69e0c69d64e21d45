"""kopf triggers of the Vehicle controller: every one adds the vehicle to one work queue.

kopf watches; :class:`~roost_operator.engine.workqueue.WorkQueue` reconciles. Each handler
below only decides *which vehicle* an event concerns and whether anything Roost reads
changed, then adds that vehicle's name to the queue and returns: handlers are async and
never touch the API, so kopf's event loop never waits on a thread, and a burst of
events about one vehicle (a component pod on its way to Ready) costs one reconcile. The queue's
workers run :meth:`~roost_operator.vehicles.controller.VehicleController.reconcile`,
retry temporary failures with a backoff, and report a permanent one once.

Triggers, and why each exists:

* the Vehicle itself (every watch event, the initial listing included) — when its
  generation, labels, annotations (the guard annotations: pause, clear the latch) or
  deletion mark changed; its status (which only this controller writes) is ignored;
* its node — a node appearing, turning Ready/NotReady or losing a Roost label queues
  the vehicles that claim it or that it is labelled for;
* what Roost made for it (its ConfigMap and component Pods) — a pod's progress to Ready,
  its end, its deletion (which lets its successor be created), and a hand edit is put
  back at once. Nodes and these are watched by Roost's own
  threads (:mod:`~roost_operator.vehicles.watched`), not by kopf: node heartbeats and
  rollout steps are most of a fleet's watch events, and they are dropped there by a
  fingerprint before any of kopf's per-event work, into stores the controller reads;
* its RedundantAutopilot — the agent reported. Reports that change nothing the
  controller reads (the periodic refresh of ``reportedAt``, heartbeat ages) are skipped
  by a fingerprint, except while the vehicle's ``AgentConnected`` is not True (a report
  is then exactly the news that the agent is back). Every report moves the vehicle's
  *staleness deadline* in the queue: if no report comes for ``agent_stale_after``, the
  deadline reconciles it and ``AgentConnected`` turns Unknown — without a timer per
  object;
* a Vehicle timer while a failover action runs or a guard holds one back (only then) —
  timeouts, and the moment a guard lifts;
* its claim Lease — the mission claim mirrored into ``status.claimedBy``. Claim Leases
  are watched by Roost's own thread with a server-side label selector
  (:mod:`roost_operator.engine.watches`): kopf filters labels itself, so a kopf handler would
  have kopf process every node's heartbeat Lease;
* optionally a fleet sweep every ``resync_seconds`` (off by default: everything above is
  event-driven, and a sweep at fleet scale is work that almost always finds nothing).

Deletion needs no finalizer: a Vehicle's deletion event queues its reconcile, which
finds it gone and removes its labels, taint, config and workloads (what cannot be
removed is reported in an Event), and queues the other Vehicles waiting for the freed
node. Everything Roost makes for a vehicle carries its label, so an operator that was
down while a Vehicle was deleted finds the leftovers on its first listing of nodes.
Vehicles that still carry the finalizer of earlier versions (``roost.dev/cleanup``)
lose it to kopf on their next event: no handler requires it any more.

Handlers are registered by :func:`register` with the operator's settings; the
:class:`~roost_operator.vehicles.controller.VehicleController`, the queue and the view
of kopf's indexes live in the operator's :class:`~roost_operator.runtime.Runtime`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any, Final

import kopf

from roost_api.meta import now
from roost_api.wellknown import PREFIX
from roost_kube import resources
from roost_operator.edge import handler_edge
from roost_operator.engine.watches import Fingerprints
from roost_operator.runtime import Runtime, runtime
from roost_operator.settings import Settings
from roost_operator.vehicles.observe import Peers
from roost_operator.vehicles.placement import NodeClaim
from roost_operator.vehicles.plan import relevant_autopilot

VEHICLES: Final = resources.VEHICLES.kopf
AUTOPILOTS: Final = resources.REDUNDANT_AUTOPILOTS.kopf
STALE_MARGIN_S: Final = 1.1
"""The staleness deadline fires this long after the report turns stale: ``reportedAt``
and the controller's clock are both whole seconds (as Kubernetes stores times), so a
report is seen stale only in the second after it turns stale."""
KOPF_ANNOTATIONS: Final = (f"{PREFIX}last-handled-configuration",)
"""Annotations kopf kept on Vehicles under Roost's prefix (not the user's input): the
diff base of operators before :class:`~roost_operator.main.NoDiffBase`, still on the
Vehicles they handled."""

NodeClaims = kopf.Index[str, NodeClaim]
AutopilotsByVehicle = kopf.Index[str, str]
FailoverActions = kopf.Index[str, bool]


log = logging.getLogger(__name__)
_vehicle_prints = Fingerprints()
_autopilot_prints = Fingerprints()


# -- indexes -------------------------------------------------------------------------
# Async so kopf calls them in its event loop: they run on every event of their kind, and a
# sync one would cost a hop to a thread each time.


async def vehicle_node_claims(
    *, name: str, spec: kopf.Spec, meta: kopf.Meta, **_: Any
) -> dict[str, NodeClaim]:
    """node name → the Vehicles naming it (a Vehicle being deleted claims nothing)."""
    if meta.get("deletionTimestamp") or not spec.get("nodeName"):
        return {}
    return {spec["nodeName"]: NodeClaim(name, str(meta["creationTimestamp"]))}


async def autopilots_by_vehicle(*, name: str, spec: kopf.Spec, **_: Any) -> dict[str, str]:
    """vehicle name → its RedundantAutopilot's name."""
    vehicle = spec.get("vehicleName")
    return {vehicle: name} if vehicle else {}


async def failover_actions(*, name: str, status: kopf.Status, **_: Any) -> dict[str, bool]:
    """Vehicles with a cluster-side failover action running (for the fleet-wide cap)."""
    action = (status.get("failover") or {}).get("action")
    return {name: True} if action else {}


def _autopilot_of(vehicle: str, indexes: Mapping[str, Any]) -> str | None:
    by_vehicle: AutopilotsByVehicle = indexes["autopilots_by_vehicle"]
    return next(iter(by_vehicle.get(vehicle, [])), None)


def peers_from(indexes: Mapping[str, Any]) -> Peers:
    """The :class:`Peers` view of the kopf indexes (a handler's ``**kwargs``; kopf's
    index objects are live, so the view stays current)."""
    claims: NodeClaims = indexes["vehicle_node_claims"]
    actions: FailoverActions = indexes["failover_actions"]
    return Peers(
        claims_on=lambda node: list(claims.get(node, [])),
        autopilots_of=lambda vehicle: _autopilot_of(vehicle, indexes),
        actions=lambda: list(actions),
    )


# -- the queue's side ------------------------------------------------------------------


def reconcile_vehicle(rt: Runtime, vehicle: str) -> None:
    """One queued reconcile (a worker thread): API errors leave as they are, and the
    engine's queue retries temporary ones and reports permanent ones once
    (:mod:`roost_operator.engine.errors`)."""
    peers = rt.peers
    if peers is None:
        # Queued by a node or a pod before kopf delivered any Vehicle event: a vehicle
        # that exists is queued again by its first event; one deleted while the operator
        # was down is released now.
        rt.vehicles.release_if_gone(vehicle)
        return
    outcome = rt.vehicles.reconcile(vehicle, peers)
    held = rt.held_reports.pop(vehicle, None)
    if outcome is not None and outcome.report_due is not None:
        # A held first report: write it then at the latest.
        wait = (outcome.report_due - now()).total_seconds()
        rt.held_reports[vehicle] = when = time.monotonic() + max(0.0, wait)
        rt.vehicle_queue.add_at(vehicle, when)
    elif held is not None:  # written (or gone) before its deadline: nothing left to do then
        rt.vehicle_queue.cancel_at(vehicle, held)
    if outcome is None:
        rt.connected.pop(vehicle, None)
    else:
        rt.connected[vehicle] = outcome.agent_connected


def enqueue(memo: Any, vehicle: str, indexes: Mapping[str, Any]) -> None:
    """Queue a reconcile of ``vehicle`` (it may not exist: then nothing happens)."""
    rt = runtime(memo)
    rt.bind_peers(lambda: peers_from(indexes))
    rt.vehicle_queue.add(vehicle)


def _stale_deadline(rt: Runtime, reported_at: str | None) -> float | None:
    """When (this process's monotonic clock) a report made at ``reported_at`` turns stale."""
    if not reported_at:
        return None
    try:
        at = datetime.fromisoformat(reported_at.replace("Z", "+00:00"))
    except ValueError:
        return None
    left = at + rt.settings.agent_stale_after - datetime.now(UTC)
    return time.monotonic() + max(0.0, left.total_seconds()) + STALE_MARGIN_S


# -- the Vehicle's own triggers -----------------------------------------------------------


def _vehicle_relevant(meta: Mapping[str, Any]) -> Any:
    """What of a Vehicle's metadata Roost acts on (its spec is in the generation)."""
    annotations = {
        key: value
        for key, value in (meta.get("annotations") or {}).items()
        if key not in KOPF_ANNOTATIONS
    }
    return [
        meta.get("generation"),
        meta.get("labels"),
        annotations,
        meta.get("deletionTimestamp"),
    ]


async def vehicle_event(
    *,
    type: str | None,
    name: str,
    meta: kopf.Meta,
    event: kopf.RawEvent,
    memo: Any,
    **indexes: Any,
) -> None:
    """The Vehicle appeared (the operator started, or it was created), its spec, labels or
    annotations changed (a human paused, resumed or cleared the latch of its failover
    actions), or it is being deleted. Status writes (this controller's own) are skipped.

    A watch-event handler: kopf's update handlers do not see annotations under the
    operator's own ``roost.dev/`` prefix (its progress storage lives there), and they
    store a diff base on every object, a write per Vehicle that nothing here needs.

    Every event, status writes included, keeps the controller's cache of Vehicles
    (:attr:`~roost_operator.runtime.Runtime.vehicles_seen`) current.
    """
    rt = runtime(memo)
    rt.vehicles_seen.observe(type or "ADDED", event["object"])
    if type == "DELETED":
        _vehicle_prints.forget(name)
        rt.vehicle_queue.forget(name)  # its deadlines and backoff: the release is queued
        enqueue(memo, name, indexes)
        node = (event["object"].get("spec") or {}).get("nodeName", "")
        claims: NodeClaims = indexes["vehicle_node_claims"]
        for claim in claims.get(node, []):
            if claim.vehicle != name:
                enqueue(memo, claim.vehicle, indexes)
        return
    if _vehicle_prints.changed(name, _vehicle_relevant(meta)):
        enqueue(memo, name, indexes)


async def failover_pending(*, name: str, memo: Any, **indexes: Any) -> None:
    """An action runs or waits for a guard: check for its end, timeout or the guard lifting."""
    enqueue(memo, name, indexes)


def _pending(status: kopf.Status, **_: Any) -> bool:
    failover = status.get("failover") or {}
    return bool(failover.get("action") or failover.get("blocked"))


# -- other objects' triggers ---------------------------------------------------------------


async def autopilot_reported(
    *, type: str | None, name: str, body: kopf.Body, memo: Any, **indexes: Any
) -> None:
    """The agent wrote a report (or someone changed the spec): act on what is new, and
    move the vehicle's staleness deadline."""
    vehicle = (body.get("spec") or {}).get("vehicleName")
    if not vehicle:
        return
    rt = runtime(memo)
    if type == "DELETED":
        _autopilot_prints.forget(name)
        enqueue(memo, vehicle, indexes)
        return
    deadline = _stale_deadline(rt, (body.get("status") or {}).get("reportedAt"))
    if deadline is not None:
        rt.bind_peers(lambda: peers_from(indexes))
        rt.vehicle_queue.add_at(vehicle, deadline)
    changed = _autopilot_prints.changed(name, relevant_autopilot(body))
    if changed or rt.connected.get(vehicle) != "True":
        enqueue(memo, vehicle, indexes)


# -- registration ------------------------------------------------------------------------


def register(registry: kopf.OperatorRegistry, settings: Settings) -> None:
    """Register the Vehicle controller's handlers with the operator's settings."""
    backoff = settings.retry_backoff_seconds
    kopf.index(*VEHICLES, registry=registry)(vehicle_node_claims)
    kopf.index(*VEHICLES, registry=registry)(failover_actions)
    kopf.index(*AUTOPILOTS, registry=registry)(autopilots_by_vehicle)
    kopf.on.event(*VEHICLES, registry=registry)(handler_edge(vehicle_event))
    kopf.timer(
        *VEHICLES,
        interval=settings.failover_poll_seconds,
        when=_pending,
        backoff=backoff,
        registry=registry,
    )(handler_edge(failover_pending))
    kopf.on.event(*AUTOPILOTS, registry=registry)(handler_edge(autopilot_reported))
