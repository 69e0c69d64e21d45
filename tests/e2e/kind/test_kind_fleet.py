"""Roost on KinD: the chart's real pods on a four-node KinD cluster (``make e2e-kind``).

tests/e2e/kind/run.sh creates the cluster from kind-config.yaml, loads Roost's images,
installs the chart and runs this module with ``ROOST_KIND_KUBECONFIG`` set; without it
(no container engine) every test here skips. Unlike the control-plane harness, the pods
here really run: the agent DaemonSet pod on each vehicle worker opens its serial port,
talks MAVLink to the vehicle's two autopilots and writes status with its own pod-bound
token. The autopilots are PX4 SITL pods on the Docker path (images pulled on first use)
and ``roost-sim`` processes in each worker's network namespace on the podman path
(``ROOST_KIND_SIMULATED=1``, :mod:`tests.support.kindfleet`), which also lets the tests
silence an autopilot (failover, shown by ``roost status``). A Mission runs an onboard
Job on every vehicle to completion; ``helm uninstall`` leaves no object behind.

The tests run in file order on one installation (each step builds on the last).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_api.wellknown import LABEL_VEHICLE, TAINT_VEHICLE
from roost_localcluster.cluster import Cluster
from roost_sim.faults import FaultKind
from tests.support.kindfleet import SimulatedKindFleet, fleet_documents
from tests.support.waiting import wait_until

KUBECONFIG = os.environ.get("ROOST_KIND_KUBECONFIG")
NAMESPACE = os.environ.get("ROOST_KIND_NAMESPACE", "roost-system")
ENGINE = os.environ.get("ROOST_KIND_ENGINE", "docker")
SIMULATED = os.environ.get("ROOST_KIND_SIMULATED") == "1"
ONBOARD_IMAGE = os.environ.get("ROOST_KIND_ONBOARD_IMAGE", "roost-agent:e2e")
FLEET = [doc for doc in fleet_documents() if doc["kind"] == "Vehicle"]
AGENT_SELECTOR = "app.kubernetes.io/component=agent,app.kubernetes.io/instance=roost"
RELEASE_SELECTOR = "app.kubernetes.io/instance=roost"
MISSION_NAMESPACE = "kind-missions"
BIN = Path(sys.executable).parent
# SITL images are pulled on first use: allow minutes, not seconds.
SLOW_S = 600.0
POLL_S = 2.0

pytestmark = pytest.mark.skipif(
    not KUBECONFIG, reason="KinD end-to-end: run `make e2e-kind` (needs a container engine)"
)
needs_simulators = pytest.mark.skipif(
    not SIMULATED, reason="needs the simulated autopilots of the podman path"
)


@pytest.fixture(scope="module")
def kind() -> Cluster:
    assert KUBECONFIG is not None
    return Cluster(Path(KUBECONFIG))


@pytest.fixture(scope="module", autouse=True)
def fleet(
    kind: Cluster, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SimulatedKindFleet | None]:
    """The fleet applied: simulators and their manifests, or fleet.yaml's SITL vehicles."""
    if not SIMULATED:
        kind.kubectl("apply", "-f", str(Path(__file__).parent / "fleet.yaml"))
        yield None
        return
    simulated = SimulatedKindFleet(ENGINE, tmp_path_factory.mktemp("kind-sims"))
    try:
        docs = simulated.start()
        kind.kubectl("apply", "-f", "-", input_text="\n---\n".join(yaml.safe_dump(d) for d in docs))
        yield simulated
    finally:
        simulated.stop()


def _get(kind: Cluster, *args: str) -> dict[str, Any]:
    result: dict[str, Any] = json.loads(kind.kubectl("get", *args, "-o", "json").stdout)
    return result


def _agent_pods(kind: Cluster) -> dict[str, dict[str, Any]]:
    pods = _get(kind, "pods", "-n", NAMESPACE, "-l", AGENT_SELECTOR)["items"]
    return {
        pod["spec"]["nodeName"]: pod
        for pod in pods
        if pod["status"].get("phase") == "Running" and pod["spec"].get("nodeName")
    }


def _exec_python(kind: Cluster, pod: dict[str, Any], code: str) -> str:
    result = kind.kubectl(
        "exec", "-n", NAMESPACE, pod["metadata"]["name"], "--", "python", "-c", code, check=False
    )
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


