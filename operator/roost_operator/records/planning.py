"""Pure decisions about a Mission's record: no I/O, no clock of its own.

* **Which flights belong** to a Mission: the flights of its claimed vehicles whose armed
  interval (arm → disarm, or → now while still armed) overlaps the Mission's run
  (``status.startTime`` → ``status.completionTime``). The agent knows nothing of
  Missions; the overlap is the whole link.
* **What to fetch**: every file of those flights not yet in the bundle. A file the agent
  finished has a sha256 and is verified after download; a mismatch is downloaded again
  from scratch, up to ``fetch_attempts`` times, then it is missing as corrupt. A file
  the agent marks Failed is missing with the agent's message. A file still Partial is
  waited for while its flight is still recording or fetching autopilot logs, and taken
  as it is (and named in ``missing``) once the flight is final or the settle time passed.
* **Whether to reach a vehicle at all** (:func:`not_gathered`): only when the agents'
  records can be reached (the operator's ``agents`` setting) or the Vehicle names its
  records server's URL. Otherwise its entry is final at once — OnVehicle (the agent
  serves on the vehicle's loopback only, the chart's default) or NotRecorded (recording
  is off) — and says where the flights are and which setting gathers them: a vehicle the
  operator cannot reach by design is not waited for (a day of "unreachable" retries
  would say nothing true).
* **A vehicle's state**: Pending (unreachable, or a flight not yet final, or files still
  to fetch), Complete, Partial (final, something missing), Missing (unreachable for
  longer than the give-up time), OnVehicle or NotRecorded (not gathered, see above).
* **The bundle's state**: Gathering while any vehicle is Pending; Complete when all are;
  Partial otherwise.
* **Retention**: final bundles beyond the newest ``keep_count`` or older than
  ``keep_for`` go; a bundle still gathering is never removed, unless nothing has written
  it for longer than gathering can last (its Mission was deleted while it gathered).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from enum import StrEnum
from pathlib import PurePosixPath
from typing import Any

from roost_api.mission import MissionRecordsStatus, RecordsState, VehicleRecordsStatus
from roost_api.records import FileState, FlightState
from roost_operator.records.settings import AgentRecords, RecordsSettings

FINAL_FLIGHT_STATES = frozenset({FlightState.COMPLETE, FlightState.FAILED})
"""Agent flight states after which nothing more is written to the flight."""


class VehicleState(StrEnum):
    PENDING = "Pending"
    COMPLETE = "Complete"
    PARTIAL = "Partial"
    MISSING = "Missing"
    ON_VEHICLE = "OnVehicle"
    NOT_RECORDED = "NotRecorded"


NOT_GATHERED = frozenset({VehicleState.ON_VEHICLE, VehicleState.NOT_RECORDED})
"""Vehicles the operator does not reach by its settings: final without a contact."""


@dataclass(frozen=True)
class AgentFile:
    """One file of a flight as the agent's ``flight.json`` lists it."""

    path: str
    kind: str
    state: str
    bytes: int = 0
    sha256: str | None = None
    autopilot: str | None = None
    message: str | None = None


@dataclass(frozen=True)
class AgentFlight:
    """One flight as the agent's ``GET /records`` lists it."""

    flight_id: str
    vehicle: str
    armed_at: datetime
    disarmed_at: datetime | None
    state: str
    message: str | None = None
    files: tuple[AgentFile, ...] = ()
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False)

    @property
    def final(self) -> bool:
        return self.state in FINAL_FLIGHT_STATES

    @classmethod
    def parse(cls, body: Mapping[str, Any]) -> AgentFlight:
        """From the agent's manifest; ValueError (or KeyError/TypeError) when malformed."""
        files = tuple(
            AgentFile(
                path=str(f["path"]),
                kind=str(f.get("kind") or ""),
                state=str(f.get("state") or FileState.PARTIAL),
                bytes=int(f.get("bytes") or 0),
                sha256=f.get("sha256") or None,
                autopilot=f.get("autopilot") or None,
                message=f.get("message") or None,
            )
            for f in body.get("files") or []
        )
        disarmed = body.get("disarmedAt")
        return cls(
            flight_id=str(body["flightId"]),
            vehicle=str(body.get("vehicle") or ""),
            armed_at=_time(body["armedAt"]),
            disarmed_at=_time(disarmed) if disarmed else None,
            state=str(body.get("state") or FlightState.RECORDING),
            message=body.get("message") or None,
            files=files,
            raw=dict(body),
        )


