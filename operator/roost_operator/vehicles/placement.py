"""Where a vehicle lives: its node's labels and taint, node claims, and pod placement.

Node labels follow node-feature-discovery's discipline. Roost writes Nodes (node
agents never do), only under keys it chose (``roost.dev/…`` and, when
``spec.starlingCompatibility`` is set, Starling's ``starling.dev/…``), and records every
key it set in the node annotation :data:`~roost_api.wellknown.ANNOTATION_MANAGED_LABELS`.
Only recorded keys are ever removed, so labels set by people or other controllers
survive every Roost operation, including deletion of the Vehicle. The vehicle taint is
recorded in the same annotation as ``taint:<key>``.

:func:`plan_node` turns "this node should carry vehicle X" (or "nothing of Roost") into
one JSON merge patch that carries the node's ``resourceVersion``: labels, annotation
and the whole taints list change together or not at all, and a concurrent writer
makes the patch fail with 409 instead of being overwritten. It returns None when the
node already matches, which is what keeps an idle reconcile free of writes.

Pods are placed with a ``nodeSelector`` on the vehicle label plus a toleration of the
vehicle's taint (:func:`place_on_vehicle`), not with ``spec.nodeName``: the scheduler
(and its taint checks) stays in charge, and a pod can only land on the node that
currently carries the vehicle's label.

Every pod placed on a vehicle also tolerates ``node.kubernetes.io/unreachable`` and
``node.kubernetes.io/not-ready`` (NoExecute) with no ``tolerationSeconds``
(:data:`LINK_TOLERATIONS`). Why: a vehicle's computer joins the cluster over WiFi, and a
drop longer than the default 300 s toleration would have the taint manager delete
mavros and the mission's pods, and the kubelet kill them when the link returns — in
flight. They cannot run anywhere else anyway, so they are kept for as long as the
vehicle exists; the vehicle reports the lost link instead (:func:`node_reachability`).

Two Vehicles naming the same node: the one created first keeps it (ties broken by
name), see :func:`claim_winner`; the other is reported, never fought over.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Final

from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import (
    ANNOTATION_MANAGED_LABELS,
    LABEL_SIMULATED,
    LABEL_STACK,
    LABEL_VEHICLE,
    LABEL_VEHICLE_CLASS,
    LABEL_VEHICLE_TYPE,
    STARLING_LABEL_CLASS,
    STARLING_LABEL_TYPE,
    STARLING_LABEL_VEHICLE_TYPE,
    TAINT_VEHICLE,
)
from roost_kube.patches import Obj

TAINT_EFFECT: Final = "NoSchedule"
TAINT_RECORD: Final = f"taint:{TAINT_VEHICLE}"
MAX_LABEL_VALUE: Final = 63


def desired_node_labels(vehicle_name: str, spec: VehicleSpec) -> dict[str, str]:
    """The labels a vehicle's node carries."""
    labels = {
        LABEL_VEHICLE: vehicle_name,
        LABEL_VEHICLE_CLASS: spec.vehicle_class,
        LABEL_VEHICLE_TYPE: spec.vehicle_type,
        LABEL_SIMULATED: "true" if spec.simulation else "false",
    }
    if spec.simulation:
        labels[LABEL_STACK] = str(spec.simulation.stack)
    if spec.starling_compatibility:
        labels[STARLING_LABEL_TYPE] = "vehicle"
        labels[STARLING_LABEL_CLASS] = spec.vehicle_class
        labels[STARLING_LABEL_VEHICLE_TYPE] = spec.vehicle_type
    return labels


def vehicle_taint(vehicle_name: str) -> dict[str, str]:
    """The taint that keeps pods not meant for this vehicle off its node."""
    return {"key": TAINT_VEHICLE, "value": vehicle_name, "effect": TAINT_EFFECT}


def vehicle_toleration(vehicle_name: str) -> dict[str, str]:
    """The toleration of :func:`vehicle_taint` (for this vehicle only)."""
    return {
        "key": TAINT_VEHICLE,
        "operator": "Equal",
        "value": vehicle_name,
        "effect": TAINT_EFFECT,
    }


TAINT_UNREACHABLE: Final = "node.kubernetes.io/unreachable"
TAINT_NOT_READY: Final = "node.kubernetes.io/not-ready"
LINK_TOLERATIONS: Final = tuple(
    {"key": key, "operator": "Exists", "effect": "NoExecute"}
    for key in (TAINT_UNREACHABLE, TAINT_NOT_READY)
)
"""Tolerations of a lost link, for as long as the pod exists (no ``tolerationSeconds``)."""


def place_on_vehicle(pod_spec: Mapping[str, Any], vehicle_name: str) -> Obj:
    """``pod_spec`` pinned to the node carrying the vehicle's label, tolerating its taint
    and a lost link (:data:`LINK_TOLERATIONS`) for good.

    Pure. Existing node selectors and other tolerations are kept; a toleration of the
    vehicle taint or of a lost link the template brings (with its own
    ``tolerationSeconds``, say) is replaced: the pod cannot run anywhere else.
    """
    ours = {TAINT_VEHICLE, TAINT_UNREACHABLE, TAINT_NOT_READY}
    tolerations = [t for t in pod_spec.get("tolerations", []) if t.get("key") not in ours]
    return {
        **pod_spec,
        "nodeSelector": {**pod_spec.get("nodeSelector", {}), LABEL_VEHICLE: vehicle_name},
        "tolerations": [
            *tolerations,
            vehicle_toleration(vehicle_name),
            *(dict(t) for t in LINK_TOLERATIONS),
        ],
    }


