"""The Helm chart, offline: lint, schema validity, CRD copies, and the privileges it grants.

Everything here runs the real ``helm`` binary (``helm lint`` / ``helm template``) and
validates what it prints against the Kubernetes 1.35 OpenAPI schemas shipped by
``kubernetes-validate``; custom resources are validated against the chart's own CRDs.
tests/e2e/test_chart.py installs the same chart onto a real control plane and proves the
RBAC and the node-restriction policy there; the chart's files as data (CRD copies,
appVersion, documented values) are checked in ``tests/unit/test_repo_chart.py``.
"""

from __future__ import annotations

import functools
import json
import re
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import pytest

from roost_api.wellknown import LABEL_NODE, LABEL_VEHICLE, TAINT_VEHICLE
from roost_localcluster.binaries import REPO_ROOT
from roost_operator.settings import load_settings
from tests.support import yamldocs
from tests.support.chart import (
    CHART_CRDS_DIR,
    CHART_DIR,
    HARDWARE_VALUES,
    KIND_VALUES,
    KUBERNETES_VERSION,
    ChartError,
    Manifest,
    find,
    helm,
    render,
)

AGENT_USER = "system:serviceaccount:roost-system:roost-agent"

# Value sets every rendering test runs with: the defaults, both shipped values files,
# and the switches that change which objects exist.
S3_VALUES = {
    "endpoint": "https://s3.example.org",
    "bucket": "flights",
    "region": "eu-central-1",
    "prefix": "site-1",
    "secretName": "bucket-key",
    "accessKeyIdKey": "AWS_ACCESS_KEY_ID",
    "secretAccessKeyKey": "AWS_SECRET_ACCESS_KEY",
}
VALUE_SETS: dict[str, tuple[dict[str, Any], tuple[Path, ...]]] = {
    "defaults": ({}, ()),
    "hardware": ({}, (HARDWARE_VALUES,)),
    "kind": ({}, (KIND_VALUES,)),
    "device-plugin": (
        {"agent": {"devices": {"access": "devicePlugin", "resources": {"squat.ai/serial": 2}}}},
        (),
    ),
    "no-node-restriction": ({"agent": {"nodeRestriction": {"enabled": False}}}, ()),
    "signing": ({"agent": {"signing": {"mode": "require", "secretName": "fleet-keys"}}}, ()),
    "signing-per-vehicle": (
        {"agent": {"signing": {"mode": "require", "vehicles": ["drone-1", "drone-2"]}}},
        (),
    ),
    "operator-only": ({"agent": {"enabled": False}}, ()),
    "monitoring": (
        {
            "agent": {"metrics": {"bindNodeAddress": True}},
            "metrics": {
                "serviceMonitor": {"enabled": True, "labels": {"release": "prom"}},
                "grafanaDashboard": {"enabled": True},
            },
        },
        (),
    ),
    "dashboard": (
        {
            "dashboard": {"enabled": True, "origin": "47.3977,8.5456"},
            "agent": {"telemetry": {"enabled": True, "bindNodeAddress": True}},
        },
        (),
    ),
    "records": (
        {
            "agent": {"records": {"enabled": True, "bindNodeAddress": True}},
            "operator": {"records": {"s3": S3_VALUES}},
        },
        (),
    ),
    "no-metrics": (
        {"operator": {"metrics": {"enabled": False}}, "agent": {"metrics": {"enabled": False}}},
        (),
    ),
}
# Custom resources of the Prometheus operator: no schema here, checked by the tests below.
PROMETHEUS_OPERATOR_KINDS = {("monitoring.coreos.com/v1", "ServiceMonitor")}


@functools.cache
def _render_set(name: str, *, include_crds: bool = False) -> list[Manifest]:
    """Rendered once per value set (read-only: callers must not modify the result)."""
    values, files = VALUE_SETS[name]
    return render(values, values_files=files, include_crds=include_crds)


@functools.cache
def _chart_crd_schemas() -> dict[tuple[str, str], dict[str, Any]]:
    """(apiVersion, kind) -> openAPIV3Schema of every version of every chart CRD (read
    once: callers must not modify the result)."""
    schemas = {}
    for path in CHART_CRDS_DIR.glob("*.yaml"):
        crd = yamldocs.load(path.read_text())
        for version in crd["spec"]["versions"]:
            key = (f"{crd['spec']['group']}/{version['name']}", crd["spec"]["names"]["kind"])
            schemas[key] = version["schema"]["openAPIV3Schema"]
    return schemas


