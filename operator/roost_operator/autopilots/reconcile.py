"""Read, decide with :func:`~roost_operator.autopilots.plan.plan`, write, post — for one vehicle.

No kopf here (the handlers are in :mod:`.handlers`), so this runs the same from a
handler, a test or a benchmark. Rules it keeps:

* **read your own write** (NHC): the Vehicle and the RedundantAutopilot are read fresh
  from the API on every run, never from a watch cache, so a decision is never made on a
  status older than the operator's own last write;
* **optimistic locking**: the Vehicle status patch carries the ``resourceVersion`` it
  was computed from (the vehicle reconcile writes other conditions of the same list);
  a conflict means "read again and decide again", never a lost update;
* **Events exactly once**: the plan's Events carry deterministic names (see
  :class:`~roost_operator.autopilots.plan.PlannedEvent`) and are posted *before* the
  status write, so a crash in between neither loses one nor, when the same decision is
  made again, records it twice; condition transitions are posted after the write that
  makes them (a crash there can lose one, never duplicate it);
* **the fleet-wide cap is race-free** within the operator (one replica, see the chart):
  counting actions elsewhere and reserving this vehicle's happen under one lock, and
  :class:`ActionLedger` overrides the kopf index with what this process itself wrote
  until the watch catches up.

It also keeps the ``roost.dev/node`` label of the RedundantAutopilot equal to its
Vehicle's node: the chart's admission policy compares that label with the node in the
agent's token, and the agent lists its RedundantAutopilot by it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Final

from roost_api.autopilot import RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.meta import Condition, now, set_condition
from roost_api.vehicle import VehicleConditionType, VehicleSpec, VehicleStatus
from roost_api.wellknown import LABEL_NODE
from roost_kube.client import Kube
from roost_kube.errors import ConflictError
from roost_kube.patches import Obj
from roost_kube.resources import CONFIGMAPS, DEPLOYMENTS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_operator.autopilots.conditions import DEFAULT_AGENT_STALE_AFTER
from roost_operator.autopilots.guards import FleetGuards, vehicle_paused
from roost_operator.autopilots.plan import FailoverPlan, PlannedEvent, mavros_follows, plan
from roost_operator.vehicles.config import config_map_name
from roost_operator.vehicles.desired import with_ready, workload_name
from roost_operator.vehicles.status import write_vehicle_status

log = logging.getLogger(__name__)

CONFLICT_RETRIES: Final = 5
MINE: Final = (VehicleConditionType.AGENT_CONNECTED, VehicleConditionType.AUTOPILOTS_HEALTHY)
EVENT_TYPES: Final = (*MINE, VehicleConditionType.READY)
OWNED: Final = ("conditions", "activeAutopilot", "fcuUrl", "failover")


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


@dataclass
class FailoverContext:
    """What every run needs: the API, where workloads live, guards and the ledger."""

    kube: Kube
    namespace: str
    guards: FleetGuards
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER
    ledger: ActionLedger = field(default_factory=ActionLedger)


@dataclass(frozen=True)
class Outcome:
    """What a run did, for the handler: whether mavros must be rolled now, and more."""

    repointed: bool
    agent_connected: str | None
    acting: bool
    blocked: str | None


_locks: dict[str, threading.Lock] = {}
_locks_guard = threading.Lock()


def _vehicle_lock(name: str) -> threading.Lock:
    with _locks_guard:
        return _locks.setdefault(name, threading.Lock())


def _with_conditions(
    previous: list[Condition], result: FailoverPlan, generation: int | None, at: datetime
) -> list[Condition]:
    conditions = previous
    for update in result.conditions:
        conditions = set_condition(
            conditions,
            type=update.type,
            status=update.status,
            reason=update.reason,
            message=update.message,
            observed_generation=generation,
            at=at,
        )
    return with_ready(conditions, generation=generation, at=at)


def _without_mine(
    previous: list[Condition], generation: int | None, at: datetime
) -> list[Condition]:
    """The conditions once the vehicle has no RedundantAutopilot: ours removed, Ready anew."""
    kept = [c for c in previous if c.type not in MINE]
    if len(kept) == len(previous):
        return previous
    return with_ready(kept, generation=generation, at=at)


def _ensure_node_label(kube: Kube, autopilot: Obj, node_name: str) -> None:
    labels = autopilot["metadata"].get("labels") or {}
    if labels.get(LABEL_NODE) != node_name:
        kube.merge_patch(
            REDUNDANT_AUTOPILOTS,
            autopilot["metadata"]["name"],
            {"metadata": {"labels": {LABEL_NODE: node_name}}},
        )


def _mavros_rolled_out(
    kube: Kube, namespace: str, vehicle: str, spec: VehicleSpec, fcu_url: str | None
) -> bool:
    if not spec.components.mavros.enabled:
        return True
    config_map = kube.get(CONFIGMAPS, config_map_name(vehicle), namespace)
    mavros = kube.get(DEPLOYMENTS, workload_name(vehicle, "mavros"), namespace)
    return mavros_follows(fcu_url, config_map, mavros)


def reconcile_failover(
    ctx: FailoverContext,
    vehicle_name: str,
    autopilot_name: str | None,
    *,
    indexed_actions: Iterable[str] = (),
) -> Outcome | None:
    """Converge the cluster side of failover for one vehicle; None when it is gone."""
    with _vehicle_lock(vehicle_name):
        for attempt in range(CONFLICT_RETRIES):
            try:
                return _reconcile_once(ctx, vehicle_name, autopilot_name, list(indexed_actions))
            except ConflictError:
                if attempt == CONFLICT_RETRIES - 1:
                    raise
                log.info("vehicle %s: concurrent status write, deciding again", vehicle_name)
    return None


def _reconcile_once(
    ctx: FailoverContext, name: str, autopilot_name: str | None, indexed: list[str]
) -> Outcome | None:
    kube = ctx.kube
    vehicle = kube.get(VEHICLES, name)
    if vehicle is None or vehicle["metadata"].get("deletionTimestamp"):
        return None
    meta = vehicle["metadata"]
    generation = meta.get("generation")
    spec = VehicleSpec.model_validate(vehicle["spec"])
    status = VehicleStatus.model_validate(vehicle.get("status") or {})
    autopilot = kube.get(REDUNDANT_AUTOPILOTS, autopilot_name) if autopilot_name else None
    at = now()
    if autopilot is None:
        conditions = _without_mine(status.conditions, generation, at)
        new = status.model_copy(update={"conditions": conditions, "active_autopilot": None})
        _write(kube, vehicle, status, new)
        return Outcome(False, None, False, None)
    _ensure_node_label(kube, autopilot, spec.node_name)

    annotations: Mapping[str, str] = meta.get("annotations") or {}
    book = status.failover
    rollout_done = (
        book is None
        or book.action is None
        or _mavros_rolled_out(kube, ctx.namespace, name, spec, status.fcu_url)
    )
    with ctx.ledger.lock:
        result = plan(
            vehicle_name=name,
            vehicle_spec=spec,
            vehicle_status=status,
            annotations=annotations,
            autopilot_spec=RedundantAutopilotSpec.model_validate(autopilot["spec"]),
            autopilot_status=RedundantAutopilotStatus.model_validate(autopilot.get("status") or {}),
            guards=ctx.guards,
            paused_here=vehicle_paused(annotations),
            actions_elsewhere=ctx.ledger.others(name, indexed),
            rollout_done=rollout_done,
            now=at,
            stale_after=ctx.stale_after,
        )
        ctx.ledger.record(name, result.acting)
    new = status.model_copy(
        update={
            "conditions": _with_conditions(status.conditions, result, generation, at),
            "active_autopilot": result.active_autopilot,
            "fcu_url": result.fcu_url,
            "failover": result.failover,
        }
    )
    try:
        _post(kube, vehicle, result.events)
        _write(kube, vehicle, status, new)
    except Exception:
        with ctx.ledger.lock:  # nothing was stored: the index/status stay the truth
            ctx.ledger.record(name, book is not None and book.action is not None)
        raise
    followed_before = book.followed_autopilot if book else None
    return Outcome(
        repointed=result.failover.followed_autopilot != followed_before
        or result.fcu_url != status.fcu_url,
        agent_connected=result.conditions[0].status,
        acting=result.acting,
        blocked=result.failover.blocked,
    )


def _post(kube: Kube, vehicle: Obj, events: Iterable[PlannedEvent]) -> None:
    """Post the plan's Events (deterministic names: a repeat is refused as a duplicate)."""
    for event in events:
        kube.post_event(
            vehicle,
            reason=event.reason,
            message=event.message,
            type=event.type,
            at=event.at.isoformat().replace("+00:00", "Z"),
        )


def _write(kube: Kube, vehicle: Obj, old: VehicleStatus, new: VehicleStatus) -> None:
    """Patch the fields this module owns (optimistic lock), with transition Events."""
    write_vehicle_status(kube, vehicle, old, new, fields=OWNED, event_types=EVENT_TYPES)
