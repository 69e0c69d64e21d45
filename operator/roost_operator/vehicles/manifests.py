"""A Vehicle's manifests, as pure functions: its autopilots, workloads and component Pods.

Given the Vehicle (and its RedundantAutopilot, when there is one) these functions return
plain manifests; they read nothing and write nothing, so every rule here is unit-tested
without a cluster. :mod:`.pods` decides what to do about a live pod, :mod:`.conditions`
what the Vehicle's conditions say.

Each component workload is one bare Pod the Vehicle controller manages itself (pinned to
one node), not a Deployment: at 1,000 vehicles the Deployment → ReplicaSet → Pod →
scheduler chain is the bottleneck of the control plane (``docs/design-decisions.md``,
``docs/scale.md``). The pod names its node (``spec.nodeName``, no scheduler) and keeps
the vehicle's node selector and toleration
(:func:`~roost_operator.vehicles.placement.place_on_vehicle`), so the kubelet's own
admission still checks that the node is the vehicle's. A pod carries the hash of what it
was built from (:data:`~roost_api.wellknown.ANNOTATION_POD_HASH`); its name is fixed
(``<vehicle>-<component>``).

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
from typing import Any, Final

from roost_api.autopilot import RedundantAutopilotSpec, hub_client_url
from roost_api.meta import Stack
from roost_api.sitl import sitl_endpoint
from roost_api.vehicle import ComponentSpec, VehicleSpec
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
from roost_operator.vehicles.placement import place_on_vehicle

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
