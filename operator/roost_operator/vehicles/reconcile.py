"""The level-based Vehicle reconcile: read everything, compare, write only differences.

Every kopf handler that concerns a Vehicle (its own events, its node's, its component
Deployments', its RedundantAutopilot's, the periodic resync) ends up in
:func:`reconcile_vehicle`, so there is exactly one path from "what the cluster looks
like" to "what it should look like". It does not import kopf: it is plain code over
:class:`~roost_kube.client.Kube`, callable from any handler (the autopilot handlers
call it when the active autopilot changes) and from tests.

Why it is safe to run at any time, any number of times, and to be killed half-way:

* every step computes the full desired state from what it has just read and writes
  only where that differs (node patch planned by
  :func:`~roost_operator.vehicles.placement.plan_node`, objects through
  :meth:`~roost_kube.client.Kube.apply`, status compared before patching);
* nodes are found by the vehicle label, not by what the last run remembered, so a
  crash between "label new node" and "release old node" is repaired by the next run;
* writes that replace lists (node taints, status conditions) carry the
  ``resourceVersion`` they were computed from; a concurrent writer causes a retry from
  a fresh read, never a lost update;
* one lock per vehicle serialises reconciles of the same vehicle within the process
  (kopf runs handlers for different objects concurrently).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.meta import Stack
from roost_api.vehicle import VehicleSpec, VehicleStatus
from roost_api.wellknown import LABEL_COMPONENT, LABEL_MANAGED_BY, LABEL_VEHICLE, MANAGED_BY
from roost_kube.client import Kube
from roost_kube.errors import ApiError, ConflictError
from roost_kube.patches import Obj, owner_reference
from roost_kube.resources import CONFIGMAPS, DEPLOYMENTS, NODES, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_operator.vehicles.config import vehicle_config, vehicle_config_map
from roost_operator.vehicles.desired import (
    DEFAULT_FCU_URL,
    EVENT_CONDITIONS,
    ComponentState,
    NodeBinding,
    active_autopilot,
    autopilots_of,
    component_workloads,
    components_condition,
    deployment,
    deployment_state,
    vehicle_conditions,
)
from roost_operator.vehicles.placement import (
    NodeClaim,
    NodeState,
    claim_winner,
    managed_label_keys,
    node_readiness,
    plan_node,
    vehicle_name_problem,
)
from roost_operator.vehicles.status import write_vehicle_status

log = logging.getLogger(__name__)

CONFLICT_RETRIES: Final = 5
# The Vehicle status fields this reconcile owns (see roost_operator.vehicles.status).
STATUS_FIELDS: Final = ("observedGeneration", "conditions", "nodeName", "managedLabels", "fcuUrl")


@dataclass(frozen=True)
class Peers:
    """What other objects say about a vehicle (kopf indexes in the operator).

    ``claims_on(node)``: every Vehicle naming ``node`` in its spec.
    ``autopilots_of(vehicle)``: name of the vehicle's RedundantAutopilot, if any.
    """

    claims_on: Callable[[str], Sequence[NodeClaim]]
    autopilots_of: Callable[[str], str | None]


_locks: dict[str, threading.Lock] = {}
_locks_guard = threading.Lock()


def _vehicle_lock(name: str) -> threading.Lock:
    with _locks_guard:
        return _locks.setdefault(name, threading.Lock())


def reconcile_vehicle(kube: Kube, namespace: str, name: str, peers: Peers) -> None:
    """Converge everything Roost owns for Vehicle ``name``; a no-op when it is gone."""
    with _vehicle_lock(name):
        for attempt in range(CONFLICT_RETRIES):
            try:
                _reconcile_once(kube, namespace, name, peers)
                return
            except ConflictError:
                if attempt == CONFLICT_RETRIES - 1:
                    raise
                log.info("vehicle %s: concurrent write, reconciling again", name)


def release_vehicle(kube: Kube, namespace: str, name: str) -> None:
    """Remove everything Roost made for Vehicle ``name`` (labels, taint, config, workloads)."""
    with _vehicle_lock(name):
        for node in kube.list_objects(NODES, labels={LABEL_VEHICLE: name}):
            _converge_node(kube, node, NodeState.released())
        owned = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: name}
        for resource in (DEPLOYMENTS, CONFIGMAPS):
            kube.delete_all(
                resource, kube.list_objects(resource, namespace=namespace, labels=owned)
            )


def _converge_node(kube: Kube, node: Obj, want: NodeState) -> Obj:
    """Patch ``node`` until it carries ``want``; re-read and re-plan on conflicts."""
    name = node["metadata"]["name"]
    for _ in range(CONFLICT_RETRIES):
        patch = plan_node(node, want)
        if patch is None:
            return node
        try:
            return kube.merge_patch(NODES, name, patch)
        except ConflictError:
            fresh = kube.get(NODES, name)
            if fresh is None:
                return node
            node = fresh
    raise ConflictError(409, "PATCH", f"nodes/{name}", "node kept changing under us")


def _autopilot_inputs(
    kube: Kube, autopilots_name: str | None
) -> tuple[RedundantAutopilotSpec | None, str | None]:
    if autopilots_name is None:
        return None, None
    obj = kube.get(REDUNDANT_AUTOPILOTS, autopilots_name)
    if obj is None:
        return None, None
    reported: str | None = (obj.get("status") or {}).get("activeAutopilot")
    return RedundantAutopilotSpec.model_validate(obj["spec"]), reported


def _bind_node(
    kube: Kube, name: str, spec: VehicleSpec, created: str, peers: Peers
) -> tuple[NodeBinding, Obj | None]:
    """Claim, label and taint the vehicle's node; release any other node it labelled."""
    problem = vehicle_name_problem(name)
    node_name = spec.node_name
    winner = claim_winner([*peers.claims_on(node_name), NodeClaim(name, created)])
    binding: NodeBinding | None = None
    if problem is not None:
        binding = NodeBinding(False, "InvalidVehicleName", problem)
    elif winner is not None and winner.vehicle != name:
        binding = NodeBinding(
            False,
            "NodeClaimedByOtherVehicle",
            f"node {node_name} already belongs to Vehicle {winner.vehicle}, which was created "
            f"first; set spec.nodeName to a free node or delete Vehicle {winner.vehicle}",
        )
    target = None if binding is not None else node_name

    for node in kube.list_objects(NODES, labels={LABEL_VEHICLE: name}):
        if node["metadata"]["name"] != target:
            _converge_node(kube, node, NodeState.released())
    if binding is not None:
        return binding, None

    found = kube.get(NODES, node_name)
    if found is None:
        return (
            NodeBinding(
                False,
                "NodeNotFound",
                f"node {node_name} does not exist; join the vehicle's computer to the cluster "
                "as that node, or correct spec.nodeName",
            ),
            None,
        )
    node = _converge_node(kube, found, NodeState.of_vehicle(name, spec))
    ready, detail = node_readiness(node)
    if not ready:
        return (
            NodeBinding(
                False,
                "NodeNotReady",
                f"node {node_name} is labelled but not Ready ({detail}); check the vehicle's "
                "computer, its network and its kubelet",
            ),
            node,
        )
    return NodeBinding(
        True, "NodeLabeled", f"node {node_name} is labelled, tainted and Ready"
    ), node