def _rules(manifests: list[Manifest], suffix: str) -> list[dict[str, Any]]:
    rules: list[dict[str, Any]] = find(manifests, "ClusterRole", suffix)["rules"]
    return rules


def _grants(rules: list[dict[str, Any]], group: str, resource: str, verb: str) -> bool:
    return any(
        group in rule["apiGroups"] and resource in rule["resources"] and verb in rule["verbs"]
        for rule in rules
    )


# -- the CRDs Helm installs ------------------------------------------------------------


# -- lint and schema validity ----------------------------------------------------------


@pytest.mark.parametrize("values_file", [None, HARDWARE_VALUES, KIND_VALUES])
def test_helm_lint_strict_reports_nothing(values_file: Path | None) -> None:
    args = ["lint", "--strict", str(CHART_DIR)]
    if values_file:
        args += ["--values", str(values_file)]
    result = helm(*args)
    assert result.returncode == 0, result.stdout + result.stderr
    findings = re.findall(r"^\[(INFO|WARNING|ERROR)\].*$", result.stdout, re.MULTILINE)
    assert not findings, result.stdout


@pytest.mark.parametrize("value_set", sorted(VALUE_SETS))
def test_every_rendered_object_is_valid_for_kubernetes_1_35(value_set: str) -> None:
    custom = _chart_crd_schemas()
    manifests = _render_set(value_set, include_crds=True)
    assert manifests
    for manifest in manifests:
        key = (manifest["apiVersion"], manifest["kind"])
        if key in custom:
            jsonschema.validate(manifest, custom[key])
        elif key not in PROMETHEUS_OPERATOR_KINDS:
            kubernetes_validate.validate(manifest, KUBERNETES_VERSION, strict=True)


def test_values_schema_rejects_a_misspelt_key() -> None:
    with pytest.raises(ChartError, match="acess"):
        render({"agent": {"devices": {"acess": "privileged"}}})


# -- operator --------------------------------------------------------------------------


def test_operator_runs_two_replicas_that_elect_a_leader_and_a_liveness_probe() -> None:
    deployment = find(_render_set("defaults"), "Deployment", "-operator")
    spec = deployment["spec"]
    assert spec["replicas"] == 2
    assert "strategy" not in spec  # rolling: a new pod stands by until the Lease is free
    container = spec["template"]["spec"]["containers"][0]
    assert "--leader-election" in container["args"]
    single = find(render({"operator": {"replicas": 1}}), "Deployment", "-operator")
    assert "--leader-election" not in single["spec"]["template"]["spec"]["containers"][0]["args"]
    assert "--liveness=http://0.0.0.0:8080/healthz" in container["args"]
    assert container["livenessProbe"]["httpGet"] == {"path": "/healthz", "port": "health"}
    assert container["resources"]["limits"]["memory"]


def test_operator_peering_is_named_after_the_release() -> None:
    manifests = render(release="fleet-a")
    peering = find(manifests, "ClusterKopfPeering")
    assert peering["metadata"]["name"] == "fleet-a-roost"
    env = find(manifests, "Deployment", "-operator")["spec"]["template"]["spec"]["containers"][0][
        "env"
    ]
    assert {"name": "ROOST_PEERING", "value": "fleet-a-roost"} in env
    # each Vehicle's key pod runs the agent's image
    agent_image = find(manifests, "DaemonSet", "-agent")["spec"]["template"]["spec"]["containers"][
        0
    ]["image"]
    assert {"name": "ROOST_AGENT_IMAGE", "value": agent_image} in env
    patch_rule = next(
        r
        for r in _rules(manifests, "-operator")
        if "clusterkopfpeerings" in r["resources"] and "patch" in r["verbs"]
    )
    assert patch_rule["resourceNames"] == ["fleet-a-roost"]


def test_operator_runs_as_non_root_with_a_read_only_root_and_no_capabilities() -> None:
    pod = find(_render_set("defaults"), "Deployment", "-operator")["spec"]["template"]["spec"]
    assert pod["securityContext"]["runAsNonRoot"] is True
    context = pod["containers"][0]["securityContext"]
    assert context["readOnlyRootFilesystem"] is True
    assert context["allowPrivilegeEscalation"] is False
    assert context["capabilities"] == {"drop": ["ALL"]}


