"""The Jobs a Mission runs: one onboard Job per assigned vehicle, one offboard Job.

Jobs, not bare pods, because the Job controller already owns "run to completion with
retries" (``backoffLimit``) and survives operator restarts; the mission only reads the
Job's terminal condition. Names are deterministic (mission + vehicle), so a reconcile
that runs twice — or an operator restarted between creating a Job and recording it —
finds the existing Job instead of starting a second workload.

Onboard pods go through the vehicle controller's two pod functions, never a copy of
them: :func:`~roost_operator.vehicles.placement.place_on_vehicle` (node selector on the
vehicle label plus a toleration of that vehicle's taint) and
:func:`~roost_operator.vehicles.config.mount_vehicle_config` (``vehicle.config`` at
``/etc/roost`` and ``/etc/starling`` plus every key as env). The ConfigMap they mount
must live in the Mission's namespace, so the mission keeps a copy of the vehicle's
authoritative ConfigMap there (:func:`config_map_copy`), owned by the Mission.

Every mission pod also gets the mission's identity and vehicle list as env
(``ROOST_MISSION``, ``ROOST_MISSION_NAMESPACE``, ``ROOST_MISSION_VEHICLES`` comma
separated in assignment order, and on vehicles ``ROOST_MISSION_VEHICLE_INDEX``), so a
controller can find its peers as in Starling's synchronised path-following example.

The offboard pod is kept off vehicles with a required node affinity on the vehicle
label being absent (the vehicle taints would keep it off anyway, unless its template
tolerates everything).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from typing import Any, Final

from roost_api.meta import API_VERSION
from roost_api.mission import MissionSpec
from roost_api.resources import MISSION
from roost_api.wellknown import (
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_MISSION,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_kube.patches import Obj, owner_reference
from roost_operator.missions.observed import MissionRef
from roost_operator.vehicles.config import mount_vehicle_config, vehicle_config_map
from roost_operator.vehicles.placement import place_on_vehicle

MAX_NAME: Final = 63
ONBOARD: Final = "mission-onboard"
OFFBOARD: Final = "mission-offboard"

ENV_MISSION: Final = "ROOST_MISSION"
ENV_MISSION_NAMESPACE: Final = "ROOST_MISSION_NAMESPACE"
ENV_MISSION_VEHICLES: Final = "ROOST_MISSION_VEHICLES"
ENV_MISSION_VEHICLE_INDEX: Final = "ROOST_MISSION_VEHICLE_INDEX"
MISSION_ENV: Final = frozenset(
    {ENV_MISSION, ENV_MISSION_NAMESPACE, ENV_MISSION_VEHICLES, ENV_MISSION_VEHICLE_INDEX}
)


def bounded_name(*parts: str, limit: int = MAX_NAME) -> str:
    """``parts`` joined by dashes; when too long, truncated with a hash of the whole.

    Job names must fit a label value (63 characters) because the Job controller labels
    its pods with them; the hash keeps two long names that share a prefix apart.
    """
    full = "-".join(parts)
    if len(full) <= limit:
        return full
    digest = hashlib.sha256(full.encode()).hexdigest()[:8]
    return f"{full[: limit - len(digest) - 1].rstrip('-.')}-{digest}"


def onboard_job_name(mission_name: str, vehicle_name: str) -> str:
    """Name of the onboard Job of ``mission_name`` on ``vehicle_name``."""
    return bounded_name(mission_name, vehicle_name)


def offboard_job_name(mission_name: str) -> str:
    """Name of the offboard Job of ``mission_name``."""
    return bounded_name(mission_name, "offboard")


def mission_labels(mission: MissionRef, component: str) -> dict[str, str]:
    """Labels on every object a mission creates; ``roost.dev/mission`` selects them."""
    return {
        LABEL_MANAGED_BY: MANAGED_BY,
        LABEL_MISSION: bounded_name(mission.name),
        LABEL_COMPONENT: component,
    }


def mission_owner(mission: MissionRef, *, controller: bool = True) -> Obj:
    """An ownerReference to the Mission, so its objects go when it goes."""
    body = {
        "apiVersion": API_VERSION,
        "kind": MISSION.kind,
        "metadata": {"name": mission.name, "uid": mission.uid},
    }
    return owner_reference(body, controller=controller)


def _with_env(pod_spec: Mapping[str, Any], env: Sequence[Obj]) -> Obj:
    names = {e["name"] for e in env}

    def container(c: Mapping[str, Any]) -> Obj:
        own = [e for e in c.get("env", []) if e.get("name") not in names]
        return {**c, "env": [*own, *env]}

    result: Obj = dict(pod_spec)
    for field in ("initContainers", "containers"):
        if field in pod_spec:
            result[field] = [container(c) for c in pod_spec[field]]
    return result


def mission_env(
    mission: MissionRef, assigned: Sequence[str], vehicle_name: str | None
) -> list[Obj]:
    """The mission's identity and vehicle list as container env."""
    env = [
        {"name": ENV_MISSION, "value": mission.name},
        {"name": ENV_MISSION_NAMESPACE, "value": mission.namespace},
        {"name": ENV_MISSION_VEHICLES, "value": ",".join(assigned)},
    ]
    if vehicle_name is not None:
        env.append({"name": ENV_MISSION_VEHICLE_INDEX, "value": str(assigned.index(vehicle_name))})
    return env


