"""What the dashboard shows, as one JSON-ready document built from the cluster and the agents.

Pure and synchronous, so every field is tested without a browser, a cluster or an agent:
the watches feed :meth:`FleetModel.apply` with the objects the API server sends, the
telemetry clients feed :meth:`FleetModel.telemetry` with the agents' samples, and the
server asks :meth:`FleetModel.snapshot` for the document it pushes (at most ten times a
second, only when something changed).

The tables are :mod:`roost_cli.tables`' rows — ``roost status`` and the dashboard read
the cluster the same way — with the agents' live samples laid over them: a sample is
fresher than the status the agent last wrote, so its active autopilot and health levels
win while it is fresh (:data:`TELEMETRY_STALE_S`).

Positions: each vehicle is drawn in one local frame, metres north and east of the
dashboard's origin (``--origin``, else the first origin an agent reported), from the
latitude and longitude the samples carry — vehicles whose agents measure from different
origins still land in one frame.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from typing import Any

from pydantic import ValidationError

from roost_api.meta import HealthLevel
from roost_api.mission import MissionPhase, MissionStatus
from roost_api.telemetry import Origin, north_east_m
from roost_cli import tables
from roost_cli.tables import NONE

TELEMETRY_STALE_S = 2.0
"""A sample older than this no longer overrides the status; the vehicle shows stale."""
TIMELINE_LIMIT = 200
EVENTS_KEPT = 500
TRAIL_POINTS = 60
"""Positions kept per vehicle for its trail (six seconds at 10 Hz)."""
LANDED_BELOW_M = 0.3
KINDS = ("Vehicle", "RedundantAutopilot", "Mission", "Event")

Obj = Mapping[str, Any]


def _key(obj: Obj) -> str:
    metadata = obj.get("metadata", {})
    return str(metadata.get("uid") or f"{metadata.get('namespace', '')}/{metadata.get('name')}")


def worst(levels: list[str]) -> str:
    """The worst :class:`HealthLevel` among ``levels`` (``-`` when none is known)."""
    known = [HealthLevel(level) for level in levels if level in HealthLevel.__members__.values()]
    return max(known, key=lambda level: level.rank).value if known else NONE


def timeline_kind(involved_kind: str, reason: str) -> str:
    """The timeline lane of an Event: failover, safety, mission or other."""
    if ("Fail" in reason and involved_kind != "Mission") or "SwitchedBy" in reason:
        return "failover"
    if reason.startswith(("Safety", "Land", "EmergencyStop", "Hold")):
        return "safety"
    if involved_kind == "Mission":
        return "mission"
    return "other"


class FleetModel:
    """The dashboard's state; thread-safe (watches and telemetry write from other threads)."""

    def __init__(
        self,
        origin: Origin | None = None,
        *,
        clock: Callable[[], float] = time.time,
        on_change: Callable[[], None] = lambda: None,
    ) -> None:
        self._lock = threading.Lock()
        self._objects: dict[str, dict[str, Obj]] = {kind: {} for kind in KINDS}
        self._events: OrderedDict[str, Obj] = OrderedDict()
        self._samples: dict[str, dict[str, Any]] = {}
        self._trails: dict[str, list[tuple[float, float]]] = {}
        self._live_failovers: dict[str, dict[str, Any]] = {}
        self._origin = origin
        self._clock = clock
        self._on_change = on_change
        self._cluster_version = 0
        self._rows_version = -1
        self._rows: tuple[list[tables.FleetRow], list[dict[str, Any]], list[dict[str, Any]]] = (
            [],
            [],
            [],
        )
        self.cluster_error: str | None = None
        self.version = 0

    # -- input -----------------------------------------------------------------------

    def replace(self, kind: str, objects: Sequence[Obj]) -> None:
        """A fresh list of ``kind`` (after a (re)list): replaces everything known of it."""
        with self._lock:
            if kind == "Event":
                self._events.clear()
                for obj in sorted(objects, key=tables.event_time)[-EVENTS_KEPT:]:
                    self._events[_key(obj)] = obj
            else:
                self._objects[kind] = {_key(obj): obj for obj in objects}
            self._changed_cluster()

    def apply(self, kind: str, change: str, obj: Obj) -> None:
        """One watch event (ADDED, MODIFIED, DELETED) of ``kind``."""
        with self._lock:
            key = _key(obj)
            if kind == "Event":
                store: Any = self._events
            else:
                store = self._objects[kind]
            if change == "DELETED":
                store.pop(key, None)
            else:
                store[key] = obj
                if kind == "Event":
                    self._events.move_to_end(key)
                    while len(self._events) > EVENTS_KEPT:
                        self._events.popitem(last=False)
            self._changed_cluster()

    def set_cluster_error(self, error: str | None) -> None:
        with self._lock:
            if error != self.cluster_error:
                self.cluster_error = error
                self.version += 1
        self._on_change()

    def telemetry(self, vehicle: str, sample: dict[str, Any]) -> None:
        """One sample from a vehicle's agent (see :mod:`roost_agent.telemetry`)."""
        sample["receivedAt"] = self._clock()
        with self._lock:
            self._samples[vehicle] = sample
            position = sample.get("position")
            if position and self._origin is None and sample.get("origin"):
                self._origin = Origin(
                    float(sample["origin"]["lat"]), float(sample["origin"]["lon"])
                )
            if position and self._origin is not None:
                north, east = north_east_m(self._origin, position["lat"], position["lon"])
                position["n"], position["e"] = round(north, 2), round(east, 2)
                trail = self._trails.setdefault(vehicle, [])
                trail.append((position["n"], position["e"]))
                del trail[:-TRAIL_POINTS]
            failover = sample.get("lastFailover")
            if failover and self._live_failovers.get(vehicle) != failover:
                self._live_failovers[vehicle] = failover
            self.version += 1
        self._on_change()

    def telemetry_lost(self, vehicle: str) -> None:
        with self._lock:
            if self._samples.pop(vehicle, None) is not None:
                self.version += 1
        self._on_change()

    def _changed_cluster(self) -> None:
        self._cluster_version += 1
        self.version += 1
        self._on_change()

    # -- output ----------------------------------------------------------------------

    def telemetry_endpoints(self, annotation: str) -> dict[str, str]:
        """Vehicle → telemetry URL from the Vehicles' ``annotation``."""
        with self._lock:
            vehicles = list(self._objects["Vehicle"].values())
        found = {}
        for vehicle in vehicles:
            metadata = vehicle.get("metadata", {})
            url = (metadata.get("annotations") or {}).get(annotation)
            if url:
                found[str(metadata.get("name"))] = str(url)
        return found

    def mission_vehicles(self, namespace: str, name: str) -> list[str]:
        """The vehicles a Mission has assigned (what an abort reaches)."""
        with self._lock:
            missions = list(self._objects["Mission"].values())
        for mission in missions:
            metadata = mission.get("metadata", {})
            if (metadata.get("namespace"), metadata.get("name")) == (namespace, name):
                try:
                    status = MissionStatus.model_validate(mission.get("status") or {})
                except ValidationError:
                    return []
                return [v.name for v in status.vehicles]
        return []

    def _cluster_rows(
        self, now: datetime
    ) -> tuple[list[tables.FleetRow], list[dict[str, Any]], list[dict[str, Any]]]:
        """Fleet rows, missions and the Event timeline, recomputed only after a change."""
        if self._rows_version == self._cluster_version:
            return self._rows
        vehicles = list(self._objects["Vehicle"].values())
        autopilots = list(self._objects["RedundantAutopilot"].values())
        missions = list(self._objects["Mission"].values())
        rows = tables.fleet_rows(vehicles, autopilots, missions, now)
        mission_docs = []
        for row, mission in zip(
            tables.mission_rows(missions, now),
            sorted(missions, key=tables.namespaced_name),
            strict=True,
        ):
            try:
                status = MissionStatus.model_validate(mission.get("status") or {})
            except ValidationError:
                status = MissionStatus()
            mission_docs.append(
                asdict(row)
                | {
                    "fence": None,
                    "spec": mission.get("spec") or {},
                    "perVehicle": [
                        {
                            "name": v.name,
                            "phase": str(v.phase),
                            "reason": v.reason or "",
                            "message": v.message or "",
                        }
                        for v in status.vehicles
                    ],
                }
            )
        timeline = []
        roost = tables.roost_events(self._events.values())
        for e in sorted(roost, key=tables.event_time)[-TIMELINE_LIMIT:]:
            involved = e.get("involvedObject") or e.get("regarding") or {}
            kind = str(involved.get("kind", ""))
            reason = str(e.get("reason", ""))
            timeline.append(
                {
                    "time": tables.event_time(e),
                    "kind": timeline_kind(kind, reason),
                    "object": f"{kind}/{involved.get('name', '')}",
                    "reason": reason,
                    "message": str(e.get("message") or e.get("note") or ""),
                    "warning": e.get("type") == "Warning",
                    "source": "event",
                }
            )
        self._rows = (rows, mission_docs, timeline)
        self._rows_version = self._cluster_version
        return self._rows

    def snapshot(self, *, read_only: bool, server: str) -> dict[str, Any]:
        """The document the browser renders (JSON-ready)."""
        wall = self._clock()
        with self._lock:
            rows, missions, timeline = self._cluster_rows(datetime.fromtimestamp(wall, UTC))
            samples = dict(self._samples)
            trails = {name: list(points) for name, points in self._trails.items()}
            live = dict(self._live_failovers)
            version = self.version
            error = self.cluster_error
            origin = self._origin
        vehicles = []
        names = [row.vehicle for row in rows]
        names += sorted(name for name in samples if name not in names)
        by_name = {row.vehicle: row for row in rows}
        for name in names:
            vehicles.append(_vehicle_doc(name, by_name.get(name), samples.get(name), wall))
            vehicles[-1]["trail"] = trails.get(name, [])
        live_entries = [
            {
                "time": record.get("time", ""),
                "kind": "failover",
                "object": f"Vehicle/{vehicle}",
                "reason": "FailedOver" if record.get("trigger") == "Automatic" else "Switched",
                "message": f"{record.get('from')} → {record.get('to')}: {record.get('reason', '')}"
                f" ({record.get('latencyMs', 0):.2f} ms)",
                "warning": True,
                "source": "agent",
            }
            for vehicle, record in live.items()
        ]
        merged = sorted(timeline + live_entries, key=lambda entry: str(entry["time"]))
        missions = [_with_fence(m, origin) for m in missions]
        return {
            "type": "state",
            "version": version,
            "now": wall,
            "server": server,
            "readOnly": read_only,
            "clusterError": error,
            "origin": None if origin is None else {"lat": origin.lat, "lon": origin.lon},
            "vehicles": vehicles,
            "missions": missions,
            "timeline": merged[-TIMELINE_LIMIT:],
        }


