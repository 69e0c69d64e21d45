"""Prometheus metrics of the operator: reconciles, API calls and the fleet as the API sees it.

Three sources, none of which needs a change in a handler:

* **reconciles** — every handler runs inside :func:`roost_operator.edge.handler_edge`,
  which reports each run to :class:`Reconciles` (the memo's ``handler_timing``):
  duration by resource and handler, and failures by kind of error.
* **API calls** — :func:`roost_kube.client.observe_requests` reports every request of
  the shared client (method, status, seconds); watches are not counted.
* **the fleet** — :class:`FleetCollector` lists Vehicles and Missions at scrape time
  (two API reads per scrape) and counts them by condition, phase, claim and failover
  guard, so the numbers are what the API says, not what one handler last saw.

kopf serves its own liveness endpoint; these metrics are on a separate port
(``--metrics-port``). Labels are bounded by code and by the API's enums: resource
plural, handler id, condition type and status, phase, guard, HTTP method and status —
never object names or UIDs. docs/metrics.md lists every metric.
"""

from __future__ import annotations

import logging
from collections import Counter as Tally
from collections.abc import Iterable
from typing import Any

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Histogram,
    ProcessCollector,
    start_http_server,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from roost_api.mission import MissionPhase
from roost_api.vehicle import FailoverGuard
from roost_kube.client import Kube, observe_requests
from roost_kube.errors import ApiError
from roost_kube.resources import MISSIONS, VEHICLES

log = logging.getLogger(__name__)

PREFIX = "roost_operator"
DEFAULT_PORT = 9466
RECONCILE_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
API_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0)


class Reconciles:
    """Duration and failures of every kopf resource handler."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.duration = Histogram(
            f"{PREFIX}_reconcile_duration_seconds",
            "Time one handler run took, by resource plural and handler id.",
            ["resource", "handler"],
            buckets=RECONCILE_BUCKETS,
            registry=registry,
        )
        self.errors = Counter(
            f"{PREFIX}_reconcile_errors",
            "Handler runs that raised, by resource, handler and error "
            "(temporary: kopf retries; permanent: kopf gives up; other: a bug or API error).",
            ["resource", "handler", "error"],
            registry=registry,
        )

    def observe(self, resource: str, handler: str, seconds: float, error: str | None) -> None:
        """One handler run (the :class:`roost_operator.edge.HandlerTiming` protocol)."""
        self.duration.labels(resource, handler).observe(seconds)
        if error is not None:
            self.errors.labels(resource, handler, error).inc()


class ApiRequests:
    """API calls of the shared client by method and result (fed by ``observe_requests``)."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.requests = Counter(
            f"{PREFIX}_api_requests",
            "API server requests by HTTP method and result (status code, or unavailable).",
            ["verb", "result"],
            registry=registry,
        )
        self.duration = Histogram(
            f"{PREFIX}_api_request_duration_seconds",
            "API server request latency by HTTP method.",
            ["verb"],
            buckets=API_BUCKETS,
            registry=registry,
        )

    def observe(self, method: str, result: str, seconds: float) -> None:
        verb = method.lower()
        self.requests.labels(verb, result).inc()
        self.duration.labels(verb).observe(seconds)


def _tally_vehicles(vehicles: Iterable[dict[str, Any]]) -> dict[str, Tally[Any]]:
    conditions: Tally[tuple[str, str]] = Tally()
    claims: Tally[str] = Tally()
    guards: Tally[str] = Tally()
    latched: Tally[str] = Tally()
    for vehicle in vehicles:
        status = vehicle.get("status") or {}
        for condition in status.get("conditions") or []:
            conditions[(str(condition.get("type")), str(condition.get("status")))] += 1
        claims["claimed" if status.get("claimedBy") else "unclaimed"] += 1
        failover = status.get("failover") or {}
        guards[str(failover.get("blocked") or "None")] += 1
        latched["latched" if failover.get("latched") else "unlatched"] += 1
    return {"conditions": conditions, "claims": claims, "guards": guards, "latched": latched}


def fleet_families(
    vehicles: list[dict[str, Any]], missions: list[dict[str, Any]]
) -> list[GaugeMetricFamily]:
    """The fleet's gauges from listed Vehicles and Missions (pure: no API calls)."""
    tally = _tally_vehicles(vehicles)
    total = GaugeMetricFamily(f"{PREFIX}_vehicles", "Vehicle objects.", value=len(vehicles))
    conditions = GaugeMetricFamily(
        f"{PREFIX}_vehicle_conditions",
        "Vehicles by condition type and status (True, False, Unknown).",
        labels=["condition", "status"],
    )
    for (kind, status), count in sorted(tally["conditions"].items()):
        conditions.add_metric([kind, status], count)
    claims = GaugeMetricFamily(
        f"{PREFIX}_vehicle_claims",
        "Vehicles claimed by a Mission (status.claimedBy) and unclaimed.",
        labels=["state"],
    )
    for state in ("claimed", "unclaimed"):
        claims.add_metric([state], tally["claims"][state])
    guards = GaugeMetricFamily(
        f"{PREFIX}_vehicle_failover_guard",
        "Vehicles by the guard holding back a cluster-side failover action "
        "(None: nothing held back).",
        labels=["guard"],
    )
    for guard in ["None", *(g.value for g in FailoverGuard if g != FailoverGuard.ALLOWED)]:
        guards.add_metric([guard], tally["guards"][guard])
    latched = GaugeMetricFamily(
        f"{PREFIX}_vehicles_failover_latched",
        "Vehicles whose failover latch is set (cluster-side actions wait for a human).",
        value=tally["latched"]["latched"],
    )
    phases: Tally[str] = Tally(
        str((m.get("status") or {}).get("phase") or "None") for m in missions
    )
    by_phase = GaugeMetricFamily(
        f"{PREFIX}_missions",
        "Missions by phase (None: not yet reconciled).",
        labels=["phase"],
    )
    for phase in ["None", *(p.value for p in MissionPhase)]:
        by_phase.add_metric([phase], phases[phase])
    return [total, conditions, claims, guards, latched, by_phase]


class FleetCollector(Collector):
    """Lists Vehicles and Missions at scrape time; nothing is exported when the API fails."""

    def __init__(self, kube: Kube) -> None:
        self._kube = kube

    def collect(self) -> Iterable[GaugeMetricFamily]:
        try:
            vehicles = self._kube.list_objects(VEHICLES)
            missions = self._kube.list_objects(MISSIONS)
        except ApiError as exc:
            log.warning("metrics: cannot list the fleet (%s)", exc)
            return []
        return fleet_families(vehicles, missions)


class OperatorMetrics:
    """The operator's registry and its HTTP endpoint."""

    def __init__(self, kube: Kube) -> None:
        self.registry = CollectorRegistry(auto_describe=False)
        ProcessCollector(registry=self.registry)
        self.reconciles = Reconciles(self.registry)
        self.api = ApiRequests(self.registry)
        self.registry.register(FleetCollector(kube))
        self._unobserve = observe_requests(self.api.observe)
        self._server: Any = None

    def serve(self, address: str, port: int) -> int:
        """Start the endpoint on its own daemon thread; returns the bound port."""
        self._server, _ = start_http_server(port, address, self.registry)
        return int(self._server.server_address[1])

    def close(self) -> None:
        self._unobserve()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
