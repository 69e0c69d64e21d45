"""The Vehicle controller: observe → plan → apply → status, once per reconcile.

Every trigger that concerns a Vehicle (its own events, its node's, its component Pods',
its RedundantAutopilot's reports, its claim Lease, the guard annotations, the fleet
sweep) queues its name on the work queue (:mod:`roost_operator.engine.workqueue`), whose
workers call :meth:`VehicleController.reconcile`. A reconcile follows the name through
four modules, each once:

1. :func:`~.observe.observe` reads everything (the clock included);
2. :func:`~.plan.plan_vehicle` decides, purely;
3. :func:`~.apply.apply` makes the plan's writes and returns what the API server said;
4. :func:`~.status.write_status` writes the status once, from the plan and that answer.

Why it is safe to run at any time, any number of times, and to be killed half-way:

* **one lock per vehicle** serialises every path that writes for one vehicle in the
  process, beyond the work queue's own rule that a name is never reconciled twice at
  once;
* **read your own write**: see :mod:`.observe`; a conflict (409) on any write decides
  again from a fresh read, never a lost update;
* **a Vehicle that is gone is released** (:func:`~.apply.release`): everything Roost
  makes for a vehicle carries its label, so no finalizer is needed, and deletion never
  waits for the operator;
* failover Events carry deterministic names and are posted before the status write,
  condition transitions after it (see :mod:`roost_operator.autopilots.plan`);
* the fleet-wide cap on failover actions is race-free within the operator: counting
  other vehicles' actions and recording this one's happen under the ledger's lock.

It does not import kopf.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta
from typing import Final

from roost_api.meta import now
from roost_kube.client import Kube
from roost_kube.errors import ConflictError, TemporaryApiError
from roost_kube.patches import Obj
from roost_kube.resources import VEHICLES
from roost_operator.autopilots.conditions import DEFAULT_AGENT_STALE_AFTER
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.engine.cache import Cached, CachedView
from roost_operator.vehicles.apply import apply, release
from roost_operator.vehicles.manifests import DEFAULT_IMAGES, SIGNING_KEYS
from roost_operator.vehicles.observe import Gone, Peers, observe
from roost_operator.vehicles.plan import Context, plan_vehicle
from roost_operator.vehicles.status import write_status

log = logging.getLogger(__name__)

CONFLICT_RETRIES: Final = 5

__all__ = ["ActionLedger", "Outcome", "Peers", "VehicleController"]


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
    """A held first report (:func:`~.status.first_report_due`): reconcile again then."""


@dataclass
class VehicleController:
    """The one writer of Vehicle status; see the module docstring."""

    kube: Kube
    namespace: str
    guards: FleetGuards = field(default_factory=FleetGuards)
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER
    first_report_hold: timedelta = timedelta(0)
    """See :func:`~roost_operator.vehicles.status.first_report_due`."""
    agent_image: str = DEFAULT_IMAGES[SIGNING_KEYS]
    """The key pod's image when a Vehicle names none (the node agent's)."""
    ledger: ActionLedger = field(default_factory=ActionLedger)
    caches: Mapping[str, Cached] = field(default_factory=dict)
    """Watch caches (by kind) of nodes, claims and owned objects; others are read from
    the API."""
    cluster: CachedView = field(init=False, repr=False)
    """Reads of nodes, claims and owned objects, and the writes that keep them."""
    context: Context = field(init=False, repr=False)
    _locks: dict[str, threading.Lock] = field(default_factory=dict, repr=False)
    _guard: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __post_init__(self) -> None:
        self.cluster = CachedView(self.kube, self.caches)
        self.context = Context(
            namespace=self.namespace,
            guards=self.guards,
            stale_after=self.stale_after,
            agent_image=self.agent_image,
            first_report_hold=self.first_report_hold,
        )

    def lock(self, name: str) -> threading.Lock:
        """The lock of vehicle ``name`` (one per vehicle, for every path that writes)."""
        with self._guard:
            return self._locks.setdefault(name, threading.Lock())

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

    def _reconcile_once(self, name: str, peers: Peers, *, fresh: bool) -> Outcome | None:
        observed = observe(self.cluster, name, peers, self.context, fresh=fresh)
        if isinstance(observed, Gone):
            self._release_gone(name, observed.body)
            return None
        was = observed.status.failover
        with self.ledger.lock:  # count the others and reserve this one in one step
            others = self.ledger.others(name, peers.actions())
            plan = plan_vehicle(replace(observed, actions_elsewhere=others))
            acting = plan.acting
            self.ledger.record(name, acting)
        try:
            applied = apply(self.cluster, plan)
            written = write_status(self.kube, plan, applied)
        except Exception:
            with self.ledger.lock:  # nothing was stored: the index/status stay the truth
                self.ledger.record(name, was is not None and was.action is not None)
            raise
        if written.vehicle is not None:
            self.cluster.remember(written.vehicle)
        # A temporary refusal is retried; a permanent one waits for a new spec.
        for error in applied.refused.values():
            if isinstance(error, TemporaryApiError):
                raise error
        failover = plan.failover
        return Outcome(
            agent_connected=failover.conditions[0].status if failover else None,
            acting=acting,
            blocked=failover.failover.blocked if failover else None,
            report_due=written.report_due,
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
        """Release what Roost made for the gone Vehicle, and say once, in a Warning
        Event, what could not be removed."""
        leftovers = release(self.cluster, name, self.namespace)
        self.ledger.forget(name)
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
