"""Roost's own watch of Nodes: heartbeats are dropped before anything else sees them.

Why not a kopf handler: every node's kubelet (or KWOK) rewrites the Node's status every
few seconds, and kopf processes each of those events in full (its per-object worker,
cause detection, a deep copy for the diff base) before a handler can say "nothing I
read changed" — about 3 ms per event here, which at 1,000 nodes was most of the
operator's idle CPU. A :class:`~roost_operator.watches.Watcher` lists and watches
Nodes with Roost's own client, keeps a fingerprint of the part Roost reads
(:func:`node_relevant`: labels, annotations, taints, the Ready condition) and queues the
vehicles of a node only when that part changed (or the node appeared or went away).

Which vehicles a node concerns comes from kopf's index of Vehicles by node
(:class:`~roost_operator.vehicles.controller.Peers`) plus the vehicle the node is
labelled for. Before the first handler has bound that index there is nothing to queue:
every Vehicle is queued by its own first event anyway.

A fresh list after the watch lost its place (:mod:`roost_operator.watches`) is compared
against the fingerprints, so a change missed in between is still seen.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

from roost_api.wellknown import LABEL_VEHICLE
from roost_kube.client import Kube
from roost_kube.resources import NODES
from roost_operator.vehicles.controller import Peers
from roost_operator.watches import Fingerprints, Watcher


def node_relevant(body: Mapping[str, Any]) -> Any:
    """What Roost reads from a node: existence, labels, annotations, taints, Ready."""
    meta = body.get("metadata", {})
    ready = [
        (c.get("status"), c.get("reason"), c.get("message"))
        for c in (body.get("status") or {}).get("conditions") or []
        if c.get("type") == "Ready"
    ]
    return [
        meta.get("labels"),
        meta.get("annotations"),
        (body.get("spec") or {}).get("taints"),
        ready,
    ]


def vehicles_of(node: Mapping[str, Any], peers: Peers | None) -> set[str]:
    """The vehicles that claim ``node`` (by spec) or that it is labelled for."""
    name = node.get("metadata", {}).get("name", "")
    vehicles = {claim.vehicle for claim in peers.claims_on(name)} if peers else set()
    labelled = (node.get("metadata", {}).get("labels") or {}).get(LABEL_VEHICLE)
    if labelled:
        vehicles.add(labelled)
    return vehicles


class NodeFingerprints(Fingerprints):
    """Fingerprints of nodes by name; decides which watch events matter."""

    def changed_node(self, kind: str, node: Mapping[str, Any]) -> bool:
        """Whether this watch event (``ADDED``/``MODIFIED``/``DELETED``) changes anything
        Roost reads (and remember it)."""
        name = node.get("metadata", {}).get("name", "")
        if kind == "DELETED":
            return self.forget(name)
        return self.changed(name, node_relevant(node))

    def relist(self, nodes: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
        """After a fresh list: the nodes that changed or vanished meanwhile (a vanished
        one is returned as its last name only)."""
        present: set[str] = set()
        changed: list[Mapping[str, Any]] = []
        for node in nodes:
            present.add(node.get("metadata", {}).get("name", ""))
            if self.changed_node("MODIFIED", node):
                changed.append(node)
        for gone in self.keys() - present:
            self.forget(gone)
            changed.append({"metadata": {"name": gone}})
        return changed


def node_watcher(
    kube: Kube, peers: Callable[[], Peers | None], enqueue: Callable[[str], None]
) -> Watcher:
    """A :class:`~roost_operator.watches.Watcher` of Nodes that calls ``enqueue(vehicle)``
    for the vehicles of each node whose relevant part changed."""
    prints = NodeFingerprints()

    def queue(node: Mapping[str, Any]) -> None:
        for vehicle in sorted(vehicles_of(node, peers())):
            enqueue(vehicle)

    def on_event(kind: str, node: Mapping[str, Any]) -> None:
        if prints.changed_node(kind, node):
            queue(node)

    def on_list(nodes: list[Mapping[str, Any]]) -> None:
        for node in prints.relist(nodes):
            queue(node)

    return Watcher(kube, NODES, on_event, on_list)
