"""Roost's own watches that queue Vehicle reconciles: Nodes, and what Roost made.

Why not kopf handlers: every node's kubelet (or KWOK) rewrites the Node's status every
few seconds, and a component pod's kubelet writes its status several times on its way to
Ready; kopf processes each of those events in full (its per-object worker, cause
detection) before a handler can say "nothing I read
changed" — at 1,000 vehicles most of the operator's CPU (``docs/scale.md``). A
:class:`~roost_operator.engine.watches.Watcher` lists and watches with Roost's own client
(owned objects with a server-side label selector, in the operator's namespace only),
keeps every object in a :class:`~roost_operator.engine.watches.Store` the controller reads
instead of the API server (:mod:`roost_operator.engine.cache`), and a :class:`VehicleTrigger`
queues the vehicles an object concerns only when the part Roost reads changed
(:func:`node_relevant`, :func:`owned_relevant`, :func:`pod_relevant`), it appeared, or
it went away. Component pods are selected by
:data:`~roost_operator.vehicles.manifests.COMPONENT_POD_SELECTOR`: a Mission's onboard Job
pods carry a vehicle's label too, and are not the vehicle controller's.

Which vehicles a node concerns comes from kopf's index of Vehicles by node
(:class:`~roost_operator.vehicles.observe.Peers`) plus the vehicle the node is
labelled for; an owned object concerns the vehicle in its ``roost.dev/vehicle`` label.
Before the first handler has bound the index there is nothing to queue: every Vehicle
is queued by its own first event anyway.

A fresh list after the watch lost its place is compared with the fingerprints, and what
vanished meanwhile comes back from the store's last version of it, so a change missed
in between is still seen.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any, Final

from roost_api.wellknown import LABEL_COMPONENT, LABEL_MANAGED_BY, LABEL_VEHICLE, MANAGED_BY
from roost_kube.client import Kube
from roost_kube.resources import CONFIGMAPS, NODES, PODS
from roost_operator.engine.watches import (
    Fingerprints,
    Store,
    Watcher,
    key_of,
    without_managed_fields,
)
from roost_operator.vehicles.manifests import COMPONENT_POD_SELECTOR
from roost_operator.vehicles.observe import Peers

OWNED_SELECTOR: Final = f"{LABEL_MANAGED_BY}={MANAGED_BY},{LABEL_VEHICLE},{LABEL_COMPONENT}"
"""The vehicle's ConfigMap the Vehicle controller made, selected by the API server."""

Relevant = Callable[[Mapping[str, Any]], Any]
Concerns = Callable[[Mapping[str, Any]], Iterable[str]]


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


def owned_relevant(body: Mapping[str, Any]) -> Any:
    """What the controller reads of a ConfigMap it made: its data, labels, annotations."""
    meta = body.get("metadata") or {}
    return [meta.get("labels"), meta.get("annotations"), body.get("data")]


def _ready(status: Mapping[str, Any]) -> Any:
    return [
        (c.get("status"), c.get("reason"))
        for c in status.get("conditions") or []
        if c.get("type") == "Ready"
    ]


def pod_relevant(body: Mapping[str, Any]) -> Any:
    """What the controller reads of a component pod: its labels and annotations (the
    hashes), whether it is being deleted, its phase and its Ready condition — not the
    timestamps, IPs and container details the kubelet rewrites on its way to Ready."""
    meta = body.get("metadata") or {}
    status = body.get("status") or {}
    return [
        meta.get("labels"),
        meta.get("annotations"),
        meta.get("deletionTimestamp"),
        status.get("phase"),
        _ready(status),
    ]


def pod_kept(pod: Mapping[str, Any]) -> Mapping[str, Any]:
    """What the pod store keeps of a component pod: its metadata and its status (phase,
    conditions, container states for the detail strings), not its spec."""
    return without_managed_fields(
        {k: pod[k] for k in ("apiVersion", "kind", "metadata", "status") if k in pod}
    )


