"""The Vehicle operator, running as a real ``roost-operator`` process, on the real control
plane (localcluster/): kube-apiserver and etcd store the objects, the operator creates each
vehicle component's Pod bound to the vehicle's node (no Deployment, no scheduler) and
kwok's fake kubelets run them on fake vehicle nodes.

The operator gets its own namespace and runs as shipped: no fleet sweep, so everything
below (hand edits put back, a freed node handed on, nothing written while idle) happens
on watch events alone. Vehicles are cluster-scoped and
the cluster is shared by the session, so every test uses unique names and deletes its
Vehicles while the operator still runs (it releases their nodes; Vehicles carry no
finalizer, so deletion itself never waits for it).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest

from roost_api.wellknown import (
    ANNOTATION_CONFIG_HASH,
    ANNOTATION_MANAGED_LABELS,
    ANNOTATION_POD_HASH,
    LABEL_COMPONENT,
    LABEL_NODE,
    LABEL_VEHICLE,
    LABEL_VEHICLE_CLASS,
    LABEL_VEHICLE_TYPE,
    PREFIX,
    STARLING_LABEL_TYPE,
    TAINT_VEHICLE,
)
from roost_kube.client import Kube
from roost_kube.patches import Obj
from roost_kube.resources import (
    CONFIGMAPS,
    NODES,
    PODS,
    REDUNDANT_AUTOPILOTS,
    VEHICLES,
)
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import KWOK_NODE_ANNOTATION
from roost_localcluster.nodes import fake_node
from roost_operator.vehicles.manifests import is_component_pod
from tests.support.apiwrites import operator_writes
from tests.support.disruption import fly_change_and_drain
from tests.support.operator import OperatorProcess
from tests.support.waiting import unique, wait_until

pytestmark = pytest.mark.cluster

NAMESPACE = "roost-it-vehicles"
WINDOW_S = 2
"""The idle windows below are counted in these."""
OPERATOR_NAMESPACE = NAMESPACE
OPERATOR_ENV = {"ROOST_FIRST_REPORT_HOLD_SECONDS": "120"}
"""A first-report hold no starting pod outlasts, however busy the machine: a new
Vehicle's way to Ready is then exactly one status write. Nothing here waits for a held
report: the tests wait for Ready, or for a problem, which is never held."""
WAIT_S = 60.0
AddNode = Callable[..., dict[str, Any]]


@pytest.fixture
def vehicles(
    roost_crds: Cluster, operator: OperatorProcess, kube: Kube
) -> Iterator[Callable[..., str]]:
    """``vehicles(name, node, **spec)`` applies a Vehicle with kubectl; deleted at the end."""
    created: list[str] = []

    def apply(name: str, node: str, **spec: Any) -> str:
        created.append(name)
        manifest = {
            "apiVersion": "roost.dev/v1alpha1",
            "kind": "Vehicle",
            "metadata": {"name": name},
            "spec": {"nodeName": node, "sysid": 10 + len(created), **spec},
        }
        roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
        return name

    yield apply
    if not operator.process.alive():
        operator.start()
    for name in created:
        roost_crds.kubectl("delete", "vehicle", name, "--ignore-not-found", "--wait=false")
    wait_until(
        "the test's Vehicles to be gone",
        lambda: all(kube.get(VEHICLES, name) is None for name in created),
    )


def condition(kube: Kube, vehicle: str, type_: str) -> Obj | None:
    obj = kube.get(VEHICLES, vehicle) or {}
    return next(
        (c for c in (obj.get("status") or {}).get("conditions", []) if c["type"] == type_), None
    )


def wait_ready(kube: Kube, vehicle: str, timeout_s: float = WAIT_S) -> Obj:
    def ready() -> Obj | None:
        cond = condition(kube, vehicle, "Ready")
        return cond if cond and cond["status"] == "True" else None

    result: Obj = wait_until(f"Vehicle {vehicle} Ready=True", ready, timeout_s)
    return result


def wait_components_ready(kube: Kube, vehicle: str) -> None:
    """NodeBound and ComponentsReady True: all the vehicle reconcile decides.

    With a RedundantAutopilot, Ready also needs the node agent's reports
    (AgentConnected, AutopilotsHealthy), and no agent runs in these tests.
    """
    for type_, reason in (("NodeBound", "NodeLabeled"), ("ComponentsReady", "AllComponentsReady")):
        wait_condition(kube, vehicle, type_, "True", reason)


def wait_condition(kube: Kube, vehicle: str, type_: str, status: str, reason: str) -> Obj:
    def matches() -> Obj | None:
        cond = condition(kube, vehicle, type_)
        if cond and cond["status"] == status and cond["reason"] == reason:
            return cond
        return None

    result: Obj = wait_until(f"{vehicle} {type_}={status} ({reason})", matches)
    return result


def component_pods(kube: Kube, vehicle: str) -> dict[str, Obj]:
    """The vehicle's component pods by component, terminating ones included."""
    return {
        p["metadata"]["labels"]["roost.dev/component"]: p
        for p in kube.list_objects(PODS, namespace=NAMESPACE, labels={LABEL_VEHICLE: vehicle})
        if is_component_pod(p)
    }