def test_operator_stays_off_vehicle_nodes() -> None:
    pod = find(_render_set("defaults"), "Deployment", "-operator")["spec"]["template"]["spec"]
    terms = pod["affinity"]["nodeAffinity"]["requiredDuringSchedulingIgnoredDuringExecution"]
    assert terms["nodeSelectorTerms"][0]["matchExpressions"] == [
        {"key": LABEL_VEHICLE, "operator": "DoesNotExist"}
    ]


def test_operator_role_grants_no_secrets_no_wildcards_and_no_rbac() -> None:
    rules = _rules(_render_set("defaults"), "-operator")
    for rule in rules:
        assert "*" not in rule["verbs"] and "*" not in rule["resources"], rule
        assert "secrets" not in rule["resources"], rule
        assert "rbac.authorization.k8s.io" not in rule["apiGroups"], rule
    assert not _grants(rules, "", "pods", "create")
    assert not _grants(rules, "", "nodes", "delete")
    assert not _grants(rules, "roost.dev", "redundantautopilots/status", "patch")


def test_operator_keeps_mission_records_on_its_own_claim_and_may_reach_the_agents() -> None:
    objects = _render_set("defaults")
    pod = find(objects, "Deployment", "-operator")["spec"]["template"]["spec"]
    claim = find(objects, "PersistentVolumeClaim", "-operator-records")
    assert claim["metadata"]["annotations"]["helm.sh/resource-policy"] == "keep"
    (volume,) = [v for v in pod["volumes"] if v["name"] == "records"]
    assert volume["persistentVolumeClaim"]["claimName"] == claim["metadata"]["name"]
    container = pod["containers"][0]
    env = {e["name"]: e.get("value") for e in container["env"]}
    (mount,) = [m for m in container["volumeMounts"] if m["name"] == "records"]
    assert env["ROOST_RECORDS_DIR"] == mount["mountPath"]
    assert pod["securityContext"]["fsGroup"] == pod["securityContext"]["runAsGroup"]
    pods_role = find(objects, "Role", "-operator-pods")["rules"]
    assert _grants(pods_role, "", "pods/proxy", "get")
    assert _grants(_rules(objects, "-operator"), "", "events", "list")  # for the bundle

    existing = render({"operator": {"records": {"persistence": {"existingClaim": "flights"}}}})
    assert not [m for m in existing if m["kind"] == "PersistentVolumeClaim"]
    pod = find(existing, "Deployment", "-operator")["spec"]["template"]["spec"]
    assert {"name": "records", "persistentVolumeClaim": {"claimName": "flights"}} in pod["volumes"]

    off = render({"operator": {"records": {"enabled": False}}})
    pod = find(off, "Deployment", "-operator")["spec"]["template"]["spec"]
    assert not [m for m in off if m["kind"] == "PersistentVolumeClaim"]
    assert "ROOST_RECORDS_DIR" not in {e["name"] for e in pod["containers"][0]["env"]}

    scratch = render({"operator": {"records": {"persistence": {"enabled": False}}}})
    pod = find(scratch, "Deployment", "-operator")["spec"]["template"]["spec"]
    assert not [m for m in scratch if m["kind"] == "PersistentVolumeClaim"]
    assert {"name": "records", "emptyDir": {}} in pod["volumes"]
    assert "ROOST_RECORDS_DIR" in {e["name"] for e in pod["containers"][0]["env"]}


@pytest.mark.parametrize(
    ("records", "expected"),
    [
        ({}, "on-vehicle"),  # the defaults: recorded, served on the vehicle's 127.0.0.1
        ({"bindNodeAddress": True}, "reachable"),
        ({"enabled": False}, "off"),
        ({"enabled": False, "bindNodeAddress": True}, "off"),
    ],
)
def test_operator_knows_whether_the_agents_records_can_be_gathered(
    records: dict[str, Any], expected: str
) -> None:
    objects = render({"agent": {"records": records}} if records else None)
    container = find(objects, "Deployment", "-operator")["spec"]["template"]["spec"]
    env = {e["name"]: e.get("value") for e in container["containers"][0]["env"]}
    assert env["ROOST_RECORDS_AGENTS"] == expected
    plain = {name: value for name, value in env.items() if value is not None}
    assert load_settings(plain).records.agents == expected  # what the operator makes of it


