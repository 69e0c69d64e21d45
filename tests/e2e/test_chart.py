"""The Helm chart on a real control plane: install, RBAC sufficient, RBAC minimal, node identity.

``helm install`` puts the chart onto the harness (etcd, kube-apiserver, controller
manager, scheduler, kwok). kwok marks the operator and agent pods Running without
running their images, so the chart's workloads are checked as the scheduler and the
controllers see them, and the operator itself is run here as a process with the
chart's service-account token, which is what proves the RBAC is sufficient.

Minimality is checked two ways, both against the real API server: ``kubectl auth
can-i`` with impersonation for RBAC, and real writes for the node-restriction
admission policy, once with impersonation (``--as-user-extra`` carrying the node name,
where the policy's CEL rule reads it) and once with a real pod-bound token of an agent pod,
which is where the node name comes from in production.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_api.wellknown import (
    ANNOTATION_PAUSE_FAILOVER_ACTIONS,
    ANNOTATION_TELEMETRY,
    ANNOTATION_TELEMETRY_POD,
    LABEL_NODE,
    LABEL_VEHICLE,
    TAINT_VEHICLE,
)
from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.cluster import Cluster, FakeNodes
from roost_localcluster.processes import ManagedProcess
from roost_sim import SimConfig, autopilot_specs, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.chart import install_args
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

RELEASE = "chart-e2e"
NAMESPACE = "roost-chart-e2e"
FULLNAME = f"{RELEASE}-roost"
OPERATOR_SA = f"{FULLNAME}-operator"
AGENT_SA = f"{FULLNAME}-agent"
AGENT_USER = f"system:serviceaccount:{NAMESPACE}:{AGENT_SA}"
OPERATOR_USER = f"system:serviceaccount:{NAMESPACE}:{OPERATOR_SA}"
NODE_NAME_KEY = "authentication.kubernetes.io/node-name"
POLICY = f"{AGENT_SA}-node-restriction"

NODE_A = "chart-e2e-node-a"
NODE_B = "chart-e2e-node-b"
NODE_PLAIN = "chart-e2e-node-plain"
NODE_OPERATED = "chart-e2e-node-operated"
VEHICLE_A = "chart-e2e-veh-a"
VEHICLE_B = "chart-e2e-veh-b"
UNLABELLED_RA = "chart-e2e-veh-unlabelled"
OPERATED_VEHICLE = "chart-e2e-veh-operated"
NODE_MISSION = "chart-e2e-node-mission"
MISSION_VEHICLE = "chart-e2e-veh-mission"
MISSION_NAMESPACE = "roost-chart-e2e-missions"
MISSION = "chart-e2e-mission"
NODE_AGENT = "chart-e2e-node-agent"
AGENT_VEHICLE = "chart-e2e-veh-agent"
WAIT_S = 60.0


def _vehicle(name: str, node: str, sysid: int) -> dict[str, Any]:
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": name},
        "spec": {"nodeName": node, "sysid": sysid},
    }


def _autopilot(name: str, node: str | None) -> dict[str, Any]:
    labels = {LABEL_NODE: node} if node else {}
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "RedundantAutopilot",
        "metadata": {"name": name, "labels": labels},
        "spec": {
            "vehicleName": name,
            "primary": "fc-a",
            "autopilots": [
                {"name": "fc-a", "stack": "px4", "connection": "udp://127.0.0.1:14540", "sysid": 1,
                 "bridgeChannel": 0},
                {"name": "fc-b", "stack": "px4", "connection": "udp://127.0.0.1:14541", "sysid": 2,
                 "bridgeChannel": 1},
            ],
        },
    }  # fmt: skip


def _apply(cluster: Cluster, *manifests: dict[str, Any]) -> None:
    text = "\n---\n".join(yaml.safe_dump(m) for m in manifests)
    cluster.kubectl("apply", "-f", "-", input_text=text)


def _get(cluster: Cluster, *args: str) -> dict[str, Any]:
    result: dict[str, Any] = json.loads(cluster.kubectl("get", *args, "-o", "json").stdout)
    return result


def _agent_pods(cluster: Cluster) -> dict[str, dict[str, Any]]:
    """node name -> this release's agent pod there."""
    pods = _get(
        cluster,
        "pods",
        "-n",
        NAMESPACE,
        "-l",
        f"app.kubernetes.io/instance={RELEASE},app.kubernetes.io/component=agent",
    )["items"]
    return {pod["spec"]["nodeName"]: pod for pod in pods if pod["spec"].get("nodeName")}