def _time(text: str) -> datetime:
    value = datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    if value.tzinfo is None:
        raise ValueError(f"time without a zone: {text}")
    return value


@dataclass(frozen=True)
class Listing:
    """What a vehicle's records server answered: its flights, or why it could not."""

    vehicle: str
    flights: tuple[AgentFlight, ...] = ()
    error: str | None = None


@dataclass(frozen=True)
class Window:
    """The Mission's run."""

    start: datetime
    end: datetime


@dataclass(frozen=True)
class Missing:
    """Something the bundle lacks, and why (the manifest's ``missing`` list)."""

    vehicle: str
    reason: str
    flight_id: str | None = None
    path: str | None = None


@dataclass(frozen=True)
class Fetch:
    """One file to download into the bundle."""

    vehicle: str
    flight_id: str
    file: AgentFile

    @property
    def key(self) -> tuple[str, str]:
        return (self.flight_id, self.file.path)


@dataclass
class VehiclePlan:
    """One vehicle's part of one gathering round."""

    vehicle: str
    state: VehicleState
    message: str | None = None
    flights: list[AgentFlight] = field(default_factory=list)
    fetch: list[Fetch] = field(default_factory=list)
    missing: list[Missing] = field(default_factory=list)


def overlaps(flight: AgentFlight, window: Window, now: datetime) -> bool:
    """The flight's armed interval overlaps the Mission's run (ends included)."""
    disarmed = flight.disarmed_at or now
    return flight.armed_at <= window.end and disarmed >= window.start


def safe_path(path: str) -> bool:
    """A relative path that stays inside its flight's directory."""
    pure = PurePosixPath(path)
    return bool(path) and not pure.is_absolute() and ".." not in pure.parts and "\\" not in path


def not_gathered(
    vehicle: str, agents: AgentRecords, *, direct: bool, node: str, port: int
) -> VehiclePlan | None:
    """The vehicle's final plan when the operator does not contact it, else None (gather).

    ``agents``: the operator's setting; ``direct``: the Vehicle names its records
    server's URL (``roost.dev/records``), which the operator reaches whatever the
    setting. ``node``/``port``: where the flights are, for the message."""
    if direct or agents is AgentRecords.REACHABLE:
        return None
    if agents is AgentRecords.OFF:
        reason = (
            "not recorded: flight recording is off on the agents (chart value "
            "agent.records.enabled: false)"
        )
        return VehiclePlan(
            vehicle, VehicleState.NOT_RECORDED, reason, missing=[Missing(vehicle, reason)]
        )
    where = (
        f"on node {node} (agent.records.dir/{node}/, /var/lib/roost/records/{node}/ by default)"
        if node
        else "in the vehicle's records directory (agent.records.dir)"
    )
    reason = (
        "not gathered: the flights stay on the vehicle, whose agent serves them on its "
        "127.0.0.1 only (chart value agent.records.bindNodeAddress: false). They are "
        f"{where} and served on the vehicle at http://127.0.0.1:{port}/records; set "
        "agent.records.bindNodeAddress: true for later Missions' bundles to include them"
    )
    return VehiclePlan(vehicle, VehicleState.ON_VEHICLE, reason, missing=[Missing(vehicle, reason)])


