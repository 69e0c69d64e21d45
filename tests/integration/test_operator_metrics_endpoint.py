"""The operator's Prometheus endpoint, scraped from a real ``roost-operator`` process.

The operator runs on the real control plane with ``ROOST_OPERATOR_METRICS_PORT`` set;
the test applies a Vehicle on a kwok node and a Mission and scrapes ``/metrics`` over
HTTP, parsed with prometheus_client's own parser: the Vehicle reconciles were timed, the
API calls counted, and the fleet gauges count the objects the API holds.
"""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Callable
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from roost_api.ports import free_port
from roost_kube.client import Kube
from roost_kube.resources import VEHICLES
from roost_localcluster.cluster import Cluster
from tests.support.operator import OperatorProcess
from tests.support.waiting import unique, wait_until

pytestmark = pytest.mark.cluster

NAMESPACE = "roost-it-metrics"
OPERATOR_NAMESPACE = NAMESPACE
METRICS_PORT = free_port()
OPERATOR_ENV = {
    "ROOST_OPERATOR_METRICS_PORT": str(METRICS_PORT),
    "ROOST_OPERATOR_METRICS_ADDRESS": "127.0.0.1",
}
Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def scrape() -> Samples:
    url = f"http://127.0.0.1:{METRICS_PORT}/metrics"
    with urllib.request.urlopen(url, timeout=10) as response:
        text = response.read().decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def total(samples: Samples, name: str, **labels: str) -> float:
    return sum(
        v
        for (n, pairs), v in samples.items()
        if n == name and all(dict(pairs).get(k) == want for k, want in labels.items())
    )


def test_scraped_operator_times_reconciles_counts_api_calls_and_the_fleet(
    roost_crds: Cluster,
    operator: OperatorProcess,
    kube: Kube,
    fake_nodes: Callable[..., dict[str, Any]],
) -> None:
    node = unique("metrics-node")
    fake_nodes(node)
    name = unique("metrics-v")
    manifest = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": name},
        "spec": {"nodeName": node, "sysid": 42},
    }
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
    try:

        def bound() -> bool:
            status = (kube.get(VEHICLES, name) or {}).get("status") or {}
            return any(
                c["type"] == "NodeBound" and c["status"] == "True"
                for c in status.get("conditions", [])
            )

        wait_until(f"Vehicle {name} NodeBound", bound, 60)
        got = scrape()
        duration = "roost_operator_reconcile_duration_seconds_count"
        assert total(got, duration, resource="vehicles") >= 1
        assert total(got, "roost_operator_api_requests_total", verb="get", result="200") >= 1
        assert total(got, "roost_operator_api_requests_total", verb="patch") >= 1
        assert total(got, "roost_operator_api_request_duration_seconds_count", verb="get") >= 1
        vehicles = got[("roost_operator_vehicles", ())]
        assert vehicles >= 1  # the session cluster may hold other modules' Vehicles
        bound_true = got[
            ("roost_operator_vehicle_conditions", (("condition", "NodeBound"), ("status", "True")))
        ]
        assert 1 <= bound_true <= vehicles
        claims = sum(
            got[("roost_operator_vehicle_claims", (("state", s),))]
            for s in ("claimed", "unclaimed")
        )
        assert claims == vehicles
        assert ("roost_operator_missions", (("phase", "Running"),)) in got
        assert ("roost_operator_vehicle_failover_guard", (("guard", "Latched"),)) in got
    finally:
        roost_crds.kubectl("delete", "vehicle", name, "--ignore-not-found", "--wait=false")
        wait_until(f"Vehicle {name} gone", lambda: kube.get(VEHICLES, name) is None, 60)