@pytest.fixture(scope="module")
def installed(
    cluster: Cluster,
    fake_nodes_module: FakeNodes,
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[Cluster]:
    """The chart installed with default values, two vehicle nodes, one plain node, and a
    Vehicle plus RedundantAutopilot on each vehicle node (as the operator would label them)."""
    # helm installs the CRDs from the chart (they may exist already: --force-conflicts).
    taint = {"key": TAINT_VEHICLE, "value": "x", "effect": "NoSchedule"}
    for node in (NODE_A, NODE_B):
        fake_nodes_module(node, labels={LABEL_VEHICLE: node}, taints=[taint])
    fake_nodes_module(NODE_PLAIN)
    values_dir = tmp_path_factory.mktemp("chart-values")
    result = cluster.helm(*install_args(RELEASE, NAMESPACE, None, values_dir), check=False)
    assert result.returncode == 0, result.stderr
    _apply(
        cluster,
        _vehicle(VEHICLE_A, NODE_A, 101),
        _vehicle(VEHICLE_B, NODE_B, 102),
        _autopilot(VEHICLE_A, NODE_A),
        _autopilot(VEHICLE_B, NODE_B),
        _autopilot(UNLABELLED_RA, None),
    )
    yield cluster
    for kind, name in [
        ("redundantautopilot", VEHICLE_A),
        ("redundantautopilot", VEHICLE_B),
        ("redundantautopilot", UNLABELLED_RA),
        ("vehicle", VEHICLE_A),
        ("vehicle", VEHICLE_B),
    ]:
        cluster.kubectl("delete", kind, name, "--ignore-not-found", "--wait=false")
    cluster.helm("uninstall", RELEASE, "--namespace", NAMESPACE, "--wait")


@pytest.fixture(scope="module")
def fake_nodes_module(cluster: Cluster) -> Iterator[FakeNodes]:
    """Like the ``fake_nodes`` fixture, for the whole module."""
    pool = FakeNodes(cluster)
    yield pool
    pool.cleanup()


def _identity(user: str, node: str | None) -> list[str]:
    """kubectl flags impersonating ``user`` with ``node`` in its token's extra info."""
    flags = [f"--as={user}"]
    if node:
        flags.append(f"--as-user-extra={NODE_NAME_KEY}={node}")
    return flags


def _can(cluster: Cluster, user: str, *args: str, node: str | None = None) -> bool:
    result = cluster.kubectl("auth", "can-i", *args, *_identity(user, node), check=False)
    answer = result.stdout.strip()
    assert answer in ("yes", "no"), result.stderr
    return answer == "yes"


def _as_agent(cluster: Cluster, node: str | None, *args: str) -> subprocess.CompletedProcess[str]:
    return cluster.kubectl(*args, *_identity(AGENT_USER, node), check=False)


def _status_patch(kind: str, name: str, node: str) -> list[str]:
    patch = {"status": {"nodeName": node}}
    return ["patch", kind, name, "--subresource=status", "--type=merge", "-p", json.dumps(patch)]


def _event(name: str, involved: str, instance: str, api: str = "v1") -> dict[str, Any]:
    involved_ref = {"apiVersion": "roost.dev/v1alpha1", "kind": "Vehicle", "name": involved}
    if api == "v1":
        return {
            "apiVersion": "v1",
            "kind": "Event",
            "metadata": {"name": name, "namespace": "default"},
            "involvedObject": involved_ref,
            "reason": "Test",
            "message": "chart e2e",
            "type": "Normal",
            "reportingComponent": "roost-agent",
            "reportingInstance": instance,
        }
    return {
        "apiVersion": "events.k8s.io/v1",
        "kind": "Event",
        "metadata": {"name": name, "namespace": "default"},
        "regarding": involved_ref,
        "reason": "Test",
        "note": "chart e2e",
        "type": "Normal",
        "action": "Report",
        "eventTime": "2025-01-01T00:00:00.000000Z",
        "reportingController": "roost.dev/agent",
        "reportingInstance": instance,
    }


def _create_as_agent(
    cluster: Cluster, node: str | None, manifest: dict[str, Any]
) -> subprocess.CompletedProcess[str]:
    return cluster.kubectl(
        "create",
        "-f",
        "-",
        *_identity(AGENT_USER, node),
        input_text=json.dumps(manifest),
        check=False,
    )


# -- install ---------------------------------------------------------------------------


def test_helm_install_runs_the_operator_and_an_agent_on_every_vehicle_node_only(
    installed: Cluster,
) -> None:
    deployment = _get(installed, "deployment", "-n", NAMESPACE, f"{FULLNAME}-operator")
    assert deployment["status"].get("availableReplicas") == 2  # a leader and a standby
    wait_until(
        "agent pods on both vehicle nodes", lambda: {NODE_A, NODE_B} <= set(_agent_pods(installed))
    )
    assert NODE_PLAIN not in _agent_pods(installed)
    peering = _get(installed, "clusterkopfpeering", FULLNAME)
    assert peering["metadata"]["name"] == FULLNAME
    policy = _get(installed, "validatingadmissionpolicy", POLICY)
    assert not policy.get("status", {}).get("typeChecking", {}).get("expressionWarnings")


# -- RBAC minimality (kubectl auth can-i, impersonated) --------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ("get", "secrets", "-n", NAMESPACE),
        ("list", "secrets", "--all-namespaces"),
        ("create", "pods", "-n", "default"),
        ("create", "deployments.apps", "-n", NAMESPACE),
        ("delete", "nodes"),
        ("create", "clusterroles"),
        ("create", "clusterrolebindings"),
        ("impersonate", "serviceaccounts"),
        ("patch", "redundantautopilots.roost.dev", "--subresource=status"),
        ("delete", "vehicles.roost.dev"),
        ("patch", "clusterkopfpeerings.kopf.dev/someone-elses-peering"),
        ("create", "customresourcedefinitions"),
        ("patch", "jobs.batch", "-n", "default"),
        ("create", "events.events.k8s.io", "-n", "default"),
        ("patch", "namespaces/default"),
        ("get", "namespaces/kube-system"),
        ("create", "leases.coordination.k8s.io", "-n", "default"),
        ("delete", "leases.coordination.k8s.io", "-n", "kube-node-lease"),
    ],
    ids=" ".join,
)
def test_operator_may_not(installed: Cluster, args: tuple[str, ...]) -> None:
    assert not _can(installed, OPERATOR_USER, *args)


