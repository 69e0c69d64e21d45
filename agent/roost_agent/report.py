"""What the agent reports on its RedundantAutopilot, decided as pure functions.

The agent's core knows the active autopilot, each autopilot's health, the last failover,
the latch and the last command; :func:`report` adds what the cluster reads first — the
conditions — and stamps the report. Kept pure and separate from the publisher thread so
the condition rules are unit-tested as a table and the publisher only moves data.

Conditions (all written by the agent; ``lastTransitionTime`` moves only when a status
changes, via :func:`set_condition`):

``ActiveHealthy``
    True when the active autopilot is OK (reason ``Healthy``) or only WARN (reason
    ``Degraded``: it flies, with a warning); False on ERROR (``Unhealthy``), while it is
    still starting up (``Starting``) or when its link is silent (``NoData``); Unknown
    while no autopilot is active.
``Redundant``
    True when some standby is OK *and* the agent would switch to it: after a failover the
    agent is latched and never returns automatically to an autopilot it left, so such a
    standby does not count, however healthy it looks (reason ``Latched``). A standby
    whose armed or landed state is unknown (no heartbeat, no EXTENDED_SYS_STATE — an
    ArduPilot nobody requested streams from) can never be switched to, because the
    arbiter takes over only from an autopilot known to be armed and in the air; it is
    not a healthy standby however quiet its findings (reason ``StandbyStateUnknown``).
``FailedOver``
    True when the active autopilot is not the primary; the reason says how it got there
    (``AutomaticFailover``, ``SwitchedByCommand``, ``NotOnPrimary``).
``Ready``
    ``ActiveHealthy`` and ``Redundant`` both True; otherwise the first that is not, with
    its status (False or Unknown) and reason.
``FirmwareAcceptable`` (only with ``spec.firmware``)
    Whether every autopilot's AUTOPILOT_VERSION meets the requirement, naming the one
    that does not (:func:`roost_agent.firmware.judge`). Not part of ``Ready``: a
    Mission's preflight checks it.

:func:`change_class` and :func:`write_delay` tell the publisher whether a new report
must go out at once (``URGENT``: the active autopilot, a failover, the latch or a
command result changed), may wait for the coalescing interval (``ROUTINE``: a health
level, a mode, armed or landed state changed) or carries nothing new (``NONE``: only
ages and numbers inside reasons moved — those are refreshed by the periodic report,
never on their own).
"""

from __future__ import annotations

import re
from collections.abc import Collection, Sequence
from dataclasses import replace
from datetime import datetime
from enum import IntEnum
from functools import partial

from roost_agent import firmware
from roost_api import core
from roost_api.autopilot_enums import AutopilotConditionReason as R
from roost_api.autopilot_enums import AutopilotConditionType, FailoverTrigger
from roost_api.core import ConditionStatus, HealthLevel, Stack
from roost_api.plain import (
    AutopilotHealth,
    Condition,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)

set_condition = partial(core.set_condition, make=Condition)
"""The agent's :func:`roost_api.core.set_condition`: its conditions are always plain
:class:`~roost_api.plain.Condition` (``make`` exists for the API's pydantic twin)."""

_NUMBER = re.compile(r"-?\d+(\.\d+)?")

_TRIGGER_REASON = {
    FailoverTrigger.AUTOMATIC: R.AUTOMATIC_FAILOVER,
    FailoverTrigger.COMMAND: R.SWITCHED_BY_COMMAND,
}


class Change(IntEnum):
    """How urgently a new report differs from the last one written."""

    NONE = 0
    ROUTINE = 1
    URGENT = 2


def _describe(health: AutopilotHealth) -> str:
    reasons = "; ".join(health.reasons)
    return f"{health.name} {health.level}" + (f" ({reasons})" if reasons else "")


