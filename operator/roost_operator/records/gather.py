"""One gathering round for one finished Mission: observe the agents, plan, fetch, record.

Called by the Mission's reconcile (:func:`~roost_operator.missions.cluster.reconcile_mission`)
once the Mission has ended and its ``status.records`` says Gathering; what it returns
goes into the same status write as the rest of the Mission's status, so the Mission's
reconcile stays the only writer. A round never raises for a vehicle: what it cannot do becomes
that vehicle's Pending (tried again in ``retry_seconds``) or Missing state. Only an
unusable records volume fails the bundle (state Failed, said once).

Per vehicle: list its flights (``GET /records``), keep those overlapping the Mission's
run (:func:`~roost_operator.records.planning.plan_vehicle`), download what the bundle
lacks (resuming ``.part`` files), verify each against the agent's sha256, and plan again
until nothing is left to fetch or the vehicle cannot be reached. A vehicle already final
in the manifest is not contacted again, nor is one the settings say the operator cannot
reach (:func:`~roost_operator.records.planning.not_gathered`): with every vehicle so, the
first round writes the bundle from what the operator holds (the Mission, its Events, the
manifest) and it is final at once.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import urllib3

from roost_api.mission import MissionRecordsStatus, MissionStatus, RecordsState
from roost_api.wellknown import ANNOTATION_RECORDS
from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.resources import EVENTS, MISSIONS
from roost_operator.records.bundle import Bundle, CorruptError, Stored, list_bundles, remove_bundle
from roost_operator.records.planning import (
    AgentFlight,
    Listing,
    Missing,
    VehiclePlan,
    VehicleState,
    Window,
    expired,
    not_gathered,
    plan_vehicle,
    records_status,
)
from roost_operator.records.settings import RecordsSettings
from roost_operator.records.source import Endpoint, SourceError, endpoint_for, read_json

log = logging.getLogger(__name__)
POOL = urllib3.PoolManager(maxsize=8)
FORMAT = 1
"""The manifest's format version."""


@dataclass(frozen=True)
class VehicleTarget:
    """What gathering needs of one claimed vehicle (None fields: the Vehicle is gone)."""

    name: str
    node: str = ""
    annotations: Mapping[str, str] | None = None


def list_flights(endpoint: Endpoint, vehicle: str) -> Listing:
    """The vehicle's flights (malformed entries are skipped with a log line)."""
    try:
        body = read_json(endpoint, "records")
    except SourceError as error:
        return Listing(vehicle, error=str(error))
    flights = []
    for entry in (body or {}).get("flights") or []:
        try:
            flights.append(AgentFlight.parse(entry))
        except (KeyError, TypeError, ValueError) as error:
            log.warning("vehicle %s: malformed flight entry skipped: %s", vehicle, error)
    return Listing(vehicle, tuple(flights))


def _gather_vehicle(
    bundle: Bundle,
    target: VehicleTarget,
    endpoint: Endpoint | None,
    unreachable: str | None,
    *,
    window: Window,
    held: dict[tuple[str, str], Stored],
    attempts: dict[str, int],
    now: datetime,
    settings: RecordsSettings,
) -> VehiclePlan:
    if endpoint is None:
        listing = Listing(target.name, error=unreachable or "unreachable")
    else:
        listing = list_flights(endpoint, target.name)

    def plan() -> VehiclePlan:
        return plan_vehicle(
            listing,
            window,
            held=frozenset(held),
            attempts={_key(k): v for k, v in attempts.items()},
            now=now,
            settings=settings,
        )

    current = plan()
    while current.fetch and endpoint is not None:
        for fetch in current.fetch:
            try:
                held[fetch.key] = bundle.download(endpoint, fetch)
            except CorruptError as error:
                key = "/".join(fetch.key)
                attempts[key] = attempts.get(key, 0) + 1
                log.warning("vehicle %s: %s (download %d)", target.name, error, attempts[key])
            except (SourceError, OSError) as error:
                current.state = VehicleState.PENDING
                current.message = f"{fetch.flight_id}/{fetch.file.path}: {error}"
                return current
        current = plan()
    for flight in current.flights:
        held[(flight.flight_id, "flight.json")] = bundle.write_flight(
            target.name, flight.flight_id, flight.raw
        )
    return current


