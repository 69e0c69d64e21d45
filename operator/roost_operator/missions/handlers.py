"""kopf triggers of the Mission controller: every one adds Mission keys to its work queue.

kopf delivers the custom resources' events and runs the deletion behind Roost's
finalizer; the engine reconciles. Each handler below only decides *which Missions* an
event concerns (:class:`~roost_operator.missions.interest.Interest`) and adds their keys
(``namespace/name``) to the Mission queue of the
:class:`~roost_operator.runtime.Runtime`; the queue's workers run
:meth:`~roost_operator.missions.controller.MissionController.reconcile` (observe → pure
plan → write), one reconcile of a Mission at a time, a burst of events costing one, with
the engine's backoff for temporary failures and one report for a permanent one.

Why level-based reconciles of a queue rather than create/update handlers: a Mission's
progress depends on other objects (Vehicles freeing up, agents reporting, Jobs
completing), so each reconcile reads everything and decides from what it finds.

Triggers, and why each exists:

* the Mission itself — when first seen (kopf's listing at start, a new Mission: this is
  how a new leader continues every Mission), when its generation changes (an abort in
  ``spec.command``) and when it is marked for deletion; its status, which only this
  controller writes, is ignored;
* a Vehicle — its holder, its claimant and every Mission waiting for vehicles (it may be
  the vehicle turning Ready that one needs);
* its claim Lease — the same, from the runtime's own claim watch
  (:meth:`~roost_operator.runtime.Runtime._claim_changed`);
* a RedundantAutopilot — the agent reported (health, failover, landed, a command's
  result): the Mission holding its vehicle;
* a Job carrying the mission label — the Mission owning it;
* a deadline per Mission in the queue, not a timer: the delay its plan asked for (an
  abort's poll, a records round) or else the resync period while it is unfinished.

Deletion: :func:`mission_deleted` (kopf's deletion handler, behind Roost's finalizer)
aborts what still flies for the Mission and releases its vehicles, after any reconcile
of it that is running; its Jobs go by owner reference. A cleanup that meets a permanent
error still lets the Mission go, with a Warning Event naming what was left.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping
from typing import Any, Final

import kopf

from roost_api.meta import now
from roost_api.wellknown import LABEL_MISSION
from roost_kube import resources
from roost_operator.edge import at_the_edge, handler_edge
from roost_operator.engine.watches import Fingerprints
from roost_operator.missions.controller import mission_key
from roost_operator.runtime import runtime
from roost_operator.settings import Settings

MISSIONS: Final = resources.MISSIONS.kopf
VEHICLES: Final = resources.VEHICLES.kopf
AUTOPILOTS: Final = resources.REDUNDANT_AUTOPILOTS.kopf

log = logging.getLogger(__name__)
_mission_prints = Fingerprints()


async def mission_deleted(
    *, name: str, namespace: str | None, body: kopf.Body, memo: Any, **_: Any
) -> None:
    """Abort what still flies for the mission and release its vehicles.

    What cannot be done (a permanent error) is named in a Warning Event and the
    deletion goes on; temporary errors are retried by kopf.
    """
    assert namespace is not None, "Missions are namespaced"
    rt = runtime(memo)
    with at_the_edge("Mission", name, namespace=namespace):
        leftovers = await asyncio.to_thread(rt.missions.delete, namespace, name)
    if leftovers:
        log.warning("Mission %s/%s: deleted, but: %s", namespace, name, "; ".join(leftovers))
        rt.kube.post_event(
            body,
            reason="CleanupIncomplete",
            message="deleted, but: " + "; ".join(leftovers),
            type="Warning",
            at=now(),
        )


def _mission_relevant(meta: Mapping[str, Any]) -> Any:
    """What of a Mission's metadata queues it (its spec is in the generation)."""
    return [meta.get("uid"), meta.get("generation"), bool(meta.get("deletionTimestamp"))]


async def mission_event(
    *, type: str | None, name: str, namespace: str | None, meta: kopf.Meta, memo: Any, **_: Any
) -> None:
    """The Mission appeared, its spec changed (abort) or it is being deleted: queue it.
    Status writes (this controller's own) are skipped."""
    rt = runtime(memo)
    key = mission_key(str(namespace), name)
    if type == "DELETED":
        _mission_prints.forget(key)
        rt.mission_queue.forget(key)
        rt.missions.forget(key)
        return
    if _mission_prints.changed(key, _mission_relevant(meta)):
        rt.mission_queue.add(key)


async def vehicle_event(*, name: str, status: kopf.Status, memo: Any, **_: Any) -> None:
    """A Vehicle changed (Ready, claim): queue its Mission and the waiting Missions."""
    claim = status.get("claimedBy") or {}
    claimant = mission_key(claim["namespace"], claim["name"]) if claim.get("name") else None
    rt = runtime(memo)
    rt.queue_missions(rt.missions.interest.for_vehicle(name, claimant))


async def autopilots_event(*, spec: kopf.Spec, memo: Any, **_: Any) -> None:
    """An agent reported (health, failover, landed, command result): queue its Mission."""
    vehicle = spec.get("vehicleName")
    if vehicle:
        rt = runtime(memo)
        rt.queue_missions(rt.missions.interest.holder(vehicle))


async def job_event(*, namespace: str | None, meta: kopf.Meta, memo: Any, **_: Any) -> None:
    """A mission's Job progressed: queue the Mission that owns it."""
    owners = {
        mission_key(str(namespace), ref["name"])
        for ref in meta.get("ownerReferences") or []
        if ref.get("kind") == "Mission"
    }
    runtime(memo).queue_missions(owners)


def register(registry: kopf.OperatorRegistry, settings: Settings) -> None:
    """Register the Mission controller's handlers with the operator's settings."""
    timings = settings.missions
    kopf.on.delete(*MISSIONS, backoff=timings.delete_backoff_seconds, registry=registry)(
        handler_edge(mission_deleted)
    )
    kopf.on.event(*MISSIONS, registry=registry)(handler_edge(mission_event))
    kopf.on.event(*VEHICLES, registry=registry)(handler_edge(vehicle_event))
    kopf.on.event(*AUTOPILOTS, registry=registry)(handler_edge(autopilots_event))
    kopf.on.event("batch", "v1", "jobs", labels={LABEL_MISSION: kopf.PRESENT}, registry=registry)(
        handler_edge(job_event)
    )
