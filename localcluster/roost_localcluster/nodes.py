"""Fake vehicle nodes: Node objects that kwok keeps Ready and whose pods it runs.

A vehicle in Roost is a Kubernetes node (its companion computer). In the local cluster the node
is an ordinary Node object carrying kwok's annotation; kwok then plays its kubelet (status,
leases, pod phases). Everything else about the node (labels, annotations, allocatable
resources, taints) is whatever the test asks for, so the operator sees what it would see on
a real fleet.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from typing import Any

from roost_kube.client import Kube
from roost_kube.patches import Obj
from roost_kube.resources import NODES
from roost_localcluster.controlplane import KWOK_NODE_ANNOTATION, KWOK_NODE_ANNOTATION_VALUE

# Taints the node lifecycle controller keeps on a node until it is Ready and reachable.
_LIFECYCLE_TAINTS = frozenset({"node.kubernetes.io/not-ready", "node.kubernetes.io/unreachable"})


def fake_node(
    name: str,
    *,
    labels: Mapping[str, str] | None = None,
    annotations: Mapping[str, str] | None = None,
    cpu: str = "4",
    memory: str = "8Gi",
    pods: int = 110,
    taints: Iterable[Mapping[str, str]] = (),
) -> dict[str, Any]:
    """The manifest of a kwok-managed Node.

    ``labels`` and ``annotations`` are added to the usual node labels (hostname, os, arch)
    and kwok's annotation. ``cpu``/``memory``/``pods`` become both capacity and allocatable.
    ``taints`` are Kubernetes taint dicts (``key``, ``value``, ``effect``).
    """
    resources = {"cpu": cpu, "memory": memory, "pods": str(pods)}
    return {
        "apiVersion": "v1",
        "kind": "Node",
        "metadata": {
            "name": name,
            "labels": {
                "kubernetes.io/hostname": name,
                "kubernetes.io/os": "linux",
                "kubernetes.io/arch": "amd64",
                "type": "kwok",
                **(labels or {}),
            },
            "annotations": {
                KWOK_NODE_ANNOTATION: KWOK_NODE_ANNOTATION_VALUE,
                "node.alpha.kubernetes.io/ttl": "0",
                **(annotations or {}),
            },
        },
        "spec": {"taints": [dict(t) for t in taints]},
        "status": {"allocatable": resources, "capacity": resources},
    }


def node_is_ready(node: Obj) -> bool:
    """Ready=True and free of the lifecycle taints that would block scheduling."""
    conditions = (node.get("status") or {}).get("conditions") or []
    ready = any(c.get("type") == "Ready" and c.get("status") == "True" for c in conditions)
    taints = {t.get("key") for t in ((node.get("spec") or {}).get("taints") or [])}
    return ready and not taints & _LIFECYCLE_TAINTS


def wait_nodes_ready(kube: Kube, names: Iterable[str], timeout_s: float = 120.0) -> None:
    """Block until every named node is ready (see :func:`node_is_ready`)."""
    pending = set(names)
    deadline = time.monotonic() + timeout_s
    while pending:
        ready = {n["metadata"]["name"] for n in kube.list_objects(NODES) if node_is_ready(n)}
        pending -= ready
        if not pending:
            return
        if time.monotonic() > deadline:
            shown = ", ".join(sorted(pending)[:10])
            raise TimeoutError(f"{len(pending)} nodes not ready after {timeout_s:.0f} s: {shown}")
        time.sleep(0.5)