def _reconcile_once(kube: Kube, namespace: str, name: str, peers: Peers) -> None:
    vehicle = kube.get(VEHICLES, name)
    if vehicle is None or vehicle["metadata"].get("deletionTimestamp"):
        return
    meta = vehicle["metadata"]
    spec = VehicleSpec.model_validate(vehicle["spec"])
    status = VehicleStatus.model_validate(vehicle.get("status") or {})
    owners = [owner_reference(vehicle)]

    ra_spec, reported_active = _autopilot_inputs(kube, peers.autopilots_of(name))
    autopilots = autopilots_of(spec, ra_spec)
    # Once the failover side (roost_operator.autopilots) has chosen the autopilot the
    # workloads follow, that choice wins: its fleet guards may hold a re-point back.
    followed = status.failover.followed_autopilot if status.failover else None
    active = active_autopilot(
        autopilots,
        reported_active=followed or reported_active,
        primary=ra_spec.primary if ra_spec else None,
    )
    fcu_url = active.fcu_url if active else DEFAULT_FCU_URL
    values = vehicle_config(
        name=name,
        spec=spec,
        fcu_url=fcu_url,
        firmware=Stack(active.stack) if active else None,
        active_autopilot=active.name if active else None,
    )

    binding, node = _bind_node(kube, name, spec, meta["creationTimestamp"], peers)
    kube.apply(vehicle_config_map(name, values, namespace=namespace, owners=owners))

    runs_workloads = binding.bound or binding.reason in ("NodeNotFound", "NodeNotReady")
    wanted = component_workloads(spec, autopilots) if runs_workloads else []
    live: dict[str, Obj] = {}
    failures: dict[str, ApiError] = {}
    for workload in wanted:
        manifest = deployment(
            name, spec.node_name, workload, values, namespace=namespace, owners=owners
        )
        try:
            live[workload.component], _ = kube.apply(manifest)
        except ConflictError:
            raise
        except ApiError as err:
            failures[workload.component] = err
    owned = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: name}
    wanted_components = {w.component for w in wanted}
    stale = [
        d
        for d in kube.list_objects(DEPLOYMENTS, namespace=namespace, labels=owned)
        if d["metadata"].get("labels", {}).get(LABEL_COMPONENT) not in wanted_components
    ]
    kube.delete_all(DEPLOYMENTS, stale)

    states = [
        ComponentState(
            w.component, False, f"its Deployment was refused: {failures[w.component].message}"
        )
        if w.component in failures
        else deployment_state(w.component, live.get(w.component))
        for w in wanted
    ]
    components = components_condition(states, blocked=None if runs_workloads else binding.message)
    conditions = vehicle_conditions(
        status.conditions,
        binding=binding,
        components=components,
        generation=meta.get("generation"),
        agent_expected=ra_spec is not None,
    )
    new_status = VehicleStatus.model_validate(
        {
            **status.to_api(),
            "observedGeneration": meta.get("generation"),
            "conditions": [c.to_api() for c in conditions],
            "nodeName": node["metadata"]["name"] if node is not None else None,
            "managedLabels": managed_label_keys(node) if node is not None else [],
            "fcuUrl": fcu_url,
        }
    )
    write_vehicle_status(
        kube,
        vehicle,
        status,
        new_status,
        fields=STATUS_FIELDS,
        event_types=EVENT_CONDITIONS,
    )
    if failures:  # reported in the status; raising makes kopf retry
        raise next(iter(failures.values()))
