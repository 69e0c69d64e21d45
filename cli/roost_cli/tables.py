"""What ``roost status`` and ``roost missions`` show, as plain rows computed from API objects.

Pure functions from the raw objects the API server returns (dicts, camelCase) to frozen
rows of text, so every column can be tested without a cluster or a terminal. Statuses are
read through the ``roost_api`` models, the same contract the agent and operator write
with; an object whose status does not parse (an older or newer writer) still gets a row,
with the columns it could not read left empty, because one odd object must not hide the
rest of the fleet. Colours and the rich ``Table`` live in :mod:`roost_cli.render`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeVar

from pydantic import ValidationError

from roost_api.autopilot import FailoverRecord, RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.fence import held_id
from roost_api.meta import GROUP, ApiModel, Condition, HealthLevel, find_condition
from roost_api.mission import MissionPhase, MissionSpec, MissionStatus
from roost_api.vehicle import VehicleConditionType, VehicleSpec, VehicleStatus

NONE = "-"
"""Shown where a column has no value, like kubectl's ``<none>`` but narrower."""

RawObject = Mapping[str, Any]
Model = TypeVar("Model", bound=ApiModel)


@dataclass(frozen=True)
class AutopilotCell:
    """One autopilot of a vehicle as the HEALTH column shows it."""

    name: str
    level: str
    """A :class:`HealthLevel` value, or ``-`` when the agent has not reported it."""
    active: bool
    reason: str
    """The first reason it is not OK, empty when OK."""
    params: str = ""
    """Its declared parameters when they are not in sync (``Drifted: GF_ACTION is 1,
    declared 3``), empty when in sync or none are declared."""
    fence: str = ""
    """A Mission's fence on it: ``held 1a2b3c4d5e6f`` or where it stands
    (``UploadRefused: uploading: MISSION_ACK result 1``); empty without one."""

    @property
    def text(self) -> str:
        suffix = f" ({self.reason})" if self.reason else ""
        params = f" [params {self.params}]" if self.params else ""
        fence = f" [fence {self.fence}]" if self.fence else ""
        return f"{self.name} {self.level}{suffix}{params}{fence}"


@dataclass(frozen=True)
class FleetRow:
    """One vehicle in ``roost status``."""

    vehicle: str
    node: str
    ready: str
    """Status of the Vehicle's Ready condition: True, False, Unknown or ``-``."""
    ready_reason: str
    """Why it is not Ready (the condition's reason), empty when Ready."""
    active: str
    autopilots: tuple[AutopilotCell, ...]
    mission: str
    last_failover: str
    failover_detail: str
    flight_hold: str = ""
    """What the operator holds back while the vehicle is armed (why, deferred pods)."""

    @property
    def health(self) -> str:
        """The HEALTH column as one line of text: every autopilot and its level."""
        return " · ".join(cell.text for cell in self.autopilots) or NONE

    @property
    def worst_level(self) -> str:
        """The worst level among this vehicle's autopilots, ``-`` when none reported."""
        known = {level.value for level in HealthLevel}
        levels = [HealthLevel(c.level) for c in self.autopilots if c.level in known]
        return max(levels, key=lambda level: level.rank).value if levels else NONE


@dataclass(frozen=True)
class MissionRow:
    """One Mission in ``roost missions``."""

    name: str
    """``namespace/name``."""
    phase: str
    assigned: str
    """``assigned/required``."""
    vehicles: str
    """Each assigned vehicle with its phase."""
    degraded: str
    abort: bool
    started: str
    """How long ago the workloads started, ``-`` before."""
    message: str


def _name(obj: RawObject) -> str:
    return str(obj.get("metadata", {}).get("name", ""))


def namespaced_name(obj: RawObject) -> str:
    metadata = obj.get("metadata", {})
    return f"{metadata.get('namespace', '')}/{metadata.get('name', '')}"


def _parse(model: type[Model], data: Any) -> Model | None:
    """``model`` from ``data``, or None when it does not match the contract."""
    try:
        return model.model_validate(data or {})
    except ValidationError:
        return None


def format_age(then: datetime | None, now: datetime) -> str:
    """A kubectl-style short age: ``42s``, ``5m``, ``3h``, ``2d`` (``-`` when unknown)."""
    if then is None:
        return NONE
    seconds = max(0, int((now - then).total_seconds()))
    for unit, size in (("d", 86400), ("h", 3600), ("m", 60)):
        if seconds >= size:
            return f"{seconds // size}{unit}"
    return f"{seconds}s"


