"""Count write requests the API server has served, from its own ``/metrics``.

A controller that claims "a reconcile that changes nothing writes nothing" is checked
here from the server's side: ``apiserver_request_total`` counts every request by verb,
resource and subresource, including writes that changed nothing (a no-op PATCH still
costs the server a request). Comparing resourceVersions would miss those.

The counters are cluster-wide and include every client, so measure over a window in
which the test itself writes nothing, and choose ``targets`` that other components do
not write while idle (kwok heartbeats go to ``nodes/status``, leases to ``leases``).

Where other components may write the same targets at any time (the scheduler's Events
for a Pending pod of an earlier test, the node lifecycle controller's taints), count the
operator's own writes from the audit log instead (:func:`operator_writes`), which names
the client of every request.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable

from roost_kube.resources import CONFIGMAPS, EVENTS, NODES, PODS, VEHICLES
from roost_localcluster.audit import (
    OPERATOR_CLIENTS,
    RequestKind,
    Window,
)
from roost_localcluster.audit import (
    WRITE_VERBS as AUDIT_WRITE_VERBS,
)
from roost_localcluster.cluster import Cluster

WRITE_VERBS = frozenset({"POST", "PUT", "PATCH", "APPLY", "DELETE", "DELETECOLLECTION"})

_SAMPLE = re.compile(r"^apiserver_request_total\{(?P<labels>[^}]*)\}\s+(?P<value>\S+)$")
_LABEL = re.compile(r'(\w+)="((?:[^"\\]|\\.)*)"')

# (resource, subresource) pairs; subresource "" is the object itself.
Target = tuple[str, str]

# What Roost's operator writes for Vehicles. Nothing else writes these while a vehicle is
# idle: kwok's node heartbeats go to nodes/status, leader election to leases, and the
# kubelet (kwok) writes pods/status, never the pod itself.
VEHICLE_WRITE_TARGETS: tuple[Target, ...] = (
    (VEHICLES.plural, ""),
    (VEHICLES.plural, "status"),
    (NODES.plural, ""),
    (CONFIGMAPS.plural, ""),
    (PODS.plural, ""),
    (EVENTS.plural, ""),
)


def write_counts(metrics_text: str) -> Counter[Target]:
    """Write requests per (resource, subresource) in a Prometheus text exposition."""
    counts: Counter[Target] = Counter()
    for line in metrics_text.splitlines():
        match = _SAMPLE.match(line)
        if match is None:
            continue
        labels = dict(_LABEL.findall(match["labels"]))
        if labels.get("verb") not in WRITE_VERBS:
            continue
        key = (labels.get("resource", ""), labels.get("subresource", ""))
        counts[key] += int(float(match["value"]))
    return counts


def write_requests(cluster: Cluster, targets: Iterable[Target]) -> int:
    """Write requests served so far to ``targets`` (a counter: diff two readings)."""
    counts = write_counts(cluster.kubectl("get", "--raw", "/metrics").stdout)
    return sum(counts[target] for target in set(targets))


def operator_writes(cluster: Cluster, window: Window) -> Counter[RequestKind]:
    """Close ``window`` (from ``cluster.audit_window()``) and return the writes Roost's
    operator made in it, by kind."""
    return Counter(
        {
            kind: n
            for kind, n in cluster.audited(window).items()
            if kind.client in OPERATOR_CLIENTS and kind.verb in AUDIT_WRITE_VERBS
        }
    )
