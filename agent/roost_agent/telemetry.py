"""The agent's live telemetry stream: a local WebSocket that pushes the vehicle's state.

Why a stream of its own (and not the RedundantAutopilot status): a dashboard wants the
vehicle's position and health ten times a second, and the API server must never carry
that — status is written on change and on a slow refresh, for controllers, not for eyes.
So each agent serves its own state, at most :data:`MAX_HZ` per second, to whoever
connects (``roost dashboard`` does), and nothing of it goes through the cluster.

Why it stays cheap:

* nothing runs per MAVLink message: the link's reader keeps a reference to the last
  GLOBAL_POSITION_INT it parsed anyway (:meth:`roost_agent.health.HealthTracker.fix`),
  and the sample is built only when it is sent — one sample per connected client per
  period, decoded from the active autopilot's last message;
* the server is the ``websockets`` library's threaded one (no event loop in the agent),
  compression off, one thread per client, at most :data:`MAX_CLIENTS` clients;
* this module imports ``websockets``, so :mod:`roost_agent.main` imports it only when the
  stream is enabled (``--telemetry``), as it does the metrics.

A sample (JSON, camelCase as the API):

``{"vehicle", "time" (Unix seconds when sampled), "seq", "active", "latched",
"health": {autopilot: level}, "position": {"north", "east", "down", "lat", "lon",
"heading", "age"} | null, "origin": {"lat", "lon"} | null, "lastFailover": {...} | null}``

``north/east/down`` are metres from the stream's origin: ``--telemetry-origin LAT,LON``
(a field's surveyed origin, shared by the fleet), else the first position the active
autopilot reported. ``lat/lon`` are sent too, so a dashboard can put vehicles whose
origins differ into one frame. ``?hz=N`` in the URL asks for a lower rate.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import parse_qs, urlsplit

from websockets.exceptions import ConnectionClosed
from websockets.sync.server import Server, ServerConnection, serve

from roost_api.telemetry import MAX_HZ, Origin, north_east_m

if TYPE_CHECKING:
    from roost_agent.health import Fix
    from roost_api.core import HealthLevel
    from roost_api.plain import FailoverRecord

log = logging.getLogger(__name__)

DEFAULT_ADDRESS = "127.0.0.1"
MAX_CLIENTS = 4


class Leveled(Protocol):
    @property
    def level(self) -> HealthLevel: ...


class FixSource(Protocol):
    def fix(self) -> Fix | None: ...


class TelemetryAgent(Protocol):
    """What the stream reads of :class:`roost_agent.agent.Agent`."""

    @property
    def active(self) -> str: ...

    @property
    def latched(self) -> bool: ...

    @property
    def vehicle_name(self) -> str: ...

    @property
    def last_failover(self) -> FailoverRecord | None: ...

    @property
    def links(self) -> Mapping[str, FixSource]: ...

    def assessments(self) -> Mapping[str, Leveled]: ...


class Sampler:
    """Builds one sample of the agent's state; called at the send rate, never per message."""

    def __init__(
        self,
        agent: TelemetryAgent,
        origin: Origin | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self._agent = agent
        self._origin = origin
        self._clock = clock
        self._wall_clock = wall_clock
        self._lock = threading.Lock()
        self._seq = 0
        self._failover: tuple[FailoverRecord | None, dict[str, Any] | None] = (None, None)

    def sample(self) -> dict[str, Any]:
        agent = self._agent
        active = agent.active
        link = agent.links.get(active)
        fix = link.fix() if link is not None else None
        with self._lock:
            self._seq += 1
            seq = self._seq
            if fix is not None and self._origin is None:
                self._origin = Origin(fix.lat_deg, fix.lon_deg)
            origin = self._origin
            record = agent.last_failover
            if record is not self._failover[0]:  # dumped once per failover, not per sample
                self._failover = (record, record.to_api() if record is not None else None)
            failover = self._failover[1]
        position = None
        if fix is not None and origin is not None:
            north, east = north_east_m(origin, fix.lat_deg, fix.lon_deg)
            position = {
                "north": round(north, 3),
                "east": round(east, 3),
                "down": round(-fix.altitude_m, 3),
                "lat": fix.lat_deg,
                "lon": fix.lon_deg,
                "heading": fix.heading_deg,
                "age": round(self._clock() - fix.at, 3),
            }
        return {
            "vehicle": agent.vehicle_name,
            "time": self._wall_clock(),
            "seq": seq,
            "active": active,
            "latched": agent.latched,
            "health": {name: a.level.value for name, a in agent.assessments().items()},
            "position": position,
            "origin": None if origin is None else {"lat": origin.lat, "lon": origin.lon},
            "lastFailover": failover,
        }


def requested_hz(path: str) -> float:
    """The rate a client asked for with ``?hz=`` (capped at :data:`MAX_HZ`)."""
    values = parse_qs(urlsplit(path).query).get("hz")
    try:
        hz = float(values[0]) if values else MAX_HZ
    except ValueError:
        hz = MAX_HZ
    return min(MAX_HZ, hz) if hz > 0 else MAX_HZ


class TelemetryServer:
    """The WebSocket endpoint on its own daemon thread (one more thread per client)."""

    def __init__(
        self,
        agent: TelemetryAgent,
        *,
        address: str = DEFAULT_ADDRESS,
        port: int = 0,
        origin: Origin | None = None,
    ) -> None:
        self.sampler = Sampler(agent, origin)
        self._stop = threading.Event()
        self._clients = threading.BoundedSemaphore(MAX_CLIENTS)
        self._server: Server = serve(
            self._serve_client, address, port, compression=None, max_size=4096
        )
        self.address = address
        self.port = int(self._server.socket.getsockname()[1])
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="telemetry", daemon=True
        )
        self._thread.start()

    @property
    def url(self) -> str:
        return f"ws://{self.address}:{self.port}/"

    def _serve_client(self, connection: ServerConnection) -> None:
        if not self._clients.acquire(blocking=False):
            connection.close(1013, f"at most {MAX_CLIENTS} telemetry clients")
            return
        try:
            period = 1.0 / requested_hz(connection.request.path if connection.request else "")
            next_at = time.monotonic()
            while not self._stop.is_set():
                connection.send(json.dumps(self.sampler.sample(), separators=(",", ":")))
                next_at += period
                delay = next_at - time.monotonic()
                if delay < 0:  # a slow client: skip the samples it missed, never burst
                    next_at, delay = time.monotonic(), 0.0
                if self._stop.wait(delay):
                    break
        except ConnectionClosed:
            pass
        finally:
            self._clients.release()

    def close(self) -> None:
        """Stop serving and close every client's connection."""
        self._stop.set()
        self._server.shutdown()
        self._thread.join(timeout=2)
