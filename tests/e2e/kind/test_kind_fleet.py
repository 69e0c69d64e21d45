"""Roost on KinD with real images and real PX4 SITL (run by ``make e2e-kind``).

tests/e2e/kind/run.sh creates the cluster from kind-config.yaml, installs the chart
with values-kind.yaml, applies tests/e2e/kind/fleet.yaml and runs this module with
``ROOST_KIND_KUBECONFIG`` set; without it (no container engine) every test here skips.
Unlike the control-plane harness, the pods here really run: the agent opens its serial
port, talks MAVLink to PX4 SITL and writes status with its own pod-bound token.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_api.wellknown import LABEL_VEHICLE, TAINT_VEHICLE
from roost_localcluster.cluster import Cluster

KUBECONFIG = os.environ.get("ROOST_KIND_KUBECONFIG")
NAMESPACE = os.environ.get("ROOST_KIND_NAMESPACE", "roost-system")
FLEET = [
    doc
    for doc in yaml.safe_load_all((Path(__file__).parent / "fleet.yaml").read_text())
    if doc and doc["kind"] == "Vehicle"
]
AGENT_SELECTOR = "app.kubernetes.io/component=agent,app.kubernetes.io/instance=roost"
# SITL images are pulled on first use: allow minutes, not seconds.
SLOW_S = 600.0

pytestmark = pytest.mark.skipif(
    not KUBECONFIG, reason="KinD end-to-end: run `make e2e-kind` (needs a container engine)"
)


@pytest.fixture(scope="module")
def kind() -> Cluster:
    assert KUBECONFIG is not None
    return Cluster(Path(KUBECONFIG))


def _wait_for(what: str, check: Callable[[], bool], timeout_s: float = SLOW_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f}s waiting for {what}")
        time.sleep(2.0)


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

        _wait_for(f"node {node} labelled and tainted for its vehicle", labelled, 120)


def test_agent_runs_on_every_vehicle_worker_and_nowhere_else(kind: Cluster) -> None:
    workers = {vehicle["spec"]["nodeName"] for vehicle in FLEET}
    _wait_for("agents on all vehicle workers", lambda: workers <= set(_agent_pods(kind)))
    assert set(_agent_pods(kind)) == workers


def test_agents_report_every_px4_sitl_autopilot_healthy(kind: Cluster) -> None:
    for vehicle in FLEET:
        name = vehicle["metadata"]["name"]

        def healthy(name: str = name) -> bool:
            status = _get(kind, "redundantautopilot", name).get("status", {})
            levels = [a.get("level") for a in status.get("autopilots", [])]
            return len(levels) == 2 and set(levels) == {"OK"}

        _wait_for(f"{name}: both PX4 SITL autopilots OK", healthy)
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
