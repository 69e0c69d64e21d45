"""The cluster side of one vehicle's failover, decided as a pure function.

:func:`plan` takes everything the operator knows about a vehicle — its Vehicle (spec,
status, annotations), its RedundantAutopilot (spec, and the status its node agent
writes), the fleet guards, how many actions run elsewhere, whether mavros has rolled
out — and returns what the Vehicle's status should become and the Events to record.
It reads nothing and writes nothing: the Vehicle planner (:mod:`roost_operator.vehicles.plan`)
calls it with what the Vehicle controller observed, and the controller writes and posts.

What it decides, in order:

1. ``AgentConnected`` and ``AutopilotsHealthy`` (:mod:`.conditions`).
2. A human's latch clear, then the agent's new failovers (counted, latch tripped;
   :mod:`.guards`).
3. Whether the action in progress (re-pointing mavros) has finished or timed out.
4. Which autopilot the vehicle's workloads follow: the agent's active autopilot, unless
   a guard holds the re-point back, in which case they keep following the previous one
   and ``status.failover.blocked`` says why. The first pointing of a vehicle is set-up,
   not remediation, and is not guarded. With the agent's MAVLink hub
   (``spec.hub``) there is nothing to re-point: mavros talks to the hub's endpoint,
   whose route the agent moves in the switch itself, so mavros keeps following the
   primary's configuration and is never rolled on a failover. Re-pointing is for
   vehicles without the hub: autopilots reached through an external MAVLink router
   (one endpoint per autopilot), and simulated vehicles whose SITLs each serve mavros.

Automatic failback (``failoverPolicy.failback: OnGround``) is decided on the vehicle by
the agent's arbiter, like every switch; its cluster side is the re-point back to the
primary, which goes through the same guards. Mission consequences of a failover are the
Mission state machine's, which asks
:func:`~roost_operator.autopilots.guards.consequence_verdict` (pause and latch, not the
cap) on the same bookkeeping this plan writes.

Everything it returns is a function of its inputs (``now`` included): running it twice
on the same inputs gives the same result, so the controller writes only on change and an
operator restart in the middle of a failover repeats nothing.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Literal

from roost_api.autopilot import (
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.vehicle import (
    FailoverAction,
    FailoverActionKind,
    VehicleFailover,
    VehicleSpec,
    VehicleStatus,
)
from roost_api.wellknown import ANNOTATION_CLEAR_FAILOVER_LATCH
from roost_operator.autopilots.conditions import (
    DEFAULT_AGENT_STALE_AFTER,
    ConditionUpdate,
    agent_connected,
    autopilots_healthy,
)
from roost_operator.autopilots.guards import (
    FleetGuards,
    Verdict,
    check,
    clear_latch,
    observe_failovers,
)

REPOINT_MAVROS = FailoverActionKind.REPOINT_MAVROS


@dataclass(frozen=True)
class PlannedEvent:
    """An Event to record on the Vehicle about this decision.

    ``at`` comes from the data the Event is about (the failover's time, the action's
    start), never from the clock, so the same decision made again — after a crash, a
    conflict, a restart — names the same Event and the API refuses the duplicate.
    That is why the handlers may post these *before* writing the status: a crash in
    between can neither lose the Event nor record it twice.
    """

    type: Literal["Normal", "Warning"]
    reason: str
    message: str
    at: datetime


@dataclass(frozen=True)
class FailoverPlan:
    """What one vehicle's cluster side of failover should look like now."""

    conditions: tuple[ConditionUpdate, ...]
    active_autopilot: str | None
    fcu_url: str | None
    failover: VehicleFailover
    events: tuple[PlannedEvent, ...] = ()
    acting: bool = field(default=False)
    """True while an action is in progress (it counts against the fleet's cap)."""