def _events(kube: Kube, namespace: str, uid: str) -> list[dict[str, Any]] | dict[str, str]:
    """The Mission's Events, oldest first, or ``{"error": why}`` when they cannot be read
    (the bundle is still written: a record without its Events beats none)."""
    try:
        items = kube.list_objects(
            EVENTS, namespace=namespace, field_selector=f"involvedObject.uid={uid}"
        )
    except ApiError as error:
        log.warning("Mission %s/%s: its Events could not be listed: %s", namespace, uid, error)
        return {"error": f"the Mission's Events could not be listed: {error}"}
    keep = ("type", "reason", "message", "count", "firstTimestamp", "lastTimestamp", "eventTime")
    rows = [{k: e.get(k) for k in keep if e.get(k) is not None} for e in items]
    return sorted(rows, key=lambda e: str(e.get("eventTime") or e.get("firstTimestamp") or ""))


def gather_round(
    kube: Kube,
    settings: RecordsSettings,
    *,
    namespace: str,
    name: str,
    uid: str,
    status: MissionStatus,
    vehicles: Sequence[VehicleTarget],
    now: datetime,
) -> MissionRecordsStatus:
    """One round for the Mission; see the module docstring. ``status.records`` and
    ``status.startTime``/``completionTime`` must be set (a mission that flew and ended)."""
    records = status.records
    assert records is not None and status.start_time is not None
    assert settings.directory is not None
    window = Window(status.start_time, status.completion_time or now)
    bundle = Bundle(settings.directory / records.bundle)
    try:
        bundle.root.mkdir(parents=True, exist_ok=True)
        before = bundle.manifest()
    except OSError as error:
        return records.model_copy(
            update={"state": RecordsState.FAILED, "message": f"records volume: {error}"}
        )
    held: dict[tuple[str, str], Stored] = {
        (f["flightId"], f["name"]): Stored(f["path"], f["bytes"], f["sha256"])
        for f in before.get("files", [])
        if f.get("flightId")
    }
    attempts: dict[str, int] = dict(before.get("attempts") or {})
    done = {v["name"]: v for v in before.get("vehicles", []) if v.get("state") != "Pending"}
    plans: list[VehiclePlan] = []
    previous_flights = {f["flightId"]: f for f in before.get("flights", [])}
    for target in vehicles:
        if target.name in done:
            plans.append(_final_plan(done[target.name], before))
            continue
        kept = not_gathered(
            target.name,
            settings.agents,
            direct=bool((target.annotations or {}).get(ANNOTATION_RECORDS)),
            node=target.node,
            port=settings.agent_port,
        )
        if kept is not None:
            plans.append(kept)
            continue
        endpoint: Endpoint | None = None
        unreachable = None
        if target.annotations is None:
            unreachable = "the Vehicle was deleted"
        else:
            try:
                endpoint = endpoint_for(
                    kube,
                    POOL,
                    annotations=target.annotations,
                    node=target.node,
                    namespace=settings.agent_namespace,
                    port=settings.agent_port,
                )
            except (SourceError, ApiError) as error:
                unreachable = str(error)
        try:
            plans.append(
                _gather_vehicle(
                    bundle,
                    target,
                    endpoint,
                    unreachable,
                    window=window,
                    held=held,
                    attempts=attempts,
                    now=now,
                    settings=settings,
                )
            )
        except OSError as error:
            return records.model_copy(
                update={"state": RecordsState.FAILED, "message": f"records volume: {error}"}
            )
    result = records_status(records.bundle, plans, previous=records, now=now)
    try:
        documents = [
            bundle.write_document("mission.json", _mission(kube, namespace, name)),
            bundle.write_document("events.json", _events(kube, namespace, uid)),
        ]
        bundle.write_manifest(
            _manifest(
                result,
                plans,
                held=held,
                documents=documents,
                attempts=attempts,
                previous_flights=previous_flights,
                mission={
                    "namespace": namespace,
                    "name": name,
                    "uid": uid,
                    "phase": str(status.phase),
                    "startTime": _iso(status.start_time),
                    "completionTime": _iso(status.completion_time),
                },
            )
        )
    except OSError as error:
        return records.model_copy(
            update={"state": RecordsState.FAILED, "message": f"records volume: {error}"}
        )
    if RecordsState(result.state).final:
        _apply_retention(settings, now, keep=records.bundle)
    return result