def pods_of(kube: Kube, vehicle: str, component: str) -> list[Obj]:
    return [
        p
        for p in kube.list_objects(
            PODS,
            namespace=NAMESPACE,
            labels={LABEL_VEHICLE: vehicle, "roost.dev/component": component},
        )
        if not p["metadata"].get("deletionTimestamp")
    ]


def node_labels(kube: Kube, node: str) -> dict[str, str]:
    labels: dict[str, str] = (kube.get(NODES, node) or {})["metadata"].get("labels", {})
    return labels


def roost_taints(kube: Kube, node: str) -> list[Obj]:
    taints = ((kube.get(NODES, node) or {}).get("spec") or {}).get("taints") or []
    return [t for t in taints if t["key"] == TAINT_VEHICLE]


def redundant_autopilot(vehicle: str) -> dict[str, Any]:
    """The vehicle's RedundantAutopilot, named after it as admission requires."""
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "RedundantAutopilot",
        "metadata": {"name": vehicle},
        "spec": {
            "vehicleName": vehicle,
            "primary": "fc-a",
            "autopilots": [
                {
                    "name": "fc-a",
                    "stack": "px4",
                    "connection": "udp://127.0.0.1:14540",
                    "sysid": 1,
                    "bridgeChannel": 0,
                },
                {
                    "name": "fc-b",
                    "stack": "px4",
                    "connection": "udp://127.0.0.1:14541",
                    "fcuUrl": "udp://127.0.0.1:14641@",
                    "sysid": 2,
                    "bridgeChannel": 1,
                },
            ],
        },
    }


# ---- binding, config and components ---------------------------------------------------


