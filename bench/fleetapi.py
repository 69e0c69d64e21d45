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

import os
from collections import Counter
from dataclasses import replace

from bench.controlplane import FLEET_SETTINGS
from bench.core import Figure
from bench.fleet import apply_until_ready, fleet_with_operator
from roost_localcluster import binaries
from roost_localcluster.audit import OPERATOR_CLIENTS, RequestKind

COMMAND = "python -m bench fleetapi"
SIZE = int(os.environ.get("ROOST_BENCH_FLEET_API", "200"))


def rollout_requests(count: int) -> Counter[RequestKind]:
    """Every request from applying ``count`` Vehicles until all are Ready."""
    settings = replace(FLEET_SETTINGS, audit=True)
    with (
        fleet_with_operator(count, settings, "bench-fleetapi-") as fleet,
        fleet.cluster.kube("roost-bench") as kube,
    ):
        window = fleet.cluster.audit_window()
        apply_until_ready(fleet.cluster, kube, count)
        return fleet.cluster.audited(window)


def _operator_counts(counted: Counter[RequestKind]) -> list[tuple[RequestKind, int]]:
    """The operator's clients' request kinds and counts, in order."""
    return [(kind, n) for kind, n in sorted(counted.items()) if kind.client in OPERATOR_CLIENTS]


def _verb(kind: RequestKind) -> str:
    """The verb, with the error code of a failed answer."""
    return f"{kind.verb} ({kind.error})" if kind.error else kind.verb


def table(counted: Counter[RequestKind], count: int) -> str:
    """The operator's requests per Vehicle, as Markdown rows (client, verb, resource)."""
    rows = ["| client | verb | resource | per Vehicle |", "|---|---|---|---|"]
    for kind, n in _operator_counts(counted):
        rows.append(f"| {kind.client} | {_verb(kind)} | {kind.resource} | {n / count:.2f} |")
    return "\n".join(rows)


def run() -> list[Figure]:
    binaries.ensure_built()
    counted = rollout_requests(SIZE)
    load = os.getloadavg()[0]
    print(table(counted, SIZE), flush=True)
    by_client: Counter[str] = Counter()
    for kind, n in counted.items():
        by_client[kind.client] += n
    operator = _operator_counts(counted)
    ours = sum(n for _, n in operator)
    mine = "; ".join(
        f"{kind.client} {_verb(kind)} {kind.resource} {n / SIZE:.2f}" for kind, n in operator
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
