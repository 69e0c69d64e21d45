"""kopf handlers for Vehicles: every trigger funnels into one level-based reconcile.

Triggers, and why each exists:

* the Vehicle itself (resume on operator start, create, update) — kopf retries these
  with a short backoff when a reconcile fails;
* a periodic resync (``ROOST_RESYNC_SECONDS``) — puts back hand edits and converges
  after anything missed; it writes nothing when nothing differs;
* its node (watch all Nodes) — a node appearing, turning Ready/NotReady or losing a
  Roost label re-reconciles the vehicles that claim it or that it is labelled for; node
  heartbeats that change nothing Roost looks at are filtered out by a fingerprint;
* its component Deployments — rollout progress updates ComponentsReady;
* its RedundantAutopilot — a new active autopilot re-points mavros (only the fields that
  matter are fingerprinted; the agent's periodic status reports are ignored).

Deletion goes through the Roost finalizer (``roost.dev/cleanup``, set in
:mod:`roost_operator.main`): labels, taint, config and workloads are removed before the
Vehicle disappears; other Vehicles waiting for the freed node are reconciled next.

Two kopf indexes answer "who claims this node" and "which RedundantAutopilot flies this
vehicle" from memory, without listing the API on every reconcile. Other handler
modules that need to reconcile a Vehicle call :func:`reconcile_now` with their
``**kwargs`` (kopf passes every index to every handler).
"""

from __future__ import annotations

import threading
from collections.abc import Hashable, Mapping
from typing import Any, Final

import kopf

from roost_api.wellknown import LABEL_COMPONENT, LABEL_MANAGED_BY, LABEL_VEHICLE, MANAGED_BY
from roost_kube import resources
from roost_kube.patches import content_hash
from roost_operator.runtime import runtime
from roost_operator.settings import SETTINGS
from roost_operator.vehicles.placement import NodeClaim
from roost_operator.vehicles.reconcile import Peers, reconcile_vehicle, release_vehicle

VEHICLES: Final = resources.VEHICLES.kopf
AUTOPILOTS: Final = resources.REDUNDANT_AUTOPILOTS.kopf
RETRY_BACKOFF_S: Final = 2.0

NodeClaims = kopf.Index[str, NodeClaim]
AutopilotsByVehicle = kopf.Index[str, str]


@kopf.index(*VEHICLES)
def vehicle_node_claims(
    *, name: str, spec: kopf.Spec, meta: kopf.Meta, **_: Any
) -> dict[str, NodeClaim]:
    """node name → the Vehicles naming it (a Vehicle being deleted claims nothing)."""
    if meta.get("deletionTimestamp") or not spec.get("nodeName"):
        return {}
    return {spec["nodeName"]: NodeClaim(name, str(meta["creationTimestamp"]))}


@kopf.index(*AUTOPILOTS)
def autopilots_by_vehicle(*, name: str, spec: kopf.Spec, **_: Any) -> dict[str, str]:
    """vehicle name → its RedundantAutopilot's name."""
    vehicle = spec.get("vehicleName")
    return {vehicle: name} if vehicle else {}


def peers_from(claims: NodeClaims, autopilots: AutopilotsByVehicle) -> Peers:
    """The :class:`Peers` view of the two indexes."""
    return Peers(
        claims_on=lambda node: list(claims.get(node, [])),
        autopilots_of=lambda vehicle: next(iter(autopilots.get(vehicle, [])), None),
    )


def reconcile_now(memo: Any, vehicle: str, indexes: Mapping[str, Any]) -> None:
    """Reconcile one Vehicle from any handler (it may not exist: then nothing happens).

    ``indexes`` is the calling handler's ``**kwargs``: kopf passes every index there, so
    any handler in the operator can call this.
    """
    rt = runtime(memo)
    peers = peers_from(indexes["vehicle_node_claims"], indexes["autopilots_by_vehicle"])
    reconcile_vehicle(rt.kube, rt.settings.namespace, vehicle, peers)