@pytest.mark.parametrize(
    "args",
    [
        ("patch", "nodes"),
        ("patch", "vehicles.roost.dev", "--subresource=status"),
        ("patch", "redundantautopilots.roost.dev"),
        ("create", "configmaps", "-n", "default"),
        ("create", "pods", "-n", NAMESPACE),
        ("delete", "pods", "-n", NAMESPACE),
        ("watch", "pods", "-n", NAMESPACE),
        ("create", "jobs.batch", "-n", "default"),
        ("delete", "jobs.batch", "-n", "default"),
        ("create", "events", "-n", "default"),
        ("patch", f"clusterkopfpeerings.kopf.dev/{FULLNAME}"),
        ("create", "leases.coordination.k8s.io", "-n", NAMESPACE),
        ("delete", "leases.coordination.k8s.io", "-n", NAMESPACE),
        ("watch", "leases.coordination.k8s.io", "--all-namespaces"),
    ],
    ids=" ".join,
)
def test_operator_may(installed: Cluster, args: tuple[str, ...]) -> None:
    assert _can(installed, OPERATOR_USER, *args)


@pytest.mark.parametrize(
    "args",
    [
        ("patch", "vehicles.roost.dev"),
        ("update", "vehicles.roost.dev"),
        ("patch", "redundantautopilots.roost.dev"),
        ("create", "vehicles.roost.dev"),
        ("delete", "redundantautopilots.roost.dev"),
        ("patch", "vehicles.roost.dev", "--subresource=status"),
        ("update", "redundantautopilots.roost.dev", "--subresource=status"),
        ("patch", "missions.roost.dev", "--subresource=status", "-n", "default"),
        ("patch", "events", "-n", "default"),
        ("get", "secrets", "-n", NAMESPACE),
        ("get", "configmaps", "-n", NAMESPACE),
        ("patch", "nodes"),
        ("list", "pods", "--all-namespaces"),
    ],
    ids=" ".join,
)
def test_agent_may_not(installed: Cluster, args: tuple[str, ...]) -> None:
    assert not _can(installed, AGENT_USER, *args, node=NODE_A)