def test_a_simulated_vehicle_gets_its_node_config_and_components(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    fake_nodes(node)
    name = unique("sim")
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(redundant_autopilot(name)))
    try:
        vehicles(
            name,
            node,
            simulation={"stack": "px4", "instance": 1},
            components={"vicon": {"enabled": True, "image": "example.org/vicon:7"}},
            config={"MISSION_AREA": "flight-arena"},
        )
        wait_components_ready(kube, name)

        labels = node_labels(kube, node)
        assert labels[LABEL_VEHICLE] == name
        assert labels["roost.dev/simulated"] == "true"
        assert labels["roost.dev/sitl-stack"] == "px4"
        assert labels[STARLING_LABEL_TYPE] == "vehicle"
        assert roost_taints(kube, node) == [
            {"key": TAINT_VEHICLE, "value": name, "effect": "NoSchedule"}
        ]

        vehicle = kube.get(VEHICLES, name)
        assert vehicle is not None
        # No write to the Vehicle itself: no finalizer (leftovers carry its label), no
        # diff base
        assert not vehicle["metadata"].get("finalizers")
        assert not any(key.startswith(PREFIX) for key in vehicle["metadata"].get("annotations", {}))
        status = vehicle["status"]
        assert status["nodeName"] == node
        assert status["observedGeneration"] == vehicle["metadata"]["generation"]
        assert LABEL_VEHICLE in status["managedLabels"]
        assert status["fcuUrl"] == "udp://127.0.0.1:14540"
        assert {c["type"] for c in status["conditions"]} >= {
            "NodeBound",
            "ComponentsReady",
            "Ready",
        }

        cm = kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE)
        assert cm is not None
        text = cm["data"]["vehicle.config"]
        for line in (
            f"VEHICLE_NAME={name}",
            "VEHICLE_FCU_URL=udp://127.0.0.1:14540",
            "VEHICLE_FIRMWARE=px4",
            "MISSION_AREA=flight-arena",
        ):
            assert line in text.splitlines()

        pods = component_pods(kube, name)
        assert set(pods) == {"mavros", "vicon", "sitl-fc-a", "sitl-fc-b"}
        for pod in pods.values():
            assert pod["metadata"]["ownerReferences"][0]["uid"] == vehicle["metadata"]["uid"]
            assert pod["metadata"]["name"] == f"{name}-{pod['metadata']['labels'][LABEL_COMPONENT]}"
            assert {ANNOTATION_CONFIG_HASH, ANNOTATION_POD_HASH} <= set(
                pod["metadata"]["annotations"]
            )
            assert pod["spec"]["nodeName"] == node
            assert pod["spec"]["nodeSelector"][LABEL_VEHICLE] == name
            assert pod["spec"]["restartPolicy"] == "Always"
        assert pods["vicon"]["spec"]["containers"][0]["image"] == "example.org/vicon:7"

        (mavros,) = pods_of(kube, name, "mavros")
        assert mavros["spec"]["nodeName"] == node
        assert mavros["status"]["phase"] == "Running"
        mounts = {m["mountPath"]: m for m in mavros["spec"]["containers"][0]["volumeMounts"]}
        assert mounts["/etc/roost"]["readOnly"] and mounts["/etc/starling"]["readOnly"]
        env = {e["name"] for e in mavros["spec"]["containers"][0]["env"]}
        assert {"VEHICLE_NAME", "VEHICLE_MAVLINK_SYSID", "MISSION_AREA"} <= env

        # a condition appearing True is the vehicle starting as it should: no Event
        assert "NodeLabeled" not in vehicle_events(roost_crds, name)
    finally:
        roost_crds.kubectl("delete", "redundantautopilot", name, "--ignore-not-found")


def wait_operator_quiet(cluster: Cluster, timeout_s: float = 60.0) -> None:
    """Return once the operator made no write for a whole window (the rollout's last
    status updates may still be landing). An operator that never stops writing never gets
    quiet, and the wait fails naming it."""

    def quiet() -> bool:
        window = cluster.audit_window()
        time.sleep(WINDOW_S)
        return not operator_writes(cluster, window)

    wait_until("a window without writes from the operator", quiet, timeout_s, 0.0)


def test_an_idle_vehicle_costs_no_api_writes(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    fake_nodes(node)
    name = vehicles(unique("idle"), node, simulation={"stack": "ardupilot"})
    wait_ready(kube, name)

    def versions() -> list[str]:
        objs = [kube.get(VEHICLES, name), kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE)]
        objs += list(component_pods(kube, name).values())
        return [o["metadata"]["resourceVersion"] for o in objs if o]

    def node_state() -> Any:
        meta = (kube.get(NODES, node) or {})["metadata"]
        return meta.get("labels"), meta.get("annotations"), roost_taints(kube, node)

    wait_operator_quiet(roost_crds)
    versions_before, node_before = versions(), node_state()
    window = roost_crds.audit_window()
    time.sleep(WINDOW_S * 4)  # nothing happens: node heartbeats, kwok's pod status
    assert not operator_writes(roost_crds, window)
    assert versions() == versions_before
    assert node_state() == node_before