def test_operator_copies_bundles_to_a_bucket_with_credentials_from_an_optional_secret() -> None:
    pod = find(_render_set("records"), "Deployment", "-operator")["spec"]["template"]["spec"]
    container = pod["containers"][0]
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert {k: v for k, v in env.items() if k.startswith("ROOST_RECORDS_S3_")} == {
        "ROOST_RECORDS_S3_ENDPOINT": "https://s3.example.org",
        "ROOST_RECORDS_S3_BUCKET": "flights",
        "ROOST_RECORDS_S3_REGION": "eu-central-1",
        "ROOST_RECORDS_S3_PREFIX": "site-1",
        "ROOST_RECORDS_S3_CREDENTIALS_DIR": "/etc/roost/records-s3",
    }
    (mount,) = [m for m in container["volumeMounts"] if m["name"] == "records-s3"]
    assert mount == {"name": "records-s3", "mountPath": "/etc/roost/records-s3", "readOnly": True}
    (volume,) = [v for v in pod["volumes"] if v["name"] == "records-s3"]
    assert volume["secret"] == {
        "secretName": "bucket-key",
        "optional": True,  # without it the operator runs; the uploads say why they fail
        "items": [
            {"key": "AWS_ACCESS_KEY_ID", "path": "accessKeyId"},
            {"key": "AWS_SECRET_ACCESS_KEY", "path": "secretAccessKey"},
        ],
    }
    # The operator's role still reads no Secret: the kubelet mounts it.
    assert not _grants(_rules(_render_set("records"), "-operator"), "", "secrets", "get")

    default = find(_render_set("defaults"), "Deployment", "-operator")["spec"]["template"]
    assert "records-s3" not in {v["name"] for v in default["spec"]["volumes"]}
    with pytest.raises(ChartError, match=r"operator\.records\.s3\.secretName is required"):
        render({"operator": {"records": {"s3": {**S3_VALUES, "secretName": ""}}}})


# -- agent -----------------------------------------------------------------------------


def _agent_pod(value_set: str) -> dict[str, Any]:
    pod: dict[str, Any] = find(_render_set(value_set), "DaemonSet", "-agent")["spec"]["template"][
        "spec"
    ]
    return pod


def test_agent_runs_only_on_vehicle_nodes_and_tolerates_the_vehicle_taint() -> None:
    pod = _agent_pod("defaults")
    terms = pod["affinity"]["nodeAffinity"]["requiredDuringSchedulingIgnoredDuringExecution"]
    assert terms["nodeSelectorTerms"] == [
        {"matchExpressions": [{"key": LABEL_VEHICLE, "operator": "Exists"}]}
    ]
    assert {"key": TAINT_VEHICLE, "operator": "Exists"} in pod["tolerations"]


def test_agent_uses_the_host_network_and_learns_its_node_from_the_downward_api() -> None:
    pod = _agent_pod("defaults")
    assert pod["hostNetwork"] is True
    assert pod["dnsPolicy"] == "ClusterFirstWithHostNet"
    env = pod["containers"][0]["env"]
    assert {"name": "NODE_NAME", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}} in env


def test_agent_without_devices_is_unprivileged_and_mounts_nothing_from_the_host() -> None:
    """Nothing from the host but its signing key directory, read-only, and its node's
    own directory of flight records."""
    pod = _agent_pod("defaults")
    context = pod["containers"][0]["securityContext"]
    assert "privileged" not in context
    assert context["capabilities"] == {"drop": ["ALL"]}
    assert context["readOnlyRootFilesystem"] is True
    host = [v["name"] for v in pod["volumes"] if "hostPath" in v]
    assert host == ["records", "signing-keys"]
    mounts = {m["name"]: m for m in pod["containers"][0]["volumeMounts"] if m["name"] in host}
    assert mounts["signing-keys"]["readOnly"]
    assert mounts["records"]["subPathExpr"] == "$(NODE_NAME)"
    off = find(render({"agent": {"records": {"enabled": False}}}), "DaemonSet", "-agent")
    host = [v["name"] for v in off["spec"]["template"]["spec"]["volumes"] if "hostPath" in v]
    assert host == ["signing-keys"]


