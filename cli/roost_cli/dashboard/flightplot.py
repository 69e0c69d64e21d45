"""One flight of a Mission's record, turned into what the dashboard plots.

Parsed server-side, with pymavlink (the reader MAVProxy uses): a tlog is a binary
stream of MAVLink frames whose dialect, signing and framing pymavlink already knows,
and a 5-minute flight of two autopilots is tens of thousands of frames. The browser
gets a small JSON document instead (series thinned to :data:`MAX_POINTS` per
autopilot), draws it in SVG like the live arena, and needs no MAVLink parser of its
own. The decisions (``decisions.jsonl``) give the markers: health levels, failovers,
safety-routine steps.

Per autopilot means per MAVLink system id in the tlog (every autopilot's frames keep
their own); a ``params/<autopilot>.json`` naming the system id (``SYSID_THISMAV`` or
``MAV_SYS_ID``) gives the autopilot's name, else the plot says ``system N``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from roost_api.telemetry import Origin, north_east_m

MAX_POINTS = 1500
MARKER_EVENTS = {"Failover", "SafetyRoutine", "LandOrdered", "EmergencyStop", "NoHealthyStandby"}
SYSID_PARAMS = ("SYSID_THISMAV", "MAV_SYS_ID")


@dataclass
class Series:
    """One autopilot's traces (times in seconds since the flight's first frame)."""

    name: str
    t: list[float] = field(default_factory=list)
    alt: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    north: list[float] = field(default_factory=list)
    east: list[float] = field(default_factory=list)
    modes: list[tuple[float, str]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        step = max(1, math.ceil(len(self.t) / MAX_POINTS))
        return {
            "name": self.name,
            "t": [round(x, 2) for x in self.t[::step]],
            "alt": [round(x, 2) for x in self.alt[::step]],
            "speed": [round(x, 2) for x in self.speed[::step]],
            "north": [round(x, 2) for x in self.north[::step]],
            "east": [round(x, 2) for x in self.east[::step]],
            "modes": [{"t": round(t, 2), "mode": m} for t, m in self.modes],
        }


def autopilot_names(params: Mapping[str, Mapping[str, Any]]) -> dict[int, str]:
    """System id → autopilot name, from each autopilot's parameters at arming."""
    names = {}
    for autopilot, doc in params.items():
        values = doc.get("params", doc) if isinstance(doc, Mapping) else {}
        for key in SYSID_PARAMS:
            value = values.get(key) if isinstance(values, Mapping) else None
            if isinstance(value, (int, float)):
                names[int(value)] = autopilot
                break
    return names


def parse_tlog(
    path: Path, names: Mapping[int, str], origin: Origin | None
) -> tuple[float | None, list[Series]]:
    """(UNIX time of the first frame, one Series per autopilot system id)."""
    from pymavlink import mavutil  # noqa: PLC0415 - only when a flight is plotted

    log = mavutil.mavlink_connection(str(path), robust_parsing=True)
    series: dict[int, Series] = {}
    start: float | None = None
    home = origin
    try:
        while (msg := log.recv_match(type=["HEARTBEAT", "GLOBAL_POSITION_INT"])) is not None:
            system = msg.get_srcSystem()
            stamp = float(getattr(msg, "_timestamp", 0.0))
            if start is None:
                start = stamp
            t = stamp - start
            if msg.get_type() == "HEARTBEAT":
                if msg.type == mavutil.mavlink.MAV_TYPE_GCS or msg.autopilot == 8:
                    continue  # a ground station or a non-autopilot component
                one = series.setdefault(system, Series(names.get(system, f"system {system}")))
                mode = mavutil.mode_string_v10(msg)
                if not one.modes or one.modes[-1][1] != mode:
                    one.modes.append((t, mode))
                continue
            one = series.setdefault(system, Series(names.get(system, f"system {system}")))
            lat, lon = msg.lat / 1e7, msg.lon / 1e7
            if home is None:
                home = Origin(lat, lon)
            north, east = north_east_m(home, lat, lon)
            one.t.append(t)
            one.alt.append(msg.relative_alt / 1000)
            one.speed.append(math.hypot(msg.vx, msg.vy) / 100)
            one.north.append(north)
            one.east.append(east)
    finally:
        log.close()
    return start, [series[k] for k in sorted(series)]


def parse_decisions(text: str, start: float | None) -> tuple[list[dict[str, Any]], list[Any]]:
    """(health levels per autopilot over time, markers) from ``decisions.jsonl``."""
    health: list[dict[str, Any]] = []
    markers: list[dict[str, Any]] = []
    for line in text.splitlines():
        try:
            event = json.loads(line)
            when = datetime.fromisoformat(str(event["time"]).replace("Z", "+00:00")).timestamp()
        except (ValueError, KeyError, TypeError):
            continue  # a line cut by a power loss
        t = round(when - start, 2) if start is not None else 0.0
        kind = event.get("event")
        level = (event.get("health") or {}).get("level")
        if kind == "HealthChanged" and level:
            health.append({"t": t, "autopilot": event.get("autopilot"), "level": level})
        elif kind in MARKER_EVENTS:
            markers.append(
                {
                    "t": t,
                    "kind": kind,
                    "reason": event.get("reason"),
                    "message": event.get("message"),
                    "autopilot": event.get("autopilot"),
                }
            )
    return health, markers


def plot_document(
    tlog: Path | None,
    decisions: str,
    params: Mapping[str, Mapping[str, Any]],
    origin: Origin | None = None,
) -> dict[str, Any]:
    """The document ``records.js`` draws."""
    start, series = (
        (None, []) if tlog is None else parse_tlog(tlog, autopilot_names(params), origin)
    )
    health, markers = parse_decisions(decisions, start)
    return {
        "start": start,
        "autopilots": [s.to_json() for s in series],
        "health": health,
        "markers": markers,
    }