@pytest.mark.parametrize(
    "args",
    [
        ("list", "vehicles.roost.dev"),
        ("watch", "redundantautopilots.roost.dev"),
        ("patch", "redundantautopilots.roost.dev", "--subresource=status"),
        ("create", "events", "-n", "default"),
    ],
    ids=" ".join,
)
def test_agent_may(installed: Cluster, args: tuple[str, ...]) -> None:
    assert _can(installed, AGENT_USER, *args, node=NODE_A)


# -- node-scoped agent identity (real writes through the admission policy) -------------


@pytest.fixture(scope="module")
def agent_over_granted(installed: Cluster) -> Iterator[Cluster]:
    """The agent with more RBAC than the chart gives it: Vehicle status and new-API Events.

    The policy must hold on its own, whatever RBAC someone adds later; this grant lets
    the requests reach it.
    """
    name = f"{AGENT_SA}-test-extra"
    role = {
        "apiVersion": "rbac.authorization.k8s.io/v1",
        "kind": "ClusterRole",
        "metadata": {"name": name},
        "rules": [
            {
                "apiGroups": ["roost.dev"],
                "resources": ["vehicles/status"],
                "verbs": ["get", "patch"],
            },
            # What the chart grants with agent.telemetry.enabled (its announcement),
            # and get, which kubectl sends before a patch.
            {"apiGroups": ["roost.dev"], "resources": ["vehicles"], "verbs": ["get", "patch"]},
            {"apiGroups": ["events.k8s.io"], "resources": ["events"], "verbs": ["create"]},
        ],
    }
    binding = {
        "apiVersion": "rbac.authorization.k8s.io/v1",
        "kind": "ClusterRoleBinding",
        "metadata": {"name": name},
        "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": name},
        "subjects": [{"kind": "ServiceAccount", "name": AGENT_SA, "namespace": NAMESPACE}],
    }
    _apply(installed, role, binding)
    wait_until(
        "the extra grant",
        lambda: _can(installed, AGENT_USER, "patch", "vehicles.roost.dev", "--subresource=status"),
    )
    yield installed
    installed.kubectl("delete", "clusterrolebinding,clusterrole", name, "--ignore-not-found")


def test_agent_of_node_a_writes_its_own_autopilot_status(installed: Cluster) -> None:
    result = _as_agent(installed, NODE_A, *_status_patch("redundantautopilot", VEHICLE_A, NODE_A))
    assert result.returncode == 0, result.stderr


def test_agent_of_node_a_is_refused_node_b_autopilot_status(installed: Cluster) -> None:
    result = _as_agent(installed, NODE_A, *_status_patch("redundantautopilot", VEHICLE_B, NODE_A))
    assert result.returncode != 0
    assert POLICY in result.stderr and f"on node {NODE_A}" in result.stderr


def test_agent_is_refused_an_autopilot_without_the_node_label(installed: Cluster) -> None:
    result = _as_agent(
        installed, NODE_A, *_status_patch("redundantautopilot", UNLABELLED_RA, NODE_A)
    )
    assert result.returncode != 0
    assert LABEL_NODE in result.stderr


def test_agent_without_a_node_in_its_token_is_refused(installed: Cluster) -> None:
    result = _as_agent(installed, None, *_status_patch("redundantautopilot", VEHICLE_A, NODE_A))
    assert result.returncode != 0
    assert "carries no node name" in result.stderr


def test_agent_vehicle_status_writes_granted_later_are_still_node_scoped(
    agent_over_granted: Cluster,
) -> None:
    own = _as_agent(agent_over_granted, NODE_A, *_status_patch("vehicle", VEHICLE_A, NODE_A))
    assert own.returncode == 0, own.stderr
    other = _as_agent(agent_over_granted, NODE_A, *_status_patch("vehicle", VEHICLE_B, NODE_A))
    assert other.returncode != 0
    assert POLICY in other.stderr and "Vehicle bound to its node" in other.stderr


def _metadata_patch(name: str, **metadata: dict[str, str | None]) -> list[str]:
    return ["patch", "vehicle", name, "--type=merge", "-p", json.dumps({"metadata": metadata})]