def test_agent_records_flights_on_a_host_directory_of_its_node_by_default() -> None:
    off = find(render({"agent": {"records": {"enabled": False}}}), "DaemonSet", "-agent")
    off = off["spec"]["template"]["spec"]
    assert "initContainers" not in off
    assert not [a for a in off["containers"][0]["args"] if a.startswith("--records")]
    pod = _agent_pod("defaults")
    container = pod["containers"][0]
    for arg in (
        "--records-dir=/var/lib/roost/records",
        "--records-port=9468",
        "--records-budget-mb=1024",
        "--records-keep-free-percent=15",
    ):
        assert arg in container["args"]
    assert {"name": "records", "containerPort": 9468, "hostPort": 9468, "protocol": "TCP"} in (
        container["ports"]
    )
    assert "ROOST_AGENT_RECORDS_ADDRESS" not in {e["name"] for e in container["env"]}
    volume = next(v for v in pod["volumes"] if v["name"] == "records")
    assert volume["hostPath"] == {"path": "/var/lib/roost/records", "type": "DirectoryOrCreate"}
    mount = next(m for m in container["volumeMounts"] if m["name"] == "records")
    assert mount["subPathExpr"] == "$(NODE_NAME)"  # nodes sharing a host keep their own
    [init] = pod["initContainers"]  # hands the root-created directory to the agent's user
    assert init["command"][-3:] == ["/var/lib/roost/records", "65532", "65532"]
    assert init["securityContext"]["capabilities"] == {"drop": ["ALL"], "add": ["CHOWN"]}
    assert init["volumeMounts"][0]["subPathExpr"] == "$(NODE_NAME)"
    values = {"agent": {"records": {"enabled": True, "bindNodeAddress": True}}}
    near = find(render(values), "DaemonSet", "-agent")
    assert {
        "name": "ROOST_AGENT_RECORDS_ADDRESS",
        "valueFrom": {"fieldRef": {"fieldPath": "status.hostIP"}},
    } in near["spec"]["template"]["spec"]["containers"][0]["env"]


def test_agent_with_hardware_mounts_exactly_the_listed_devices_and_stays_non_root() -> None:
    pod = _agent_pod("hardware")
    listed = yamldocs.load(HARDWARE_VALUES.read_text())["agent"]["devices"]["paths"]
    host_paths = [v["hostPath"] for v in pod["volumes"] if v["name"].startswith("device")]
    assert host_paths == [{"path": path, "type": "CharDevice"} for path in listed]
    container = pod["containers"][0]
    assert container["securityContext"]["privileged"] is True
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["runAsUser"] != 0
    assert pod["securityContext"]["supplementalGroups"] == [20]
    mounted = [m["mountPath"] for m in container["volumeMounts"] if m["name"].startswith("device")]
    assert mounted == listed


def test_agent_with_a_device_plugin_requests_the_devices_and_is_not_privileged() -> None:
    container = _agent_pod("device-plugin")["containers"][0]
    assert container["resources"]["requests"]["squat.ai/serial"] == 2
    assert container["resources"]["limits"]["squat.ai/serial"] == 2
    assert "privileged" not in container["securityContext"]


def _signing_keys_volume(pod: dict[str, Any], mode: str) -> dict[str, Any]:
    """The agent's key volume, after checking the agent reads it read-only under ``mode``."""
    container = pod["containers"][0]
    assert f"--signing={mode}" in container["args"]
    assert "--signing-keys=/etc/roost/signing" in container["args"]
    mount = next(m for m in container["volumeMounts"] if m["name"] == "signing-keys")
    assert mount == {"name": "signing-keys", "mountPath": "/etc/roost/signing", "readOnly": True}
    volume: dict[str, Any] = next(v for v in pod["volumes"] if v["name"] == "signing-keys")
    return volume


def test_agent_reads_signing_keys_from_a_read_only_secret_and_nowhere_else() -> None:
    pod = _agent_pod("signing")
    container = pod["containers"][0]
    volume = _signing_keys_volume(pod, "require")
    assert volume["projected"] == {
        "defaultMode": 0o444,
        "sources": [{"secret": {"name": "fleet-keys"}}],
    }
    assert "fleet-keys" not in str(container.get("env", []))  # not an env var, not an arg


def test_by_default_the_agent_mounts_no_secret_only_its_nodes_key_directory() -> None:
    """The per-node layout: each Vehicle's key pod leaves its key in the host directory;
    the agent pod references no Secret, so no node's kubelet is let read one for it."""
    pod = _agent_pod("defaults")
    assert _signing_keys_volume(pod, "auto") == {
        "name": "signing-keys",
        "hostPath": {"path": "/var/lib/roost/signing", "type": "DirectoryOrCreate"},
    }
    assert "secret" not in str(pod["volumes"]).lower()
    required = render({"agent": {"signing": {"mode": "require"}}})
    assert "/var/lib/roost/signing" in str(required)


