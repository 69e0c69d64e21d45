"""A vehicle's WiFi drop on real harness nodes: what survives it, and how soon the status
catches up once the link is back.

Shared by ``tests/e2e_node/test_partition.py`` and ``bench/partition.py``, which measure
the same run. The control plane runs with a short node-monitor grace period and a short
eviction window (:func:`plane_settings`), so a cut longer than both takes under a minute
instead of the six a default cluster needs (50 s + 300 s).

The vehicle is :class:`~tests.support.realfleet.RealFleet`'s, with one component pod
(vicon, running the node's pause image: only its survival matters) and a Mission's
onboard pod beside the chart's agent. A bare pod without Roost's tolerations runs on
the same node as the witness that the eviction window really passed: the taint manager
evicts it during the cut.

What :func:`cut_and_restore` does, in order: marks every pod on the vehicle node (UID,
container restarts), takes the node's link down (its veth), waits for the Vehicle and
the Mission to report the node unreachable, silences the active autopilot so the agent
fails over with nobody to tell, waits until the witness is evicted and the cut has
lasted :data:`CUT_S`, brings the link back, and times how long until the
RedundantAutopilot's status shows that failover.
"""

from __future__ import annotations

import json
import subprocess
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import yaml

from roost_localcluster import binaries
from roost_localcluster.controlplane import Settings
from roost_sim.faults import FaultKind
from tests.support.realfleet import VEHICLE, WAIT_S, RealFleet
from tests.support.waiting import wait_until

GRACE_S = 20
"""The controller manager's node-monitor grace period (the kubelet renews its lease every
10 s, so a loaded machine still has 10 s of slack)."""
EVICTION_S = 5
"""The API server's default unreachable/not-ready toleration: the eviction window."""
MONITOR_PERIOD_S = 5
"""The controller manager's default ``--node-monitor-period``."""
CUT_S = GRACE_S + MONITOR_PERIOD_S + EVICTION_S + 15
"""How long the link stays down at least: past the grace period, the node controller's
next look and the eviction window, with a margin."""

MISSION = "partition-flight"
MISSION_NAMESPACE = "default"
WITNESS = "partition-witness"


def plane_settings() -> Settings:
    """The control plane's settings for a cut that outlasts the eviction window quickly."""
    return Settings(node_monitor_grace_period_s=GRACE_S, eviction_toleration_s=EVICTION_S)


def vicon_components() -> dict[str, Any]:
    """No mavros (no image on the node); vicon running the node's pause image."""
    return {
        "mavros": {"enabled": False},
        "vicon": {"enabled": True, "image": binaries.pause_image(binaries.node_dir())},
    }


TELEMETRY_VALUES = {"telemetry": {"enabled": True, "port": 9467, "bindNodeAddress": True}}
"""The agent's telemetry stream on the node's address: announced on its Vehicle, and
followed by ``roost dashboard`` through the API server's pod proxy."""


@dataclass(frozen=True)
class PodMark:
    """What must not change across the cut: the pod's identity and its restarts."""

    key: str
    uid: str
    restarts: int


@dataclass
class PartitionRun:
    """What one cut showed."""

    before: dict[str, PodMark]
    after: dict[str, PodMark]
    cut_at: datetime
    silenced_at: datetime
    restored_at: datetime
    cut_s: float
    catchup_s: float
    last_failover: dict[str, Any]
    vehicle_node_bound: dict[str, Any]
    """The Vehicle's NodeBound condition while the link was down."""
    mission_vehicle: dict[str, Any]
    """The Mission's entry of the vehicle while the link was down."""

    @property
    def pod_restarts(self) -> int:
        """Container restarts of the pods that were there before, across the cut."""
        return sum(
            max(0, self.after[k].restarts - m.restarts)
            for k, m in self.before.items()
            if k in self.after
        )

    @property
    def pods_replaced(self) -> int:
        """Pods that were there before and are gone or are another pod (another UID)."""
        return sum(
            1 for k, m in self.before.items() if k not in self.after or self.after[k].uid != m.uid
        )


