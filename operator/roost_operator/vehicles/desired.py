"""Pure desired state of a Vehicle: its autopilots, config, workloads and conditions.

Given the Vehicle (and its RedundantAutopilot, when there is one) these functions
return plain manifests and condition values; they read nothing and write nothing, so
every rule here is unit-tested without a cluster and the Vehicle controller only
observes, calls and applies.

Each component workload is one bare Pod the Vehicle controller manages itself (as a
DaemonSet controller would, pinned to one node), not a Deployment. Why: at 1,000
vehicles the Deployment → ReplicaSet → Pod → scheduler chain is the bottleneck of the
control plane, several times the cost of bare Pods (``docs/design-decisions.md``,
``docs/scale.md``). The pod names its node (``spec.nodeName``, no
scheduler) and keeps the vehicle's node selector and toleration
(:func:`~roost_operator.vehicles.placement.place_on_vehicle`), so the kubelet's own
admission still checks that the node is the vehicle's. What the Deployment gave, the
controller keeps (:func:`pod_step` decides, see :mod:`.controller`):

* **Recreate**: a pod carries the hash of what it was built from
  (:data:`~roost_api.wellknown.ANNOTATION_POD_HASH`); a pod whose hash differs from
  the desired one is deleted, and the new one is created only once the old one is gone
  (its deletion event queues the next reconcile). The pod's name is fixed
  (``<vehicle>-<component>``), so the API server itself refuses a second pod of one
  component while the old one still exists: a MAVLink endpoint, a sysid or a serial
  device is never held by two processes. A live pod's spec is never patched (most of it
  is immutable).
* a pod that ended (``Failed``/``Succeeded``, e.g. evicted) is deleted and recreated;
  ``restartPolicy: Always`` restarts crashed containers in place.
* readiness (:func:`pod_state`): the pod exists with the desired hash, is not being
  deleted, runs and is Ready.

The FCU URL mavros uses is that of the *active* autopilot: the RedundantAutopilot's
``status.activeAutopilot`` (written by the node agent), else its ``spec.primary``.
:func:`active_autopilot` takes both as plain inputs, so a failover is nothing more than
a different input to the same functions: mavros' config hash changes and it rolls,
while the SITL pods keep a hash without the failover keys and keep running.

Default images are Starling's (``uobflightlabstarling/…`` on Docker Hub), so a fleet
moving from Starling keeps the images it knows; every one can be overridden per
vehicle (``spec.components.<c>.image``, ``spec.simulation.image``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from copy import deepcopy
from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import Any, Final

from roost_api.autopilot import RedundantAutopilotSpec, hub_client_url
from roost_api.meta import Condition, ConditionStatus, Stack, set_condition
from roost_api.sitl import sitl_endpoint
from roost_api.vehicle import (
    ComponentSpec,
    VehicleConditionReason,
    VehicleConditionType,
    VehicleSpec,
)
from roost_api.wellknown import (
    ANNOTATION_CONFIG_HASH,
    ANNOTATION_POD_HASH,
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_MISSION,
    LABEL_NODE,
    LABEL_VEHICLE,
    MANAGED_BY,
    SIGNING_HOST_DIR,
    SIGNING_SECRET_PREFIX,
)
from roost_kube.patches import Obj, content_hash
from roost_operator.vehicles.config import config_hash, mount_vehicle_config
from roost_operator.vehicles.placement import node_reachability, place_on_vehicle

# Starling's default for a real vehicle without a RedundantAutopilot: the flight
# controller's USB serial device.
DEFAULT_FCU_URL: Final = "serial:///dev/px4fmu:115200"
DEFAULT_SIM_AUTOPILOT: Final = "fc0"

DEFAULT_IMAGES: Final[Mapping[str, str]] = {
    "mavros": "uobflightlabstarling/starling-mavros:latest",
    "vicon": "uobflightlabstarling/starling-vicon:latest",
    "hardware": "uobflightlabstarling/starling-hardware:latest",
    "sitl-px4": "uobflightlabstarling/starling-sim-px4-sitl:latest",
    "sitl-ardupilot": "uobflightlabstarling/starling-sim-ardupilot-copter:latest",
    # The key pod is a mode of the node agent's image (roost_agent.keysync): no new image.
    "signing-keys": "roost-agent:latest",
}

COMPONENT_RESOURCES: Final[Mapping[str, Obj]] = {
    "mavros": {"requests": {"cpu": "100m", "memory": "128Mi"}, "limits": {"memory": "512Mi"}},
    "vicon": {"requests": {"cpu": "50m", "memory": "64Mi"}, "limits": {"memory": "256Mi"}},
    "hardware": {"requests": {"cpu": "50m", "memory": "64Mi"}, "limits": {"memory": "256Mi"}},
    "sitl": {"requests": {"cpu": "500m", "memory": "512Mi"}, "limits": {"memory": "2Gi"}},
    "signing-keys": {"requests": {"cpu": "5m", "memory": "24Mi"}, "limits": {"memory": "64Mi"}},
}


# -- autopilots -----------------------------------------------------------------------


@dataclass(frozen=True)
class Autopilot:
    """One autopilot of a vehicle as the operator needs it."""

    name: str
    stack: Stack
    sysid: int
    connection: str
    fcu_url: str


def autopilots_of(spec: VehicleSpec, autopilots: RedundantAutopilotSpec | None) -> list[Autopilot]:
    """The vehicle's autopilots: those of its RedundantAutopilot, else one derived SITL.

    A simulated vehicle without a RedundantAutopilot still flies: one SITL with the
    vehicle's stack, ports derived from ``spec.simulation.instance``. A real vehicle
    without one has no autopilot Roost knows of (mavros uses Starling's default URL).
    """
    if autopilots is not None:
        # With the hub, mavros reaches every autopilot through the agent's endpoint.
        hub = hub_client_url(autopilots.hub) if autopilots.hub is not None else None
        return [
            Autopilot(
                name=a.name,
                stack=Stack(a.stack),
                sysid=a.sysid,
                connection=a.connection,
                fcu_url=hub or a.fcu_url or a.connection,
            )
            for a in autopilots.autopilots
        ]
    if spec.simulation is None:
        return []
    stack = Stack(spec.simulation.stack)
    endpoint = sitl_endpoint(spec.simulation.instance, 0, stack)
    return [
        Autopilot(
            name=DEFAULT_SIM_AUTOPILOT,
            stack=stack,
            sysid=spec.sysid,
            connection=endpoint.connection,
            fcu_url=endpoint.connection,
        )
    ]


def active_autopilot(
    autopilots: Sequence[Autopilot], *, reported_active: str | None, primary: str | None
) -> Autopilot | None:
    """The autopilot mavros follows: the reported active one, else the primary, else first."""
    by_name = {a.name: a for a in autopilots}
    for name in (reported_active, primary):
        if name and name in by_name:
            return by_name[name]
    return autopilots[0] if autopilots else None


# -- workloads ----------------------------------------------------------------------


@dataclass(frozen=True)
class Workload:
    """One controller-managed component of a vehicle."""

    component: str  # mavros, vicon, hardware, sitl-<autopilot>
    image: str
    container: Obj  # container fields besides name/image/env (ports, probes, securityContext)
    pod: Obj  # pod spec fields besides containers (hostNetwork, volumes)
    follows_failover: bool  # whether a failover (FCU URL change) restarts it


def workload_name(vehicle_name: str, component: str) -> str:
    """Name of a vehicle's component Pod (fixed: one pod of a component at a time)."""
    return f"{vehicle_name}-{component}"


# Container and pod fields of each optional component beyond its image and resources.
_HOST_NETWORK: Final[Obj] = {"hostNetwork": True, "dnsPolicy": "ClusterFirstWithHostNet"}
_COMPONENT_FIELDS: Final[dict[str, tuple[Obj, Obj]]] = {
    "mavros": ({}, _HOST_NETWORK),
    "vicon": ({}, _HOST_NETWORK),
    # Device access (cameras, payload buses) needs the host's /dev and a privileged
    # container; this is the only privileged Roost workload and it is off by default.
    "hardware": (
        {
            "securityContext": {"privileged": True},
            "volumeMounts": [{"name": "dev", "mountPath": "/dev"}],
        },
        {"volumes": [{"name": "dev", "hostPath": {"path": "/dev"}}]},
    ),
}


def component_workloads(
    spec: VehicleSpec,
    autopilots: Sequence[Autopilot],
    *,
    vehicle_name: str,
    agent_image: str | None = None,
) -> list[Workload]:
    """Every workload the vehicle should run, in a stable order.

    Only mavros follows a failover: it is the component pointed at the active autopilot.
    ``agent_image`` is the key pod's image unless the Vehicle names one (the operator's
    setting, the chart's agent image).
    """
    workloads: list[Workload] = []
    for component, (container, pod) in _COMPONENT_FIELDS.items():
        chosen: ComponentSpec = getattr(spec.components, component)
        if chosen.enabled:
            workloads.append(
                Workload(
                    component,
                    chosen.image or DEFAULT_IMAGES[component],
                    {"resources": COMPONENT_RESOURCES[component], **deepcopy(container)},
                    deepcopy(pod),
                    follows_failover=component == "mavros",
                )
            )
    if spec.components.signing_keys.enabled:
        chosen_keys = spec.components.signing_keys
        image = chosen_keys.image or agent_image or DEFAULT_IMAGES[SIGNING_KEYS]
        workloads.append(signing_keys_workload(vehicle_name, image))
    if spec.simulation is not None:
        workloads.extend(
            sitl_workload(spec, index, autopilot) for index, autopilot in enumerate(autopilots)
        )
    return workloads


SIGNING_KEYS: Final = "signing-keys"
AGENT_USER: Final = 65532
"""The agent image's user (docker/Dockerfile ``USER``; the chart's ``runAsUser``): the
key files are handed to it, mode 0600."""
_KEY_SOURCE: Final = "/var/run/secrets/roost-signing"
_KEY_TARGET: Final = "/var/lib/roost-signing"


def signing_keys_workload(vehicle_name: str, image: str) -> Workload:
    """The vehicle's key pod: its one Secret in, the agent's key directory on the node out.

    Why a pod per Vehicle (``roost_agent.keysync`` says more): the Node authorizer lets a
    kubelet read only the Secrets of pods bound to its node, so this pod, pinned to the
    vehicle's node like every component, is what lets that node (and only that node)
    read ``roost-signing-<vehicle>``. The Secret's name is derived from the Vehicle's,
    never taken from the spec: a Vehicle cannot have another Secret mounted on its node.

    It runs as root with every capability dropped but ``CHOWN`` (the host directory is
    root's; the files are handed to the agent's user), reads the Secret through the
    kubelet (the pod's ServiceAccount token is not mounted: it calls no API) and writes
    only under ``SIGNING_HOST_DIR/<vehicle>``.
    """
    host_dir = f"{SIGNING_HOST_DIR}/{vehicle_name}"
    container: Obj = {
        "command": ["python3", "-m", "roost_agent.keysync"],
        "args": [
            f"--source={_KEY_SOURCE}",
            f"--target={_KEY_TARGET}",
            f"--owner={AGENT_USER}:{AGENT_USER}",
        ],
        "resources": COMPONENT_RESOURCES[SIGNING_KEYS],
        "securityContext": {
            "runAsUser": 0,
            "runAsNonRoot": False,
            "allowPrivilegeEscalation": False,
            "readOnlyRootFilesystem": True,
            "capabilities": {"drop": ["ALL"], "add": ["CHOWN"]},
        },
        "volumeMounts": [
            {"name": "signing-key", "mountPath": _KEY_SOURCE, "readOnly": True},
            {"name": "agent-keys", "mountPath": _KEY_TARGET},
        ],
    }
    pod: Obj = {
        "automountServiceAccountToken": False,
        "securityContext": {"seccompProfile": {"type": "RuntimeDefault"}},
        "volumes": [
            {
                "name": "signing-key",
                "secret": {
                    "secretName": f"{SIGNING_SECRET_PREFIX}{vehicle_name}",
                    "defaultMode": 0o400,
                    "items": [
                        {"key": "key", "path": "key"},
                        {"key": "previous", "path": "previous"},
                    ],
                },
            },
            {"name": "agent-keys", "hostPath": {"path": host_dir, "type": "DirectoryOrCreate"}},
        ],
    }
    return Workload(
        SIGNING_KEYS,
        image,
        container,
        pod,
        follows_failover=False,
    )


def sitl_workload(spec: VehicleSpec, index: int, autopilot: Autopilot) -> Workload:
    """The SITL of one autopilot of a simulated vehicle.

    Ports come from :func:`roost_api.sitl.sitl_endpoint` (vehicle instance, autopilot
    index), so two autopilots on one node never share a port; the sysid is the
    autopilot's declared one, which the node agent filters on. ArduPilot's SITL serves
    TCP, which gives it a readiness probe; PX4's SITL speaks UDP only, so it has none.
    """
    assert spec.simulation is not None
    endpoint = sitl_endpoint(spec.simulation.instance, index, autopilot.stack)
    container: Obj = {
        "resources": COMPONENT_RESOURCES["sitl"],
        "env": [
            {"name": "ROOST_SITL_AUTOPILOT", "value": autopilot.name},
            {"name": "ROOST_SITL_STACK", "value": str(autopilot.stack)},
            {"name": "ROOST_SITL_INSTANCE", "value": str(endpoint.instance)},
            {"name": "ROOST_SITL_SYSID", "value": str(autopilot.sysid)},
            {"name": "ROOST_SITL_AGENT_PORT", "value": str(endpoint.agent_port)},
            {"name": "ROOST_SITL_AUTOPILOT_PORT", "value": str(endpoint.autopilot_port)},
            {"name": "PX4_INSTANCE", "value": str(endpoint.instance)},
            {"name": "PX4_SYSID", "value": str(autopilot.sysid)},
        ],
    }
    if autopilot.stack is Stack.ARDUPILOT:
        container["ports"] = [
            {"name": "mavlink-tcp", "containerPort": endpoint.autopilot_port, "protocol": "TCP"}
        ]
        container["readinessProbe"] = {
            "tcpSocket": {"port": endpoint.autopilot_port},
            "periodSeconds": 5,
        }
    image = spec.simulation.image or DEFAULT_IMAGES[f"sitl-{autopilot.stack}"]
    return Workload(
        f"sitl-{autopilot.name}",
        image,
        container,
        {"hostNetwork": True, "dnsPolicy": "ClusterFirstWithHostNet"},
        follows_failover=False,
    )


def workload_labels(vehicle_name: str, component: str) -> dict[str, str]:
    """Labels of a component Pod (the controller's watch selects them)."""
    return {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: vehicle_name, LABEL_COMPONENT: component}


COMPONENT_POD_SELECTOR: Final = (
    f"{LABEL_MANAGED_BY}={MANAGED_BY},{LABEL_VEHICLE},{LABEL_COMPONENT},!{LABEL_MISSION}"
)
"""The vehicles' component pods, as a label selector: a Mission's onboard Job pods also
carry the vehicle's label, and its mission label sets them apart."""


def is_component_pod(pod: Mapping[str, Any]) -> bool:
    """Whether ``pod`` is a vehicle component pod (:data:`COMPONENT_POD_SELECTOR`)."""
    labels = (pod.get("metadata") or {}).get("labels") or {}
    return (
        labels.get(LABEL_MANAGED_BY) == MANAGED_BY
        and LABEL_VEHICLE in labels
        and LABEL_COMPONENT in labels
        and LABEL_MISSION not in labels
    )


def component_pod(
    vehicle_name: str,
    node_name: str,
    workload: Workload,
    config_values: Mapping[str, str],
    *,
    namespace: str,
    owners: Iterable[Obj],
) -> Obj:
    """The Pod running one workload on the vehicle's node, carrying its own hash."""
    container: Obj = {
        "name": workload.component,
        "image": workload.image,
        "imagePullPolicy": "IfNotPresent",
        **workload.container,
    }
    pod_spec = place_on_vehicle(
        mount_vehicle_config(
            {**workload.pod, "containers": [container]}, vehicle_name, config_values
        ),
        vehicle_name,
    )
    labels = workload_labels(vehicle_name, workload.component)
    annotations = {
        ANNOTATION_CONFIG_HASH: config_hash(
            config_values, include_failover_keys=workload.follows_failover
        ),
        LABEL_NODE: node_name,
    }
    spec: Obj = {**pod_spec, "nodeName": node_name, "restartPolicy": "Always"}
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {
            "name": workload_name(vehicle_name, workload.component),
            "namespace": namespace,
            "labels": labels,
            "annotations": {
                **annotations,
                ANNOTATION_POD_HASH: content_hash([spec, labels, annotations]),
            },
            "ownerReferences": list(owners),
        },
        "spec": spec,
    }


