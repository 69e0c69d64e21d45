"""What to do about a component's live Pod, and whether it runs as desired (pure).

The Vehicle controller keeps what a Deployment's Recreate strategy would give, with bare
Pods (:mod:`.manifests` says why bare):

* **Recreate**: a pod whose hash differs from the desired one is deleted, and the new one
  is created only once the old one is gone (its deletion event queues the next
  reconcile). The pod's name is fixed, so the API server itself refuses a second pod of
  one component while the old one still exists: a MAVLink endpoint, a sysid or a serial
  device is never held by two processes. A live pod's spec is never patched.
* a pod that ended (``Failed``/``Succeeded``, e.g. evicted) is deleted and recreated;
  ``restartPolicy: Always`` restarts crashed containers in place.
* readiness (:func:`pod_state`): the pod exists with the desired hash, is not being
  deleted, runs and is Ready.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Final

from roost_api.wellknown import ANNOTATION_CONFIG_HASH, LABEL_NODE
from roost_operator.vehicles.config import config_hash, config_values_of
from roost_operator.vehicles.manifests import pod_hash
from roost_operator.vehicles.placement import node_reachability

# -- replacing pods (the Recreate guarantee) -----------------------------------------

ENDED_PHASES: Final = ("Failed", "Succeeded")


class PodStep(StrEnum):
    """What the controller does about one component's pod."""

    KEEP = "keep"
    """The live pod is the desired one."""
    CREATE = "create"
    """No pod: create the desired one."""
    REPLACE = "replace"
    """The live pod differs: delete it; its deletion event brings the create."""
    RESTART = "restart"
    """The live pod ended (evicted, failed): delete it, as for REPLACE."""
    WAIT = "wait"
    """The old pod is terminating, or its node does not exist yet: nothing to write."""
    DEFER = "defer"
    """The live pod differs but the vehicle is in the air: keep it until it lands
    (:mod:`roost_operator.vehicles.flight`)."""


def pod_step(
    live: Mapping[str, Any] | None, desired: Mapping[str, Any], *, node_exists: bool = True
) -> PodStep:
    """The step towards ``desired`` from ``live`` (None: no pod). Never two pods of a
    component: a new pod is created only when none exists."""
    if live is None:
        return PodStep.CREATE if node_exists else PodStep.WAIT
    if (live.get("metadata") or {}).get("deletionTimestamp"):
        return PodStep.WAIT
    if pod_hash(live) != pod_hash(desired):
        return PodStep.REPLACE
    if (live.get("status") or {}).get("phase") in ENDED_PHASES:
        return PodStep.RESTART
    return PodStep.KEEP


class ReleaseStep(StrEnum):
    """What a release (the Vehicle is gone) does about one of its component pods."""

    DELETE = "delete"
    """Delete it; its kubelet stops it within its grace period."""
    FORCE = "force"
    """Its node cannot be reached (or is gone): remove it at once (grace period 0)."""
    LEAVE = "leave"
    """Already terminating on a reachable node: its kubelet is finishing it."""


def release_step(pod: Mapping[str, Any], node: Mapping[str, Any] | None) -> ReleaseStep:
    """How to remove a gone Vehicle's pod, given its node as read (None: no such node).

    A pod on an unreachable node would stay Terminating until the link returns — for
    ever, if it never does — so it is removed without the kubelet's confirmation, even
    when someone (the garbage collector) already asked for its graceful end. Nothing of
    the vehicle can use it any more, and a kubelet that comes back stops the containers
    of pods the API server no longer has.
    """
    if node is None or node_reachability(node) is not None:
        return ReleaseStep.FORCE
    if (pod.get("metadata") or {}).get("deletionTimestamp"):
        return ReleaseStep.LEAVE
    return ReleaseStep.DELETE


def pod_node(pod: Mapping[str, Any]) -> str | None:
    """The node a component pod was made for (its ``roost.dev/node`` annotation; the pod
    stores keep no spec)."""
    return ((pod.get("metadata") or {}).get("annotations") or {}).get(LABEL_NODE)