def test_per_vehicle_keys_are_mounted_by_the_kubelet_and_the_agent_may_read_no_secret() -> None:
    pod = _agent_pod("signing-per-vehicle")
    volume = next(v for v in pod["volumes"] if v["name"] == "signing-keys")
    sources = volume["projected"]["sources"]
    assert [s["secret"]["name"] for s in sources] == [
        "roost-signing-drone-1",
        "roost-signing-drone-2",
    ]
    assert sources[0]["secret"]["optional"] is True  # a Vehicle without a key yet: no signing
    assert sources[0]["secret"]["items"] == [
        {"key": "key", "path": "drone-1/key"},
        {"key": "previous", "path": "drone-1/previous"},
    ]
    rules = _rules(_render_set("signing-per-vehicle"), "-agent")
    for verb in ("get", "list", "watch"):
        assert not _grants(rules, "", "secrets", verb), verb


def test_signing_without_its_secret_is_refused() -> None:
    with pytest.raises(ChartError, match=r"needs agent\.signing\.hostPath"):
        render({"agent": {"signing": {"mode": "require", "hostPath": ""}}})


def test_privileged_agent_without_a_device_list_is_refused() -> None:
    with pytest.raises(ChartError, match=r"needs agent\.devices\.paths"):
        render({"agent": {"devices": {"access": "privileged"}}})


def test_agent_role_writes_autopilot_status_and_new_events_only() -> None:
    rules = _rules(_render_set("defaults"), "-agent")
    for resource in ("vehicles", "redundantautopilots"):
        for verb in ("create", "update", "patch", "delete"):
            assert not _grants(rules, "roost.dev", resource, verb), (resource, verb)
    assert _grants(rules, "roost.dev", "redundantautopilots/status", "patch")
    assert not _grants(rules, "roost.dev", "vehicles/status", "patch")
    assert _grants(rules, "", "events", "create")
    assert not _grants(rules, "", "events", "patch")
    assert all("*" not in r["verbs"] for r in rules)


def test_agent_role_may_patch_vehicles_only_with_its_telemetry_stream_on() -> None:
    """To announce the stream on its Vehicle; the admission policy narrows the patch to
    its own Vehicle's roost.dev/telemetry* annotations. The pod proxy way in for
    dashboards comes with it (a Role in the release's namespace)."""
    docs = render({"agent": {"telemetry": {"enabled": True}}})
    rules = _rules(docs, "-agent")
    assert _grants(rules, "roost.dev", "vehicles", "patch")
    assert not _grants(rules, "roost.dev", "vehicles", "update")
    (role,) = [
        d
        for d in docs
        if d["kind"] == "Role" and d["metadata"]["name"].endswith("-agent-telemetry")
    ]
    assert role["rules"] == [{"apiGroups": [""], "resources": ["pods/proxy"], "verbs": ["get"]}]
    policy = next(d for d in docs if d["kind"] == "ValidatingAdmissionPolicy")
    variables = {v["name"]: v["expression"] for v in policy["spec"]["variables"]}
    assert "roost.dev/telemetry" in variables["telemetryOnly"]


def test_agent_drives_the_gpio_bridge_on_hardware_and_a_simulated_one_otherwise() -> None:
    assert "--bridge=simulated" in _agent_pod("defaults")["containers"][0]["args"]
    args = _agent_pod("hardware")["containers"][0]["args"]
    assert "--bridge=gpio" in args and "--gpio-chip=/dev/gpiochip0" in args
    assert "--status-interval=0" in args and "--cluster=on" in args


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"agent": {"bridge": {"driver": "gpio"}}}, "needs device access"),
        (
            {
                "agent": {
                    "bridge": {"driver": "gpio", "gpioChip": "/dev/gpiochip1"},
                    "devices": {"access": "privileged", "paths": ["/dev/ttyUSB0"]},
                }
            },
            "must be listed in agent.devices.paths",
        ),
    ],
)
def test_gpio_bridge_without_its_device_is_refused(values: dict[str, Any], message: str) -> None:
    with pytest.raises(ChartError, match=message):
        render(values)