def fence_doc(fence: Mapping[str, Any], origin: Origin) -> dict[str, Any] | None:
    """A Mission's ``spec.fence`` in the arena's frame (metres north and east of
    ``origin``): ``{"polygon": [[n, e], ...]}`` or ``{"circle": [n, e, r]}``, with its
    altitude limit and breach action; None when it cannot be read."""
    try:
        doc: dict[str, Any] = {
            "maxAltitudeM": float(fence["maxAltitudeM"]),
            "action": str(fence.get("action", "Return")),
        }
        circle = fence.get("circle")
        if circle is not None:
            n, e = north_east_m(origin, float(circle["latitude"]), float(circle["longitude"]))
            doc["circle"] = [round(n, 2), round(e, 2), float(circle["radiusM"])]
        else:
            points = [
                north_east_m(origin, float(p["latitude"]), float(p["longitude"]))
                for p in fence.get("polygon") or []
            ]
            doc["polygon"] = [[round(n, 2), round(e, 2)] for n, e in points]
    except (KeyError, TypeError, ValueError):
        return None
    return doc


def _with_fence(mission: dict[str, Any], origin: Origin | None) -> dict[str, Any]:
    """The mission's document with its fence placed in the arena (unfinished Missions
    with a fence, once the arena has an origin), without its raw spec."""
    out = {k: v for k, v in mission.items() if k != "spec"}
    fence = (mission.get("spec") or {}).get("fence")
    finished = mission.get("phase") in {p.value for p in MissionPhase if p.finished}
    if fence and origin is not None and not finished:
        out["fence"] = fence_doc(fence, origin)
    return out