def plan(
    *,
    vehicle_name: str,
    vehicle_spec: VehicleSpec,
    vehicle_status: VehicleStatus,
    annotations: Mapping[str, str],
    autopilot_spec: RedundantAutopilotSpec,
    autopilot_status: RedundantAutopilotStatus,
    fcu_urls: Mapping[str, str],
    guards: FleetGuards,
    paused_here: bool,
    actions_elsewhere: int,
    rollout_done: bool,
    now: datetime,
    stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER,
) -> FailoverPlan:
    """Decide the cluster side of failover for one vehicle; see the module docstring.

    ``fcu_urls``: the URL mavros uses for each autopilot, by name, in the spec's order
    (the Vehicle's manifests know how it is made). ``rollout_done``: whether the
    vehicle's mavros runs with the FCU URL in ``vehicle_status.fcu_url`` (True when
    mavros is disabled).
    """
    events: list[PlannedEvent] = []
    connected = agent_connected(
        autopilot_status, vehicle_node=vehicle_spec.node_name, now=now, stale_after=stale_after
    )
    healthy = autopilots_healthy(autopilot_status, connected)

    last = autopilot_status.last_failover
    # Events are stamped with the failover they are about (or the latch or action), never
    # with "now": the same decision made again after a crash names the same Event.
    about = last.time if last is not None else now
    book = vehicle_status.failover or VehicleFailover()
    latched_at = book.latched_at
    book, cleared = clear_latch(book, annotations)
    if cleared:
        events.append(
            PlannedEvent(
                "Normal",
                "FailoverLatchCleared",
                f"latch cleared by {ANNOTATION_CLEAR_FAILOVER_LATCH}={book.cleared_token}; "
                "cluster-side failover actions resume",
                latched_at or about,
            )
        )
    was_latched = book.latched
    book, new = observe_failovers(book, autopilot_status, guards=guards, now=now)
    if new and last is not None:
        earlier = f"; {new - 1} earlier switch(es) while reports were missing" if new > 1 else ""
        events.append(
            PlannedEvent(
                "Warning",
                "FailedOver",
                f"{last.from_autopilot} -> {last.to_autopilot} ({last.trigger}): {last.reason}; "
                f"switched on-vehicle in {last.latency_ms:.1f} ms{earlier}",
                last.time,
            )
        )
    if book.latched and not was_latched:
        events.append(
            PlannedEvent(
                "Warning",
                "FailoverLatched",
                f"{len(book.recent)} failovers within {guards.latch_window}; cluster-side "
                "actions wait for a human: kubectl annotate vehicle "
                f"{vehicle_name} {ANNOTATION_CLEAR_FAILOVER_LATCH}=<new token> --overwrite",
                about,
            )
        )

    action = book.action
    if action is not None and rollout_done:
        events.append(
            PlannedEvent(
                "Normal",
                "MavrosRepointed",
                f"mavros follows {action.autopilot}",
                action.started_at,
            )
        )
        action = None
    elif action is not None and now - action.started_at > guards.action_timeout:
        events.append(
            PlannedEvent(
                "Warning",
                "MavrosRepointTimedOut",
                f"mavros not rolled out on {action.autopilot} after {guards.action_timeout}; "
                "no longer counted against the fleet's concurrency cap",
                action.started_at,
            )
        )
        action = None

    by_name = dict(fcu_urls)
    active = autopilot_status.active_autopilot
    target = active if active in by_name else None
    followed = book.followed_autopilot or next(
        (name for name, url in by_name.items() if url == vehicle_status.fcu_url), None
    )
    fcu_url = vehicle_status.fcu_url
    blocked: Verdict | None = None
    verdict = check(
        guards,
        paused_here=paused_here,
        latched=book.latched,
        actions_elsewhere=actions_elsewhere,
    )
    if autopilot_spec.hub is not None and autopilot_spec.primary in by_name:
        # mavros talks to the agent's hub, which moves the route itself: nothing to
        # re-point, no rollout. mavros keeps the primary's configuration (firmware).
        followed = autopilot_spec.primary
        fcu_url = by_name[followed]
        action = None
    elif target is not None and (followed is None or followed not in by_name):
        followed, fcu_url = target, by_name[target]
    elif target is not None and target != followed:
        if verdict is Verdict.ALLOWED:
            previous, followed, fcu_url = followed, target, by_name[target]
            action = FailoverAction(kind=REPOINT_MAVROS, autopilot=target, started_at=now)
            events.append(
                PlannedEvent(
                    "Normal",
                    "RepointingMavros",
                    f"pointing mavros at {target} ({fcu_url}), was {previous}",
                    about,
                )
            )
        else:
            blocked = verdict
    elif followed in by_name:
        fcu_url = by_name[followed]

    if blocked is not None and blocked.value != book.blocked:
        events.append(
            PlannedEvent(
                "Warning",
                "FailoverActionBlocked",
                f"re-pointing mavros at {active} held back: {blocked.value}",
                about,
            )
        )
    book = book.model_copy(
        update={
            "action": action,
            "followed_autopilot": followed,
            "blocked": blocked.value if blocked is not None else None,
        }
    )
    return FailoverPlan(
        conditions=(connected, healthy),
        active_autopilot=active,
        fcu_url=fcu_url,
        failover=book,
        events=tuple(events),
        acting=action is not None,
    )