def test_node_restriction_policy_matches_only_the_agent_and_uses_the_node_label() -> None:
    manifests = _render_set("defaults")
    policy = find(manifests, "ValidatingAdmissionPolicy")
    binding = find(manifests, "ValidatingAdmissionPolicyBinding")
    assert binding["spec"]["policyName"] == policy["metadata"]["name"]
    assert binding["spec"]["validationActions"] == ["Deny"]
    condition = policy["spec"]["matchConditions"][0]["expression"]
    assert condition == f'request.userInfo.username == "{AGENT_USER}"'
    expressions = " ".join(v["expression"] for v in policy["spec"]["validations"])
    assert f"'{LABEL_NODE}'" in expressions
    assert policy["spec"]["failurePolicy"] == "Fail"


def test_node_restriction_can_be_switched_off_for_old_clusters() -> None:
    kinds = {m["kind"] for m in _render_set("no-node-restriction")}
    assert "ValidatingAdmissionPolicy" not in kinds
    assert "DaemonSet" in kinds


def test_operator_only_install_creates_no_agent_objects() -> None:
    names = [m["metadata"]["name"] for m in _render_set("operator-only")]
    assert not [name for name in names if "-agent" in name]


def test_kubernetes_1_29_is_refused_the_node_restriction_and_told_the_fallback() -> None:
    with pytest.raises(ChartError, match=r"nodeRestriction\.enabled=false"):
        render(kube_version="1.29.4")


def test_kubernetes_1_29_installs_without_the_node_restriction() -> None:
    manifests = render({"agent": {"nodeRestriction": {"enabled": False}}}, kube_version="1.29.4")
    for manifest in manifests:
        if manifest["kind"] != "ClusterKopfPeering":
            kubernetes_validate.validate(manifest, "1.29.0", strict=True)
    assert "ValidatingAdmissionPolicy" not in {m["kind"] for m in manifests}


# -- metrics ---------------------------------------------------------------------------


def _annotations(manifest: Manifest) -> dict[str, str]:
    return dict(manifest["spec"]["template"]["metadata"].get("annotations") or {})


def test_operator_serves_metrics_on_their_own_port_with_scrape_annotations() -> None:
    deployment = find(_render_set("defaults"), "Deployment", "-operator")
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    assert "--metrics-port=9466" in container["args"]
    assert "--metrics-address=0.0.0.0" in container["args"]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    assert ports == {"health": 8080, "metrics": 9466, "records": 9469}
    assert _annotations(deployment) == {
        "prometheus.io/scrape": "true",
        "prometheus.io/port": "9466",
        "prometheus.io/path": "/metrics",
    }


def test_agent_metrics_stay_on_the_vehicle_unless_the_node_address_is_bound() -> None:
    daemonset = find(_render_set("defaults"), "DaemonSet", "-agent")
    container = daemonset["spec"]["template"]["spec"]["containers"][0]
    assert "--metrics-port=9465" in container["args"]
    names = [e["name"] for e in container["env"]]
    assert "ROOST_AGENT_METRICS_ADDRESS" not in names  # the agent's default: 127.0.0.1
    assert "prometheus.io/scrape" not in _annotations(daemonset)  # nothing could reach it
    assert not [m for m in _render_set("defaults") if m["kind"] == "ServiceMonitor"]

    bound = find(_render_set("monitoring"), "DaemonSet", "-agent")
    container = bound["spec"]["template"]["spec"]["containers"][0]
    address = {
        "name": "ROOST_AGENT_METRICS_ADDRESS",
        "valueFrom": {"fieldRef": {"fieldPath": "status.hostIP"}},
    }
    assert address in container["env"]
    assert container["ports"] == [
        {"name": "records", "containerPort": 9468, "hostPort": 9468, "protocol": "TCP"},
        {"name": "metrics", "containerPort": 9465, "hostPort": 9465, "protocol": "TCP"},
        {"name": "mavlink", "containerPort": 14550, "hostPort": 14550, "protocol": "UDP"},
    ]
    assert _annotations(bound)["prometheus.io/port"] == "9465"