def node_kept(node: Mapping[str, Any]) -> Mapping[str, Any]:
    """What the node store keeps of a node: what the controller reads (its metadata, its
    spec, its conditions), not its images, addresses or capacity."""
    status = node.get("status") or {}
    return {
        **without_managed_fields(
            {k: node[k] for k in ("apiVersion", "kind", "metadata", "spec") if k in node}
        ),
        "status": {"conditions": status.get("conditions") or []},
    }


def vehicles_of(node: Mapping[str, Any], peers: Peers | None) -> set[str]:
    """The vehicles that claim ``node`` (by spec) or that it is labelled for."""
    name = node.get("metadata", {}).get("name", "")
    vehicles = {claim.vehicle for claim in peers.claims_on(name)} if peers else set()
    labelled = (node.get("metadata", {}).get("labels") or {}).get(LABEL_VEHICLE)
    if labelled:
        vehicles.add(labelled)
    return vehicles


def labelled_vehicle(obj: Mapping[str, Any]) -> set[str]:
    """The vehicle an object Roost made belongs to (its ``roost.dev/vehicle`` label)."""
    vehicle = ((obj.get("metadata") or {}).get("labels") or {}).get(LABEL_VEHICLE)
    return {vehicle} if vehicle else set()


class VehicleTrigger:
    """Decides which watch events queue which vehicles: only a change of the
    ``relevant`` part of an object, its appearance or its disappearance — and not the
    echo of the controller's own write (the reconcile that wrote it used the answer)."""

    def __init__(
        self, relevant: Relevant, concerns: Concerns, enqueue: Callable[[str], None]
    ) -> None:
        self.relevant = relevant
        self.concerns = concerns
        self.enqueue = enqueue
        self.prints = Fingerprints()

    def on_event(self, kind: str, obj: Mapping[str, Any], news: bool = True) -> None:
        """One watch event (``ADDED``/``MODIFIED``/``DELETED``); ``news`` False: the
        store already had it from the controller's own write."""
        if kind == "DELETED":
            if self.prints.forget(key_of(obj)):
                self._queue(obj)
        elif self.prints.changed(key_of(obj), self.relevant(obj)) and news:
            self._queue(obj)

    def on_list(self, objects: list[Mapping[str, Any]], vanished: list[Mapping[str, Any]]) -> None:
        """A (re)list: what changed meanwhile, and what vanished (its last version)."""
        for obj in objects:
            self.on_event("MODIFIED", obj)
        for obj in vanished:
            self.on_event("DELETED", obj)

    def _queue(self, obj: Mapping[str, Any]) -> None:
        for vehicle in sorted(self.concerns(obj)):
            self.enqueue(vehicle)


def node_watcher(
    kube: Kube, peers: Callable[[], Peers | None], enqueue: Callable[[str], None], store: Store
) -> Watcher:
    """Nodes into ``store``; ``enqueue(vehicle)`` for the vehicles of each node whose
    relevant part changed."""
    trigger = VehicleTrigger(node_relevant, lambda node: vehicles_of(node, peers()), enqueue)
    return Watcher(kube, NODES, trigger.on_event, trigger.on_list, store=store)


def owned_watchers(
    kube: Kube, namespace: str, enqueue: Callable[[str], None], stores: Mapping[str, Store]
) -> list[Watcher]:
    """The vehicles' ConfigMaps and component Pods (``stores`` by kind) in ``namespace``."""
    return [
        Watcher(
            kube,
            resource,
            trigger.on_event,
            trigger.on_list,
            label_selector=selector,
            namespace=namespace,
            store=stores[resource.kind],
        )
        for resource, relevant, selector in (
            (CONFIGMAPS, owned_relevant, OWNED_SELECTOR),
            (PODS, pod_relevant, COMPONENT_POD_SELECTOR),
        )
        for trigger in [VehicleTrigger(relevant, labelled_vehicle, enqueue)]
    ]