def pod_hash(pod: Mapping[str, Any] | None) -> str | None:
    """The hash a component pod (desired or live) was built with."""
    if pod is None:
        return None
    return ((pod.get("metadata") or {}).get("annotations") or {}).get(ANNOTATION_POD_HASH)


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


# -- readiness and conditions --------------------------------------------------------


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


@dataclass(frozen=True)
class NodeBinding:
    """Outcome of binding the vehicle to its node, for the NodeBound condition."""

    bound: bool
    reason: str
    message: str
    since: datetime | None = None
    """When the problem began, if known (an unreachable node: when the node controller
    noticed); NodeBound's transition time when it changes."""


def components_condition(
    states: Sequence[ComponentState], *, blocked: str | None = None
) -> tuple[ConditionStatus, str, str]:
    """ComponentsReady from the states of all desired components.

    ``blocked`` says why no components run at all (the vehicle has no node to run on).
    """
    if blocked is not None:
        return "False", VehicleConditionReason.WAITING_FOR_NODE, f"no components run: {blocked}"
    if not states:
        return "True", VehicleConditionReason.NO_COMPONENTS, "no components are enabled"
    waiting = [s for s in states if not s.ready]
    if not waiting:
        names = ", ".join(s.component for s in states)
        return "True", VehicleConditionReason.ALL_COMPONENTS_READY, f"ready: {names}"
    message = "; ".join(f"component {s.component} not ready: {s.detail}" for s in waiting)
    return "False", VehicleConditionReason.COMPONENTS_NOT_READY, message