@pytest.mark.parametrize(
    ("vehicle", "metadata", "allowed"),
    [
        # whose     what it changes                                          → allowed
        (VEHICLE_A, {"annotations": {ANNOTATION_TELEMETRY: "ws://10.0.0.5:9467/",
                                     ANNOTATION_TELEMETRY_POD: "ns/pod:9467"}}, True),
        (VEHICLE_A, {"annotations": {ANNOTATION_TELEMETRY_POD: None}}, True),
        (VEHICLE_A, {"annotations": {ANNOTATION_PAUSE_FAILOVER_ACTIONS: "true"}}, False),
        (VEHICLE_A, {"annotations": {ANNOTATION_TELEMETRY: "ws://x:1/", "other": "x"}}, False),
        (VEHICLE_A, {"labels": {"fleet": "stolen"}}, False),
        (VEHICLE_B, {"annotations": {ANNOTATION_TELEMETRY: "ws://10.0.0.6:9467/"}}, False),
    ],
)  # fmt: skip
def test_agent_may_patch_only_its_own_vehicles_telemetry_annotations(
    agent_over_granted: Cluster,
    vehicle: str,
    metadata: dict[str, dict[str, str | None]],
    *,
    allowed: bool,
) -> None:
    result = _as_agent(agent_over_granted, NODE_A, *_metadata_patch(vehicle, **metadata))
    assert (result.returncode == 0) == allowed, result.stderr
    if not allowed:
        assert POLICY in result.stderr


def test_agent_events_must_name_its_own_node(agent_over_granted: Cluster) -> None:
    cluster = agent_over_granted
    own = _create_as_agent(cluster, NODE_A, _event("chart-e2e-own", VEHICLE_A, NODE_A))
    assert own.returncode == 0, own.stderr
    forged = _create_as_agent(cluster, NODE_A, _event("chart-e2e-forged", VEHICLE_B, NODE_B))
    assert forged.returncode != 0 and POLICY in forged.stderr
    forged_new_api = _create_as_agent(
        cluster, NODE_A, _event("chart-e2e-forged-v1", VEHICLE_B, NODE_B, api="events.k8s.io")
    )
    assert forged_new_api.returncode != 0 and POLICY in forged_new_api.stderr
    cluster.kubectl("delete", "event", "chart-e2e-own", "-n", "default", "--ignore-not-found")


def test_agent_events_about_non_roost_objects_are_refused(installed: Cluster) -> None:
    event = _event("chart-e2e-about-node", NODE_A, NODE_A)
    event["involvedObject"] = {"apiVersion": "v1", "kind": "Node", "name": NODE_A}
    result = _create_as_agent(installed, NODE_A, event)
    assert result.returncode != 0 and "Vehicles and RedundantAutopilots only" in result.stderr


def test_policy_leaves_other_users_alone(installed: Cluster) -> None:
    result = installed.kubectl(*_status_patch("redundantautopilot", VEHICLE_B, NODE_A), check=False)
    assert result.returncode == 0, result.stderr


def _bound_token_kubeconfig(cluster: Cluster, pod: dict[str, Any], path: Path) -> Cluster:
    """A kubeconfig holding a token bound to ``pod``, as the kubelet gives the agent."""
    token = cluster.kubectl(
        "create",
        "token",
        AGENT_SA,
        "-n",
        NAMESPACE,
        "--bound-object-kind=Pod",
        f"--bound-object-name={pod['metadata']['name']}",
        f"--bound-object-uid={pod['metadata']['uid']}",
        "--duration=10m",
    ).stdout.strip()
    agent = cluster.as_service_account(NAMESPACE, AGENT_SA, path)
    config = yaml.safe_load(path.read_text())
    config["users"][0]["user"] = {"token": token}
    path.write_text(yaml.safe_dump(config))
    return agent


def test_real_pod_bound_agent_token_carries_its_node_and_is_scoped_to_it(
    installed: Cluster, tmp_path: Path
) -> None:
    wait_until("agent pod on node A", lambda: NODE_A in _agent_pods(installed))
    agent = _bound_token_kubeconfig(installed, _agent_pods(installed)[NODE_A], tmp_path / "kc")
    whoami = json.loads(agent.kubectl("auth", "whoami", "-o", "json").stdout)
    assert whoami["status"]["userInfo"]["username"] == AGENT_USER
    assert whoami["status"]["userInfo"]["extra"][NODE_NAME_KEY] == [NODE_A]
    own = agent.kubectl(*_status_patch("redundantautopilot", VEHICLE_A, NODE_A), check=False)
    assert own.returncode == 0, own.stderr
    other = agent.kubectl(*_status_patch("redundantautopilot", VEHICLE_B, NODE_A), check=False)
    assert other.returncode != 0 and POLICY in other.stderr
    # A change the schema allows (vehicleType is mutable), so that only the policy can
    # refuse it: the agent may announce its telemetry on its own Vehicle, nothing else.
    change = '{"spec":{"vehicleType":"hexa"}}'
    spec = agent.kubectl("patch", "vehicle", VEHICLE_A, "--type=merge", "-p", change, check=False)
    assert spec.returncode != 0 and "forbidden" in spec.stderr.lower(), spec.stderr