def _active_healthy(
    active: str | None, health: AutopilotHealth | None
) -> tuple[ConditionStatus, R, str]:
    if active is None:
        return "Unknown", R.NO_ACTIVE_AUTOPILOT, "no autopilot is connected to the motors yet"
    if health is None:
        return "Unknown", R.NO_HEALTH, f"{active} is active but has not been assessed yet"
    level = HealthLevel(health.level)
    if level is HealthLevel.OK:
        return "True", R.HEALTHY, f"{active} active and healthy"
    if level is HealthLevel.WARN:
        return "True", R.DEGRADED, f"{_describe(health)} active"
    if level is HealthLevel.STALE:
        return "False", R.NO_DATA, f"{_describe(health)} active"
    if level is HealthLevel.STARTING:
        return "False", R.STARTING, f"{_describe(health)} active"
    return "False", R.UNHEALTHY, f"{_describe(health)} active"


def _redundant(
    active: str | None, standbys: Sequence[AutopilotHealth], left_behind: Collection[str]
) -> tuple[ConditionStatus, R, str]:
    if active is None:
        return "Unknown", R.NO_ACTIVE_AUTOPILOT, "no autopilot is connected to the motors yet"
    if not standbys:
        return "False", R.NO_STANDBY, "no standby autopilot has been assessed"
    quiet = [h for h in standbys if h.level == HealthLevel.OK]
    healthy = [h for h in quiet if _state_known(h)]
    usable = [h for h in healthy if h.name not in left_behind]
    if usable:
        names = ", ".join(h.name for h in usable)
        return "True", R.STANDBY_AVAILABLE, f"healthy standby: {names}"
    if healthy:
        names = ", ".join(h.name for h in healthy)
        return (
            "False",
            R.LATCHED,
            f"standby {names} failed earlier this flight; no automatic switch back to it "
            "until a ClearLatch or Switch command",
        )
    if quiet:
        names = ", ".join(h.name for h in quiet)
        return (
            "False",
            R.STANDBY_STATE_UNKNOWN,
            f"standby {names}: armed or landed state unknown (no heartbeat or "
            "EXTENDED_SYS_STATE), so it cannot be a failover target",
        )
    return "False", R.NO_HEALTHY_STANDBY, "; ".join(f"standby {_describe(h)}" for h in standbys)


def _state_known(health: AutopilotHealth) -> bool:
    """Armed and landed state both reported (a failover needs armed and in the air)."""
    return health.armed is not None and health.landed_state not in (None, "Undefined")


def _failed_over(
    spec: RedundantAutopilotSpec, status: RedundantAutopilotStatus
) -> tuple[ConditionStatus, R, str]:
    active = status.active_autopilot
    if active is None:
        return "Unknown", R.NO_ACTIVE_AUTOPILOT, "no autopilot is connected to the motors yet"
    if active == spec.primary:
        return "False", R.ON_PRIMARY, f"primary {active} is active"
    last = status.last_failover
    if last is None or last.to_autopilot != active:
        return "True", R.NOT_ON_PRIMARY, f"{active} active, not the primary"
    reason = _TRIGGER_REASON.get(FailoverTrigger(last.trigger), R.NOT_ON_PRIMARY)
    return (
        "True",
        reason,
        f"{last.from_autopilot} -> {active} at {last.time:%H:%M:%S}: {last.reason}",
    )


def _ready(
    active: tuple[ConditionStatus, R, str], redundant: tuple[ConditionStatus, R, str]
) -> tuple[ConditionStatus, R, str]:
    for status, reason, message in (active, redundant):
        if status != "True":
            return status, reason, message
    return "True", R.READY, f"{active[2]}; {redundant[2]}"


