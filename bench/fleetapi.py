"""What the operator asks of the API server per Vehicle while a fleet rolls out.

The same rollout as ``python -m bench fleet`` (N Vehicles, default components, one KWOK
node each, the operator as its own process), on a control plane that writes an audit log
(:mod:`roost_localcluster.audit`): every request from the first ``kubectl apply`` until
every Vehicle is Ready, by client, verb and resource. The operator's requests are those
of its two clients: Roost's own (user agent ``roost-operator``: reconciles, watches,
Events) and kopf's (``kopf``: its watches, finalizer and annotation patches).

- ``fleet.operator_requests_per_vehicle_<N>``: the operator's requests (both clients)
  divided by N; the note has the breakdown, the other clients' totals and the load.

The audit log costs the API server CPU, so no time is measured here; the timings are
``python -m bench fleet``'s. Size: ``ROOST_BENCH_FLEET_API`` (default 200).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections import Counter
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

from bench.controlplane import FLEET_SETTINGS
from bench.core import Figure
from bench.fleet import (
    NAMESPACE,
    READY_TIMEOUT_S,
    _apply_streams,
    _create_nodes,
    _ready_count,
    vehicle_manifest,
    vehicle_name,
)
from roost_kube.client import Kube
from roost_localcluster import binaries
from roost_localcluster.audit import AUDIT_LOG, RequestKind, count_requests
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

COMMAND = "python -m bench fleetapi"
SIZE = int(os.environ.get("ROOST_BENCH_FLEET_API", "200"))
OPERATOR_CLIENTS = ("roost-operator", "kopf")
AUDIT_FLUSH_S = 3.0
"""The audit log is written in batches: wait this long after Ready before reading it."""


def _stamp() -> str:
    """Now as the audit log writes times (RFC 3339, microseconds, UTC)."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def rollout_requests(count: int) -> Counter[RequestKind]:
    """Every request from applying ``count`` Vehicles until all are Ready."""
    settings = replace(FLEET_SETTINGS, audit=True)
    with (
        tempfile.TemporaryDirectory(prefix="bench-fleetapi-") as tmp,
        ControlPlane(Path(tmp), settings=settings) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        _create_nodes(cluster, [(f"{vehicle_name(i)}-node", {}) for i in range(count)])
        operator = OperatorProcess(cluster, Path(tmp) / "operator.log", namespace=NAMESPACE)
        operator.start()
        try:
            with cluster.api_client() as api:
                kube = Kube(api, "roost-bench")
                since = _stamp()
                _apply_streams(cluster, [json.dumps(vehicle_manifest(i)) for i in range(count)])
                wait_until(
                    f"{count} Vehicles Ready",
                    lambda: _ready_count(kube) >= count,
                    READY_TIMEOUT_S,
                    poll_s=1.0,
                )
                until = _stamp()
                time.sleep(AUDIT_FLUSH_S)
        finally:
            operator.stop()
        return count_requests(plane.logs_dir / AUDIT_LOG, since=since, until=until)


def table(counted: Counter[RequestKind], count: int) -> str:
    """The operator's requests per Vehicle, as Markdown rows (client, verb, resource)."""
    rows = ["| client | verb | resource | per Vehicle |", "|---|---|---|---|"]
    for kind, n in sorted(counted.items()):
        if kind.client in OPERATOR_CLIENTS:
            error = f" ({kind.error})" if kind.error else ""
            rows.append(
                f"| {kind.client} | {kind.verb}{error} | {kind.resource} | {n / count:.2f} |"
            )
    return "\n".join(rows)


def run() -> list[Figure]:
    binaries.ensure_built()
    counted = rollout_requests(SIZE)
    load = os.getloadavg()[0]
    print(table(counted, SIZE), flush=True)
    by_client: Counter[str] = Counter()
    for kind, n in counted.items():
        by_client[kind.client] += n
    ours = sum(n for kind, n in counted.items() if kind.client in OPERATOR_CLIENTS)
    mine = "; ".join(
        f"{kind.client} {kind.verb}{'(' + kind.error + ')' if kind.error else ''} "
        f"{kind.resource} {n / SIZE:.2f}"
        for kind, n in sorted(counted.items())
        if kind.client in OPERATOR_CLIENTS
    )
    others = ", ".join(f"{client} {n}" for client, n in by_client.most_common())
    return [
        Figure(
            f"fleet.operator_requests_per_vehicle_{SIZE}",
            round(ours / SIZE, 2),
            "requests",
            "informational",
            COMMAND,
            f"{SIZE} Vehicles applied until all Ready, counted in the API server's audit "
            f"log; per Vehicle: {mine}. All clients' requests in the window: {others}; "
            f"1-min load average {load:.1f}",
        )
    ]