# -- RBAC sufficiency: the agent, run with a token bound to the chart's agent pod ------


def test_agent_with_its_pod_bound_token_reports_its_autopilots(
    installed: Cluster, fake_nodes_module: FakeNodes, tmp_path: Path
) -> None:
    """The real roost-agent, as the chart runs it but outside the (kwok) pod: NODE_NAME
    and a token bound to the agent pod on its node. It finds its Vehicle and labelled
    RedundantAutopilot and writes their health from simulated autopilots over UDP."""
    taint = {"key": TAINT_VEHICLE, "value": "x", "effect": "NoSchedule"}
    fake_nodes_module(NODE_AGENT, labels={LABEL_VEHICLE: AGENT_VEHICLE}, taints=[taint])
    sims = start_vehicle_sims(["px4", "px4"], config=SimConfig.fast())
    agent: AgentProcess | None = None
    try:
        autopilot = _autopilot(AGENT_VEHICLE, NODE_AGENT)
        autopilot["spec"]["autopilots"] = [spec.to_api() for spec in autopilot_specs(sims)]
        autopilot["spec"]["primary"] = sims[0].name
        _apply(installed, _vehicle(AGENT_VEHICLE, NODE_AGENT, 105), autopilot)
        wait_until("the agent pod on its node", lambda: NODE_AGENT in _agent_pods(installed))
        token_cluster = _bound_token_kubeconfig(
            installed, _agent_pods(installed)[NODE_AGENT], tmp_path / "agent.kubeconfig"
        )
        agent = AgentProcess.in_cluster(token_cluster, NODE_AGENT, tmp_path / "agent")
        agent.start()

        def reported_healthy() -> bool:
            status = _get(installed, "redundantautopilot", AGENT_VEHICLE).get("status", {})
            levels = {a.get("level") for a in status.get("autopilots", [])}
            return levels == {"OK"} and status.get("nodeName") == NODE_AGENT

        wait_until("the agent's healthy report", reported_healthy)
        log = agent.log.read_text()
        assert f'User "{AGENT_USER}" cannot' not in log, log[-3000:]
        assert "denied request" not in log, log[-3000:]
    finally:
        if agent is not None:
            agent.stop()
        stop_sims(sims)
        installed.kubectl("delete", "redundantautopilot,vehicle", AGENT_VEHICLE, "--wait=false")


# -- RBAC sufficiency: the operator, run with the chart's service account --------------


@pytest.fixture
def operator_as_chart_account(installed: Cluster, tmp_path: Path) -> Iterator[OperatorProcess]:
    """roost-operator with a token of the chart's operator service account, the chart's
    peering (not standalone) and its leader election, serving its liveness endpoint."""
    account = installed.as_service_account(NAMESPACE, OPERATOR_SA, tmp_path / "kubeconfig")
    operator = OperatorProcess(
        account,
        tmp_path / "operator.log",
        namespace=NAMESPACE,
        environment={"ROOST_PEERING": FULLNAME},
        standalone=False,
        args=["--leader-election"],
    )
    operator.start()
    try:
        yield operator
    finally:
        operator.stop()


def _condition(obj: dict[str, Any], kind: str) -> str | None:
    for condition in obj.get("status", {}).get("conditions", []):
        if condition["type"] == kind:
            return str(condition["status"])
    return None