def _json(fleet: RealFleet, *args: str) -> dict[str, Any]:
    found: dict[str, Any] = json.loads(fleet.cluster.kubectl(*args, "-o", "json").stdout)
    return found


def node_pods(fleet: RealFleet) -> list[dict[str, Any]]:
    """Every pod bound to the vehicle node, in any namespace."""
    field = f"spec.nodeName={fleet.vehicle.node}"
    items: list[dict[str, Any]] = _json(fleet, "get", "pods", "-A", "--field-selector", field)[
        "items"
    ]
    return items


def marks(fleet: RealFleet) -> dict[str, PodMark]:
    """Each pod on the vehicle node except the witness, by namespace/name."""
    found = {}
    for pod in node_pods(fleet):
        meta = pod["metadata"]
        if meta["name"] == WITNESS:
            continue
        key = f"{meta['namespace']}/{meta['name']}"
        restarts = sum(
            c.get("restartCount", 0) for c in pod.get("status", {}).get("containerStatuses", [])
        )
        found[key] = PodMark(key, meta["uid"], restarts)
    return found


def all_ready(fleet: RealFleet) -> bool:
    """Every pod on the vehicle node (the witness aside) runs and is Ready."""
    pods = [p for p in node_pods(fleet) if p["metadata"]["name"] != WITNESS]
    return bool(pods) and all(
        any(
            c.get("type") == "Ready" and c.get("status") == "True"
            for c in p.get("status", {}).get("conditions", [])
        )
        for p in pods
    )


def condition(obj: dict[str, Any], kind: str) -> dict[str, Any] | None:
    return next(
        (c for c in obj.get("status", {}).get("conditions", []) if c.get("type") == kind), None
    )


def node_bound(fleet: RealFleet) -> dict[str, Any]:
    return condition(fleet.get("vehicle", VEHICLE), "NodeBound") or {}


def mission_manifest() -> dict[str, Any]:
    """A Mission on the fleet's one vehicle whose onboard pod runs the pause image; a
    failover neither stops it (Continue) nor does a lost link (the default)."""
    pause = binaries.pause_image(binaries.node_dir())
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": MISSION, "namespace": MISSION_NAMESPACE},
        "spec": {
            "vehicles": {"names": [VEHICLE], "count": 1},
            "onFailover": "Continue",
            "onboard": {
                "spec": {
                    "containers": [
                        {"name": "controller", "image": pause, "imagePullPolicy": "Never"}
                    ]
                }
            },
        },
    }


def mission_vehicle(fleet: RealFleet) -> dict[str, Any]:
    status = _json(fleet, "get", "mission", MISSION, "-n", MISSION_NAMESPACE).get("status") or {}
    return next((v for v in status.get("vehicles") or [] if v.get("name") == VEHICLE), {})


def witness_manifest(fleet: RealFleet) -> dict[str, Any]:
    """A bare pod on the vehicle node with only the API server's default tolerations."""
    pause = binaries.pause_image(binaries.node_dir())
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {"name": WITNESS, "namespace": MISSION_NAMESPACE},
        "spec": {
            "nodeName": fleet.vehicle.node,
            "hostNetwork": True,
            "terminationGracePeriodSeconds": 1,
            "tolerations": [{"key": "roost.dev/vehicle", "operator": "Exists"}],
            "containers": [{"name": "main", "image": pause, "imagePullPolicy": "Never"}],
        },
    }


def witness_evicted(fleet: RealFleet) -> bool:
    found = fleet.cluster.kubectl(
        "get", "pod", WITNESS, "-n", MISSION_NAMESPACE, "-o", "json", check=False
    )
    if found.returncode != 0:
        return True  # gone altogether
    return bool(json.loads(found.stdout)["metadata"].get("deletionTimestamp"))