# The detail conditions Ready summarises, in the order their problems are reported.
READY_INPUTS: Final = (
    VehicleConditionType.NODE_BOUND,
    VehicleConditionType.COMPONENTS_READY,
    VehicleConditionType.AUTOPILOTS_HEALTHY,
    VehicleConditionType.AGENT_CONNECTED,
)


def ready_condition(
    conditions: Sequence[Condition], *, agent_expected: bool = False
) -> tuple[ConditionStatus, str, str]:
    """Ready from the detail conditions present: False on any False, else Unknown on any
    Unknown, else True. AutopilotsHealthy and AgentConnected count once they exist;
    ``agent_expected`` (the vehicle has a RedundantAutopilot) makes a missing
    AgentConnected count as Unknown, so Ready is never True before the failover side
    has heard from the vehicle's agent.
    """
    present = {c.type: c for c in conditions}
    inputs = [
        (c.type, c.status, c.reason, c.message)
        for c in (present.get(t) for t in READY_INPUTS)
        if c is not None
    ]
    if agent_expected and VehicleConditionType.AGENT_CONNECTED not in present:
        inputs.append(
            (
                VehicleConditionType.AGENT_CONNECTED.value,
                "Unknown",
                VehicleConditionReason.AGENT_NOT_HEARD_YET,
                "the vehicle's node agent has not been heard from yet",
            )
        )
    for wanted in ("False", "Unknown"):
        failing = [i for i in inputs if i[1] == wanted]
        if failing:
            message = "; ".join(f"{kind}: {text}" for kind, _, _, text in failing)
            return wanted, failing[0][2], message
    return "True", VehicleConditionReason.VEHICLE_READY, "node bound, components ready"