# -- readiness ---------------------------------------------------------------------


@dataclass(frozen=True)
class ComponentState:
    """Whether one component's pod runs as desired and is Ready."""

    component: str
    ready: bool
    detail: str
    starting: bool = False
    """Not Ready yet, and nothing is wrong: the desired pod is Pending or not yet Ready,
    and no container waits for anything but its own start (:data:`STARTING_REASONS`)."""


STARTING_REASONS: Final = frozenset({"ContainerCreating", "PodInitializing"})
"""Why a container waits while its pod starts as it should (the kubelet's words)."""


def _only_starting(status: Mapping[str, Any]) -> bool:
    """Whether nothing but the pod's own start keeps it from running: no container has
    ended or waits for another reason, and the pod carries no reason of its own."""
    if status.get("reason"):
        return False
    for container in status.get("containerStatuses") or []:
        state = container.get("state") or {}
        if "terminated" in state:
            return False
        if "waiting" in state and state["waiting"].get("reason") not in STARTING_REASONS:
            return False
    return True


def _pod_problem(status: Mapping[str, Any]) -> str:
    """Why a pod's containers do not run, from their waiting/terminated states."""
    for container in status.get("containerStatuses") or []:
        state = container.get("state") or {}
        for kind in ("waiting", "terminated"):
            if kind in state:
                why = state[kind].get("reason") or kind
                message = state[kind].get("message")
                return f"{why}: {message}" if message else str(why)
    return str(status.get("message") or status.get("reason") or "")


def pod_state(
    component: str, live: Mapping[str, Any] | None, want_hash: str | None = None
) -> ComponentState:
    """Whether the component's pod is the desired one (``want_hash``; None: any), is not
    being deleted, runs and is Ready; otherwise what is missing."""
    if live is None:
        return ComponentState(component, False, "its Pod does not exist yet")
    if (live.get("metadata") or {}).get("deletionTimestamp"):
        return ComponentState(component, False, "its old Pod is terminating")
    if want_hash is not None and pod_hash(live) != want_hash:
        return ComponentState(component, False, "its Pod is outdated and being replaced")
    status = live.get("status") or {}
    phase = status.get("phase") or "Pending"
    problem = _pod_problem(status)
    if phase in ENDED_PHASES:
        return ComponentState(
            component,
            False,
            f"its Pod ended ({phase}" + (f", {problem}" if problem else "") + "); recreating it",
        )
    ready = (
        next((c for c in status.get("conditions") or [] if c.get("type") == "Ready"), None) or {}
    )
    if phase != "Running":
        return ComponentState(
            component,
            False,
            f"its Pod is {phase}" + (f" ({problem})" if problem else ""),
            starting=_only_starting(status),
        )
    if ready.get("status") != "True":
        why = ready.get("message") or problem
        return ComponentState(
            component,
            False,
            "its Pod runs but is not Ready" + (f" ({why})" if why else ""),
            starting=_only_starting(status),
        )
    return ComponentState(component, True, "")


def mavros_follows(
    fcu_url: str | None, config_map: Mapping[str, Any] | None, mavros: Mapping[str, Any] | None
) -> bool:
    """Whether the vehicle's mavros runs with ``fcu_url`` (ends a re-point action).

    Three things must hold: the vehicle's config carries the URL, the mavros Pod
    carries that config's hash (so it was made from it), and it runs and is Ready (the
    old pod gone: a terminating pod does not count).
    """
    if fcu_url is None or config_map is None or mavros is None:
        return False
    values = config_values_of(config_map)
    if values.get("VEHICLE_FCU_URL") != fcu_url:
        return False
    annotations = (mavros.get("metadata") or {}).get("annotations") or {}
    if annotations.get(ANNOTATION_CONFIG_HASH) != config_hash(values):
        return False
    return pod_state("mavros", mavros).ready