def vehicle_name_problem(vehicle_name: str) -> str | None:
    """Why this name cannot be a node label value, or None when it can."""
    if len(vehicle_name) > MAX_LABEL_VALUE:
        return (
            f"the name is {len(vehicle_name)} characters; node label values allow "
            f"{MAX_LABEL_VALUE}: recreate the Vehicle with a shorter name"
        )
    return None


@dataclass(frozen=True)
class NodeClaim:
    """A Vehicle naming a node in ``spec.nodeName``."""

    vehicle: str
    created: str  # RFC 3339 creationTimestamp; compares chronologically as a string


def claim_winner(claims: Iterable[NodeClaim]) -> NodeClaim | None:
    """The claim that keeps the node: the oldest Vehicle, ties broken by name."""
    return min(claims, key=lambda c: (c.created, c.vehicle), default=None)


def managed_keys(node: Mapping[str, Any]) -> set[str]:
    """Keys Roost recorded on this node (labels, and ``taint:<key>`` for the taint)."""
    raw = node.get("metadata", {}).get("annotations", {}).get(ANNOTATION_MANAGED_LABELS, "")
    return {key for key in raw.split(",") if key}


def managed_label_keys(node: Mapping[str, Any]) -> list[str]:
    """The recorded label keys only, sorted (what Vehicle status reports)."""
    return sorted(k for k in managed_keys(node) if not k.startswith("taint:"))


@dataclass(frozen=True)
class NodeState:
    """What Roost wants on one node: a vehicle's labels and taint, or nothing."""

    labels: Mapping[str, str]
    taint: Mapping[str, str] | None

    @classmethod
    def of_vehicle(cls, vehicle_name: str, spec: VehicleSpec) -> NodeState:
        return cls(desired_node_labels(vehicle_name, spec), vehicle_taint(vehicle_name))

    @classmethod
    def released(cls) -> NodeState:
        return cls({}, None)


def plan_node(node: Mapping[str, Any], want: NodeState) -> Obj | None:
    """The merge patch that makes ``node`` carry ``want``, or None if it already does."""
    meta = node.get("metadata", {})
    labels: Mapping[str, str] = meta.get("labels") or {}
    taints: list[Obj] = list((node.get("spec") or {}).get("taints") or [])
    recorded = managed_keys(node)

    label_patch: dict[str, str | None] = {
        key: value for key, value in want.labels.items() if labels.get(key) != value
    }
    for key in recorded:
        if not key.startswith("taint:") and key not in want.labels and key in labels:
            label_patch[key] = None

    ours = [t for t in taints if t.get("key") == TAINT_VEHICLE]
    others = [t for t in taints if t.get("key") != TAINT_VEHICLE]
    if want.taint is not None:
        new_taints = [*others, dict(want.taint)]
        taints_change = ours != [dict(want.taint)]
    elif TAINT_RECORD in recorded:
        new_taints = others
        taints_change = bool(ours)
    else:
        new_taints = taints
        taints_change = False

    new_record = set(want.labels) | ({TAINT_RECORD} if want.taint is not None else set())
    record_change = new_record != recorded

    if not label_patch and not taints_change and not record_change:
        return None
    patch_meta: Obj = {"resourceVersion": meta.get("resourceVersion")}
    if label_patch:
        patch_meta["labels"] = label_patch
    if record_change:
        patch_meta["annotations"] = {
            ANNOTATION_MANAGED_LABELS: ",".join(sorted(new_record)) if new_record else None
        }
    patch: Obj = {"metadata": patch_meta}
    if taints_change:
        patch["spec"] = {"taints": new_taints or None}
    return patch


@dataclass(frozen=True)
class Unreachable:
    """The node's link is lost: the node controller could not hear its kubelet."""

    since: datetime | None
    """When the node controller noticed (its Ready condition's last transition, else the
    unreachable taint's ``timeAdded``); None when neither says."""
    detail: str


def node_reachability(node: Mapping[str, Any]) -> Unreachable | None:
    """Whether the node's kubelet is out of reach (None: it is heard from).

    Unreachable is the node controller's verdict: ``Ready=Unknown`` (the kubelet stopped
    posting its status), or its ``node.kubernetes.io/unreachable`` taint. A node whose
    kubelet says ``Ready=False`` is reachable, just not Ready.
    """
    ready = next(
        (c for c in (node.get("status") or {}).get("conditions") or [] if c.get("type") == "Ready"),
        None,
    )
    taint = next(
        (
            t
            for t in (node.get("spec") or {}).get("taints") or []
            if t.get("key") == TAINT_UNREACHABLE
        ),
        None,
    )
    unknown = ready is not None and ready.get("status") == "Unknown"
    if not unknown and taint is None:
        return None
    stamps = [ready.get("lastTransitionTime") if unknown and ready else None]
    stamps.append(taint.get("timeAdded") if taint else None)
    since = next((parsed for s in stamps if (parsed := _time(s)) is not None), None)
    detail = (ready or {}).get("message") or (ready or {}).get("reason") or "tainted unreachable"
    return Unreachable(since, str(detail))


def _time(stamp: Any) -> datetime | None:
    if not isinstance(stamp, str) or not stamp:
        return None
    try:
        return datetime.fromisoformat(stamp)
    except ValueError:
        return None


def node_readiness(node: Mapping[str, Any]) -> tuple[bool, str]:
    """Whether the node reports Ready, and the kubelet's words when it does not."""
    for cond in (node.get("status") or {}).get("conditions") or []:
        if cond.get("type") == "Ready":
            if cond.get("status") == "True":
                return True, ""
            detail = cond.get("message") or cond.get("reason") or "no reason given"
            return False, f"Ready={cond.get('status')}: {detail}"
    return False, "the node has not reported a Ready condition yet"
