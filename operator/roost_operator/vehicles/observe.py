"""Everything one decision about a Vehicle reads, read in one place: :func:`observe`.

The Vehicle, its RedundantAutopilot, its node and every node labelled for it, the other
Vehicles naming the same node, its claim Lease, its ConfigMap, its live component Pods
and the clock. A Vehicle with a RedundantAutopilot (whose reconcile may act on a
failover) and the RedundantAutopilot are read fresh from the API; the rest comes from
watch caches that the controller's own writes update at once, and a retry after a
conflict (``fresh``) reads the Vehicle and its nodes fresh
(:class:`~roost_operator.engine.cache.CachedView` says why that is safe).

A Vehicle that does not exist, or is being deleted, is :class:`Gone`: asked of the API
server, never concluded from a cache.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from roost_api.autopilot import RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.meta import now
from roost_api.vehicle import VehicleSpec, VehicleStatus
from roost_api.wellknown import (
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_NODE,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_kube.patches import Obj, owner_reference
from roost_kube.resources import CONFIGMAPS, LEASES, NODES, PODS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_operator import claims
from roost_operator.engine.cache import CachedView
from roost_operator.vehicles.config import config_map_name
from roost_operator.vehicles.manifests import is_component_pod
from roost_operator.vehicles.placement import NodeClaim
from roost_operator.vehicles.plan import Context, Observed


@dataclass(frozen=True)
class Peers:
    """What other objects say about a vehicle (kopf indexes in the operator).

    ``claims_on(node)``: every Vehicle naming ``node`` in its spec.
    ``autopilots_of(vehicle)``: name of the vehicle's RedundantAutopilot, if any.
    ``actions``: vehicles with a failover action running, as the index last saw them.
    """

    claims_on: Callable[[str], Sequence[NodeClaim]]
    autopilots_of: Callable[[str], str | None]
    actions: Callable[[], Iterable[str]] = lambda: ()


@dataclass(frozen=True)
class Gone:
    """The Vehicle does not exist (``body`` None) or is being deleted."""

    body: Obj | None


def observe(
    cluster: CachedView,
    name: str,
    peers: Peers,
    context: Context,
    *,
    fresh: bool,
) -> Observed | Gone:
    """Read everything :func:`~.plan.plan_vehicle` decides on, for Vehicle ``name``.

    The failover actions on other vehicles are left at 0: the controller counts them
    under the lock it holds while it decides (the fleet's cap).
    """
    autopilots_name = peers.autopilots_of(name)
    if fresh or autopilots_name is not None:
        vehicle = cluster.fresh(VEHICLES, name)
    else:
        vehicle = cluster.get(VEHICLES, name)
    if vehicle is None or vehicle["metadata"].get("deletionTimestamp"):
        return Gone(vehicle)
    meta = vehicle["metadata"]
    spec = VehicleSpec.model_validate(vehicle["spec"])
    autopilot = cluster.kube.get(REDUNDANT_AUTOPILOTS, autopilots_name) if autopilots_name else None
    namespace = context.namespace
    claim = claims.claim_of(cluster.get(LEASES, claims.lease_name(name), namespace) or {})
    read_node = cluster.fresh if fresh else cluster.get
    labelled = cluster.list_objects(NODES, labels={LABEL_VEHICLE: name})
    if fresh:
        labelled = [cluster.fresh(NODES, n["metadata"]["name"]) or n for n in labelled]
    owned = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: name}
    pods = cluster.list_objects(PODS, namespace=namespace, labels=owned)
    return Observed(
        name=name,
        uid=meta.get("uid", ""),
        generation=meta.get("generation"),
        created=str(meta.get("creationTimestamp", "")),
        annotations=dict(meta.get("annotations") or {}),
        spec=spec,
        status=VehicleStatus.model_validate(vehicle.get("status") or {}),
        autopilot_spec=(
            RedundantAutopilotSpec.model_validate(autopilot["spec"]) if autopilot else None
        ),
        autopilot_status=(
            RedundantAutopilotStatus.model_validate(autopilot.get("status") or {})
            if autopilot
            else None
        ),
        node=read_node(NODES, spec.node_name),
        node_claims=[c for c in peers.claims_on(spec.node_name) if c.vehicle != name],
        claimed_by=claim.holder if claim else None,
        actions_elsewhere=0,
        now=now(),
        context=context,
        body=vehicle,
        owners=[owner_reference(vehicle)],
        autopilot_name=autopilots_name if autopilot is not None else None,
        autopilot_node_label=(
            (autopilot["metadata"].get("labels") or {}).get(LABEL_NODE) if autopilot else None
        ),
        labelled_nodes=labelled,
        pods={
            pod["metadata"]["labels"][LABEL_COMPONENT]: pod for pod in pods if is_component_pod(pod)
        },
        config_map=cluster.get(CONFIGMAPS, config_map_name(name), namespace),
    )