def format_latency(milliseconds: float) -> str:
    """Switch latency as people read it: ``0.42 ms``, ``7.5 ms``, ``21 ms``."""
    if milliseconds < 1:
        return f"{milliseconds:.2f} ms"
    if milliseconds < 10:
        return f"{milliseconds:.1f} ms"
    return f"{milliseconds:.0f} ms"


def describe_failover(record: FailoverRecord | None, now: datetime) -> tuple[str, str]:
    """(summary, detail) of the last failover: ``a → b 12s ago`` and why, how fast, outcome."""
    if record is None:
        return NONE, ""
    summary = f"{record.from_autopilot} → {record.to_autopilot} {format_age(record.time, now)} ago"
    detail = [record.reason, format_latency(record.latency_ms), record.trigger]
    if record.safety_routine:
        detail.append(f"safety routine {record.safety_routine}")
    return summary, ", ".join(detail)


def autopilot_cells(
    spec: RedundantAutopilotSpec | None, status: RedundantAutopilotStatus | None
) -> tuple[AutopilotCell, ...]:
    """One cell per autopilot in spec order; autopilots the agent has not reported show ``-``.

    Spec order keeps a vehicle's columns stable while its health changes; an autopilot the
    agent reports but the spec no longer lists (removed while running) is still shown.
    """
    reported = {h.name: h for h in status.autopilots} if status else {}
    names = [a.name for a in spec.autopilots] if spec else []
    names += [name for name in reported if name not in names]
    active = status.active_autopilot if status else None
    cells = []
    for name in names:
        health = reported.get(name)
        level = str(health.level) if health else NONE
        reason = health.reasons[0] if health and health.reasons and level != "OK" else ""
        params = find_condition(health.conditions, "ParametersInSync") if health else None
        drift = (
            f"{params.reason}: {params.message.partition(': ')[2] or params.message}"
            if params is not None and params.status != "True"
            else ""
        )
        cells.append(
            AutopilotCell(
                name=name,
                level=level,
                active=name == active,
                reason=reason,
                params=drift,
                fence=fence_text(health.conditions if health else []),
            )
        )
    return tuple(cells)


def fence_text(conditions: Sequence[Condition]) -> str:
    """An autopilot's FenceInSync condition as the HEALTH column shows it."""
    fence = find_condition(conditions, "FenceInSync")
    if fence is None:
        return ""
    fid = held_id(fence.message)
    if fence.status == "True" and fid is not None:
        return f"held {fid}"
    return f"{fence.reason}: {fence.message}"


def describe_flight_hold(status: VehicleStatus | None) -> str:
    """``autopilot fc1 is armed; deferred mavros`` while the operator holds the vehicle."""
    hold = status.flight_hold if status else None
    if hold is None:
        return ""
    deferred = f"; deferred {', '.join(hold.deferred)}" if hold.deferred else ""
    return f"{hold.reason}{deferred}"


def _mission_of_vehicle(vehicle: str, claimed_by: str | None, missions: Sequence[RawObject]) -> str:
    """``namespace/name Phase`` of the mission flying this vehicle, ``-`` when none.

    The Vehicle's ``claimedBy`` is authoritative; without it the vehicle may still be
    listed by a mission that has not finished (claims are released when it ends).
    """
    for mission in missions:
        key = namespaced_name(mission)
        status = _parse(MissionStatus, mission.get("status"))
        if status is None:
            continue
        entry = next((v for v in status.vehicles if v.name == vehicle), None)
        if key == claimed_by or (
            claimed_by is None and entry and not MissionPhase(status.phase).finished
        ):
            phase = entry.phase if entry else status.phase
            return f"{key} {phase}"
    return claimed_by or NONE