def _mission(kube: Kube, namespace: str, name: str) -> dict[str, Any]:
    try:
        body = kube.get(MISSIONS, name, namespace) or {}
    except ApiError as error:
        return {"error": f"the Mission could not be read: {error}"}
    meta = body.get("metadata", {})
    meta.pop("managedFields", None)
    return body


def _final_plan(entry: Mapping[str, Any], manifest: Mapping[str, Any]) -> VehiclePlan:
    """A vehicle the manifest already holds as final, rebuilt without contacting it."""
    flights = [
        AgentFlight.parse(f["agent"])
        for f in manifest.get("flights", [])
        if f.get("vehicle") == entry["name"] and f.get("agent")
    ]
    missing = [
        Missing(m["vehicle"], m["reason"], m.get("flightId"), m.get("path"))
        for m in manifest.get("missing", [])
        if m.get("vehicle") == entry["name"]
    ]
    return VehiclePlan(
        entry["name"], VehicleState(entry["state"]), entry.get("message"), flights, [], missing
    )


def _manifest(
    result: MissionRecordsStatus,
    plans: Sequence[VehiclePlan],
    *,
    held: Mapping[tuple[str, str], Stored],
    documents: Sequence[Stored],
    attempts: Mapping[str, int],
    previous_flights: Mapping[str, Any],
    mission: Mapping[str, Any],
) -> dict[str, Any]:
    kinds: dict[tuple[str, str], Mapping[str, Any]] = {}
    flights = []
    for plan in plans:
        for flight in plan.flights:
            flights.append(
                {
                    "flightId": flight.flight_id,
                    "vehicle": plan.vehicle,
                    "armedAt": flight.armed_at.isoformat(),
                    "disarmedAt": flight.disarmed_at.isoformat() if flight.disarmed_at else None,
                    "state": flight.state,
                    "directory": f"vehicles/{plan.vehicle}/{flight.flight_id}",
                    "agent": dict(flight.raw),
                }
            )
            for item in flight.files:
                kinds[(flight.flight_id, item.path)] = {
                    "kind": item.kind,
                    "autopilot": item.autopilot,
                    "vehicle": plan.vehicle,
                }
    for flight_id, entry in previous_flights.items():
        if not any(f["flightId"] == flight_id for f in flights):
            flights.append(entry)
    files = [
        {"path": d.path, "bytes": d.bytes, "sha256": d.sha256, "kind": d.path.removesuffix(".json")}
        for d in documents
    ]
    for (flight_id, relative), stored in sorted(held.items()):
        extra = kinds.get(
            (flight_id, relative), {"kind": "flight" if relative == "flight.json" else ""}
        )
        files.append(
            {
                "path": stored.path,
                "bytes": stored.bytes,
                "sha256": stored.sha256,
                "flightId": flight_id,
                "name": relative,
                **{k: v for k, v in extra.items() if v},
            }
        )
    return {
        "format": FORMAT,
        "bundle": result.bundle,
        "state": str(result.state),
        "message": result.message,
        "readyAt": result.ready_time.isoformat() if result.ready_time else None,
        "mission": dict(mission),
        "vehicles": [
            {
                "name": p.vehicle,
                "state": p.state.value,
                "message": p.message,
                "flights": [f.flight_id for f in p.flights],
            }
            for p in plans
        ],
        "flights": flights,
        "files": files,
        "missing": [
            {
                k: v
                for k, v in (
                    ("vehicle", m.vehicle),
                    ("flightId", m.flight_id),
                    ("path", m.path),
                    ("reason", m.reason),
                )
                if v
            }
            for p in plans
            for m in p.missing
        ],
        "attempts": dict(attempts),
    }


def _apply_retention(settings: RecordsSettings, now: datetime, *, keep: str) -> None:
    assert settings.directory is not None
    gone = expired(
        list_bundles(settings.directory),
        keep_count=settings.keep_count,
        keep_for=settings.keep_for,
        now=now,
        abandoned_after=settings.give_up_after + settings.settle_after,
    )
    for name in gone:
        if name != keep:
            log.info("records: bundle %s removed by retention", name)
            remove_bundle(settings.directory, name)


def _key(text: str) -> tuple[str, str]:
    """``flightId/path`` (the manifest's ``attempts`` keys) as (flightId, path)."""
    flight_id, _, path = text.partition("/")
    return (flight_id, path)


def _iso(value: datetime | None) -> str | None:
    return value.isoformat() if value is not None else None