def _vehicle_doc(
    name: str, row: tables.FleetRow | None, sample: dict[str, Any] | None, wall: float
) -> dict[str, Any]:
    """One vehicle: its ``roost status`` row with the agent's live sample laid over it."""
    autopilots: list[dict[str, Any]] = (
        [
            {"name": c.name, "level": c.level, "active": c.active, "reason": c.reason}
            for c in row.autopilots
        ]
        if row
        else []
    )
    active = row.active if row else NONE
    age = None if sample is None else wall - float(sample.get("time", 0))
    fresh = sample is not None and age is not None and age <= TELEMETRY_STALE_S
    position = None
    if sample is not None and fresh:
        active = str(sample.get("active") or active)
        health: dict[str, str] = sample.get("health") or {}
        known = {a["name"] for a in autopilots}
        for cell in autopilots:
            if cell["name"] in health:
                cell["level"] = health[cell["name"]]
                if cell["level"] == HealthLevel.OK.value:
                    cell["reason"] = ""
            cell["active"] = cell["name"] == active
        autopilots += [
            {"name": n, "level": lvl, "active": n == active, "reason": ""}
            for n, lvl in health.items()
            if n not in known
        ]
        position = sample.get("position")
    altitude = None if position is None else -float(position["down"])
    return {
        "name": name,
        "node": row.node if row else NONE,
        "ready": row.ready if row else NONE,
        "readyReason": row.ready_reason if row else "",
        "active": active,
        "autopilots": autopilots,
        "worst": worst([str(a["level"]) for a in autopilots]),
        "mission": row.mission if row else NONE,
        "lastFailover": row.last_failover if row else NONE,
        "failoverDetail": row.failover_detail if row else "",
        "telemetry": "live" if fresh else ("stale" if sample is not None else "none"),
        "sampledAt": None if sample is None else sample.get("time"),
        "position": position,
        "altitude": altitude,
        "landed": None if altitude is None else altitude < LANDED_BELOW_M,
        "latched": bool(sample.get("latched")) if sample else False,
    }