def fleet_rows(
    vehicles: Iterable[RawObject],
    autopilots: Iterable[RawObject],
    missions: Sequence[RawObject],
    now: datetime,
) -> list[FleetRow]:
    """The ``roost status`` table: one row per Vehicle, sorted by name.

    A RedundantAutopilot belongs to the Vehicle named by its ``spec.vehicleName``.
    """
    by_vehicle: dict[str, RawObject] = {}
    for ra in autopilots:
        ra_spec = ra.get("spec") or {}
        by_vehicle[str(ra_spec.get("vehicleName", _name(ra)))] = ra
    rows = []
    for vehicle in sorted(vehicles, key=_name):
        name = _name(vehicle)
        spec = _parse(VehicleSpec, vehicle.get("spec"))
        status = _parse(VehicleStatus, vehicle.get("status"))
        ra = by_vehicle.get(name, {})
        ra_spec = _parse(RedundantAutopilotSpec, ra.get("spec")) if ra else None
        ra_status = _parse(RedundantAutopilotStatus, ra.get("status")) if ra else None
        ready = find_condition(status.conditions, VehicleConditionType.READY) if status else None
        claimed = str(status.claimed_by) if status and status.claimed_by else None
        active = (ra_status.active_autopilot if ra_status else None) or (
            status.active_autopilot if status else None
        )
        summary, detail = describe_failover(ra_status.last_failover if ra_status else None, now)
        rows.append(
            FleetRow(
                vehicle=name,
                node=spec.node_name if spec else NONE,
                ready=ready.status if ready else NONE,
                ready_reason=ready.reason if ready and ready.status != "True" else "",
                active=active or NONE,
                autopilots=autopilot_cells(ra_spec, ra_status),
                mission=_mission_of_vehicle(name, claimed, missions),
                last_failover=summary,
                failover_detail=detail,
                flight_hold=describe_flight_hold(status),
            )
        )
    return rows


def mission_rows(missions: Iterable[RawObject], now: datetime) -> list[MissionRow]:
    """The ``roost missions`` table: one row per Mission, sorted by namespace and name."""
    rows = []
    for mission in sorted(missions, key=namespaced_name):
        spec = _parse(MissionSpec, mission.get("spec"))
        status = _parse(MissionStatus, mission.get("status")) or MissionStatus()
        degraded = find_condition(status.conditions, "Degraded")
        required = str(spec.vehicles.count) if spec else "?"
        rows.append(
            MissionRow(
                name=namespaced_name(mission),
                phase=str(status.phase),
                assigned=f"{status.assigned_count}/{required}",
                vehicles=", ".join(f"{v.name} {v.phase}" for v in status.vehicles) or NONE,
                degraded=degraded.status if degraded else NONE,
                abort=bool(spec and spec.abort),
                started=format_age(status.start_time, now),
                message=status.message or status.reason or "",
            )
        )
    return rows


@dataclass(frozen=True)
class EventRow:
    """One Kubernetes Event about a Roost object."""

    age: str
    type: str
    """Normal or Warning."""
    object: str
    """``Kind/name`` of the object the event is about."""
    reason: str
    message: str


def event_time(event: RawObject) -> str:
    """The event's latest time as an ISO string (they sort correctly as text)."""
    series = event.get("series") or {}
    return str(
        series.get("lastObservedTime")
        or event.get("lastTimestamp")
        or event.get("eventTime")
        or event.get("metadata", {}).get("creationTimestamp")
        or ""
    )


def roost_events(events: Iterable[RawObject]) -> list[RawObject]:
    """The Events about roost.dev objects."""
    return [
        e
        for e in events
        if str((e.get("involvedObject") or e.get("regarding") or {}).get("apiVersion", ""))
        .split("/")[0]
        .endswith(GROUP)
    ]


def event_rows(events: Iterable[RawObject], now: datetime, limit: int) -> list[EventRow]:
    """The ``limit`` most recent Events about roost.dev objects, oldest first.

    Events are how operator and agents explain their decisions (failover, safety routine,
    claims), so the fleet view shows them next to the state they changed.
    """
    newest = sorted(roost_events(events), key=event_time)[-limit:] if limit > 0 else []
    rows = []
    for event in newest:
        involved = event.get("involvedObject") or event.get("regarding") or {}
        stamp = event_time(event)
        when = datetime.fromisoformat(stamp.replace("Z", "+00:00")) if stamp else None
        rows.append(
            EventRow(
                age=format_age(when, now),
                type=str(event.get("type", "")),
                object=f"{involved.get('kind', '')}/{involved.get('name', '')}",
                reason=str(event.get("reason", "")),
                message=str(event.get("message") or event.get("note") or ""),
            )
        )
    return rows