class Fingerprints:
    """Remembers a digest per object to skip events that change nothing relevant."""

    def __init__(self) -> None:
        self._seen: dict[Hashable, str] = {}
        self._lock = threading.Lock()

    def changed(self, key: Hashable, relevant: Any) -> bool:
        digest = content_hash(relevant)
        with self._lock:
            if self._seen.get(key) == digest:
                return False
            self._seen[key] = digest
            return True

    def forget(self, key: Hashable) -> None:
        with self._lock:
            self._seen.pop(key, None)


_node_prints = Fingerprints()
_autopilot_prints = Fingerprints()


@kopf.on.resume(*VEHICLES, backoff=RETRY_BACKOFF_S)
@kopf.on.create(*VEHICLES, backoff=RETRY_BACKOFF_S)
@kopf.on.update(*VEHICLES, backoff=RETRY_BACKOFF_S)
def vehicle_changed(
    *,
    name: str,
    memo: Any,
    **indexes: Any,
) -> None:
    """The Vehicle was created or its spec/labels changed (or the operator started)."""
    reconcile_now(memo, name, indexes)


@kopf.timer(*VEHICLES, interval=SETTINGS.resync_seconds, initial_delay=SETTINGS.resync_seconds)
def vehicle_resync(
    *,
    name: str,
    memo: Any,
    **indexes: Any,
) -> None:
    """Periodic level-based resync (NFD practice: put hand edits back)."""
    reconcile_now(memo, name, indexes)


@kopf.on.delete(*VEHICLES, backoff=RETRY_BACKOFF_S)
def vehicle_deleted(
    *,
    name: str,
    spec: kopf.Spec,
    memo: Any,
    **indexes: Any,
) -> None:
    """Remove the vehicle's labels, taint, config and workloads; hand its node on."""
    rt = runtime(memo)
    release_vehicle(rt.kube, rt.settings.namespace, name)
    claims: NodeClaims = indexes["vehicle_node_claims"]
    for claim in claims.get(spec.get("nodeName", ""), []):
        if claim.vehicle != name:
            reconcile_now(memo, claim.vehicle, indexes)


def _node_relevant(body: Mapping[str, Any]) -> Any:
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


@kopf.on.event("", "v1", "nodes")
def node_event(
    *,
    type: str | None,
    name: str,
    body: kopf.Body,
    memo: Any,
    **indexes: Any,
) -> None:
    """A node changed: reconcile the vehicles that claim it or that it carries."""
    if type == "DELETED":
        _node_prints.forget(name)
    elif not _node_prints.changed(name, _node_relevant(body)):
        return
    claims: NodeClaims = indexes["vehicle_node_claims"]
    vehicles = {claim.vehicle for claim in claims.get(name, [])}
    labelled = body.get("metadata", {}).get("labels", {}).get(LABEL_VEHICLE)
    if labelled:
        vehicles.add(labelled)
    for vehicle in sorted(vehicles):
        reconcile_now(memo, vehicle, indexes)


@kopf.on.event(
    "apps",
    "v1",
    "deployments",
    labels={
        LABEL_MANAGED_BY: MANAGED_BY,
        LABEL_VEHICLE: kopf.PRESENT,
        LABEL_COMPONENT: kopf.PRESENT,
    },
)
def component_event(
    *,
    labels: kopf.Labels,
    memo: Any,
    **indexes: Any,
) -> None:
    """A component Deployment changed (rollout progress, deletion): update the vehicle."""
    reconcile_now(memo, labels[LABEL_VEHICLE], indexes)


@kopf.on.event(*AUTOPILOTS)
def autopilots_event(
    *,
    type: str | None,
    name: str,
    body: kopf.Body,
    memo: Any,
    **indexes: Any,
) -> None:
    """A RedundantAutopilot changed its autopilots, primary or active one."""
    spec = body.get("spec") or {}
    relevant = [type == "DELETED", spec, (body.get("status") or {}).get("activeAutopilot")]
    if not _autopilot_prints.changed(name, relevant):
        return
    if type == "DELETED":
        _autopilot_prints.forget(name)
    vehicle = spec.get("vehicleName")
    if vehicle:
        reconcile_now(memo, vehicle, indexes)
