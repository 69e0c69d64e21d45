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
owner reference. A cleanup that meets a permanent error still lets the Mission go,
with a Warning Event naming what was left.

Errors: a reconcile that fails is retried with the engine's doubling backoff
(:class:`~roost_operator.engine.workqueue.Backoff`, timed by
:class:`~roost_operator.settings.MissionTimings`), a refusal for good
(:func:`~roost_operator.engine.errors.is_permanent`) reported once; its log line names
the Mission.
Handlers are registered by :func:`register`; timings are read from the settings in
the operator's memo.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Final

import kopf

from roost_api.meta import now
from roost_api.wellknown import LABEL_MISSION
from roost_kube import resources
from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_operator.claims import Claim
from roost_operator.edge import at_the_edge, handler_edge
from roost_operator.engine.errors import is_permanent
from roost_operator.engine.workqueue import Backoff
from roost_operator.missions.cluster import reconcile_mission, release_deleted_mission
from roost_operator.missions.wakeups import Wakeups, sleep_until_woken
from roost_operator.runtime import runtime
from roost_operator.settings import Settings

MISSIONS: Final = resources.MISSIONS.kopf
VEHICLES: Final = resources.VEHICLES.kopf
AUTOPILOTS: Final = resources.REDUNDANT_AUTOPILOTS.kopf

WAKEUPS: Final = Wakeups()
log = logging.getLogger(__name__)


def report_refusal(kube: Kube, body: kopf.Body, key: str, error: ApiError) -> None:
    """A write the API server refuses for good: one log line and one Warning Event.

    The reconcile is still retried with the longest backoff (a human may fix what the
    refusal names, e.g. a quota or a policy), but the refusal is not reported again
    until it changes.
    """
    log.error("Mission %s: the API server refused a write: %s", key, error)
    try:
        kube.post_event(
            body,
            reason="WriteRefused",
            message=f"the API server refused a write for this mission: {error.message}",
            type="Warning",
            at=now(),
        )
    except ApiError as failed:
        log.warning("Mission %s: could not post the Event: %s", key, failed)


async def mission_daemon(
    *,
    name: str,
    namespace: str | None,
    body: kopf.Body,
    stopped: kopf.DaemonStopped,
    memo: Any,
    **_: Any,
) -> None:
    """Reconcile the Mission until it is finished and holds nothing."""
    assert namespace is not None, "Missions are namespaced"
    rt = runtime(memo)
    timings = rt.settings.missions
    retry = Backoff(timings.error_backoff_seconds, timings.max_backoff_seconds)
    key = f"{namespace}/{name}"
    wakeup = WAKEUPS.register(key)
    failures = 0
    reported: str | None = None
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
                    guards=rt.settings.guards,
                    records=rt.settings.records,
                )
            except ApiError as error:
                failures += 1
                delay = retry.delay(failures)
                if not is_permanent(error):
                    log.warning("Mission %s: %s; retrying in %.1f s", key, error, delay)
                elif str(error) != reported:  # once per distinct refusal, no traceback
                    reported = str(error)
                    await asyncio.to_thread(report_refusal, rt.kube, body, key, error)
            except Exception:
                failures += 1
                delay = retry.delay(failures)
                log.exception("Mission %s: reconcile failed; retrying in %.1f s", key, delay)
            else:
                failures = 0
                reported = None
                if outcome is None or outcome.finished:
                    return
                WAKEUPS.track(key, vehicles=outcome.assigned, waiting=outcome.waiting_for_vehicles)
                delay = (
                    timings.resync_seconds
                    if outcome.requeue_after is None
                    else outcome.requeue_after
                )
            if await sleep_until_woken(wakeup, stopped.wait(), delay):
                await asyncio.sleep(timings.coalesce_seconds)
    finally:
        WAKEUPS.forget(key)


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
        leftovers = await asyncio.to_thread(
            release_deleted_mission,
            rt.kube,
            namespace=namespace,
            name=name,
            operator_namespace=rt.settings.namespace,
            guards=rt.settings.guards,
        )
    if leftovers:
        log.warning("Mission %s/%s: deleted, but: %s", namespace, name, "; ".join(leftovers))
        rt.kube.post_event(
            body,
            reason="CleanupIncomplete",
            message="deleted, but: " + "; ".join(leftovers),
            type="Warning",
            at=now(),
        )


async def mission_event(
    *, name: str, namespace: str | None, meta: kopf.Meta, status: kopf.Status, **_: Any
) -> None:
    """The Mission's spec changed (abort) or it is being deleted: wake its loop."""
    unobserved = meta.get("generation") != status.get("observedGeneration")
    if unobserved or meta.get("deletionTimestamp"):
        WAKEUPS.wake(f"{namespace}/{name}")


async def vehicle_event(*, name: str, status: kopf.Status, **_: Any) -> None:
    """A Vehicle changed (Ready, claim): wake its mission and the waiting missions."""
    claim = status.get("claimedBy") or {}
    claimant = f"{claim['namespace']}/{claim['name']}" if claim.get("name") else None
    WAKEUPS.wake_for_vehicle(name, claimant)


async def listen_to_claims(memo: Any, **_: Any) -> None:
    """At startup: wake missions on claim Lease events (the runtime's own claim watch
    calls back from its thread, so the wake-up is handed to this event loop)."""
    loop = asyncio.get_running_loop()

    def claimed(claim: Claim) -> None:
        loop.call_soon_threadsafe(WAKEUPS.wake_for_vehicle, claim.vehicle, claim.holder_key)

    runtime(memo).claim_listeners.append(claimed)


async def autopilots_event(*, spec: kopf.Spec, **_: Any) -> None:
    """An agent reported (health, failover, landed, command result): wake the mission."""
    vehicle = spec.get("vehicleName")
    if vehicle:
        WAKEUPS.wake_holder(vehicle)


async def job_event(*, namespace: str | None, meta: kopf.Meta, **_: Any) -> None:
    """A mission's Job progressed: wake the Mission that owns it."""
    for ref in meta.get("ownerReferences") or []:
        if ref.get("kind") == "Mission":
            WAKEUPS.wake(f"{namespace}/{ref['name']}")


def register(registry: kopf.OperatorRegistry, settings: Settings) -> None:
    """Register the Mission controller's handlers with the operator's settings."""
    timings = settings.missions
    kopf.daemon(
        *MISSIONS,
        id="mission",
        cancellation_timeout=timings.stop_timeout_seconds,
        registry=registry,
    )(handler_edge(mission_daemon))
    kopf.on.delete(*MISSIONS, backoff=timings.delete_backoff_seconds, registry=registry)(
        handler_edge(mission_deleted)
    )
    kopf.on.event(*MISSIONS, registry=registry)(handler_edge(mission_event))
    kopf.on.event(*VEHICLES, registry=registry)(handler_edge(vehicle_event))
    kopf.on.startup(registry=registry)(listen_to_claims)
    kopf.on.event(*AUTOPILOTS, registry=registry)(handler_edge(autopilots_event))
    kopf.on.event("batch", "v1", "jobs", labels={LABEL_MISSION: kopf.PRESENT}, registry=registry)(
        handler_edge(job_event)
    )
