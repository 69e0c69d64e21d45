"""What every handler needs at run time, created once at operator startup.

:func:`roost_operator.main.main` builds the :class:`~roost_operator.settings.Settings`
and hands them to kopf in the operator's ``memo``; the startup handler adds the API
client, the controllers that keep per-process state (locks, the failover ledger), one
work queue per controller (:mod:`roost_operator.engine.workqueue`: Vehicles, Missions),
whose workers start with it and stop at the operator's cleanup, and Roost's own watches
that feed them and whose stores the Vehicle controller reads
(:mod:`roost_operator.vehicles.watched`, claims here). Handlers call :func:`runtime` to
get it typed. Nothing here talks to kopf's own API client: all of Roost's reads and writes
go through :class:`roost_kube.client.Kube`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, cast

from roost_api.wellknown import LABEL_COMPONENT, LABEL_MANAGED_BY, LABEL_VEHICLE, MANAGED_BY
from roost_kube.client import Kube
from roost_kube.resources import CONFIGMAPS, LEASES, NODES, PODS, VEHICLES
from roost_operator.claims import CLAIM_COMPONENT, claim_of
from roost_operator.edge import HandlerTiming
from roost_operator.engine.cache import Cached
from roost_operator.engine.errors import error_kind, is_permanent
from roost_operator.engine.watches import Store, Watcher
from roost_operator.engine.workqueue import Backoff, WorkQueue
from roost_operator.missions.controller import MissionController
from roost_operator.settings import Settings
from roost_operator.vehicles.controller import VehicleController
from roost_operator.vehicles.observe import Peers
from roost_operator.vehicles.watched import node_kept, node_watcher, owned_watchers, pod_kept

log = logging.getLogger(__name__)

CLAIM_SELECTOR = f"{LABEL_MANAGED_BY}={MANAGED_BY},{LABEL_COMPONENT}={CLAIM_COMPONENT}"
"""The claim Leases, selected by the API server (never every node's heartbeat Lease)."""


@dataclass
class Runtime:
    """The API client, the settings, the Vehicle and Mission controllers and their
    queues."""

    kube: Kube
    settings: Settings
    vehicles: VehicleController
    missions: MissionController
    vehicle_queue: WorkQueue = field(init=False)
    mission_queue: WorkQueue = field(init=False)
    peers: Peers | None = None
    """The kopf indexes as :class:`Peers` (bound by the first handler that runs: kopf
    hands its live index objects only to handlers)."""
    connected: dict[str, str | None] = field(default_factory=dict)
    """Each vehicle's ``AgentConnected`` status as its last reconcile wrote it."""
    held_reports: dict[str, float] = field(default_factory=dict)
    """The queue deadline of each new Vehicle's held first report (dropped once written)."""
    timing: HandlerTiming | None = None
    """Where each queued reconcile's duration goes (the operator's metrics), if anywhere."""
    watchers: list[Watcher] = field(default_factory=list)
    """Roost's own watches (Nodes, claim Leases): see :mod:`roost_operator.engine.watches`."""
    _sweep_stop: threading.Event = field(default_factory=threading.Event)

    @classmethod
    def start(
        cls,
        kube: Kube,
        settings: Settings,
        reconcile: Callable[[Runtime, str], None] | None = None,
        *,
        timing: HandlerTiming | None = None,
    ) -> Runtime:
        """The runtime of an operator with ``settings`` talking through ``kube``; its
        queue's workers run ``reconcile(runtime, vehicle)`` (none: the queue is not
        started, for unit tests); the Mission queue's workers, with it, run the
        :class:`~roost_operator.missions.controller.MissionController`."""
        namespace = settings.namespace
        stores = {
            NODES.kind: Store(index_label=LABEL_VEHICLE, trim=node_kept),
            LEASES.kind: Store(),
            CONFIGMAPS.kind: Store(index_label=LABEL_VEHICLE),
            PODS.kind: Store(index_label=LABEL_VEHICLE, trim=pod_kept),
        }
        controller = VehicleController(
            kube=kube,
            namespace=namespace,
            guards=settings.guards,
            stale_after=settings.agent_stale_after,
            first_report_hold=settings.first_report_hold,
            agent_image=settings.agent_image,
            caches={
                **{
                    kind: Cached(store, "" if kind == NODES.kind else namespace)
                    for kind, store in stores.items()
                },
                VEHICLES.kind: Cached(Store(), listed=False),
            },
        )
        rt = cls(
            kube=kube,
            settings=settings,
            vehicles=controller,
            missions=MissionController(kube, settings),
            timing=timing,
        )
        rt.vehicle_queue = WorkQueue(
            lambda vehicle: rt._timed("vehicles", reconcile, vehicle),
            workers=settings.reconcile_workers,
            backoff=Backoff(settings.retry_backoff_seconds, settings.max_backoff_seconds),
            is_permanent=is_permanent,
            on_permanent=rt._report_permanent,
            name="vehicle-reconcile",
        )
        timings = settings.missions
        rt.mission_queue = WorkQueue(
            lambda mission: rt._timed("missions", Runtime._reconcile_mission, mission),
            workers=timings.workers,
            backoff=Backoff(timings.error_backoff_seconds, timings.max_backoff_seconds),
            is_permanent=is_permanent,
            on_permanent=rt.missions.report_permanent,
            name="mission-reconcile",
        )
        if reconcile is not None:
            rt.vehicle_queue.start()
            rt.mission_queue.start()
            enqueue = rt.vehicle_queue.add
            rt.watchers = [
                node_watcher(kube, lambda: rt.peers, enqueue, stores[NODES.kind]),
                Watcher(
                    kube,
                    LEASES,
                    lambda kind, lease, news: rt._claim_changed(lease),
                    rt._claims_listed,
                    label_selector=CLAIM_SELECTOR,
                    namespace=namespace,
                    store=stores[LEASES.kind],
                ),
                *owned_watchers(kube, namespace, enqueue, stores),
            ]
            for watcher in rt.watchers:
                watcher.start()
            if settings.resync_seconds > 0:
                threading.Thread(target=rt._sweep, name="vehicle-sweep", daemon=True).start()
        return rt

    @property
    def vehicles_seen(self) -> Store:
        """Every Vehicle as kopf's watch last delivered it (or the controller last wrote
        it): the Vehicle controller's cache of Vehicles without a RedundantAutopilot, fed
        by the Vehicle event handler."""
        return self.vehicles.caches[VEHICLES.kind].store

    def bind_peers(self, make: Callable[[], Peers]) -> None:
        """Keep the index view from the first handler that offers it."""
        if self.peers is None:
            self.peers = make()

    def _timed(
        self, resource: str, reconcile: Callable[[Runtime, str], None] | None, key: str
    ) -> None:
        """Run one queued reconcile, reporting its duration (``resource``, handler
        ``reconcile``) and how it failed, as every kopf handler's run is."""
        if reconcile is None:
            return
        started, failed = time.perf_counter(), None
        try:
            reconcile(self, key)
        except Exception as error:
            failed = error_kind(error)
            raise
        finally:
            if self.timing is not None:
                self.timing.observe(resource, "reconcile", time.perf_counter() - started, failed)

    def _reconcile_mission(self, key: str) -> None:
        """One queued Mission reconcile; its next look without an event becomes the key's
        deadline (a finished Mission has none)."""
        delay = self.missions.reconcile(key)
        if delay is None:
            self.mission_queue.forget(key)
        else:
            self.mission_queue.add_at(key, time.monotonic() + delay)

    def queue_missions(self, keys: set[str]) -> None:
        """Queue a reconcile of each Mission in ``keys``."""
        for key in keys:
            self.mission_queue.add(key)

    def stop(self) -> None:
        """Stop the sweep and the queues' workers (after their running reconciles)."""
        self._sweep_stop.set()
        for watcher in self.watchers:
            watcher.stop()
        self.vehicle_queue.stop()
        self.mission_queue.stop()

    def _claim_changed(self, lease: Mapping[str, Any]) -> None:
        """A mission claimed or released a vehicle: queue it (``status.claimedBy``), its
        claimant and the Missions waiting for vehicles."""
        claim = claim_of(lease)
        if claim is None:
            return
        self.vehicle_queue.add(claim.vehicle)
        self.queue_missions(self.missions.interest.for_vehicle(claim.vehicle, claim.holder_key))

    def _claims_listed(
        self, leases: list[Mapping[str, Any]], vanished: list[Mapping[str, Any]]
    ) -> None:
        for lease in [*leases, *vanished]:  # a vanished claim was released meanwhile
            self._claim_changed(lease)

    def _report_permanent(self, vehicle: str, error: BaseException) -> None:
        """A reconcile failed for good: say so once (the queue does not retry it)."""
        log.error("Vehicle %s: not reconciled until it changes: %s", vehicle, error)

    def _sweep(self) -> None:
        """Queue every known vehicle each ``resync_seconds`` (a safety net; off by
        default, see :attr:`Settings.resync_seconds`)."""
        while not self._sweep_stop.wait(self.settings.resync_seconds):
            if self.peers is None:
                continue
            for vehicle in list(self.connected):
                self.vehicle_queue.add(vehicle)


def runtime(memo: Any) -> Runtime:
    """The :class:`Runtime` stored in kopf's ``memo`` at startup."""
    return cast(Runtime, memo.runtime)


def settings_of(memo: Any) -> Settings:
    """The :class:`Settings` :func:`roost_operator.main.main` put in kopf's ``memo``."""
    return cast(Settings, memo.settings)