def conditions(
    previous: Sequence[Condition],
    *,
    spec: RedundantAutopilotSpec,
    status: RedundantAutopilotStatus,
    left_behind: Collection[str] = (),
    generation: int | None,
    now: datetime,
) -> list[Condition]:
    """The four conditions for ``status`` (its own conditions are ignored).

    ``left_behind`` names the autopilots the agent failed over from this flight (never
    automatic targets while latched); without it, a latched report treats the last
    failover's source as left behind.
    """
    active = status.active_autopilot
    if not left_behind and status.latched and status.last_failover is not None:
        left_behind = {status.last_failover.from_autopilot}
    by_name = {h.name: h for h in status.autopilots}
    standbys = [h for h in status.autopilots if h.name != active]
    active_healthy = _active_healthy(active, by_name.get(active) if active else None)
    redundant = _redundant(active, standbys, left_behind)
    values = {
        AutopilotConditionType.ACTIVE_HEALTHY: active_healthy,
        AutopilotConditionType.REDUNDANT: redundant,
        AutopilotConditionType.FAILED_OVER: _failed_over(spec, status),
        AutopilotConditionType.READY: _ready(active_healthy, redundant),
    }
    result = list(previous)
    if spec.firmware is not None:
        stacks = {a.name: Stack(a.stack) for a in spec.autopilots}
        values[AutopilotConditionType.FIRMWARE_ACCEPTABLE] = firmware.judge(
            spec.firmware, stacks, status.autopilots
        )
    else:
        result = [c for c in result if c.type != AutopilotConditionType.FIRMWARE_ACCEPTABLE]
    for kind, (cond_status, reason, message) in values.items():
        result = set_condition(
            result,
            type=kind.value,
            status=cond_status,
            reason=reason,
            message=message,
            observed_generation=generation,
            at=now,
        )
    return result


def report(
    previous: RedundantAutopilotStatus | None,
    observed: RedundantAutopilotStatus,
    *,
    spec: RedundantAutopilotSpec,
    left_behind: Collection[str] = (),
    generation: int | None,
    node_name: str,
    now: datetime,
) -> RedundantAutopilotStatus:
    """The status to write: ``observed`` (the agent's state) with conditions and stamps.

    ``previous`` is the last status written (or read back), so condition transition
    times survive across reports and agent restarts.
    """
    prior = previous.conditions if previous is not None else []
    return replace(
        observed,
        conditions=conditions(
            prior,
            spec=spec,
            status=observed,
            left_behind=left_behind,
            generation=generation,
            now=now,
        ),
        observed_generation=generation,
        node_name=node_name,
        reported_at=now,
    )


def _health_key(health: AutopilotHealth) -> tuple[object, ...]:
    return (
        health.name,
        health.level,
        health.mode,
        health.armed,
        health.landed_state,
        health.system_status,
        tuple(sorted(health.unhealthy_sensors)),
        tuple(_NUMBER.sub("#", r) for r in health.reasons),
        tuple((c.type, c.status, c.reason) for c in health.conditions),  # StandbyInStep
        health.firmware,
    )


def change_class(
    before: RedundantAutopilotStatus | None, after: RedundantAutopilotStatus
) -> Change:
    """How urgently ``after`` must be written, given ``before`` was the last written."""
    if before is None:
        return Change.URGENT
    urgent = (
        before.active_autopilot != after.active_autopilot
        or before.failover_count != after.failover_count
        or before.last_failover != after.last_failover
        or before.latched != after.latched
        or before.last_command != after.last_command
    )
    if urgent:
        return Change.URGENT
    if [_health_key(h) for h in before.autopilots] != [_health_key(h) for h in after.autopilots]:
        return Change.ROUTINE
    if [(c.type, c.status, c.reason) for c in before.conditions] != [
        (c.type, c.status, c.reason) for c in after.conditions
    ] or before.observed_generation != after.observed_generation:
        return Change.ROUTINE
    return Change.NONE


def write_delay(
    change: Change, since_last_write_s: float, *, min_interval_s: float, refresh_s: float
) -> float:
    """Seconds until a report with ``change`` must be written (0: now).

    Urgent changes go at once; routine ones wait until ``min_interval_s`` after the last
    write (so a burst becomes one write carrying its latest state); with nothing new,
    the periodic refresh is due ``refresh_s`` after the last write.
    """
    if change is Change.URGENT:
        return 0.0
    wait = min(min_interval_s, refresh_s) if change is Change.ROUTINE else refresh_s
    return max(0.0, wait - since_last_write_s)