def plan_vehicle(
    listing: Listing,
    window: Window,
    *,
    held: frozenset[tuple[str, str]],
    attempts: Mapping[tuple[str, str], int],
    now: datetime,
    settings: RecordsSettings,
) -> VehiclePlan:
    """What to do about one vehicle now; ``held``: (flightId, path) already in the
    bundle and verified; ``attempts``: failed checksum verifications so far per file."""
    name = listing.vehicle
    since_end = now - window.end
    if listing.error is not None:
        if since_end >= settings.give_up_after:
            return VehiclePlan(
                name,
                VehicleState.MISSING,
                f"unreachable since the mission ended: {listing.error}",
                missing=[Missing(name, f"vehicle unreachable: {listing.error}")],
            )
        return VehiclePlan(
            name,
            VehicleState.PENDING,
            f"unreachable, gathered when it is back: {listing.error}",
        )
    settled = since_end >= settings.settle_after
    plan = VehiclePlan(name, VehicleState.PENDING)
    plan.flights = sorted(
        (f for f in listing.flights if overlaps(f, window, now)), key=lambda f: f.armed_at
    )
    waiting: list[str] = []
    for flight in plan.flights:
        done = flight.final or settled
        if not done:
            waiting.append(f"flight {flight.flight_id} is {flight.state}")
            continue
        if not flight.final:
            reason = f"still {flight.state} when the settle time ended; taken as it was"
            plan.missing.append(Missing(name, reason, flight.flight_id))
        elif flight.state == FlightState.FAILED:
            reason = "recording Failed on the vehicle" + (
                f": {flight.message}" if flight.message else ""
            )
            plan.missing.append(Missing(name, reason, flight.flight_id))
        for item in flight.files:
            _plan_file(plan, flight, item, held=held, attempts=attempts, settings=settings)
    if waiting:
        plan.message = "waiting: " + "; ".join(waiting)
        plan.fetch.clear()  # fetch once the whole vehicle is final: one pass, one manifest
        return plan
    if plan.fetch:
        plan.message = f"{len(plan.fetch)} file(s) to fetch"
        return plan
    count = len(plan.flights)
    if plan.missing:
        plan.state = VehicleState.PARTIAL
        plan.message = "; ".join(_describe(m) for m in plan.missing)
    else:
        plan.state = VehicleState.COMPLETE
        plan.message = None if count else "no flight of this vehicle overlaps the mission's run"
    return plan


def _plan_file(
    plan: VehiclePlan,
    flight: AgentFlight,
    item: AgentFile,
    *,
    held: frozenset[tuple[str, str]],
    attempts: Mapping[tuple[str, str], int],
    settings: RecordsSettings,
) -> None:
    key = (flight.flight_id, item.path)
    if key in held:
        if item.state != FileState.COMPLETE:
            plan.missing.append(
                Missing(plan.vehicle, _file_reason(item), flight.flight_id, item.path)
            )
        return
    if not safe_path(item.path):
        plan.missing.append(
            Missing(plan.vehicle, "path outside the flight refused", flight.flight_id, item.path)
        )
        return
    if item.state == FileState.FAILED:
        plan.missing.append(Missing(plan.vehicle, _file_reason(item), flight.flight_id, item.path))
        return
    if attempts.get(key, 0) >= settings.fetch_attempts:
        plan.missing.append(
            Missing(
                plan.vehicle,
                f"corrupt: sha256 did not match after {attempts[key]} downloads",
                flight.flight_id,
                item.path,
            )
        )
        return
    plan.fetch.append(Fetch(plan.vehicle, flight.flight_id, item))


def _file_reason(item: AgentFile) -> str:
    return f"{item.state} on the vehicle" + (f": {item.message}" if item.message else "")


def _describe(missing: Missing) -> str:
    where = "/".join(p for p in (missing.flight_id, missing.path) if p)
    return f"{where}: {missing.reason}" if where else missing.reason


