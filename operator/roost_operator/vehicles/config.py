"""A vehicle's config (Starling's ``vehicle.config``) and how it enters a pod.

This is the one place that decides the KEY=VALUE entries of a vehicle's config, the
ConfigMap that carries them, and how any pod on a vehicle gets them. The vehicle
component workloads use it, and so does the Mission handler for onboard pods: call
:func:`vehicle_config_map` for the pod's namespace and :func:`mount_vehicle_config` on
the pod spec.

Namespace decision: a ConfigMap can only be mounted in its own namespace. The operator
keeps the authoritative copy, ``roost-vehicle-<vehicle>``, in its namespace
(``ROOST_NAMESPACE``, default ``roost-system``), owned by the Vehicle, next to the
component Pods. A Mission's onboard pods live in the Mission's namespace, so
the Mission handler applies a copy there with the same name and the same data
(``vehicle_config_map(name, config_values_of(authoritative), namespace=...,
  owners=[mission])``),
owned by the Mission so it disappears with it.

How a pod gets it (:func:`mount_vehicle_config`):

* the ConfigMap's ``vehicle.config`` key is mounted read-only as a directory at
  ``/etc/roost`` and ``/etc/starling`` (not via ``subPath``), so the kubelet refreshes
  the file when the config changes and Starling images that read
  ``/etc/starling/vehicle.config`` work unchanged;
* every key is also an environment variable through ``configMapKeyRef``, so the pod
  template names keys, never values, and values cannot disagree with the file;
* controller-managed pod templates carry
  :data:`~roost_api.wellknown.ANNOTATION_CONFIG_HASH`, so a
  config change rolls controller-managed pods. :func:`config_hash` with
  ``include_failover_keys=False`` leaves out the keys that follow the active autopilot,
  for pods that must not restart on a failover (the simulated autopilots themselves).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Final

from roost_api.meta import Stack
from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import (
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_VEHICLE,
    MANAGED_BY,
    VEHICLE_CONFIG_FILE,
    VEHICLE_CONFIG_MOUNTS,
)
from roost_kube.patches import Obj, content_hash

CONFIG_COMPONENT: Final = "config"
VOLUME_NAME: Final = "roost-vehicle-config"

# Keys whose values change when the vehicle fails over to another autopilot.
FAILOVER_KEYS: Final = frozenset({"VEHICLE_FCU_URL", "VEHICLE_FIRMWARE", "ROOST_ACTIVE_AUTOPILOT"})


def config_map_name(vehicle_name: str) -> str:
    """Name of a vehicle's config ConfigMap (the same in every namespace)."""
    return f"roost-vehicle-{vehicle_name}"


def vehicle_config(
    *,
    name: str,
    spec: VehicleSpec,
    fcu_url: str,
    firmware: Stack | None,
    active_autopilot: str | None,
) -> dict[str, str]:
    """The vehicle's config entries, Starling's keys first, then Roost's, then the spec's.

    ``fcu_url``, ``firmware`` and ``active_autopilot`` are those of the autopilot mavros
    should talk to (see :func:`roost_operator.vehicles.manifests.active_autopilot`).
    """
    values = {
        "VEHICLE_NAME": name,
        "VEHICLE_MAVLINK_SYSID": str(spec.sysid),
        "VEHICLE_FCU_URL": fcu_url,
        "VEHICLE_FIRMWARE": str(firmware) if firmware else "",
        "ROOST_VEHICLE": name,
        "ROOST_NODE_NAME": spec.node_name,
        "ROOST_VEHICLE_CLASS": spec.vehicle_class,
        "ROOST_VEHICLE_TYPE": spec.vehicle_type,
        "ROOST_SIMULATED": "true" if spec.simulation else "false",
        "ROOST_ACTIVE_AUTOPILOT": active_autopilot or "",
    }
    for key in sorted(spec.config):
        values.setdefault(key, spec.config[key])
    return values


def render_vehicle_config(values: Mapping[str, str]) -> str:
    """``vehicle.config`` text: one KEY=VALUE per line, in the given order."""
    return "".join(f"{key}={value}\n" for key, value in values.items())


def config_hash(values: Mapping[str, str], *, include_failover_keys: bool = True) -> str:
    """Hash for :data:`ANNOTATION_CONFIG_HASH`; see the module docstring."""
    kept = {k: v for k, v in values.items() if include_failover_keys or k not in FAILOVER_KEYS}
    return content_hash(kept)


def vehicle_config_map(
    vehicle_name: str,
    values: Mapping[str, str],
    *,
    namespace: str,
    owners: Iterable[Obj] = (),
) -> Obj:
    """The ConfigMap carrying ``vehicle.config`` and each key separately."""
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": config_map_name(vehicle_name),
            "namespace": namespace,
            "labels": {
                LABEL_MANAGED_BY: MANAGED_BY,
                LABEL_VEHICLE: vehicle_name,
                LABEL_COMPONENT: CONFIG_COMPONENT,
            },
            "ownerReferences": list(owners),
        },
        "data": {VEHICLE_CONFIG_FILE: render_vehicle_config(values), **values},
    }


def config_values_of(config_map: Mapping[str, Any]) -> dict[str, str]:
    """The KEY=VALUE entries of a vehicle ConfigMap (everything but the file itself)."""
    data: Mapping[str, str] = config_map.get("data") or {}
    return {k: v for k, v in data.items() if k != VEHICLE_CONFIG_FILE}


def mount_vehicle_config(
    pod_spec: Mapping[str, Any],
    vehicle_name: str,
    values: Mapping[str, str],
) -> Obj:
    """``pod_spec`` with the vehicle config mounted and exported in every container.

    Pure: returns a new pod spec. Containers keep their other env entries and mounts;
    an env entry of the container with the name of a config key is dropped, because the
    vehicle's identity must not be overridden by a pod template.
    """
    volume = {
        "name": VOLUME_NAME,
        "configMap": {
            "name": config_map_name(vehicle_name),
            "items": [{"key": VEHICLE_CONFIG_FILE, "path": VEHICLE_CONFIG_FILE}],
        },
    }
    mounts = [
        {"name": VOLUME_NAME, "mountPath": path, "readOnly": True} for path in VEHICLE_CONFIG_MOUNTS
    ]
    env = [
        {
            "name": key,
            "valueFrom": {"configMapKeyRef": {"name": config_map_name(vehicle_name), "key": key}},
        }
        for key in values
    ]

    def with_config(container: Mapping[str, Any]) -> Obj:
        own_mounts = [m for m in container.get("volumeMounts", []) if m.get("name") != VOLUME_NAME]
        own_env = [e for e in container.get("env", []) if e.get("name") not in values]
        return {
            **container,
            "env": [*env, *own_env],
            "volumeMounts": [*own_mounts, *mounts],
        }

    result: Obj = dict(pod_spec)
    result["volumes"] = [
        *(v for v in pod_spec.get("volumes", []) if v.get("name") != VOLUME_NAME),
        volume,
    ]
    for field in ("initContainers", "containers"):
        if field in pod_spec:
            result[field] = [with_config(c) for c in pod_spec[field]]
    return result
