"""A real node of the harness: kubelet, containerd and CNI in a network namespace of its own.

Proves the harness part the chart suite stands on: the node registers and gets Ready beside
kwok nodes, runs a host-network pod in *its* namespace (the node's address) and a pod on
the CNI bridge (an address of the node's pod subnet), serves ``kubectl logs`` and ``exec``
through its kubelet (certificate signed by the harness CA, the API server's kubelet client
certificate authorised by webhook), and leaves nothing behind when removed: no process,
mount, cgroup, namespace or link.
"""

from __future__ import annotations

import atexit
import ipaddress
import json
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster, FakeNodes
from roost_localcluster.realnode import (
    CNI_CACHE,
    CONTAINER_LOG_LINKS,
    RUNTIME_ROOT,
    RealNode,
    RealNodes,
    cgroup_mounts,
    mounts_under,
    sweep_stale,
)
from tests.support.waiting import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

NODE = "real-node-basic"
NAMESPACE = "real-node-basic"


def _pod(name: str, node: str, host_network: bool) -> dict[str, Any]:
    image = binaries.pause_image(binaries.node_dir())
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {"name": name, "namespace": NAMESPACE},
        "spec": {
            "nodeName": node,
            "hostNetwork": host_network,
            "terminationGracePeriodSeconds": 1,
            "containers": [{"name": "main", "image": image, "imagePullPolicy": "Never"}],
        },
    }


def _running(cluster: Cluster, name: str) -> dict[str, Any] | None:
    pod: dict[str, Any] = json.loads(
        cluster.kubectl("get", "pod", name, "-n", NAMESPACE, "-o", "json").stdout
    )
    return pod if pod.get("status", {}).get("phase") == "Running" else None


@pytest.fixture(scope="module")
def node(cluster: Cluster, real_nodes: RealNodes) -> Iterator[RealNode]:
    added = real_nodes.add(NODE, labels={"roost.dev/test": "real-node"})
    cluster.kubectl("create", "namespace", NAMESPACE)
    yield added
    cluster.kubectl("delete", "namespace", NAMESPACE, "--wait=false")
    real_nodes.remove(NODE)


def test_node_is_ready_beside_kwok_nodes(
    cluster: Cluster, node: RealNode, fake_nodes: FakeNodes
) -> None:
    fake_nodes("real-node-basic-kwok")
    cluster.wait_nodes_ready([NODE, "real-node-basic-kwok"])
    found = json.loads(cluster.kubectl("get", "node", NODE, "-o", "json").stdout)
    addresses = {a["type"]: a["address"] for a in found["status"]["addresses"]}
    assert addresses["InternalIP"] == node.address
    assert found["status"]["nodeInfo"]["containerRuntimeVersion"].startswith("containerd://")
    assert found["metadata"]["labels"]["roost.dev/test"] == "real-node"


def test_host_network_pod_runs_in_the_node_namespace_with_logs_and_exec(
    cluster: Cluster, node: RealNode
) -> None:
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(_pod("host", NODE, True)))
    pod = wait_until("the host-network pod Running", lambda: _running(cluster, "host"), 120)
    assert pod["status"]["podIP"] == node.address
    logs = cluster.kubectl("logs", "host", "-n", NAMESPACE).stdout
    assert "roost-pause: holding the pod's namespaces" in logs
    done = cluster.kubectl("exec", "host", "-n", NAMESPACE, "--", "/pause", "-v")
    assert done.stdout.strip() == "roost-pause"


def test_pod_network_pod_gets_an_address_of_the_node_pod_subnet(
    cluster: Cluster, node: RealNode
) -> None:
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(_pod("bridged", NODE, False)))
    pod = wait_until("the bridged pod Running", lambda: _running(cluster, "bridged"), 120)
    address = ipaddress.ip_address(pod["status"]["podIP"])
    assert address in ipaddress.ip_network(node.pod_subnet)
    # The pod's own network namespace, on the CNI bridge inside the node's namespace.
    links = subprocess.run(
        ["ip", "-n", node.namespace, "-br", "link"], capture_output=True, text=True, check=True
    ).stdout
    assert "cni0" in links


def _leftovers(node: RealNode) -> list[str]:
    found = []
    if any(p.alive() for p in node.processes.values()):
        found.append("processes")
    if mounts_under(node.directory, node.runtime_dir):
        found.append(f"mounts {mounts_under(node.directory, node.runtime_dir)}")
    found += [f"cgroup {m}" for m in cgroup_mounts() if (m / node.cgroup.lstrip("/")).exists()]
    namespaces = subprocess.run(
        ["ip", "netns", "list"], capture_output=True, text=True, check=True
    ).stdout
    if node.namespace in namespaces.split():
        found.append(f"netns {node.namespace}")
    found += [f"CNI cache {p}" for p in CNI_CACHE.glob(f"{node.namespace}-*")]
    found += [
        f"log link {link}"
        for link in CONTAINER_LOG_LINKS.glob("*.log")
        if link.is_symlink() and link.readlink().is_relative_to(node.directory)
    ]
    tag = node.namespace.split("-")[1]
    if Path(f"/sys/class/net/rn{tag}-{node.index}").exists():
        found.append("veth")
    return found


def test_removing_a_node_with_a_running_pod_leaves_nothing(
    cluster: Cluster, real_nodes: RealNodes
) -> None:
    name = "real-node-removed"
    removed = real_nodes.add(name)
    manifest = _pod("doomed", name, False)
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
    wait_until("the doomed pod Running", lambda: _running(cluster, "doomed"), 120)
    processes = dict(removed.processes)
    real_nodes.remove(name)
    cluster.kubectl(
        "delete", "pod", "doomed", "-n", NAMESPACE, "--force", "--grace-period=0", check=False
    )
    assert not any(p.alive() for p in processes.values())
    removed.processes = processes
    assert _leftovers(removed) == []
    gone = cluster.kubectl("get", "node", name, check=False)
    assert gone.returncode != 0


def test_a_dead_pools_leftovers_are_swept_by_the_next_pool(
    cluster: Cluster, real_nodes: RealNodes, tmp_path: Path
) -> None:
    """A test run killed with SIGKILL takes its node programs along (parent-death signal)
    but leaves namespaces, links, cgroups, mounts and running containers: the next pool
    takes them down from the record the dead one left."""
    orphaned = RealNodes(cluster, tmp_path / "orphaned")
    atexit.unregister(orphaned.cleanup)  # this pool's process "dies" below
    name = "real-node-orphan"
    node = orphaned.add(name)
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(_pod("orphan", name, False)))
    wait_until("the orphan's pod Running", lambda: _running(cluster, "orphan"), 120)
    for proc in [*node.processes.values(), orphaned.relay]:
        assert proc is not None
        proc.crash()
    record_path = RUNTIME_ROOT / f"{orphaned.tag}.json"
    record = json.loads(record_path.read_text())
    record["create_time"] = 0.0  # the owner is another process than the one recorded
    record_path.write_text(json.dumps(record))
    assert _leftovers(node), "the dead pool left nothing to sweep"

    assert orphaned.tag in sweep_stale()
    assert _leftovers(node) == []
    assert not record_path.exists()
    assert orphaned.network is not None
    assert not Path(f"/sys/class/net/{orphaned.network.bridge}").exists()
    cluster.kubectl(
        "delete", "pod", "orphan", "-n", NAMESPACE, "--force", "--grace-period=0", check=False
    )
    cluster.kubectl("delete", "node", name)
    # The orphaned pool pointed the `kubernetes` Service at its own (dead) relay: the
    # session pool's pods of later modules (the operator) must reach the API server again.
    real_nodes.publish_api()
