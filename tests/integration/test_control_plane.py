"""The harness's control plane behaves like a real cluster, and Roost's API holds up on it.

Everything here runs against real binaries (localcluster/): the CRDs and their CEL rules are
evaluated by kube-apiserver, workloads are reconciled by kube-controller-manager, bound by
kube-scheduler and "run" by kwok's fake kubelets. Names are unique per test because the
cluster is shared by the whole session.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.mission import MissionSpec
from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import LABEL_VEHICLE, LABEL_VEHICLE_CLASS
from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.cluster import Cluster, FakeNodes
from roost_localcluster.controlplane import ControlPlane, Settings
from roost_localcluster.processes import ManagedProcess
from tests.support.waiting import unique, wait_until

pytestmark = pytest.mark.cluster

CRDS = REPO_ROOT / "crds"
EXAMPLES = REPO_ROOT / "examples"
EXPECT_PREFIX = "# expect: "


def get_json(cluster: Cluster, *args: str) -> Any:
    return json.loads(cluster.kubectl("get", *args, "-o", "json").stdout)


# ---- CRDs ------------------------------------------------------------------------------


@pytest.mark.parametrize("crd_file", sorted(CRDS.glob("*.yaml")), ids=lambda p: p.stem)
def test_crd_is_established(roost_crds: Cluster, crd_file: Path) -> None:
    name = yaml.safe_load(crd_file.read_text())["metadata"]["name"]
    conditions = {
        c["type"]: c["status"] for c in get_json(roost_crds, "crd", name)["status"]["conditions"]
    }
    assert conditions.get("Established") == "True"
    assert conditions.get("NamesAccepted") == "True"


@pytest.mark.parametrize(
    ("path", "model", "field"),
    [
        ("vehicle.spec.sysid", VehicleSpec, "sysid"),
        ("redundantautopilot.spec.primary", RedundantAutopilotSpec, "primary"),
        ("mission.spec.vehicles", MissionSpec, "vehicles"),
    ],
)
def test_kubectl_explain_shows_field_descriptions(
    roost_crds: Cluster, path: str, model: Any, field: str
) -> None:
    description: str = model.model_fields[field].description
    explained = roost_crds.kubectl("explain", path).stdout
    assert " ".join(description.split()) in " ".join(explained.split())


# ---- examples ----------------------------------------------------------------------------


def _expected_error(path: Path) -> str:
    first = path.read_text().splitlines()[0]
    assert first.startswith(EXPECT_PREFIX), f"{path} must start with '{EXPECT_PREFIX}<message>'"
    return first[len(EXPECT_PREFIX) :].strip()


@pytest.mark.parametrize("example", sorted(EXAMPLES.glob("*.yaml")), ids=lambda p: p.stem)
def test_valid_example_is_accepted(roost_crds: Cluster, example: Path) -> None:
    result = roost_crds.kubectl("create", "--dry-run=server", "-f", str(example), check=False)
    assert result.returncode == 0, result.stderr
    created = len([d for d in yaml.safe_load_all(example.read_text()) if d])
    assert result.stdout.count("created (server dry run)") == created


@pytest.mark.parametrize(
    "example", sorted((EXAMPLES / "invalid").glob("*.yaml")), ids=lambda p: p.stem
)
def test_invalid_example_is_rejected_with_its_message(roost_crds: Cluster, example: Path) -> None:
    expected = _expected_error(example)
    result = roost_crds.kubectl("create", "--dry-run=server", "-f", str(example), check=False)
    assert result.returncode != 0, f"accepted: {result.stdout}"
    assert expected in result.stderr


# ---- workloads on fake vehicle nodes ---------------------------------------------------------


def test_daemonset_runs_one_pod_per_vehicle_node(cluster: Cluster, fake_nodes: FakeNodes) -> None:
    fleet = unique("fleet")
    vehicles = [unique("vehicle") for _ in range(3)]
    for name in vehicles:
        fake_nodes(name, labels={LABEL_VEHICLE: name, LABEL_VEHICLE_CLASS: fleet})
    fake_nodes(unique("ground"), labels={"roost.dev/test-ground": fleet})
    ds = unique("agent")
    manifest = {
        "apiVersion": "apps/v1",
        "kind": "DaemonSet",
        "metadata": {"name": ds, "namespace": "default"},
        "spec": {
            "selector": {"matchLabels": {"app": ds}},
            "template": {
                "metadata": {"labels": {"app": ds}},
                "spec": {
                    "nodeSelector": {LABEL_VEHICLE_CLASS: fleet},
                    "containers": [{"name": "agent", "image": "roost-agent:test"}],
                },
            },
        },
    }
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))

    def running_nodes() -> list[str]:
        pods = get_json(cluster, "pods", "-n", "default", "-l", f"app={ds}")["items"]
        return sorted(p["spec"]["nodeName"] for p in pods if p["status"]["phase"] == "Running")

    wait_until("one Running pod per vehicle node", lambda: running_nodes() == sorted(vehicles))
    status = get_json(cluster, "daemonset", ds, "-n", "default")["status"]
    assert status["desiredNumberScheduled"] == len(vehicles)
    cluster.kubectl("delete", "daemonset", ds, "-n", "default", "--wait=false")


def test_job_on_a_fake_node_completes(cluster: Cluster, fake_nodes: FakeNodes) -> None:
    node = unique("vehicle")
    fake_nodes(node, labels={LABEL_VEHICLE: node})
    job = unique("mission-step")
    manifest = {
        "apiVersion": "batch/v1",
        "kind": "Job",
        "metadata": {"name": job, "namespace": "default"},
        "spec": {
            "backoffLimit": 0,
            "template": {
                "spec": {
                    "nodeSelector": {LABEL_VEHICLE: node},
                    "restartPolicy": "Never",
                    "containers": [{"name": "step", "image": "busybox"}],
                }
            },
        },
    }
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
    cluster.kubectl(
        "wait", "--for=condition=Complete", f"job/{job}", "-n", "default", "--timeout=60s"
    )
    pods = get_json(cluster, "pods", "-n", "default", "-l", f"job-name={job}")["items"]
    assert [p["spec"]["nodeName"] for p in pods] == [node]
    assert pods[0]["status"]["phase"] == "Succeeded"
    cluster.kubectl("delete", "job", job, "-n", "default", "--cascade=background")


def test_deleting_an_owner_garbage_collects_its_dependents(roost_crds: Cluster) -> None:
    vehicle = unique("gc-vehicle")
    roost_crds.kubectl(
        "apply",
        "-f",
        "-",
        input_text=json.dumps(
            {
                "apiVersion": "roost.dev/v1alpha1",
                "kind": "Vehicle",
                "metadata": {"name": vehicle},
                "spec": {"nodeName": vehicle, "sysid": 7},
            }
        ),
    )
    uid = get_json(roost_crds, "vehicle", vehicle)["metadata"]["uid"]
    dependent = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": f"{vehicle}-config",
            "namespace": "default",
            "ownerReferences": [
                {"apiVersion": "roost.dev/v1alpha1", "kind": "Vehicle", "name": vehicle, "uid": uid}
            ],
        },
        "data": {"VEHICLE_NAME": vehicle},
    }
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(dependent))
    roost_crds.kubectl("delete", "vehicle", vehicle)

    def dependent_gone() -> bool:
        result = roost_crds.kubectl(
            "get", "configmap", f"{vehicle}-config", "-n", "default", check=False
        )
        return "NotFound" in result.stderr

    wait_until("the garbage collector to delete the dependent ConfigMap", dependent_gone)


# ---- authorisation and admission ---------------------------------------------------------


def test_role_limits_a_service_account(cluster: Cluster, tmp_path: Path) -> None:
    ns = unique("rbac")
    cluster.kubectl("create", "namespace", ns)
    cluster.kubectl("create", "serviceaccount", "narrow", "-n", ns)
    cluster.kubectl(
        "create", "role", "read-configmaps", "-n", ns, "--verb=get,list", "--resource=configmaps"
    )
    cluster.kubectl(
        "create",
        "rolebinding",
        "narrow",
        "-n",
        ns,
        "--role=read-configmaps",
        f"--serviceaccount={ns}:narrow",
    )
    cluster.kubectl("create", "configmap", "present", "-n", ns)

    impersonated = ["--as", f"system:serviceaccount:{ns}:narrow", "-n", ns]
    assert "present" in cluster.kubectl("get", "configmaps", *impersonated).stdout
    for refused in (
        ["create", "configmap", "new"],
        ["delete", "configmap", "present"],
        ["get", "secrets"],
    ):
        result = cluster.kubectl(*refused, *impersonated, check=False)
        assert result.returncode != 0
        assert "forbidden: User" in result.stderr, result.stderr

    # The same with a real signed token (TokenRequest), as a pod would authenticate.
    narrow = cluster.as_service_account(ns, "narrow", tmp_path / "narrow.kubeconfig")
    assert "present" in narrow.kubectl("get", "configmaps").stdout
    result = narrow.kubectl("get", "configmaps", "-n", "default", check=False)
    assert "forbidden: User" in result.stderr, result.stderr
    cluster.kubectl("delete", "namespace", ns, "--wait=false")


def test_validating_admission_policy_is_enforced(cluster: Cluster) -> None:
    name = unique("no-red")
    ns = unique("vap")
    cluster.kubectl("create", "namespace", ns)
    cluster.kubectl("label", "namespace", ns, f"vap-test={name}")
    policy = {
        "apiVersion": "admissionregistration.k8s.io/v1",
        "kind": "ValidatingAdmissionPolicy",
        "metadata": {"name": name},
        "spec": {
            "failurePolicy": "Fail",
            "matchConstraints": {
                "resourceRules": [
                    {
                        "apiGroups": [""],
                        "apiVersions": ["v1"],
                        "operations": ["CREATE", "UPDATE"],
                        "resources": ["configmaps"],
                    }
                ]
            },
            "validations": [
                {
                    "expression": "!has(object.data) || !('colour' in object.data) || "
                    "object.data['colour'] != 'red'",
                    "message": "no red configmaps",
                }
            ],
        },
    }
    binding = {
        "apiVersion": "admissionregistration.k8s.io/v1",
        "kind": "ValidatingAdmissionPolicyBinding",
        "metadata": {"name": name},
        "spec": {
            "policyName": name,
            "validationActions": ["Deny"],
            "matchResources": {"namespaceSelector": {"matchLabels": {"vap-test": name}}},
        },
    }
    cluster.kubectl(
        "apply",
        "-f",
        "-",
        input_text=json.dumps({"kind": "List", "apiVersion": "v1", "items": [policy, binding]}),
    )

    def red_refused() -> bool:
        result = cluster.kubectl(
            "create",
            "configmap",
            unique("red"),
            "-n",
            ns,
            "--from-literal=colour=red",
            "--dry-run=server",
            check=False,
        )
        return "no red configmaps" in result.stderr

    wait_until("the policy to take effect", red_refused, timeout_s=30)
    cluster.kubectl("create", "configmap", "blue", "-n", ns, "--from-literal=colour=blue")
    cluster.kubectl("delete", "validatingadmissionpolicybinding", name)
    cluster.kubectl("delete", "validatingadmissionpolicy", name)
    cluster.kubectl("delete", "namespace", ns, "--wait=false")


# ---- harness lifecycle -----------------------------------------------------------------------


def test_api_server_restart_keeps_the_cluster(cluster: Cluster, fake_nodes: FakeNodes) -> None:
    """stop_apiserver/start_apiserver (for partition tests): same port, same data."""
    plane = cluster.control_plane
    assert plane is not None
    node = unique("vehicle")
    fake_nodes(node)
    server = plane.server
    plane.stop_apiserver()
    assert not plane.ready()
    assert cluster.kubectl("get", "node", node, check=False, timeout_s=30).returncode != 0
    plane.start_apiserver()
    assert plane.server == server
    assert plane.ready()
    cluster.wait_nodes_ready([node])


def _none_alive(processes: list[ManagedProcess]) -> bool:
    return not any(p.alive() for p in processes)


def test_cli_up_and_down_stop_exactly_their_processes(tmp_path: Path, datastore: str) -> None:
    state = tmp_path / "cluster"
    cli = [sys.executable, "-m", "roost_localcluster.cli"]
    up = subprocess.run(
        [*cli, "up", "--dir", str(state), "--datastore", datastore],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert up.returncode == 0, up.stderr
    assert up.stdout.strip() == str(state / "kubeconfig")
    try:
        plane = ControlPlane.attach(state)
        assert plane is not None
        started = list(plane.processes.values())
        assert sorted(plane.processes) == sorted(Settings(datastore=datastore).start_order)
        assert all(plane.alive().values())  # outlived the `up` command
        status = subprocess.run(
            [*cli, "status", "--dir", str(state)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert status.returncode == 0, status.stdout
        assert "ready" in status.stdout
    finally:
        subprocess.run([*cli, "down", "--dir", str(state)], timeout=120, check=True)
    assert _none_alive(started)
    assert not (state / "state.json").exists()


def test_killed_owner_takes_its_control_plane_with_it(tmp_path: Path, datastore: str) -> None:
    """A test session killed with SIGKILL (no cleanup runs) leaves no component behind."""
    script = (
        "import json, sys, time\n"
        "from pathlib import Path\n"
        "from roost_localcluster.controlplane import ControlPlane, Settings\n"
        "plane = ControlPlane(Path(sys.argv[1]), settings=Settings(datastore=sys.argv[2]))\n"
        "plane.start()\n"
        "print(json.dumps([p.to_state() for p in plane.processes.values()]), flush=True)\n"
        "time.sleep(600)\n"
    )
    owner = subprocess.Popen(
        [sys.executable, "-c", script, str(tmp_path / "owned"), datastore],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert owner.stdout is not None
        started = [ManagedProcess.from_state(p) for p in json.loads(owner.stdout.readline())]
        assert len(started) == len(Settings(datastore=datastore).start_order)
        assert all(p.alive() for p in started)
    finally:
        os.kill(owner.pid, signal.SIGKILL)
        owner.wait()
    wait_until("the orphaned components to exit", lambda: _none_alive(started), timeout_s=30)


def test_helm_installs_a_chart(cluster: Cluster, tmp_path: Path) -> None:
    chart = tmp_path / "tiny"
    (chart / "templates").mkdir(parents=True)
    (chart / "Chart.yaml").write_text("apiVersion: v2\nname: tiny\nversion: 0.1.0\n")
    (chart / "templates" / "cm.yaml").write_text(
        "apiVersion: v1\nkind: ConfigMap\nmetadata: {name: '{{ .Release.Name }}-cm'}\n"
        "data: {colour: '{{ .Values.colour }}'}\n"
    )
    ns = unique("helm")
    release = unique("tiny")
    cluster.helm(
        "install", release, str(chart), "-n", ns, "--create-namespace", "--set", "colour=green"
    )
    cm = get_json(cluster, "configmap", f"{release}-cm", "-n", ns)
    assert cm["data"] == {"colour": "green"}
    assert release in cluster.helm("list", "-n", ns, "--short").stdout
    cluster.helm("uninstall", release, "-n", ns)
    cluster.kubectl("delete", "namespace", ns, "--wait=false")
