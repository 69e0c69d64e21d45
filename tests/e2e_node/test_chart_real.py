"""The Helm chart's real pods on real harness nodes, end to end.

Unlike ``tests/e2e/test_chart.py`` (kwok marks pods Running without running them), here
the operator and agent images built by ``make images`` run in containerd on real kubelets
(:mod:`tests.support.realfleet`): ``helm install`` with values pointing at the imported
images; the operator pod, on a ground node, reaches the API server through the
``kubernetes`` Service and binds a Vehicle to the vehicle node; the chart's agent
DaemonSet pod starts there on the node's host network, with its pod-bound service-account
token under the chart's admission policy, talks MAVLink to two simulated autopilots on
the node's loopback, reports their health, and fails over when the active one goes
silent, which ``roost status`` shows. ``helm upgrade`` with changed values leaves the
agent of the flying vehicle running; ``helm uninstall`` leaves no object and no container.

The tests run in file order on one installation (each step builds on the last).
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from roost_localcluster.cluster import Cluster
from roost_localcluster.realnode import RealNodes
from roost_operator.engine.leader import LEASE_NAME
from roost_sim.faults import FaultKind
from tests.support.images import missing_tools
from tests.support.realfleet import GROUND_NODE, VEHICLE, WAIT_S, RealFleet
from tests.support.waiting import wait_until

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(1800),  # builds the images first when they are not cached
    pytest.mark.skipif(
        bool(missing_tools()),
        reason=f"image tools not installed: {', '.join(missing_tools())} "
        "(`make images` installs them on Debian)",
    ),
]

BIN = Path(sys.executable).parent
NODE_NAME_KEY = "authentication.kubernetes.io/node-name"


@pytest.fixture(scope="module")
def fleet(
    cluster: Cluster, real_nodes: RealNodes, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[RealFleet]:
    running = RealFleet(cluster, real_nodes, tmp_path_factory.mktemp("real-fleet"))
    try:
        running.start()
        yield running
    finally:
        running.stop()


def _conditions(obj: dict[str, Any]) -> dict[str, str]:
    return {c["type"]: c["status"] for c in obj.get("status", {}).get("conditions", [])}


def test_operator_pods_run_on_the_ground_node_one_leads_and_it_binds_the_vehicle(
    fleet: RealFleet,
) -> None:
    pods = fleet.pods("operator")
    assert len(pods) == 2  # the chart's replicas, electing a leader on a Lease
    for pod in pods:
        assert pod["spec"]["nodeName"] == GROUND_NODE
        assert pod["status"]["phase"] == "Running"
        # On the pod network: it reached the API server through the kubernetes Service.
        assert fleet.ground is not None and pod["status"]["podIP"] != fleet.ground.address
    lease = fleet.get("lease", LEASE_NAME, namespaced=True)
    assert lease["spec"]["holderIdentity"] in {pod["metadata"]["name"] for pod in pods}
    assert fleet.node_labelled()
    wait_until(
        "Vehicle NodeBound=True",
        lambda: _conditions(fleet.get("vehicle", VEHICLE)).get("NodeBound") == "True",
        WAIT_S,
    )


def test_agent_pod_runs_on_the_vehicle_node_with_its_node_bound_token(fleet: RealFleet) -> None:
    pod = fleet.agent_pod()
    assert pod is not None and pod["status"]["phase"] == "Running"
    assert fleet.vehicle_node is not None
    assert pod["spec"]["hostNetwork"] is True
    assert pod["status"]["podIP"] == fleet.vehicle_node.address  # the node's own network
    # The token the kubelet mounted is bound to the pod and carries its node, which is
    # what the chart's admission policy checks on every status write.
    name = pod["metadata"]["name"]
    read_token = "print(open('/var/run/secrets/kubernetes.io/serviceaccount/token').read())"
    token = fleet.cluster.kubectl(
        "exec", name, "-n", fleet.namespace, "--", "python3", "-c", read_token
    ).stdout.strip()
    review = {"apiVersion": "authentication.k8s.io/v1", "kind": "TokenReview"}
    review["spec"] = {"token": token}  # type: ignore[assignment]
    answer = json.loads(
        fleet.cluster.kubectl(
            "create", "-o", "json", "-f", "-", input_text=json.dumps(review)
        ).stdout
    )
    user = answer["status"]["user"]
    assert (
        user["username"] == f"system:serviceaccount:{fleet.namespace}:{fleet.release}-roost-agent"
    )
    assert user["extra"][NODE_NAME_KEY] == [fleet.vehicle.node]


def test_agent_reports_both_autopilots_healthy_from_its_node(fleet: RealFleet) -> None:
    assert fleet.reported()
    status = fleet.autopilot_status()
    assert status["activeAutopilot"] == "px4-a"
    assert _conditions({"status": status})["Ready"] == "True"


def test_kubectl_logs_of_the_agent(fleet: RealFleet) -> None:
    pod = fleet.agent_pod()
    assert pod is not None
    logs = fleet.cluster.kubectl("logs", pod["metadata"]["name"], "-n", fleet.namespace).stdout
    assert logs.strip(), "the agent logged nothing"
    assert "Traceback" not in logs, logs[-3000:]


def test_helm_upgrade_leaves_the_agent_of_a_flying_vehicle_running(fleet: RealFleet) -> None:
    fleet.fly()
    wait_until(
        "the vehicle airborne",
        lambda: all(a.get("armed") for a in fleet.autopilot_status().get("autopilots", [])),
        WAIT_S,
    )
    before = fleet.agent_pod()
    assert before is not None and fleet.ground is not None
    daemonset = fleet.get("daemonset", fleet.agent_daemonset, namespaced=True)
    fleet.helm(fleet.values(logLevel="DEBUG"))
    wait_until(
        "the DaemonSet controller to see the new template",
        lambda: (
            (found := fleet.get("daemonset", fleet.agent_daemonset, namespaced=True))["metadata"][
                "generation"
            ]
            > daemonset["metadata"]["generation"]
            and found["status"].get("observedGeneration") == found["metadata"]["generation"]
        ),
        WAIT_S,
    )
    after = fleet.agent_pod()
    assert after is not None
    assert after["metadata"]["uid"] == before["metadata"]["uid"]
    assert after["status"]["containerStatuses"][0]["restartCount"] == 0
    assert "--log-level=INFO" in after["spec"]["containers"][0]["args"]  # the old template
    # the same agent, never restarted, still reports every autopilot healthy (a flying
    # autopilot's level may pass through a warning on a loaded machine: waited out)
    wait_until("the agent reporting every autopilot OK", fleet.reported, WAIT_S)


def test_silenced_autopilot_fails_over_and_roost_status_shows_it(fleet: RealFleet) -> None:
    answer = fleet.control("px4-a", {"op": "fault", "kind": FaultKind.SILENCE.value, "value": None})
    assert answer.get("ok"), answer
    wait_until(
        "the failover to px4-b",
        lambda: fleet.autopilot_status().get("activeAutopilot") == "px4-b",
        WAIT_S,
    )
    last = fleet.autopilot_status()["lastFailover"]
    assert (last["from"], last["to"], last["trigger"]) == ("px4-a", "px4-b", "Automatic")
    done = subprocess.run(
        [str(BIN / "roost"), "--kubeconfig", str(fleet.cluster.kubeconfig), "status", "-o", "json"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    rows = {row["vehicle"]: row for row in json.loads(done.stdout)}
    row = rows[VEHICLE]
    assert row["node"] == fleet.vehicle.node
    assert row["active"] == "px4-b"


def test_helm_uninstall_leaves_nothing(fleet: RealFleet) -> None:
    agent = fleet.agent_pod()
    assert agent is not None and fleet.containers(), "the agent's containers before uninstall"
    fleet.uninstall()
    selector = f"app.kubernetes.io/instance={fleet.release}"
    kinds = (
        "all,serviceaccounts,configmaps,roles,rolebindings,clusterroles,clusterrolebindings,"
        "validatingadmissionpolicies,validatingadmissionpolicybindings,clusterkopfpeerings"
    )

    def left() -> str:
        return fleet.cluster.kubectl("get", kinds, "-A", "-l", selector, "-o", "name").stdout

    # Pods go with a grace period after their owners (garbage collector, then kubelet).
    wait_until("no object of the release left", lambda: not left().strip(), WAIT_S)
    wait_until(
        "the agent's containers gone from the vehicle node",
        lambda: not fleet.containers(),
        WAIT_S,
    )