def test_a_new_vehicle_whose_pods_start_at_once_is_reported_once(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    """Its "components starting" report waits for its pods (the operator's default
    first-report hold), so the way to Ready costs one status write. A Vehicle whose first
    status is Ready started as it should: that is no Event's news."""
    node = unique("veh-node")
    fake_nodes(node)
    window = roost_crds.audit_window()
    name = vehicles(unique("once"), node)
    wait_ready(kube, name)
    wait_operator_quiet(roost_crds)
    writes = operator_writes(roost_crds, window)
    by_resource = {kind.resource: n for kind, n in writes.items() if not kind.error}
    assert by_resource.get("vehicles/status") == 1, writes
    assert not by_resource.get("events"), writes
    assert vehicle_events(roost_crds, name) == []


# ---- node labels: only Roost's own keys ------------------------------------------------


def test_hand_edits_are_put_back_and_others_labels_survive_deletion(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    foreign_taint = {
        "key": "example.org/maintenance",
        "value": "soon",
        "effect": "PreferNoSchedule",
    }
    fake_nodes(node, labels={"team": "blue", "roost.dev/hand-set": "keep"}, taints=[foreign_taint])
    name = vehicles(unique("edit"), node, vehicleClass="fixed-wing")
    wait_ready(kube, name)
    assert node_labels(kube, node)[LABEL_VEHICLE_CLASS] == "fixed-wing"

    roost_crds.kubectl("label", "node", node, f"{LABEL_VEHICLE_CLASS}-", "team=red", "--overwrite")
    wait_until(
        "the operator to put its label back",
        lambda: node_labels(kube, node).get(LABEL_VEHICLE_CLASS) == "fixed-wing",
    )
    assert node_labels(kube, node)["team"] == "red"

    roost_crds.kubectl("delete", "vehicle", name, "--wait=true", "--timeout=60s")
    wait_until(
        "the operator to release the node",
        lambda: LABEL_VEHICLE not in node_labels(kube, node),
    )
    labels = node_labels(kube, node)
    assert labels["team"] == "red"
    assert labels["roost.dev/hand-set"] == "keep"
    assert not {k for k in labels if k.startswith("starling.dev/")}
    assert LABEL_VEHICLE not in labels
    node_obj = kube.get(NODES, node)
    assert node_obj is not None
    assert ANNOTATION_MANAGED_LABELS not in node_obj["metadata"].get("annotations", {})
    assert node_obj["spec"]["taints"] == [foreign_taint]
    assert kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE) is None
    wait_until("the workloads to be deleted", lambda: not component_pods(kube, name))


# ---- config changes, failover input, self-healing ---------------------------------------


def test_config_changes_roll_pods_and_a_new_active_autopilot_repoints_only_mavros(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    fake_nodes(node)
    name = unique("roll")
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(redundant_autopilot(name)))
    try:
        vehicles(name, node, simulation={"stack": "px4"})
        wait_components_ready(kube, name)
        (mavros_before,) = pods_of(kube, name, "mavros")
        sitl_before = {
            p["metadata"]["uid"] for c in ("sitl-fc-a", "sitl-fc-b") for p in pods_of(kube, name, c)
        }

        roost_crds.kubectl(
            "patch", "vehicle", name, "--type=merge", "-p", '{"spec":{"config":{"FOO":"bar"}}}'
        )
        wait_until(
            "the config to reach the ConfigMap",
            lambda: (
                "FOO=bar"
                in (kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE) or {})["data"][
                    "vehicle.config"
                ]
            ),
        )
        mavros_after = wait_until(
            "mavros to be replaced",
            lambda: [
                p
                for p in pods_of(kube, name, "mavros")
                if p["metadata"]["uid"] != mavros_before["metadata"]["uid"]
                and p["status"].get("phase") == "Running"
            ],
        )
        assert {
            "name": "FOO",
            "valueFrom": {"configMapKeyRef": {"name": f"roost-vehicle-{name}", "key": "FOO"}},
        } in mavros_after[0]["spec"]["containers"][0]["env"]
        wait_components_ready(kube, name)

        # The node agent reports a failover to fc-b: mavros follows, the SITLs stay up.
        sitl_before = {
            p["metadata"]["uid"] for c in ("sitl-fc-a", "sitl-fc-b") for p in pods_of(kube, name, c)
        }
        roost_crds.kubectl(
            "patch",
            "redundantautopilot",
            name,
            "--subresource=status",
            "--type=merge",
            "-p",
            '{"status":{"activeAutopilot":"fc-b"}}',
        )
        wait_until(
            "status.fcuUrl to follow the active autopilot",
            lambda: (
                (kube.get(VEHICLES, name) or {}).get("status", {}).get("fcuUrl")
                == "udp://127.0.0.1:14641@"
            ),
        )
        cm = kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE)
        assert cm is not None and cm["data"]["VEHICLE_FCU_URL"] == "udp://127.0.0.1:14641@"
        assert cm["data"]["ROOST_ACTIVE_AUTOPILOT"] == "fc-b"
        wait_components_ready(kube, name)
        sitl_after = {
            p["metadata"]["uid"] for c in ("sitl-fc-a", "sitl-fc-b") for p in pods_of(kube, name, c)
        }
        assert sitl_after == sitl_before
    finally:
        roost_crds.kubectl("delete", "redundantautopilot", name, "--ignore-not-found")