def vehicle_conditions(
    previous: Sequence[Condition],
    *,
    binding: NodeBinding,
    components: tuple[ConditionStatus, str, str],
    generation: int | None,
    agent_expected: bool = False,
) -> list[Condition]:
    """The Vehicle's conditions after this reconcile (others' condition types kept).

    ``agent_expected``: see :func:`ready_condition`.
    """
    conditions = set_condition(
        previous,
        type=VehicleConditionType.NODE_BOUND,
        status="True" if binding.bound else "False",
        reason=binding.reason,
        message=binding.message,
        observed_generation=generation,
        at=binding.since,
    )
    status, reason, message = components
    conditions = set_condition(
        conditions,
        type=VehicleConditionType.COMPONENTS_READY,
        status=status,
        reason=reason,
        message=message,
        observed_generation=generation,
    )
    return with_ready(conditions, generation=generation, agent_expected=agent_expected)


def with_ready(
    conditions: Sequence[Condition],
    *,
    generation: int | None,
    at: datetime | None = None,
    agent_expected: bool = False,
) -> list[Condition]:
    """``conditions`` with Ready recomputed from the detail conditions (see
    :func:`ready_condition`); the one place every Vehicle condition writer summarises."""
    status, reason, message = ready_condition(conditions, agent_expected=agent_expected)
    return set_condition(
        conditions,
        type=VehicleConditionType.READY,
        status=status,
        reason=reason,
        message=message,
        observed_generation=generation,
        at=at,
    )


def transitions(
    before: Sequence[Condition], after: Sequence[Condition], types: Iterable[str]
) -> list[Condition]:
    """Conditions of ``types`` worth an Event: those whose status changed, and a detail
    condition that appears False (a problem from the start, such as a missing node).

    Other first appearances are no news: a condition that appears True or Unknown is the
    vehicle starting as it should, and Ready's first False says that its components are
    still rolling out or repeats a detail condition's own Event. Ready turning True is
    news; a Vehicle whose first status is already Ready (its "starting" report was held
    until its pods were Ready, see :func:`~.plan.first_report_due`) posts no Event.
    """
    wanted = set(types)
    old = {c.type: c.status for c in before}
    return [
        c
        for c in after
        if c.type in wanted
        and (
            old[c.type] != c.status
            if c.type in old
            else c.status == "False" and c.type != VehicleConditionType.READY
        )
    ]
