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
lasted ``cut_s`` (:data:`CUT_S` in the test, :data:`BENCH_CUT_S` in the benchmark),
brings the link back, and times how long until the RedundantAutopilot's status shows
that failover.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from roost_localcluster.realnode import RealNodes
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
CUT_S = GRACE_S + MONITOR_PERIOD_S + EVICTION_S
"""How long the link stays down at least: past the grace period, the node controller's
next look and the eviction window, by when the taint manager has evicted every pod that
tolerates the taint for the default window; the cut also lasts until the witness is
evicted (the proof that it did). Roost's pods tolerate the taint with no
``tolerationSeconds``: the taint manager sets them no timer, so a longer cut would
show nothing more about them."""
BENCH_CUT_S = CUT_S + 15
"""The benchmark's cut (bench/partition.py): 15 s more, as its recorded figures were
measured (the agent's API retries back off further in a longer cut)."""

HOLD_S = 120
"""The safety routine's hold after the failover in the cut (the API's maximum): it still
runs when the node reboots after the cut."""

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


def long_hold(fleet: RealFleet) -> None:
    """Make the safety routine after a failover hold for :data:`HOLD_S` (still running
    when the node reboots after the cut); returns once the agent applied it."""
    patch = {"spec": {"failoverPolicy": {"safetyRoutine": {"holdSeconds": HOLD_S}}}}
    fleet.cluster.kubectl(
        "patch", "redundantautopilot", VEHICLE, "--type=merge", "-p", json.dumps(patch)
    )

    def applied() -> bool:
        found = fleet.get("redundantautopilot", VEHICLE)
        observed = (found.get("status") or {}).get("observedGeneration")
        return bool(observed == found["metadata"]["generation"])

    wait_until("the agent to apply the long hold", applied, WAIT_S)


def start_workloads(fleet: RealFleet) -> None:
    """The Mission and the witness on the vehicle node, each running, the vehicle flying
    with a long hold after a failover."""
    long_hold(fleet)
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


@contextlib.contextmanager
def flying_fleet(directory: Path) -> Iterator[RealFleet]:
    """The whole setup under ``directory``: a control plane with :func:`plane_settings`,
    real nodes, :class:`RealFleet` with vicon and the telemetry stream, the Mission and
    the witness (:func:`start_workloads`); all stopped again on leaving."""
    with (
        ControlPlane(directory / "control-plane", settings=plane_settings()) as plane,
        RealNodes(Cluster.of(plane), directory / "nodes") as pool,
    ):
        fleet = RealFleet(
            Cluster.of(plane),
            pool,
            directory / "fleet",
            components=vicon_components(),
            agent_values=TELEMETRY_VALUES,
        )
        try:
            fleet.start()
            start_workloads(fleet)
            yield fleet
        finally:
            stop_workloads(fleet)
            fleet.stop()


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


def cut_and_restore(
    fleet: RealFleet, silence: str = "px4-a", *, cut_s: float = CUT_S
) -> PartitionRun:
    """One WiFi drop of at least ``cut_s`` with a failover inside it; see the module
    docstring."""
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
        wait_until(
            f"the cut to last {cut_s:g} s", lambda: time.monotonic() - started >= cut_s, cut_s
        )
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


# -- reboots ---------------------------------------------------------------------------------


@dataclass
class RebootRun:
    """What one power cycle of the vehicle's computer showed."""

    agent_before: PodMark
    agent_after: PodMark
    active_before: str
    active_after: str
    routine_before: str
    """The safety routine's phase when the power went (lastFailover.safetyRoutine)."""
    booted_at: datetime
    restart_to_report_s: float
    """From starting containerd and the kubelet again to the agent's first report."""
    resumed: list[str]
    """The agent's SafetyRoutineResumed messages after the boot."""
    log_tail: str = ""
    """The end of the agent's log after the boot (for a failing check to show)."""


def _agent_mark(fleet: RealFleet) -> PodMark:
    pod = fleet.agent_pod()
    assert pod is not None
    return next(m for m in marks(fleet).values() if m.uid == pod["metadata"]["uid"])


def reported_since(fleet: RealFleet, since: datetime) -> dict[str, Any] | None:
    """The RedundantAutopilot status once the agent reported at or after ``since`` (the
    API keeps whole seconds)."""
    status = fleet.autopilot_status()
    stamp = status.get("reportedAt")
    if stamp and datetime.fromisoformat(stamp.replace("Z", "+00:00")) >= since.replace(
        microsecond=0
    ):
        return status
    return None


def agent_log(fleet: RealFleet) -> str:
    """The agent's current container's log (``kubectl logs``), or kubectl's complaint."""
    pod = fleet.agent_pod()
    if pod is None:
        return "no agent pod"
    done = fleet.cluster.kubectl(
        "logs", pod["metadata"]["name"], "-n", fleet.namespace, check=False
    )
    return done.stdout if done.returncode == 0 else done.stderr


def resumed_in_log(fleet: RealFleet) -> list[str]:
    """The agent's ``SafetyRoutineResumed`` lines in its current container's log (the
    container the boot started)."""
    return [
        line.split("SafetyRoutineResumed: ", 1)[1]
        for line in agent_log(fleet).splitlines()
        if "SafetyRoutineResumed: " in line
    ]


def power_cycle(fleet: RealFleet, *, down_s: float = 2.0) -> RebootRun:
    """The vehicle's computer loses power for ``down_s`` and boots again (kubelet and
    containerd started anew, every container gone); timed to the agent's first report."""
    assert fleet.vehicle_node is not None
    node = fleet.vehicle_node.name
    before = fleet.autopilot_status()
    agent_before = _agent_mark(fleet)
    routine = str((before.get("lastFailover") or {}).get("safetyRoutine") or "")
    fleet.pool.power_off(node)
    time.sleep(down_s)  # the computer stays off a moment (not a limit on anything)
    booted_at = _utc_now()
    started = time.monotonic()
    fleet.pool.power_on(node)
    after = wait_until(
        "the agent's first report after the boot",
        lambda: reported_since(fleet, booted_at),
        WAIT_S,
        poll_s=0.05,
    )
    restart_to_report_s = time.monotonic() - started
    wait_until("every pod on the vehicle node Ready again", lambda: all_ready(fleet), WAIT_S)
    try:
        resumed = wait_until(
            "the agent's SafetyRoutineResumed in its new container's log",
            lambda: resumed_in_log(fleet),
            30.0,
        )
    except TimeoutError:
        resumed = []  # the caller says what it expected, with the log below
    return RebootRun(
        agent_before=agent_before,
        agent_after=_agent_mark(fleet),
        active_before=str(before.get("activeAutopilot")),
        active_after=str(after.get("activeAutopilot")),
        routine_before=routine,
        booted_at=booted_at,
        restart_to_report_s=restart_to_report_s,
        resumed=resumed,
        log_tail=agent_log(fleet)[-4000:],
    )


def running_tasks(fleet: RealFleet, pod: str) -> int:
    """How many of the pod's containers (sandbox included) have a running process."""
    assert fleet.vehicle_node is not None
    done = subprocess.run(
        fleet.vehicle_node.ctr("tasks", "list"), capture_output=True, text=True, check=True
    )
    running = {
        line.split()[0] for line in done.stdout.splitlines()[1:] if line.split()[-1:] == ["RUNNING"]
    }
    return len(running & set(pod_containers(fleet, pod)))
