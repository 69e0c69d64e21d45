"""Carrying out a Vehicle's plan, and releasing what Roost made for a Vehicle that is gone.

:func:`apply` makes the writes :class:`~.plan.Plan` lists, in its field order, and returns
what the API server answered (:class:`~.status.Applied`): it decides nothing. A write
the API server refuses for good (a :class:`~roost_kube.errors.PermanentApiError`) is
returned, not raised: it shows in the status and waits for the user to change the spec.
A conflict is raised: the controller decides again from a fresh read. Component pods
are created only where the plan found none, and an outdated or ended pod is deleted
(its successor follows from the reconcile its deletion event queues), so two pods of a
component never run at once; a live pod is never patched.

:func:`release` removes what Roost made for a vehicle that is gone (labels, taint,
config, pods) and returns what it could not remove, so the caller can say it once.
Deletion never waits for a node that cannot be reached: the pods of a gone Vehicle on
such a node are removed at once (:func:`~.pods.release_step`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from roost_api.wellknown import LABEL_MANAGED_BY, LABEL_NODE, LABEL_VEHICLE, MANAGED_BY
from roost_kube.errors import ApiError, ConflictError, PermanentApiError
from roost_kube.patches import Obj
from roost_kube.resources import (
    CONFIGMAPS,
    NODES,
    PODDISRUPTIONBUDGETS,
    PODS,
    REDUNDANT_AUTOPILOTS,
)
from roost_operator.engine.cache import CachedView
from roost_operator.vehicles.manifests import is_component_pod
from roost_operator.vehicles.placement import NodeState, plan_node
from roost_operator.vehicles.plan import Plan, PodMove
from roost_operator.vehicles.pods import PodStep, ReleaseStep, pod_node, release_step
from roost_operator.vehicles.status import (
    REFUSED_AUTOPILOT_LABEL,
    REFUSED_BUDGET,
    REFUSED_CONFIG,
    REFUSED_NODE,
    Applied,
)

log = logging.getLogger(__name__)

CONFLICT_RETRIES: Final = 5


def apply(cluster: CachedView, plan: Plan) -> Applied:
    """Carry out ``plan``; the live component Pods and the writes refused for good."""
    refused: dict[str, ApiError] = {}

    def attempt(key: str, write: Callable[[], object]) -> None:
        try:
            write()
        except PermanentApiError as error:  # reported in the status, not retried
            refused[key] = error

    for node_patch in plan.node_patches:

        def write_node(node: str = node_patch.node, patch: Obj = node_patch.patch) -> Obj:
            return cluster.merge_patch(NODES, node, patch)

        if node_patch.own:
            attempt(REFUSED_NODE, write_node)
        else:
            write_node()
    if plan.autopilot_label is not None:
        autopilot, node = plan.autopilot_label
        label = {"metadata": {"labels": {LABEL_NODE: node}}}
        attempt(
            REFUSED_AUTOPILOT_LABEL,
            lambda: cluster.kube.merge_patch(REDUNDANT_AUTOPILOTS, autopilot, label),
        )
    attempt(REFUSED_CONFIG, lambda: cluster.apply(plan.config_map))
    budget = plan.disruption_budget
    if budget is not None:
        attempt(REFUSED_BUDGET, lambda: cluster.apply(budget))
    elif plan.delete_budget is not None:
        cluster.delete(PODDISRUPTIONBUDGETS, plan.delete_budget, plan.namespace)
    live: dict[str, Obj | None] = {}
    for move in plan.pod_moves:
        try:
            live[move.component] = converge_pod(cluster, move)
        except ConflictError:
            raise
        except ApiError as err:
            refused[move.component] = err
    for name in plan.stray_pods:
        cluster.delete(PODS, name, plan.namespace)
    for event in plan.events:  # deterministic names: a repeat is refused as a duplicate
        cluster.kube.post_event(
            plan.body, reason=event.reason, message=event.message, type=event.type, at=event.at
        )
    return Applied(live=live, refused=refused)


def converge_pod(cluster: CachedView, move: PodMove) -> Obj | None:
    """Take one component's pod step; the pod as it is after it (None: none yet)."""
    desired = move.desired
    name, namespace = desired["metadata"]["name"], desired["metadata"]["namespace"]
    if move.step is PodStep.CREATE:
        try:
            return cluster.create(desired)
        except ConflictError as error:
            if not error.already_exists:
                raise
            # The cache had not seen the old pod yet (or its deletion is not over):
            # judge the pod that exists; its events queue the next reconcile.
            return cluster.fresh(PODS, name, namespace)
    if move.step in (PodStep.REPLACE, PodStep.RESTART):
        log.info(
            "pod %s/%s: %s (deleting it; its successor follows)", namespace, name, move.step.value
        )
        cluster.delete(PODS, name, namespace)
    return move.live


@dataclass(frozen=True)
class Leftovers:
    """What a release could not remove, and why (for the Event that says so)."""

    problems: tuple[str, ...] = ()

    @property
    def clean(self) -> bool:
        return not self.problems


def _release_node(cluster: CachedView, node: Obj, vehicle: str) -> None:
    """Take ``vehicle``'s labels and taint off ``node``; re-read on conflicts. A node
    that another Vehicle took meanwhile (the one waiting for it) is left alone."""
    name = node["metadata"]["name"]
    for _ in range(CONFLICT_RETRIES):
        if (node["metadata"].get("labels") or {}).get(LABEL_VEHICLE) != vehicle:
            return
        patch = plan_node(node, NodeState.released())
        if patch is None:
            return
        try:
            cluster.merge_patch(NODES, name, patch)
            return
        except ConflictError:
            fresh = cluster.fresh(NODES, name)
            if fresh is None:
                return
            node = fresh
    raise ConflictError(409, "PATCH", f"nodes/{name}", "node kept changing under us")


def release(cluster: CachedView, name: str, namespace: str) -> Leftovers:
    """Remove what Roost made for Vehicle ``name`` (labels, taint, config, pods).

    Every part is attempted even when another is refused for good; what could not be
    removed is returned. A temporary error is raised: the release is retried. Finding
    nothing to remove costs no request: nodes, ConfigMaps and Pods come from the caches.
    """
    problems: list[str] = []
    for node in cluster.list_objects(NODES, labels={LABEL_VEHICLE: name}):
        try:
            _release_node(cluster, node, name)
        except PermanentApiError as error:
            problems.append(f"node {node['metadata']['name']}: {error.message}")
    owned = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: name}
    for resource in (PODS, CONFIGMAPS):
        listed = cluster.list_objects(resource, namespace=namespace, labels=owned)
        # A Mission's onboard Job pods carry the vehicle's label too: not ours.
        for obj in [o for o in listed if resource is not PODS or is_component_pod(o)]:
            step = ReleaseStep.LEAVE if obj["metadata"].get("deletionTimestamp") else None
            if resource is PODS:
                on = pod_node(obj)
                step = release_step(obj, cluster.get(NODES, on) if on else None)
            if step is ReleaseStep.LEAVE:
                continue
            try:
                cluster.delete(
                    resource,
                    obj["metadata"]["name"],
                    namespace,
                    grace_period_s=0 if step is ReleaseStep.FORCE else None,
                )
            except PermanentApiError as error:
                problems.append(
                    f"{resource.kind} {namespace}/{obj['metadata']['name']}: {error.message}"
                )
    return Leftovers(tuple(problems))