def test_operator_with_the_chart_service_account_reconciles_a_vehicle(
    installed: Cluster,
    fake_nodes_module: FakeNodes,
    operator_as_chart_account: OperatorProcess,
) -> None:
    process = operator_as_chart_account.process
    fake_nodes_module(NODE_OPERATED)
    _apply(installed, _vehicle(OPERATED_VEHICLE, NODE_OPERATED, 103))
    try:
        wait_until(
            "the node to be labelled by the operator",
            lambda: (
                LABEL_VEHICLE
                in _get(installed, "node", NODE_OPERATED)["metadata"].get("labels", {})
            ),
        )
        wait_until(
            "Vehicle NodeBound=True",
            lambda: _condition(_get(installed, "vehicle", OPERATED_VEHICLE), "NodeBound") == "True",
        )
        _operator_log_is_clean(process)
    finally:
        installed.kubectl("delete", "vehicle", OPERATED_VEHICLE, "--wait=false")
    wait_until(
        "the deleted Vehicle gone and its node released by the operator",
        lambda: (
            installed.kubectl("get", "vehicle", OPERATED_VEHICLE, check=False).returncode != 0
            and LABEL_VEHICLE
            not in _get(installed, "node", NODE_OPERATED)["metadata"].get("labels", {})
        ),
    )
    _operator_log_is_clean(process)


def _operator_log_is_clean(process: ManagedProcess) -> None:
    """No request of the operator was refused by RBAC (the API server's own wording)."""
    log = process.log.read_text()
    assert f'User \\"{OPERATOR_USER}\\" cannot' not in log, process.log_tail(60)
    assert f'User "{OPERATOR_USER}" cannot' not in log, process.log_tail(60)
    assert process.alive(), process.log_tail(60)


def test_operator_with_the_chart_service_account_labels_the_autopilot_and_flies_a_mission(
    installed: Cluster,
    fake_nodes_module: FakeNodes,
    operator_as_chart_account: OperatorProcess,
) -> None:
    """A Mission on one vehicle runs to its Job (preflight limited to the operator's own
    conditions, so no agent is needed); every step is a write the chart must allow."""
    process = operator_as_chart_account.process
    fake_nodes_module(NODE_MISSION)
    installed.kubectl("create", "namespace", MISSION_NAMESPACE)
    mission = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": MISSION, "namespace": MISSION_NAMESPACE},
        "spec": {
            "vehicles": {"names": [MISSION_VEHICLE], "count": 1},
            "preflight": {
                "requireAgentConnected": False,
                "requireActiveHealthy": False,
                "requireRedundancy": False,
            },
            "onboard": {
                "spec": {
                    "restartPolicy": "Never",
                    "containers": [{"name": "controller", "image": "controller:e2e"}],
                }
            },
        },
    }
    _apply(
        installed,
        _vehicle(MISSION_VEHICLE, NODE_MISSION, 104),
        _autopilot(MISSION_VEHICLE, None),
        mission,
    )
    try:
        wait_until(
            "the operator to label the RedundantAutopilot with its node",
            lambda: (
                _get(installed, "redundantautopilot", MISSION_VEHICLE)["metadata"]
                .get("labels", {})
                .get(LABEL_NODE)
                == NODE_MISSION
            ),
        )
        wait_until(
            "the mission's onboard Job",
            lambda: bool(
                _get(installed, "jobs", "-n", MISSION_NAMESPACE, "-l", "roost.dev/mission")["items"]
            ),
            timeout_s=120,
        )
        phase = _get(installed, "mission", MISSION, "-n", MISSION_NAMESPACE)["status"]["phase"]
        assert phase in ("Running", "Succeeded"), phase
        _operator_log_is_clean(process)
    finally:
        installed.kubectl("delete", "namespace", MISSION_NAMESPACE, "--wait=false")
        installed.kubectl("delete", "redundantautopilot,vehicle", MISSION_VEHICLE, "--wait=false")
    wait_until(
        "the Vehicle to be gone",
        lambda: installed.kubectl("get", "vehicle", MISSION_VEHICLE, check=False).returncode != 0,
        timeout_s=120,
    )
    _operator_log_is_clean(process)


def test_documented_crd_upgrade_path_works_after_helm_installed_the_crds(
    installed: Cluster,
) -> None:
    """README: apply the chart's CRDs server-side (Helm never upgrades them), then upgrade."""
    crds = str(REPO_ROOT / "charts" / "roost" / "crds")
    applied = installed.kubectl("apply", "--server-side", "--force-conflicts", "-f", crds)
    assert "serverside-applied" in applied.stdout
    installed.kubectl("wait", "--for=condition=Established", "--timeout=60s", "-f", crds)
    upgraded = installed.helm(
        "upgrade", RELEASE, str(REPO_ROOT / "charts" / "roost"), "--namespace", NAMESPACE,
        "--reuse-values", "--wait", "--timeout", "3m", check=False,
    )  # fmt: skip
    assert upgraded.returncode == 0, upgraded.stderr