def start_workloads(fleet: RealFleet) -> None:
    """The Mission and the witness on the vehicle node, each running, the vehicle flying."""
    text = "\n---\n".join(yaml.safe_dump(m) for m in (mission_manifest(), witness_manifest(fleet)))
    fleet.cluster.kubectl("apply", "-f", "-", input_text=text)
    wait_until(
        "the mission's onboard pod running",
        lambda: mission_vehicle(fleet).get("reason") == "PodRunning",
        WAIT_S,
    )
    wait_until("every pod on the vehicle node Ready", lambda: all_ready(fleet), WAIT_S)
    wait_until(
        "the witness running",
        lambda: any(
            p["metadata"]["name"] == WITNESS and p.get("status", {}).get("phase") == "Running"
            for p in node_pods(fleet)
        ),
        WAIT_S,
    )
    fleet.fly()
    wait_until(
        "the vehicle airborne",
        lambda: all(a.get("armed") for a in fleet.autopilot_status().get("autopilots", [])),
        WAIT_S,
    )


def stop_workloads(fleet: RealFleet) -> None:
    fleet.cluster.kubectl(
        "delete", "mission", MISSION, "-n", MISSION_NAMESPACE, "--ignore-not-found",
        "--timeout=60s", check=False,
    )  # fmt: skip
    fleet.cluster.kubectl(
        "delete", "pod", WITNESS, "-n", MISSION_NAMESPACE, "--ignore-not-found",
        "--grace-period=0", "--force", check=False,
    )  # fmt: skip


def pod_containers(fleet: RealFleet, pod: str) -> list[str]:
    """IDs of the containers (sandbox included) the vehicle node's containerd holds for
    the pod named ``pod``."""
    assert fleet.vehicle_node is not None
    done = subprocess.run(
        fleet.vehicle_node.ctr(
            "containers", "list", "--quiet", f'labels."io.kubernetes.pod.name"=={pod}'
        ),
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.split()


def _utc_now() -> datetime:
    return datetime.now(UTC)


def cut_and_restore(fleet: RealFleet, silence: str = "px4-a") -> PartitionRun:
    """One WiFi drop with a failover inside it; see the module docstring."""
    assert fleet.vehicle_node is not None
    node = fleet.vehicle_node.name
    before = marks(fleet)
    started = time.monotonic()
    cut_at = _utc_now()
    fleet.pool.set_link(node, up=False)
    try:
        bound = wait_until(
            "the Vehicle's NodeBound to say NodeUnreachable",
            lambda: (c := node_bound(fleet)).get("reason") == "NodeUnreachable" and c,
            GRACE_S + WAIT_S,
        )
        entry = wait_until(
            "the Mission to show the vehicle unreachable",
            lambda: (v := mission_vehicle(fleet)).get("reason") == "VehicleUnreachable" and v,
            WAIT_S,
        )
        silenced_at = _utc_now()
        answer = fleet.control(
            silence, {"op": "fault", "kind": FaultKind.SILENCE.value, "value": None}
        )
        assert answer.get("ok"), answer
        wait_until("the witness evicted", lambda: witness_evicted(fleet), WAIT_S)
        wait_until(f"the cut to last {CUT_S} s", lambda: time.monotonic() - started >= CUT_S, CUT_S)
    finally:
        restored = time.monotonic()
        restored_at = _utc_now()
        fleet.pool.set_link(node, up=True)
    last = wait_until(
        "the failover made during the cut in the status",
        lambda: (
            (status := fleet.autopilot_status()).get("activeAutopilot") != silence
            and status.get("lastFailover")
        ),
        WAIT_S,
        poll_s=0.05,
    )
    catchup_s = time.monotonic() - restored
    wait_until(
        "the Vehicle's node bound again", lambda: node_bound(fleet).get("status") == "True", WAIT_S
    )
    wait_until("every pod on the vehicle node Ready again", lambda: all_ready(fleet), WAIT_S)
    return PartitionRun(
        before=before,
        after=marks(fleet),
        cut_at=cut_at,
        silenced_at=silenced_at,
        restored_at=restored_at,
        cut_s=restored - started,
        catchup_s=catchup_s,
        last_failover=dict(last),
        vehicle_node_bound=dict(bound),
        mission_vehicle=dict(entry),
    )