def test_deleted_pods_come_back_and_disabled_components_go_away(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    fake_nodes(node)
    name = vehicles(unique("heal"), node, components={"vicon": {"enabled": True}})
    wait_ready(kube, name)
    (pod,) = pods_of(kube, name, "mavros")
    roost_crds.kubectl("delete", "pod", "-n", NAMESPACE, pod["metadata"]["name"], "--wait=false")
    wait_until(
        "a replacement mavros pod",
        lambda: [
            p
            for p in pods_of(kube, name, "mavros")
            if p["metadata"]["uid"] != pod["metadata"]["uid"]
        ],
    )
    # An ended pod (here: vicon, as the kubelet reports an eviction) is replaced too.
    (vicon,) = pods_of(kube, name, "vicon")
    roost_crds.kubectl(
        "patch",
        "pod",
        "-n",
        NAMESPACE,
        vicon["metadata"]["name"],
        "--subresource=status",
        "--type=merge",
        "-p",
        '{"status":{"phase":"Failed","reason":"Evicted","message":"the node ran out of memory"}}',
    )
    wait_until(
        "a replacement vicon pod, Running",
        lambda: [
            p
            for p in pods_of(kube, name, "vicon")
            if p["metadata"]["uid"] != vicon["metadata"]["uid"]
            and p["status"].get("phase") == "Running"
        ],
    )
    wait_ready(kube, name)
    roost_crds.kubectl(
        "patch",
        "vehicle",
        name,
        "--type=merge",
        "-p",
        '{"spec":{"components":{"vicon":{"enabled":false}}}}',
    )
    wait_until("the vicon pod to be removed", lambda: set(component_pods(kube, name)) == {"mavros"})
    wait_ready(kube, name)


# ---- hot swap, missing node, contested node -----------------------------------------


def test_hot_swap_moves_the_workloads_and_releases_the_old_node(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    old, new = unique("veh-old"), unique("veh-new")
    fake_nodes(old, labels={"team": "blue"})
    fake_nodes(new)
    name = vehicles(unique("swap"), old)
    wait_ready(kube, name)
    roost_crds.kubectl(
        "patch", "vehicle", name, "--type=merge", "-p", json.dumps({"spec": {"nodeName": new}})
    )

    wait_until(
        "mavros to run on the new node",
        lambda: [
            p
            for p in pods_of(kube, name, "mavros")
            if p["spec"].get("nodeName") == new and p["status"].get("phase") == "Running"
        ],
    )
    wait_ready(kube, name)
    assert node_labels(kube, new)[LABEL_VEHICLE] == name
    assert node_labels(kube, old) == {
        k: v
        for k, v in node_labels(kube, old).items()
        if not k.startswith(("roost.dev/", "starling.dev/"))
    }
    assert node_labels(kube, old)["team"] == "blue"
    assert roost_taints(kube, old) == []
    assert all(p["spec"].get("nodeName") == new for p in pods_of(kube, name, "mavros"))
    assert (kube.get(VEHICLES, name) or {})["status"]["nodeName"] == new


def test_a_missing_node_is_reported_and_the_vehicle_converges_when_it_joins(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-late")
    name = vehicles(unique("late"), node)
    cond = wait_condition(kube, name, "NodeBound", "False", "NodeNotFound")
    assert node in cond["message"]
    ready = condition(kube, name, "Ready")
    assert ready is not None and (ready["status"], ready["reason"]) == ("False", "NodeNotFound")

    fake_nodes(node)
    wait_ready(kube, name)
    assert node_labels(kube, node)[LABEL_VEHICLE] == name

    # Events: the problem from the start (NodeBound's, not Ready's repeat of it), then
    # each condition turning True
    def started() -> list[str] | None:
        reasons = vehicle_events(roost_crds, name)
        return reasons if "VehicleReady" in reasons else None

    reasons = wait_until("the Events of the vehicle's start", started)
    assert sorted(reasons) == ["NodeLabeled", "NodeNotFound", "VehicleReady"]


def test_a_node_that_is_not_ready_is_reported_with_the_kubelets_words(
    roost_crds: Cluster, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-down")
    # A node no kubelet (here: kwok) looks after: it never reports Ready.
    manifest = fake_node(node)
    del manifest["metadata"]["annotations"][KWOK_NODE_ANNOTATION]
    roost_crds.kubectl("create", "-f", "-", input_text=json.dumps(manifest))
    try:
        name = vehicles(unique("down"), node)
        cond = wait_condition(kube, name, "NodeBound", "False", "NodeNotReady")
        assert node in cond["message"] and "Ready" in cond["message"]
        assert node_labels(kube, node)[LABEL_VEHICLE] == name  # labelled all the same
        ready = condition(kube, name, "Ready")
        assert ready is not None and (ready["status"], ready["reason"]) == ("False", "NodeNotReady")
    finally:
        roost_crds.kubectl("delete", "node", node, "--ignore-not-found", "--wait=false")


def test_two_vehicles_on_one_node_the_older_keeps_it_without_a_fight(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    fake_nodes(node)
    first = vehicles(unique("first"), node)
    wait_ready(kube, first)
    stamp = (kube.get(VEHICLES, first) or {})["metadata"]["creationTimestamp"]
    created = datetime.fromisoformat(stamp.replace("Z", "+00:00"))
    wait_until(  # creationTimestamps have one-second resolution: the second must be later
        "the clock to pass the first Vehicle's creation second",
        lambda: datetime.now(UTC) >= created + timedelta(seconds=1),
    )
    second = vehicles(unique("second"), node)

    cond = wait_condition(kube, second, "NodeBound", "False", "NodeClaimedByOtherVehicle")
    assert first in cond["message"]
    assert not component_pods(kube, second)
    assert node_labels(kube, node)[LABEL_VEHICLE] == first

    window = roost_crds.audit_window()
    time.sleep(WINDOW_S * 3)  # nothing happens: no fight over the node
    node_writes = [kind for kind in operator_writes(roost_crds, window) if kind.resource == "nodes"]
    assert not node_writes, "the two vehicles fight"
    assert node_labels(kube, node)[LABEL_VEHICLE] == first
    assert condition(kube, first, "Ready")["status"] == "True"  # type: ignore[index]

    roost_crds.kubectl("delete", "vehicle", first, "--wait=true", "--timeout=60s")
    wait_ready(kube, second)
    assert node_labels(kube, node)[LABEL_VEHICLE] == second


def test_a_vehicle_deleted_while_the_operator_is_down_is_released_when_it_is_back(
    fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube, operator: OperatorProcess
) -> None:
    cluster = operator.cluster
    node = unique("veh-node")
    fake_nodes(node)
    name = vehicles(unique("gone"), node)
    wait_ready(kube, name)
    operator.stop()
    # Nothing waits for the operator: the Vehicle is gone at once.
    cluster.kubectl("delete", "vehicle", name, "--wait=true", "--timeout=30s")
    assert node_labels(kube, node)[LABEL_VEHICLE] == name
    assert roost_taints(kube, node)
    operator.start()
    # Its node still carries its label: the operator's first listing of nodes finds it.
    wait_until(
        "the deleted Vehicle's node released",
        lambda: LABEL_VEHICLE not in node_labels(kube, node) and not roost_taints(kube, node),
    )
    wait_until("its pods gone", lambda: not component_pods(kube, name))
    assert kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE) is None


# ---- crash in the middle of a reconcile ------------------------------------------------


@pytest.fixture
def pods_refused(roost_crds: Cluster) -> Iterator[Callable[[], None]]:
    """A ResourceQuota allowing no new Pods in the operator's namespace; call to lift it."""
    quota = {
        "apiVersion": "v1",
        "kind": "ResourceQuota",
        "metadata": {"name": "it-no-pods", "namespace": NAMESPACE},
        "spec": {"hard": {"count/pods": "0"}},
    }
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(quota))

    def lift() -> None:
        roost_crds.kubectl(
            "delete", "resourcequota", "-n", NAMESPACE, "it-no-pods", "--ignore-not-found"
        )

    yield lift
    lift()


def test_an_operator_killed_mid_reconcile_converges_after_restart(
    fake_nodes: AddNode,
    vehicles: Callable[..., str],
    kube: Kube,
    operator: OperatorProcess,
    pods_refused: Callable[[], None],
) -> None:
    cluster = operator.cluster
    node = unique("veh-node")
    fake_nodes(node)
    name = vehicles(unique("crash"), node)

    # Half-way: node labelled and config written, the Pod refused by the quota.
    cond = wait_condition(kube, name, "ComponentsReady", "False", "ComponentsNotReady")
    assert "refused" in cond["message"] and "quota" in cond["message"]
    assert node_labels(kube, node)[LABEL_VEHICLE] == name
    assert kube.get(CONFIGMAPS, f"roost-vehicle-{name}", NAMESPACE) is not None
    assert not component_pods(kube, name)

    operator.crash()
    cluster.kubectl(
        "patch", "vehicle", name, "--type=merge", "-p", '{"spec":{"vehicleType":"hexarotor"}}'
    )
    pods_refused()
    operator.start()

    wait_ready(kube, name)
    assert node_labels(kube, node)[LABEL_VEHICLE_TYPE] == "hexarotor"
    assert set(component_pods(kube, name)) == {"mavros"}
    assert len(pods_of(kube, name, "mavros")) == 1
    vehicle = kube.get(VEHICLES, name)
    assert vehicle is not None
    assert vehicle["status"]["observedGeneration"] == vehicle["metadata"]["generation"]


# ---- bad input: reported once, and deletion always finishes --------------------------------


def vehicle_events(cluster: Cluster, vehicle: str) -> list[str]:
    """Reasons of the Events about Vehicle ``vehicle`` (cluster-scoped: in ``default``)."""
    out = cluster.kubectl(
        "get",
        "events",
        "-n",
        "default",
        "--field-selector",
        f"involvedObject.name={vehicle}",
        "-o",
        "jsonpath={range .items[*]}{.reason}{'\\n'}{end}",
    ).stdout
    return out.split()


def label_refusing_policy(rap: str) -> list[dict[str, Any]]:
    """A site admission policy (as Kyverno or Gatekeeper would be) that refuses the
    roost.dev/node label on one RedundantAutopilot: a write Roost must make, refused for
    good by the API server (422) although the Vehicle passed admission."""
    name = f"it-refuse-{rap}"
    return [
        {
            "apiVersion": "admissionregistration.k8s.io/v1",
            "kind": "ValidatingAdmissionPolicy",
            "metadata": {"name": name},
            "spec": {
                "failurePolicy": "Fail",
                "matchConstraints": {
                    "resourceRules": [
                        {
                            "apiGroups": ["roost.dev"],
                            "apiVersions": ["*"],
                            "operations": ["CREATE", "UPDATE"],
                            "resources": ["redundantautopilots"],
                        }
                    ]
                },
                "validations": [
                    {
                        "expression": (
                            f"object.metadata.name != '{rap}' || "
                            "!has(object.metadata.labels) || "
                            f"!('{LABEL_NODE}' in object.metadata.labels)"
                        ),
                        "message": "site policy: this autopilot set may not be bound to a node",
                    }
                ],
            },
        },
        {
            "apiVersion": "admissionregistration.k8s.io/v1",
            "kind": "ValidatingAdmissionPolicyBinding",
            "metadata": {"name": name},
            "spec": {"policyName": name, "validationActions": ["Deny"]},
        },
    ]


def test_a_write_the_api_server_refuses_is_reported_once_and_deletion_still_finishes(
    roost_crds: Cluster, vehicles: Callable[..., str], kube: Kube
) -> None:
    """A write the API server refuses for good (a site policy refusing the RedundantAutopilot's
    roost.dev/node label): the operator reports it in NodeBound with the API's words (no
    retry loop), and both objects can still be deleted."""
    name = unique("vrefused")
    rap = name
    policy = label_refusing_policy(rap)
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(redundant_autopilot(name)))
    roost_crds.kubectl(
        "apply",
        "-f",
        "-",
        input_text=json.dumps({"kind": "List", "apiVersion": "v1", "items": policy}),
    )
    try:

        def policy_in_force() -> bool:
            trial = roost_crds.kubectl(
                "label",
                "redundantautopilot",
                rap,
                f"{LABEL_NODE}=x",
                "--dry-run=server",
                check=False,
            )
            return trial.returncode != 0 and "site policy" in trial.stderr

        wait_until("the site policy in force", policy_in_force)
        vehicles(name, unique("node"))
        cond = wait_condition(kube, name, "NodeBound", "False", "AutopilotLabelRefused")
        assert "site policy" in cond["message"]
        wait_until("the Refused Event", lambda: "Refused" in vehicle_events(roost_crds, name))
        # "Nothing happens" for a while: the refusal is not retried into a storm.
        time.sleep(3 * WINDOW_S)
        assert vehicle_events(roost_crds, name).count("Refused") == 1
        roost_crds.kubectl("delete", "redundantautopilot", rap, "--wait=false")
        roost_crds.kubectl("delete", "vehicle", name, "--wait=false")
        wait_until(
            "the broken Vehicle and RedundantAutopilot to be gone",
            lambda: (
                kube.get(VEHICLES, name) is None and kube.get(REDUNDANT_AUTOPILOTS, rap) is None
            ),
        )
    finally:
        for obj in policy:
            roost_crds.kubectl(
                "delete", obj["kind"].lower(), obj["metadata"]["name"], "--ignore-not-found"
            )


# ---- nothing changes under a vehicle in the air -----------------------------------------


def test_in_the_air_a_config_change_waits_and_a_drain_is_refused_naming_the_vehicle(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    node = unique("veh-node")
    fake_nodes(node)
    name = unique("flying")
    roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(redundant_autopilot(name)))
    try:
        vehicles(name, node, simulation={"stack": "px4"})
        wait_components_ready(kube, name)
        outcome = fly_change_and_drain(
            roost_crds, kube, vehicle=name, node=node, namespace=NAMESPACE
        )
        assert outcome.drain_in_flight.returncode != 0, outcome.drain_in_flight.stdout
        assert outcome.evictions_in_flight, "the vehicle had no component pods to evict"
        for pod, answer in outcome.evictions_in_flight.items():
            assert pod.startswith(f"{name}-"), pod  # each pod's name carries the vehicle's
            assert "violate the pod's disruption budget" in answer, (pod, answer)
        assert outcome.replacements_in_flight == 0
        assert "mavros" in outcome.deferred
        assert outcome.hold_reason == "autopilot fc-a, fc-b are armed"
        assert outcome.replaced_after_landing
        assert outcome.drain_after_landing.returncode == 0, outcome.drain_after_landing.stderr
        assert not outcome.budget_left
        wait_components_ready(kube, name)
    finally:
        roost_crds.kubectl("delete", "redundantautopilot", name, "--ignore-not-found")


# ---- per-Vehicle signing keys ----------------------------------------------------------


def test_each_vehicles_key_pod_is_pinned_to_its_node_and_mounts_only_its_own_secret(
    roost_crds: Cluster, fake_nodes: AddNode, vehicles: Callable[..., str], kube: Kube
) -> None:
    """spec.components.signingKeys: the operator runs one key pod per Vehicle, bound to
    that vehicle's node, mounting that Vehicle's Secret and no other (so only that node's
    kubelet is let read it), and removes it when the Vehicle stops asking for it."""
    nodes = [unique("key-node"), unique("key-node")]
    names = [unique("keyed"), unique("keyed")]
    for node, name in zip(nodes, names, strict=True):
        fake_nodes(node)
        vehicles(name, node, components={"signingKeys": {"enabled": True}})
    for node, name in zip(nodes, names, strict=True):
        wait_components_ready(kube, name)
        pods = component_pods(kube, name)
        assert set(pods) == {"mavros", "signing-keys"}
        spec = pods["signing-keys"]["spec"]
        assert spec["nodeName"] == node
        secrets = [v["secret"]["secretName"] for v in spec["volumes"] if "secret" in v]
        assert secrets == [f"roost-signing-{name}"]
        assert [v["hostPath"]["path"] for v in spec["volumes"] if "hostPath" in v] == [
            f"/var/lib/roost/signing/{name}"
        ]
        assert spec["automountServiceAccountToken"] is False
        # no other pod of the vehicle references a Secret
        for component, pod in pods.items():
            if component != "signing-keys":
                assert "secret" not in json.dumps(pod["spec"]["volumes"]), component

    first = names[0]
    roost_crds.kubectl(
        "patch",
        "vehicle",
        first,
        "--type=merge",
        "-p",
        json.dumps({"spec": {"components": {"signingKeys": {"enabled": False}}}}),
    )
    wait_until(f"{first}'s key pod to be gone", lambda: not pods_of(kube, first, "signing-keys"))
    assert pods_of(kube, names[1], "signing-keys")