def test_service_monitors_select_the_metrics_services_of_operator_and_agents() -> None:
    manifests = _render_set("monitoring")
    for component, port in (("operator", 9466), ("agent", 9465)):
        monitor = find(manifests, "ServiceMonitor", f"-{component}")
        assert monitor["metadata"]["labels"]["release"] == "prom"
        assert monitor["spec"]["endpoints"] == [
            {"port": "metrics", "path": "/metrics", "interval": "30s"}
        ]
        service = find(manifests, "Service", f"-{component}-metrics")
        selected = monitor["spec"]["selector"]["matchLabels"]
        assert selected.items() <= service["metadata"]["labels"].items()
        assert service["spec"]["ports"][0]["port"] == port
        pods = find(manifests, "Deployment" if component == "operator" else "DaemonSet")
        assert (
            service["spec"]["selector"].items()
            <= pods["spec"]["template"]["metadata"]["labels"].items()
        )


def test_no_metrics_means_no_flags_ports_or_annotations() -> None:
    manifests = _render_set("no-metrics")
    for kind in ("Deployment", "DaemonSet"):
        pod = find(manifests, kind)["spec"]["template"]
        container = pod["spec"]["containers"][0]
        assert not [a for a in container["args"] if a.startswith("--metrics")]
        assert "prometheus.io/scrape" not in (pod["metadata"].get("annotations") or {})
    with pytest.raises(ChartError, match="serviceMonitor"):
        render({"metrics": {"serviceMonitor": {"enabled": True, "interval": "often"}}})


def test_grafana_dashboard_ships_valid_json_using_only_documented_metrics() -> None:
    configmap = find(_render_set("monitoring"), "ConfigMap", "-dashboard")
    assert configmap["metadata"]["labels"]["grafana_dashboard"] == "1"
    dashboard = json.loads(configmap["data"]["roost.json"])
    assert dashboard["uid"] == "roost-fleet"
    exprs = [t["expr"] for panel in dashboard["panels"] for t in panel.get("targets", [])]
    used = {
        re.sub(r"_(bucket|sum|count)$", "", name)
        for expr in exprs
        for name in re.findall(r"\b(roost_(?:agent|operator)_[a-z_]+)", expr)
    }
    documented = set(
        re.findall(
            r"`(roost_(?:agent|operator)_[a-z_]+)`", (REPO_ROOT / "docs" / "metrics.md").read_text()
        )
    )
    assert used and used <= documented, used - documented
    assert not [m for m in _render_set("defaults") if m["kind"] == "ConfigMap"]


# -- dashboard -------------------------------------------------------------------------


def test_dashboard_is_off_by_default_and_agents_stream_nothing() -> None:
    manifests = _render_set("defaults")
    assert not [m for m in manifests if m["metadata"]["name"].endswith("-dashboard")]
    container = find(manifests, "DaemonSet", "-agent")["spec"]["template"]["spec"]["containers"][0]
    assert not [a for a in container["args"] if a.startswith("--telemetry")]


def test_dashboard_runs_read_only_with_a_role_that_only_reads() -> None:
    manifests = _render_set("dashboard")
    role = find(manifests, "ClusterRole", "-dashboard")
    verbs = {verb for rule in role["rules"] for verb in rule["verbs"]}
    assert verbs == {"get", "list", "watch"}
    resources = {r for rule in role["rules"] for r in rule["resources"]}
    assert resources == {"vehicles", "redundantautopilots", "missions", "events"}
    binding = find(manifests, "ClusterRoleBinding", "-dashboard")
    deployment = find(manifests, "Deployment", "-dashboard")
    pod = deployment["spec"]["template"]["spec"]
    assert binding["subjects"][0]["name"] == pod["serviceAccountName"]
    [container] = pod["containers"]
    assert container["command"] == ["roost"]
    assert container["args"][:3] == ["dashboard", "--in-cluster", "--read-only"]
    assert "--origin=47.3977,8.5456" in container["args"]
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    service = find(manifests, "Service", "-dashboard")
    assert service["spec"]["selector"] == deployment["spec"]["selector"]["matchLabels"]


def test_agent_telemetry_binds_the_node_address_only_when_asked() -> None:
    daemonset = find(_render_set("dashboard"), "DaemonSet", "-agent")
    container = daemonset["spec"]["template"]["spec"]["containers"][0]
    assert "--telemetry-port=9467" in container["args"]
    assert {
        "name": "ROOST_AGENT_TELEMETRY_ADDRESS",
        "valueFrom": {"fieldRef": {"fieldPath": "status.hostIP"}},
    } in container["env"]
    assert {"name": "telemetry", "containerPort": 9467, "hostPort": 9467, "protocol": "TCP"} in (
        container["ports"]
    )
