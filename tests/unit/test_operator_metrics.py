"""The operator's metric pieces: the API request observer, fleet gauges, errors counted as
kopf makes of them.

The fleet gauges come from Vehicles and Missions shaped as the API returns them. Handler
timing through kopf-style sync and async handlers (an event loop) is in
``tests/integration/test_operator_metrics_handlers.py``; the scraped operator process in
``tests/integration/test_operator_metrics_endpoint.py``.
"""

from __future__ import annotations

from typing import Any

import kopf
import pytest
from prometheus_client import CollectorRegistry, generate_latest

from roost_kube.errors import error_for_status
from roost_operator.edge import handler_edge
from roost_operator.metrics import ApiRequests, Reconciles, fleet_families
from tests.support.kopfstub import Resource
from tests.support.prometheus import Samples, parse


def render(families: list[Any]) -> Samples:
    registry = CollectorRegistry()

    class Fixed:
        def collect(self) -> list[Any]:
            return families

    registry.register(Fixed())
    return parse(generate_latest(registry).decode())


def vehicle(conditions: dict[str, str], claimed: bool = False, **failover: Any) -> dict[str, Any]:
    status: dict[str, Any] = {
        "conditions": [{"type": t, "status": s} for t, s in conditions.items()],
        "failover": failover,
    }
    if claimed:
        status["claimedBy"] = {"name": "m1", "namespace": "default"}
    return {"metadata": {"name": "v"}, "status": status}


def test_fleet_gauges_count_conditions_claims_guards_and_phases() -> None:
    vehicles = [
        vehicle({"Ready": "True", "NodeBound": "True"}, claimed=True),
        vehicle({"Ready": "False", "NodeBound": "True"}, blocked="Latched", latched=True),
        {"metadata": {"name": "new"}},  # not reconciled yet: no status
    ]
    missions = [{"status": {"phase": "Running"}}, {"status": {"phase": "Running"}}, {}]
    got = render(fleet_families(vehicles, missions))
    assert got[("roost_operator_vehicles", ())] == 3
    conditions = "roost_operator_vehicle_conditions"
    assert got[(conditions, (("condition", "Ready"), ("status", "True")))] == 1
    assert got[(conditions, (("condition", "Ready"), ("status", "False")))] == 1
    assert got[(conditions, (("condition", "NodeBound"), ("status", "True")))] == 2
    assert got[("roost_operator_vehicle_claims", (("state", "claimed"),))] == 1
    assert got[("roost_operator_vehicle_claims", (("state", "unclaimed"),))] == 2
    guard = "roost_operator_vehicle_failover_guard"
    assert got[(guard, (("guard", "Latched"),))] == 1
    assert got[(guard, (("guard", "None"),))] == 2
    assert got[(guard, (("guard", "ConcurrencyLimit"),))] == 0
    assert got[("roost_operator_vehicles_failover_latched", ())] == 1
    assert got[("roost_operator_missions", (("phase", "Running"),))] == 2
    assert got[("roost_operator_missions", (("phase", "None"),))] == 1
    assert got[("roost_operator_missions", (("phase", "Aborted"),))] == 0


def test_an_api_error_is_counted_as_what_kopf_makes_of_it() -> None:
    registry = CollectorRegistry()
    memo = kopf.Memo(handler_timing=Reconciles(registry))

    @handler_edge
    def vehicle_changed(**_: Any) -> None:
        raise error_for_status(422, "PATCH", "/vehicles/x", "{}")

    with pytest.raises(kopf.PermanentError):
        vehicle_changed(memo=memo, resource=Resource("vehicles"), name="x")
    got = parse(generate_latest(registry).decode())
    key = (("error", "permanent"), ("handler", "vehicle_changed"), ("resource", "vehicles"))
    assert got[("roost_operator_reconcile_errors_total", key)] == 1


def test_api_requests_by_verb_and_result() -> None:
    registry = CollectorRegistry()
    api = ApiRequests(registry)
    api.observe("GET", "200", 0.002)
    api.observe("PATCH", "409", 0.004)
    api.observe("GET", "unavailable", 5.0)
    got = parse(generate_latest(registry).decode())
    assert got[("roost_operator_api_requests_total", (("result", "200"), ("verb", "get")))] == 1
    assert got[("roost_operator_api_requests_total", (("result", "409"), ("verb", "patch")))] == 1
    bucket = "roost_operator_api_request_duration_seconds_bucket"
    assert got[(bucket, (("le", "0.0025"), ("verb", "get")))] == 1
    assert got[(bucket, (("le", "+Inf"), ("verb", "get")))] == 2
