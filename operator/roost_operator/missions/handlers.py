"""kopf handlers for Missions: one reconcile loop per Mission, woken by what it reads.

Why a daemon per Mission rather than create/update handlers: a mission's progress
depends on other objects (Vehicles freeing up, agents reporting, Jobs completing), so
convergence must be level-based. The daemon runs
:func:`~roost_operator.missions.cluster.reconcile_mission` (observe → pure plan → write),
then sleeps until :mod:`~roost_operator.missions.wakeups` wakes it or its resync period
passes. One loop per Mission also means one reconcile of that Mission at a time. kopf
starts the loop for every Mission it sees, including after an operator restart, so a
restarted operator resumes each mission from what the cluster shows (deterministic Job
names and command ids keep the repeat harmless). The loop ends once the mission is
finished and holds nothing.

Deletion: kopf stops the loop, then :func:`mission_deleted` (behind Roost's finalizer)
aborts what still flies for the mission and releases its vehicles; its Jobs go by
owner reference.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Final

import kopf

from roost_api.wellknown import LABEL_MISSION
from roost_kube import resources
from roost_operator.autopilots.handlers import GUARDS
from roost_operator.missions.cluster import reconcile_mission, release_deleted_mission
from roost_operator.missions.wakeups import Wakeups, sleep_until_woken
from roost_operator.runtime import runtime

MISSIONS: Final = resources.MISSIONS.kopf
VEHICLES: Final = resources.VEHICLES.kopf
AUTOPILOTS: Final = resources.REDUNDANT_AUTOPILOTS.kopf

RESYNC_S: Final = 10.0
"""Reconcile a mission at least this often (Jobs and agents also wake it)."""
ERROR_BACKOFF_S: Final = 5.0
COALESCE_S: Final = 0.5
"""After a wake-up, wait this long so a burst of events costs one reconcile."""

WAKEUPS: Final = Wakeups()
log = logging.getLogger(__name__)


@kopf.daemon(*MISSIONS, id="mission", cancellation_timeout=30.0)
async def mission_daemon(
    *, name: str, namespace: str | None, stopped: kopf.DaemonStopped, memo: Any, **_: Any
) -> None:
    """Reconcile the Mission until it is finished and holds nothing."""
    assert namespace is not None, "Missions are namespaced"
    rt = runtime(memo)
    key = f"{namespace}/{name}"
    wakeup = WAKEUPS.register(key)
    try:
        while not stopped:
            wakeup.clear()
            try:
                outcome = await asyncio.to_thread(
                    reconcile_mission,
                    rt.kube,
                    namespace=namespace,
                    name=name,
                    operator_namespace=rt.settings.namespace,
                    guards=GUARDS,
                )
            except Exception:
                log.exception("reconciling mission %s failed; retrying", key)
                delay = ERROR_BACKOFF_S
            else:
                if outcome is None or outcome.finished:
                    return
                WAKEUPS.track(key, vehicles=outcome.assigned, waiting=outcome.waiting_for_vehicles)
                delay = RESYNC_S if outcome.requeue_after is None else outcome.requeue_after
            if await sleep_until_woken(wakeup, stopped.wait(), delay):
                await asyncio.sleep(COALESCE_S)
    finally:
        WAKEUPS.forget(key)


@kopf.on.delete(*MISSIONS, backoff=2.0)
async def mission_deleted(*, name: str, namespace: str | None, memo: Any, **_: Any) -> None:
    """Abort what still flies for the mission and release its vehicles."""
    assert namespace is not None, "Missions are namespaced"
    rt = runtime(memo)
    await asyncio.to_thread(
        release_deleted_mission,
        rt.kube,
        namespace=namespace,
        name=name,
        operator_namespace=rt.settings.namespace,
        guards=GUARDS,
    )


@kopf.on.event(*MISSIONS)
async def mission_event(
    *, name: str, namespace: str | None, meta: kopf.Meta, status: kopf.Status, **_: Any
) -> None:
    """The Mission's spec changed (abort) or it is being deleted: wake its loop."""
    unobserved = meta.get("generation") != status.get("observedGeneration")
    if unobserved or meta.get("deletionTimestamp"):
        WAKEUPS.wake(f"{namespace}/{name}")


@kopf.on.event(*VEHICLES)
async def vehicle_event(*, name: str, status: kopf.Status, **_: Any) -> None:
    """A Vehicle changed (Ready, claim): wake its mission and the waiting missions."""
    claim = status.get("claimedBy") or {}
    claimant = f"{claim['namespace']}/{claim['name']}" if claim.get("name") else None
    WAKEUPS.wake_for_vehicle(name, claimant)


@kopf.on.event(*AUTOPILOTS)
async def autopilots_event(*, spec: kopf.Spec, **_: Any) -> None:
    """An agent reported (health, failover, landed, command result): wake the mission."""
    vehicle = spec.get("vehicleName")
    if vehicle:
        WAKEUPS.wake_holder(vehicle)


@kopf.on.event("batch", "v1", "jobs", labels={LABEL_MISSION: kopf.PRESENT})
async def job_event(*, namespace: str | None, meta: kopf.Meta, **_: Any) -> None:
    """A mission's Job progressed: wake the Mission that owns it."""
    for ref in meta.get("ownerReferences") or []:
        if ref.get("kind") == "Mission":
            WAKEUPS.wake(f"{namespace}/{ref['name']}")