def bundle_state(plans: Sequence[VehiclePlan]) -> RecordsState:
    """Gathering while a vehicle is pending; Complete when all are; else Partial."""
    if any(p.state is VehicleState.PENDING for p in plans):
        return RecordsState.GATHERING
    if all(p.state is VehicleState.COMPLETE for p in plans):
        return RecordsState.COMPLETE
    return RecordsState.PARTIAL


def records_status(
    bundle: str,
    plans: Sequence[VehiclePlan],
    *,
    previous: MissionRecordsStatus | None,
    now: datetime,
) -> MissionRecordsStatus:
    """The Mission's ``status.records`` after a gathering round."""
    state = bundle_state(plans)
    ready = previous.ready_time if previous is not None else None
    if state.final and ready is None:
        ready = now
    pending = [p.vehicle for p in plans if p.state is VehicleState.PENDING]
    incomplete = [
        p.vehicle for p in plans if p.state in (VehicleState.PARTIAL, VehicleState.MISSING)
    ]
    kept = [p.vehicle for p in plans if p.state in NOT_GATHERED]
    parts = []
    if incomplete:
        parts.append(
            f"incomplete: {', '.join(incomplete)} (the bundle's manifest says what and why)"
        )
    if kept:
        parts.append(
            f"not gathered: {', '.join(kept)} (each vehicle's message says where its flights are)"
        )
    message = f"pending: {', '.join(pending)}" if pending else "; ".join(parts) or None
    return MissionRecordsStatus(
        state=state,
        bundle=bundle,
        message=message,
        ready_time=ready,
        vehicles=[
            VehicleRecordsStatus(
                name=p.vehicle, state=p.state.value, flights=len(p.flights), message=p.message
            )
            for p in plans
        ],
    )


def gathering(bundle: str, vehicles: Sequence[str]) -> MissionRecordsStatus:
    """The first ``status.records`` of a mission that flew and just ended."""
    return MissionRecordsStatus(
        state=RecordsState.GATHERING,
        bundle=bundle,
        message="gathering the flights of " + ", ".join(vehicles) if vehicles else None,
        vehicles=[VehicleRecordsStatus(name=v, state=VehicleState.PENDING.value) for v in vehicles],
    )


def bundle_name(namespace: str, name: str, uid: str) -> str:
    """``NAMESPACE_NAME_UID8``: unique per Mission object (a re-created Mission of the
    same name gets a new bundle), and safe as a directory name (``_`` appears in neither
    a namespace nor a Mission name)."""
    return f"{namespace}_{name}_{uid.replace('-', '')[:8]}"


@dataclass(frozen=True)
class BundleInfo:
    """A bundle on the volume, as retention sees it."""

    name: str
    ready_at: datetime | None
    """None while it is still gathering."""
    written_at: datetime | None = None
    """When its manifest was last written."""


def expired(
    bundles: Sequence[BundleInfo],
    *,
    keep_count: int,
    keep_for: timedelta | None,
    now: datetime,
    abandoned_after: timedelta = timedelta(days=2),
) -> list[str]:
    """The final bundles retention removes: beyond the newest ``keep_count`` (0: no
    limit) or ready longer ago than ``keep_for`` (None: no limit). Never a bundle still
    gathering; one nothing has written for ``abandoned_after`` (its Mission was deleted
    while it gathered) counts as final since its last write."""
    final = sorted(
        (
            (at, b.name)
            for b in bundles
            if (at := b.ready_at or _abandoned(b, now, abandoned_after)) is not None
        ),
        reverse=True,
    )
    gone = []
    for index, (at, name) in enumerate(final):
        too_many = keep_count > 0 and index >= keep_count
        too_old = keep_for is not None and now - at > keep_for
        if too_many or too_old:
            gone.append(name)
    return sorted(gone)


def _abandoned(info: BundleInfo, now: datetime, after: timedelta) -> datetime | None:
    written = info.written_at
    return written if written is not None and now - written >= after else None
