"""Per-Vehicle signing keys on real kubelets: a node may read its own vehicle's key only.

Two real nodes of the harness (kubelets with node credentials, the API server with the
Node authorizer and NodeRestriction) each get the key pod the operator builds for their
vehicle (:func:`roost_operator.vehicles.manifests.signing_keys_workload`, the same
manifest the operator applies). The kubelet of node A then reads A's key Secret with
its own credentials, and is refused B's: the agent DaemonSet mounts no Secret, so no pod
on A gives A's kubelet a reason to read B's. The kubelet also really mounts the Secret
into the key pod (the pod runs).

The key pod's container here runs the harness's pause image, not the agent image: the
images ``make images`` builds are shared by every checkout of this machine and are
built from one of them, so this test does not depend on them; what it proves is the
authorisation, which the image does not affect. The hand-over itself (files, modes,
rotation reaching the agent's key watcher) is tested on real files in
tests/unit/test_operator_vehicles_desired_signing_keys.py and tests/unit/test_agent_keysync.py.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import LABEL_VEHICLE, SIGNING_HOST_DIR
from roost_cli.keys import key_secret
from roost_localcluster import binaries
from roost_localcluster.clients import tool_path
from roost_localcluster.cluster import Cluster
from roost_localcluster.realnode import RealNode, RealNodes
from roost_operator.vehicles.config import vehicle_config, vehicle_config_map
from roost_operator.vehicles.manifests import (
    DEFAULT_FCU_URL,
    SIGNING_KEYS,
    component_pod,
    component_workloads,
)
from tests.support.waiting import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

NAMESPACE = "real-node-keys"
VEHICLES = {"keys-drone-a": "real-node-keys-a", "keys-drone-b": "real-node-keys-b"}


def key_pod(vehicle: str, node: str) -> dict[str, Any]:
    """The operator's key pod for ``vehicle``, with the pause image (module docstring)."""
    spec = VehicleSpec.model_validate(
        {"nodeName": node, "sysid": 1, "components": {"signingKeys": {"enabled": True}}}
    )
    (workload,) = [
        w
        for w in component_workloads(spec, [], vehicle_name=vehicle)
        if w.component == SIGNING_KEYS
    ]
    values = vehicle_config(
        name=vehicle, spec=spec, fcu_url=DEFAULT_FCU_URL, firmware=None, active_autopilot=None
    )
    pod = component_pod(vehicle, node, workload, values, namespace=NAMESPACE, owners=[])
    container = pod["spec"]["containers"][0]
    container.update(image=binaries.pause_image(binaries.node_dir()), imagePullPolicy="Never")
    for field in ("command", "args"):
        container.pop(field)
    # The vehicle config the operator writes beside it (the pod mounts it).
    config = vehicle_config_map(vehicle, values, namespace=NAMESPACE)
    return {"apiVersion": "v1", "kind": "List", "items": [config, pod]}


@pytest.fixture(scope="module")
def nodes(cluster: Cluster, real_nodes: RealNodes) -> Iterator[dict[str, RealNode]]:
    cluster.kubectl("create", "namespace", NAMESPACE)
    added: dict[str, RealNode] = {}
    try:
        for vehicle, node in VEHICLES.items():
            added[vehicle] = real_nodes.add(node)
            # As the operator binds a Vehicle (the key pod selects the vehicle's node:
            # without the label, the node's own kubelet refuses the pod).
            cluster.kubectl("label", "node", node, f"{LABEL_VEHICLE}={vehicle}")
            secret = key_secret(vehicle, NAMESPACE, f"passphrase-of-{vehicle}")
            cluster.kubectl("apply", "-f", "-", input_text=json.dumps(secret))
            cluster.kubectl("apply", "-f", "-", input_text=json.dumps(key_pod(vehicle, node)))
        yield added
    finally:
        cluster.kubectl("delete", "namespace", NAMESPACE, "--wait=false", check=False)
        for node in added.values():
            real_nodes.remove(node.name)
        # The harness's nodes share this machine's file system: the kubelet made the key
        # pods' (empty: pause writes nothing) host directories here.
        for vehicle in added:
            host_dir = Path(SIGNING_HOST_DIR) / vehicle
            if host_dir.is_dir() and not any(host_dir.iterdir()):
                host_dir.rmdir()


def as_kubelet(node: RealNode, *args: str) -> subprocess.CompletedProcess[str]:
    """kubectl with the node's own kubelet credentials, from the node's namespace."""
    argv = [str(tool_path("kubectl")), "--kubeconfig", str(node.directory / "kubelet.kubeconfig")]
    return subprocess.run(
        node.run_in_namespace([*argv, *args]), capture_output=True, text=True, check=False
    )


def running(cluster: Cluster, name: str) -> bool:
    pod = json.loads(cluster.kubectl("get", "pod", name, "-n", NAMESPACE, "-o", "json").stdout)
    return bool(pod.get("status", {}).get("phase") == "Running")


def test_each_key_pod_runs_on_its_node_with_its_secret_mounted(
    cluster: Cluster, nodes: dict[str, RealNode]
) -> None:
    for vehicle in VEHICLES:
        name = f"{vehicle}-{SIGNING_KEYS}"
        wait_until(f"{name} Running (its Secret mounted)", lambda n=name: running(cluster, n), 120)


def test_a_nodes_kubelet_reads_its_own_vehicles_key_and_is_refused_the_others(
    cluster: Cluster, nodes: dict[str, RealNode]
) -> None:
    node_a, node_b = nodes["keys-drone-a"], nodes["keys-drone-b"]
    for node, own, other in (
        (node_a, "keys-drone-a", "keys-drone-b"),
        (node_b, "keys-drone-b", "keys-drone-a"),
    ):
        mine = as_kubelet(
            node, "get", "secret", f"roost-signing-{own}", "-n", NAMESPACE, "-o", "name"
        )
        assert mine.returncode == 0, mine.stderr
        theirs = as_kubelet(node, "get", "secret", f"roost-signing-{other}", "-n", NAMESPACE)
        assert theirs.returncode != 0
        assert "forbidden" in theirs.stderr.lower(), theirs.stderr
        assert "no relationship found between node" in theirs.stderr, theirs.stderr
    # nor may a kubelet list the namespace's Secrets
    listed = as_kubelet(node_a, "get", "secrets", "-n", NAMESPACE)
    assert listed.returncode != 0 and "forbidden" in listed.stderr.lower()