def test_operator_labels_and_taints_every_vehicle_worker(kind: Cluster) -> None:
    for vehicle in FLEET:
        node = vehicle["spec"]["nodeName"]

        def labelled(node: str = node, name: str = vehicle["metadata"]["name"]) -> bool:
            found = _get(kind, "node", node)
            taints = found["spec"].get("taints", [])
            return found["metadata"].get("labels", {}).get(LABEL_VEHICLE) == name and any(
                t["key"] == TAINT_VEHICLE for t in taints
            )

        wait_until(f"node {node} labelled and tainted for its vehicle", labelled, 120, POLL_S)


def test_agent_runs_on_every_vehicle_worker_and_nowhere_else(kind: Cluster) -> None:
    workers = {vehicle["spec"]["nodeName"] for vehicle in FLEET}
    wait_until(
        "agents on all vehicle workers", lambda: workers <= set(_agent_pods(kind)), SLOW_S, POLL_S
    )
    assert set(_agent_pods(kind)) == workers


def test_cluster_dns_answers_in_a_vehicle_agent_pod(kind: Cluster) -> None:
    """CoreDNS (built for the podman path's node image) serves the cluster's names: the
    agent pod (host network, ``ClusterFirstWithHostNet``) resolves the API's Service."""
    wait_until(
        "CoreDNS available",
        lambda: (
            _get(kind, "deployment", "coredns", "-n", "kube-system")
            .get("status", {})
            .get("availableReplicas", 0)
            >= 1
        ),
        SLOW_S,
        POLL_S,
    )
    pod = next(iter(_agent_pods(kind).values()))
    service_ip = _get(kind, "service", "kubernetes", "-n", "default")["spec"]["clusterIP"]
    resolved = _exec_python(
        kind,
        pod,
        "import socket; print(socket.getaddrinfo("
        "'kubernetes.default.svc.cluster.local', 443, proto=socket.IPPROTO_TCP)[0][4][0])",
    )
    assert resolved == service_ip


def test_agents_report_every_px4_sitl_autopilot_healthy(kind: Cluster) -> None:
    for vehicle in FLEET:
        name = vehicle["metadata"]["name"]

        def healthy(name: str = name) -> bool:
            status = _get(kind, "redundantautopilot", name).get("status", {})
            levels = [a.get("level") for a in status.get("autopilots", [])]
            return len(levels) == 2 and set(levels) == {"OK"}

        wait_until(f"{name}: both PX4 SITL autopilots OK", healthy, SLOW_S, POLL_S)
        status = _get(kind, "redundantautopilot", name)["status"]
        assert status["activeAutopilot"] == "px4-a"


def test_agent_opens_the_fake_serial_port_as_a_non_root_user(kind: Cluster) -> None:
    code = (
        "import os, termios; "
        "fd = os.open('/dev/ttyUSB0', os.O_RDWR | os.O_NOCTTY); "
        "termios.tcgetattr(fd); print(os.getuid())"
    )
    for pod in _agent_pods(kind).values():
        assert _exec_python(kind, pod, code) == "65532"


def test_agent_token_writes_only_its_own_vehicles_autopilot(kind: Cluster) -> None:
    pods = _agent_pods(kind)
    own, other = FLEET[0], FLEET[1]
    pod = pods[own["spec"]["nodeName"]]
    code = (
        "import json, os, sys\n"
        "from kubernetes import client, config\n"
        "from kubernetes.client.exceptions import ApiException\n"
        "config.load_incluster_config()\n"
        "api = client.CustomObjectsApi()\n"
        "out = {}\n"
        "for name in sys.argv[1:]:\n"
        "    try:\n"
        "        body = {'status': {'nodeName': os.environ['NODE_NAME']}}\n"
        "        api.patch_cluster_custom_object_status('roost.dev', 'v1alpha1',\n"
        "            'redundantautopilots', name, body)\n"
        "        out[name] = 200\n"
        "    except ApiException as error:\n"
        "        out[name] = error.status\n"
        "print(json.dumps(out))\n"
    )
    result = kind.kubectl(
        "exec",
        "-n",
        NAMESPACE,
        pod["metadata"]["name"],
        "--",
        "python",
        "-c",
        code,
        own["metadata"]["name"],
        other["metadata"]["name"],
    )
    answers = json.loads(result.stdout)
    assert answers == {own["metadata"]["name"]: 200, other["metadata"]["name"]: 403}


