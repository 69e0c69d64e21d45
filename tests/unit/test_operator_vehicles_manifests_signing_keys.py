"""The per-Vehicle key pod the operator plans: when it runs, what it mounts, where it runs
(the hand-over the pod performs is in ``test_agent_keysync.py``)."""

from __future__ import annotations

from typing import Any

import pytest

from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import SIGNING_HOST_DIR
from roost_kube.patches import Obj
from roost_operator.vehicles.config import vehicle_config
from roost_operator.vehicles.manifests import (
    DEFAULT_FCU_URL,
    DEFAULT_IMAGES,
    SIGNING_KEYS,
    component_pod,
    component_workloads,
    pod_hash,
)


def spec(signing_keys: dict[str, Any] | None = None, **overrides: object) -> VehicleSpec:
    components = {} if signing_keys is None else {"signingKeys": signing_keys}
    return VehicleSpec.model_validate(
        {"nodeName": "node-a", "sysid": 12, "components": components, **overrides}
    )


def key_pod(vehicle: str, s: VehicleSpec, node: str = "node-a") -> Obj:
    (workload,) = [
        w for w in component_workloads(s, [], vehicle_name=vehicle) if w.component == SIGNING_KEYS
    ]
    values = vehicle_config(
        name=vehicle, spec=s, fcu_url=DEFAULT_FCU_URL, firmware=None, active_autopilot=None
    )
    return component_pod(vehicle, node, workload, values, namespace="roost", owners=[])


# -- when: decision table ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("signing_keys", "simulated", "runs"),
    [
        (None, False, False),  # default: no key pod (a vehicle without signing)
        ({"enabled": False}, False, False),
        ({"enabled": True}, False, True),
        ({"enabled": True}, True, True),  # simulated vehicles sign too
        ({"enabled": True, "image": "registry.example/roost-agent:1"}, False, True),
    ],
)
def test_the_key_pod_runs_exactly_when_the_vehicle_asks_for_it(
    signing_keys: dict[str, Any] | None, simulated: bool, runs: bool
) -> None:
    extra: dict[str, object] = {"simulation": {"stack": "px4"}} if simulated else {}
    components = [
        w.component for w in component_workloads(spec(signing_keys, **extra), [], vehicle_name="d1")
    ]
    assert (SIGNING_KEYS in components) is runs


@pytest.mark.parametrize(
    ("image", "agent_image", "expected"),
    [
        (None, None, DEFAULT_IMAGES[SIGNING_KEYS]),
        (None, "roost-agent:1.4.0", "roost-agent:1.4.0"),  # the chart's agent image
        ("registry.example/roost-agent:1", "roost-agent:1.4.0", "registry.example/roost-agent:1"),
    ],
)
def test_the_key_pod_uses_the_agent_image_unless_the_vehicle_names_one(
    image: str | None, agent_image: str | None, expected: str
) -> None:
    workloads = component_workloads(
        spec({"enabled": True, "image": image}), [], vehicle_name="d1", agent_image=agent_image
    )
    assert [w.image for w in workloads if w.component == SIGNING_KEYS] == [expected]


# -- what and where ----------------------------------------------------------------------


@pytest.mark.parametrize("vehicle", ["drone-1", "drone-2"])
def test_the_key_pod_mounts_only_its_own_vehicles_secret_on_its_own_node(vehicle: str) -> None:
    pod = key_pod(vehicle, spec({"enabled": True}), node=f"node-of-{vehicle}")
    pod_spec = pod["spec"]
    assert pod_spec["nodeName"] == f"node-of-{vehicle}"
    secrets = [v["secret"]["secretName"] for v in pod_spec["volumes"] if "secret" in v]
    assert secrets == [f"roost-signing-{vehicle}"]
    host = [v["hostPath"]["path"] for v in pod_spec["volumes"] if "hostPath" in v]
    assert host == [f"{SIGNING_HOST_DIR}/{vehicle}"]
    # no API credentials: it reads its Secret through the kubelet only
    assert pod_spec["automountServiceAccountToken"] is False
    container = pod_spec["containers"][0]
    assert container["securityContext"]["capabilities"] == {"drop": ["ALL"], "add": ["CHOWN"]}
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    assert "--owner=65532:65532" in container["args"]


def test_the_secret_name_cannot_be_chosen_by_the_spec() -> None:
    """Only the Vehicle's name picks the Secret: a Vehicle cannot have another Secret
    mounted on its node (the spec has no field that names one; an unknown one is
    dropped)."""
    pod = key_pod("d1", spec({"enabled": True, "secretName": "roost-operator-token"}))
    secrets = [v["secret"]["secretName"] for v in pod["spec"]["volumes"] if "secret" in v]
    assert secrets == ["roost-signing-d1"]


def test_a_node_change_replaces_the_key_pod() -> None:
    s = spec({"enabled": True})
    assert pod_hash(key_pod("d1", s, "node-a")) != pod_hash(key_pod("d1", s, "node-b"))


# -- the hand-over ----------------------------------------------------------------------
