"""kopf handlers for the cluster side of failover; all funnel into one reconcile.

Triggers, and why each exists:

* a RedundantAutopilot event — the agent reported. Reports that change nothing the
  operator reads (the 10 s refresh of ``reportedAt``, heartbeat ages) are skipped by a
  fingerprint, except while the vehicle's ``AgentConnected`` is not True (a report is
  then exactly the news that the agent is back);
* a RedundantAutopilot timer that only fires once the object has been *idle* for the
  staleness window — the agent went silent: ``AgentConnected`` becomes Unknown. Busy
  objects cost nothing, silent ones are re-checked every third of the window;
* Vehicle events that change the guard annotations (pause, clear the latch), and the
  first sight of each Vehicle (so a restarted operator converges every vehicle);
* a Vehicle timer while an action runs or a guard holds one back — timeouts, and the
  moment a guard lifts (a paused fleet resumed, the cap freed elsewhere);
* the vehicle's mavros Deployment — its rollout finishing ends the re-point action.

When a run re-points the vehicle, the vehicle reconcile is called at once (it applies
the config and the mavros Deployment for the autopilot now followed), rather than
waiting for the Vehicle watch to deliver the status change.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, Final

import kopf

from roost_api.wellknown import (
    ANNOTATION_CLEAR_FAILOVER_LATCH,
    ANNOTATION_PAUSE_FAILOVER_ACTIONS,
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_operator.autopilots.conditions import load_stale_after
from roost_operator.autopilots.guards import load_fleet_guards
from roost_operator.autopilots.reconcile import (
    ActionLedger,
    FailoverContext,
    reconcile_failover,
)
from roost_operator.runtime import runtime
from roost_operator.vehicles.handlers import AUTOPILOTS, VEHICLES, Fingerprints, reconcile_now

GUARDS: Final = load_fleet_guards(os.environ)
STALE_AFTER: Final = load_stale_after(os.environ)
PENDING_POLL_S: Final = 2.0
RETRY_BACKOFF_S: Final = 2.0

_ledger = ActionLedger()
_report_prints = Fingerprints()
_annotation_prints = Fingerprints()
_connected: dict[str, str | None] = {}

FailoverActions = kopf.Index[str, bool]


@kopf.index(*VEHICLES)
def failover_actions(*, name: str, status: kopf.Status, **_: Any) -> dict[str, bool]:
    """Vehicles with a cluster-side failover action running (for the fleet-wide cap)."""
    action = (status.get("failover") or {}).get("action")
    return {name: True} if action else {}


def _run(memo: Any, vehicle: str, autopilot: str | None, indexes: Mapping[str, Any]) -> None:
    rt = runtime(memo)
    context = FailoverContext(
        kube=rt.kube,
        namespace=rt.settings.namespace,
        guards=GUARDS,
        stale_after=STALE_AFTER,
        ledger=_ledger,
    )
    actions: FailoverActions = indexes["failover_actions"]
    outcome = reconcile_failover(context, vehicle, autopilot, indexed_actions=list(actions))
    if outcome is None:
        _connected.pop(vehicle, None)
        return
    _connected[vehicle] = outcome.agent_connected
    if outcome.repointed:
        reconcile_now(memo, vehicle, indexes)


def _autopilot_of(vehicle: str, indexes: Mapping[str, Any]) -> str | None:
    by_vehicle = indexes["autopilots_by_vehicle"]
    return next(iter(by_vehicle.get(vehicle, [])), None)


def _report_relevant(body: Mapping[str, Any]) -> Any:
    """What the operator reads from a report, without the numbers that tick every report."""
    status = dict(body.get("status") or {})
    status.pop("reportedAt", None)
    healths = status.pop("autopilots", None) or []
    return [
        body.get("spec"),
        (body.get("metadata") or {}).get("labels"),
        status,
        [(h.get("name"), h.get("level"), h.get("landedState"), h.get("armed")) for h in healths],
    ]


@kopf.on.event(*AUTOPILOTS)
def autopilot_reported(
    *, type: str | None, name: str, body: kopf.Body, memo: Any, **indexes: Any
) -> None:
    """The agent wrote a report (or someone changed the spec): act on what is new."""
    vehicle = (body.get("spec") or {}).get("vehicleName")
    if not vehicle:
        return
    if type == "DELETED":
        _report_prints.forget(name)
        _run(memo, vehicle, None, indexes)
        return
    changed = _report_prints.changed(name, _report_relevant(body))
    if changed or _connected.get(vehicle) != "True":
        _run(memo, vehicle, name, indexes)


@kopf.timer(
    *AUTOPILOTS,
    interval=STALE_AFTER.total_seconds() / 3,
    idle=STALE_AFTER.total_seconds(),
    backoff=RETRY_BACKOFF_S,
)
def autopilot_silent(*, name: str, spec: kopf.Spec, memo: Any, **indexes: Any) -> None:
    """No report for the whole staleness window: AgentConnected turns Unknown."""
    vehicle = spec.get("vehicleName")
    if vehicle:
        _run(memo, vehicle, name, indexes)


@kopf.on.event(*VEHICLES)
def vehicle_guard_annotations(
    *, type: str | None, name: str, meta: kopf.Meta, memo: Any, **indexes: Any
) -> None:
    """A human paused, resumed or cleared the latch of this vehicle's failover actions."""
    if type == "DELETED":
        _annotation_prints.forget(name)
        return
    annotations = meta.get("annotations") or {}
    relevant = [
        annotations.get(ANNOTATION_PAUSE_FAILOVER_ACTIONS),
        annotations.get(ANNOTATION_CLEAR_FAILOVER_LATCH),
    ]
    if _annotation_prints.changed(name, relevant):
        _run(memo, name, _autopilot_of(name, indexes), indexes)


def _pending(status: kopf.Status, **_: Any) -> bool:
    failover = status.get("failover") or {}
    return bool(failover.get("action") or failover.get("blocked"))


@kopf.timer(*VEHICLES, interval=PENDING_POLL_S, when=_pending, backoff=RETRY_BACKOFF_S)
def failover_pending(*, name: str, memo: Any, **indexes: Any) -> None:
    """An action runs or waits for a guard: check for its end, timeout or the guard lifting."""
    _run(memo, name, _autopilot_of(name, indexes), indexes)


@kopf.on.event(
    "apps",
    "v1",
    "deployments",
    labels={LABEL_MANAGED_BY: MANAGED_BY, LABEL_COMPONENT: "mavros", LABEL_VEHICLE: kopf.PRESENT},
)
def mavros_progress(*, labels: kopf.Labels, memo: Any, **indexes: Any) -> None:
    """The vehicle's mavros Deployment moved: a running re-point may have finished."""
    vehicle = labels[LABEL_VEHICLE]
    actions: FailoverActions = indexes["failover_actions"]
    if vehicle in actions:
        _run(memo, vehicle, _autopilot_of(vehicle, indexes), indexes)
