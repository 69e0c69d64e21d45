"""Fleet guards on the cluster side of failover, after node-healthcheck-operator.

A failover on a vehicle is decided and executed by its node agent alone; nothing here
can delay or veto it (automatic failback included: the agent decides it on the ground).
Right after every failover the agent also runs its own safety routine (hold, then land)
locally, so the vehicle is protected without the cluster. What the cluster does *in
response* — re-pointing the vehicle's mavros at the new autopilot (after a failover or
a failback), a mission's ``spec.onFailover`` consequence (AbortVehicle, AbortMission) —
is remediation, and remediation can itself cause a storm (a flapping link rolling mavros
pods every few seconds, a fleet-wide network blip re-pointing every vehicle or aborting
every mission at once). So, as NHC does for node remediation:

* **pause switch** — ``roost.dev/pause-failover-actions: "true"`` on a Vehicle, or the
  operator's fleet-wide setting, holds every cluster-side action back, mission
  consequences included;
* **latch** — ``latch_after`` failovers of one vehicle within ``latch_window`` latch it:
  no further cluster-side action, mission consequences included, until a human sets a
  new value in the annotation ``roost.dev/clear-failover-latch`` (one value clears one
  latch, so a leftover token can never pre-clear a future latch). The failover that
  trips the latch is itself not acted on;
* **concurrency cap** — at most ``max_concurrent_actions`` re-points run at once across
  the fleet; an action runs until its effect is observed or ``action_timeout`` passes.
  Mission consequences are not counted and never wait for the cap
  (:func:`consequence_verdict`): they stop Jobs and ask vehicles to land — they remove
  risk rather than add it, and a fleet-wide blip is exactly when they must not queue.

A held-back action is not dropped: the decision is level-based, so it runs as soon as
the guard lifts. The bookkeeping lives in ``Vehicle.status.failover`` so an operator
restart neither forgets a latch nor repeats an action. A user's own abort of a mission
(``spec.abort``) is not a failover consequence and no guard applies to it.

Pure functions: no API calls, ``now`` is a parameter.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta

from roost_api.autopilot import RedundantAutopilotStatus
from roost_api.vehicle import FailoverGuard, VehicleFailover
from roost_api.wellknown import ANNOTATION_CLEAR_FAILOVER_LATCH, ANNOTATION_PAUSE_FAILOVER_ACTIONS

MAX_RECENT = 64
"""Upper bound of the failover times kept per vehicle (the schema's maxItems)."""

TRUE_VALUES = frozenset({"true", "1", "yes", "on"})


@dataclass(frozen=True)
class FleetGuards:
    """Limits on cluster-side failover actions; see the module docstring.

    Environment variables (read by :func:`roost_operator.settings.load_guards`) in
    brackets.
    """

    max_concurrent_actions: int = 5
    """Actions running at once across the fleet (``ROOST_FAILOVER_MAX_CONCURRENT``)."""

    latch_after: int = 3
    """Failovers of one vehicle within the window that latch it (``ROOST_FAILOVER_LATCH_AFTER``)."""

    latch_window: timedelta = timedelta(minutes=10)
    """Window for counting repeated failovers (``ROOST_FAILOVER_LATCH_WINDOW_SECONDS``)."""

    action_timeout: timedelta = timedelta(minutes=2)
    """An action not seen to finish by then stops counting against the cap, with a
    Warning Event (``ROOST_FAILOVER_ACTION_TIMEOUT_SECONDS``)."""

    paused: bool = False
    """Fleet-wide pause of every cluster-side action (``ROOST_FAILOVER_PAUSED``)."""


Verdict = FailoverGuard
"""Whether a cluster-side action may start now, and if not, which guard holds it."""


def vehicle_paused(annotations: Mapping[str, str]) -> bool:
    """Whether the Vehicle's pause annotation is set to a true value."""
    value = annotations.get(ANNOTATION_PAUSE_FAILOVER_ACTIONS, "")
    return value.strip().lower() in TRUE_VALUES


def pause_or_latch(guards: FleetGuards, *, paused_here: bool, latched: bool) -> Verdict:
    """The pause and latch guards alone; a pause wins so its reason is shown first."""
    if guards.paused or paused_here:
        return Verdict.PAUSED
    if latched:
        return Verdict.LATCHED
    return Verdict.ALLOWED


def check(
    guards: FleetGuards,
    *,
    paused_here: bool,
    latched: bool,
    actions_elsewhere: int,
) -> Verdict:
    """May a cluster-side action start on this vehicle now?

    ``actions_elsewhere`` counts actions in progress on *other* vehicles: replacing this
    vehicle's own running action (a second switch before the first re-point finished)
    does not add to the fleet's load. Order: a pause wins over a latch, which wins over
    the cap, so the reason shown is the one a human must act on first.
    """
    verdict = pause_or_latch(guards, paused_here=paused_here, latched=latched)
    if verdict is not Verdict.ALLOWED:
        return verdict
    if actions_elsewhere >= guards.max_concurrent_actions:
        return Verdict.CONCURRENCY_LIMIT
    return Verdict.ALLOWED


def new_failovers(book: VehicleFailover, status: RedundantAutopilotStatus) -> int:
    """How many failovers the agent reports that ``book`` has not accounted for yet.

    A failover is identified by ``lastFailover.time``; ``failoverCount`` tells how many
    happened since the last one accounted (several can pile up during a partition, when
    only the last is visible). A count that went down means the agent restarted and
    began counting again: the latest failover is new if its time is.
    """
    last = status.last_failover
    if last is None or last.time == book.observed_failover_time:
        return 0
    if status.failover_count > book.observed_failover_count:
        return status.failover_count - book.observed_failover_count
    return 1


def observe_failovers(
    book: VehicleFailover,
    status: RedundantAutopilotStatus,
    *,
    guards: FleetGuards,
    now: datetime,
) -> tuple[VehicleFailover, int]:
    """Account the agent's new failovers; latch when too many fall within the window.

    Returns the new bookkeeping and the number of failovers newly accounted. Failovers
    that piled up unseen are all stamped with the last one's time (the only time known).
    """
    count = new_failovers(book, status)
    recent = list(book.recent)
    if count and status.last_failover is not None:
        recent.extend([status.last_failover.time] * count)
    horizon = now - guards.latch_window
    recent = [t for t in recent if t >= horizon][-MAX_RECENT:]
    trips = count > 0 and not book.latched and len(recent) >= guards.latch_after
    updated = book.model_copy(
        update={
            "observed_failover_count": status.failover_count,
            "observed_failover_time": (
                status.last_failover.time if status.last_failover else book.observed_failover_time
            ),
            "recent": recent,
            "latched": book.latched or trips,
            "latched_at": now if trips else book.latched_at,
        }
    )
    return updated, count


def clear_latch(
    book: VehicleFailover, annotations: Mapping[str, str]
) -> tuple[VehicleFailover, bool]:
    """Honour a new ``roost.dev/clear-failover-latch`` token; True when a latch was cleared.

    A new token is recorded even when nothing is latched, so it cannot clear a latch
    that happens later. Clearing also forgets the recent failovers: the human has looked
    at them, and the count starts again.
    """
    token = annotations.get(ANNOTATION_CLEAR_FAILOVER_LATCH)
    if not token or token == book.cleared_token:
        return book, False
    cleared = book.latched
    update: dict[str, object] = {"cleared_token": token}
    if cleared:
        update |= {"latched": False, "latched_at": None, "recent": []}
    return book.model_copy(update=update), cleared


def consequence_verdict(
    guards: FleetGuards,
    *,
    annotations: Mapping[str, str],
    book: VehicleFailover | None,
    status: RedundantAutopilotStatus,
    now: datetime,
) -> Verdict:
    """May a mission apply its ``spec.onFailover`` consequence on this vehicle now?

    Pause and latch only, never the cap (see the module docstring). The latch is judged
    on the bookkeeping as the vehicle's failover reconcile is about to make it — a new
    clear token honoured, the agent's unaccounted failovers counted — so a mission that
    sees a failover before that reconcile has written ``Vehicle.status.failover`` still
    holds back the failover that trips the latch, and resumes with the same clear.
    """
    projected, _ = clear_latch(book or VehicleFailover(), annotations)
    projected, _ = observe_failovers(projected, status, guards=guards, now=now)
    return pause_or_latch(
        guards, paused_here=vehicle_paused(annotations), latched=projected.latched
    )