def _mission() -> dict[str, Any]:
    """Every vehicle flies: a short onboard Job on each (the agent image's Python)."""
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": "kind-survey", "namespace": MISSION_NAMESPACE},
        "spec": {
            "vehicles": {"selector": {"matchLabels": {"fleet": "kind-e2e"}}, "count": len(FLEET)},
            "onFailover": "AbortVehicle",
            "onboard": {
                "spec": {
                    "restartPolicy": "Never",
                    "containers": [
                        {
                            "name": "survey",
                            "image": ONBOARD_IMAGE,
                            "imagePullPolicy": "Never",
                            "command": ["python", "-c", "import time; time.sleep(3)"],
                        }
                    ],
                }
            },
        },
    }


@needs_simulators
def test_a_mission_runs_to_completion_on_every_vehicle(
    kind: Cluster, fleet: SimulatedKindFleet | None
) -> None:
    assert fleet is not None
    fleet.fly([v["metadata"]["name"] for v in FLEET])
    kind.kubectl("create", "namespace", MISSION_NAMESPACE, check=False)
    kind.kubectl("apply", "-f", "-", input_text=yaml.safe_dump(_mission()))

    def phase() -> str | None:
        status = _get(kind, "mission", "kind-survey", "-n", MISSION_NAMESPACE).get("status", {})
        found = status.get("phase")
        return found if found in ("Succeeded", "Failed", "Aborted") else None

    assert wait_until("the mission finished", phase, SLOW_S, POLL_S) == "Succeeded"
    status = _get(kind, "mission", "kind-survey", "-n", MISSION_NAMESPACE)["status"]
    assert {v["name"] for v in status["vehicles"]} == {v["metadata"]["name"] for v in FLEET}
    assert {v["nodeName"] for v in status["vehicles"]} == {v["spec"]["nodeName"] for v in FLEET}


@needs_simulators
def test_silenced_autopilot_fails_over_and_roost_status_shows_it(
    kind: Cluster, fleet: SimulatedKindFleet | None
) -> None:
    assert fleet is not None
    vehicle = FLEET[0]
    name = vehicle["metadata"]["name"]
    answer = fleet.control(
        name, "px4-a", {"op": "fault", "kind": FaultKind.SILENCE.value, "value": None}
    )
    assert answer.get("ok"), answer

    def active() -> str | None:
        found: str | None = (
            _get(kind, "redundantautopilot", name).get("status", {}).get("activeAutopilot")
        )
        return found

    wait_until("the failover to px4-b", lambda: active() == "px4-b", SLOW_S, POLL_S)
    last = _get(kind, "redundantautopilot", name)["status"]["lastFailover"]
    assert (last["from"], last["to"], last["trigger"]) == ("px4-a", "px4-b", "Automatic")
    done = subprocess.run(
        [str(BIN / "roost"), "--kubeconfig", str(KUBECONFIG), "status", "-o", "json"],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    rows = {row["vehicle"]: row for row in json.loads(done.stdout)}
    assert rows[name]["node"] == vehicle["spec"]["nodeName"]
    assert rows[name]["active"] == "px4-b"
    others = [v["metadata"]["name"] for v in FLEET[1:]]
    assert [rows[other]["active"] for other in others] == ["px4-a"] * len(others)


def test_helm_uninstall_leaves_nothing(kind: Cluster) -> None:
    kind.kubectl("delete", "namespace", MISSION_NAMESPACE, "--ignore-not-found", "--wait=true")
    kind.helm("uninstall", "roost", "--namespace", NAMESPACE, "--wait")
    kinds = (
        "all,serviceaccounts,configmaps,roles,rolebindings,clusterroles,clusterrolebindings,"
        "validatingadmissionpolicies,validatingadmissionpolicybindings"
    )

    def left() -> str:
        return kind.kubectl("get", kinds, "-A", "-l", RELEASE_SELECTOR, "-o", "name").stdout

    wait_until("no object of the release left", lambda: not left().strip(), SLOW_S, POLL_S)
    wait_until("no agent pod left", lambda: not _agent_pods(kind), SLOW_S, POLL_S)