def _job(
    *,
    name: str,
    mission: MissionRef,
    component: str,
    template: Mapping[str, Any],
    pod_spec: Obj,
    backoff_limit: int,
    extra_labels: Mapping[str, str],
) -> Obj:
    labels = {**mission_labels(mission, component), **extra_labels}
    template_meta = template.get("metadata") or {}
    pod_spec.setdefault("restartPolicy", "Never")
    return {
        "apiVersion": "batch/v1",
        "kind": "Job",
        "metadata": {
            "name": name,
            "namespace": mission.namespace,
            "labels": labels,
            "ownerReferences": [mission_owner(mission)],
        },
        "spec": {
            "backoffLimit": backoff_limit,
            "template": {
                "metadata": {
                    "labels": {**(template_meta.get("labels") or {}), **labels},
                    "annotations": dict(template_meta.get("annotations") or {}),
                },
                "spec": pod_spec,
            },
        },
    }


def onboard_job(
    *,
    mission: MissionRef,
    spec: MissionSpec,
    vehicle_name: str,
    assigned: Sequence[str],
    config_values: Mapping[str, str],
) -> Obj:
    """The onboard Job for one vehicle: pinned, tolerating, config mounted, env set."""
    pod_spec = dict(spec.onboard.get("spec") or {})
    pod_spec = place_on_vehicle(pod_spec, vehicle_name)
    pod_spec = mount_vehicle_config(pod_spec, vehicle_name, config_values)
    pod_spec = _with_env(pod_spec, mission_env(mission, assigned, vehicle_name))
    return _job(
        name=onboard_job_name(mission.name, vehicle_name),
        mission=mission,
        component=ONBOARD,
        template=spec.onboard,
        pod_spec=pod_spec,
        backoff_limit=spec.backoff_limit,
        extra_labels={LABEL_VEHICLE: vehicle_name},
    )


def _off_vehicles(pod_spec: Mapping[str, Any]) -> Obj:
    """``pod_spec`` with a required node affinity: no vehicle label on the node."""
    away = {"key": LABEL_VEHICLE, "operator": "DoesNotExist"}
    affinity = dict(pod_spec.get("affinity") or {})
    node_affinity = dict(affinity.get("nodeAffinity") or {})
    required = dict(node_affinity.get("requiredDuringSchedulingIgnoredDuringExecution") or {})
    terms = list(required.get("nodeSelectorTerms") or [{}])
    required["nodeSelectorTerms"] = [
        {**term, "matchExpressions": [*(term.get("matchExpressions") or []), away]}
        for term in terms
    ]
    node_affinity["requiredDuringSchedulingIgnoredDuringExecution"] = required
    affinity["nodeAffinity"] = node_affinity
    return {**pod_spec, "affinity": affinity}


def offboard_job(*, mission: MissionRef, spec: MissionSpec, assigned: Sequence[str]) -> Obj:
    """The offboard Job: once, on a node that is not a vehicle."""
    template = spec.offboard or {}
    pod_spec = _off_vehicles(dict(template.get("spec") or {}))
    pod_spec = _with_env(pod_spec, mission_env(mission, assigned, None))
    return _job(
        name=offboard_job_name(mission.name),
        mission=mission,
        component=OFFBOARD,
        template=template,
        pod_spec=pod_spec,
        backoff_limit=spec.backoff_limit,
        extra_labels={},
    )


def config_map_copy(
    mission: MissionRef, vehicle_name: str, config_values: Mapping[str, str]
) -> Obj:
    """The vehicle's ConfigMap in the Mission's namespace, co-owned by the Mission.

    Not a controller reference: a later Mission in the same namespace flying the same
    vehicle applies the same ConfigMap.
    """
    return vehicle_config_map(
        vehicle_name,
        config_values,
        namespace=mission.namespace,
        owners=[mission_owner(mission, controller=False)],
    )


def template_probes(
    *,
    mission: MissionRef,
    spec: MissionSpec,
    vehicles: Sequence[str],
    config_values: Mapping[str, Mapping[str, str]],
) -> list[tuple[str, Obj]]:
    """The Jobs to send as a server-side dry run before the mission claims ``vehicles``.

    One onboard Job (on the first vehicle: the template is the same on all, only the
    placement and env differ) and the offboard Job, each with the name of the template
    it checks. The API server validates them exactly as it would the real ones, so a
    template it would refuse fails the mission before any vehicle is claimed.
    """
    if not vehicles:
        return []
    first = vehicles[0]
    probes = [
        (
            "spec.onboard",
            onboard_job(
                mission=mission,
                spec=spec,
                vehicle_name=first,
                assigned=vehicles,
                config_values=config_values.get(first, {}),
            ),
        )
    ]
    if spec.offboard is not None:
        probes.append(
            ("spec.offboard", offboard_job(mission=mission, spec=spec, assigned=vehicles))
        )
    return probes
