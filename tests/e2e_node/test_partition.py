"""A vehicle's WiFi drop and its bad cases, on real harness nodes with the chart's real pods.

The agent serves its telemetry stream on the node's address and announces it on its
Vehicle; ``roost dashboard`` follows the vehicle through the API server's pod proxy.

The control plane here is this module's own, started with a 20 s node-monitor grace
period and a 5 s eviction window (:mod:`tests.support.partition`), so a cut longer than
both (and the node controller's next look) takes 30 s. The vehicle node runs the chart's
agent, a component pod the operator made (vicon), a Mission's onboard pod, and a bare
witness pod that has only the API server's default tolerations.

* A cut longer than the grace period plus the eviction window, with a failover inside
  it: the witness is evicted (the window passed), nothing of Roost's is — zero container
  restarts, the same pod UIDs; the Vehicle says NodeUnreachable since when, the Mission
  shows the vehicle unreachable and keeps flying; once the link is back the status shows
  the failover with the time it happened, within seconds.
* A reboot of the vehicle's computer mid-routine (every process killed at once,
  containerd's and runc's runtime state gone, then containerd and the kubelet started
  again): the same agent pod comes back and resumes the safety routine from its state
  directory, without switching back; three power cuts in a row end the same way, with
  one sandbox and one container running per pod.
* A node that never comes back and whose Vehicle is deleted meanwhile: the Vehicle's
  pods are removed at once (they would otherwise wait for a kubelet that never answers),
  its node keeps no Roost label; when the link does return, the kubelet stops what the
  API server no longer has: nothing is left on the node.

About three minutes with the images cached (a cut of 30 s and one of about 20 s with
the kubelet's reconnection after it, four boots, the fleet's start).
The tests run in file order on one fleet.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from websockets.exceptions import WebSocketException
from websockets.sync.client import connect

from roost_api.ports import free_port
from roost_api.wellknown import ANNOTATION_TELEMETRY_POD, LABEL_VEHICLE
from roost_localcluster.nodenet import missing_prerequisites
from tests.support import partition
from tests.support.images import missing_tools
from tests.support.realfleet import VEHICLE, WAIT_S, RealFleet
from tests.support.waiting import wait_until

BIN = Path(sys.executable).parent

# serial: the vehicle flies its simulated autopilots in real time against a 200 ms silence
# limit through a 120 s hold; beside the other worker's qemu-emulated image runs at a load
# of 18-21, the standby it had failed over to went silent too and the agent landed,
# cancelling the hold that the reboot must resume. `make e2e` runs this after the rest,
# beside at most one other serial file (Makefile, E2E_SERIAL).
pytestmark = [
    pytest.mark.slow,
    pytest.mark.serial,
    pytest.mark.timeout(1800),  # builds the images first when they are not cached
    pytest.mark.skipif(
        bool(missing_prerequisites() or missing_tools()),
        reason="real nodes or image tools missing: "
        + "; ".join(missing_prerequisites() + missing_tools()),
    ),
]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealFleet]:
    with partition.flying_fleet(tmp_path_factory.mktemp("partition")) as running:
        yield running


@pytest.fixture(scope="module")
def cut(fleet: RealFleet) -> partition.PartitionRun:
    return partition.cut_and_restore(fleet)


def test_the_agent_announces_its_stream_and_the_dashboard_follows_it_via_the_api(
    fleet: RealFleet, tmp_path: Path
) -> None:
    """Runs before the cut. The agent annotated its Vehicle itself; ``roost dashboard``
    with the admin kubeconfig reads the stream through the API server's pod proxy (the
    agent pod's name is in the annotation) and shows the vehicle live."""
    agent = fleet.agent_pod()
    assert agent is not None
    annotations = fleet.get("vehicle", VEHICLE)["metadata"].get("annotations", {})
    assert annotations.get(ANNOTATION_TELEMETRY_POD) == (
        f"{fleet.namespace}/{agent['metadata']['name']}:9467"
    )
    port = free_port()
    log = tmp_path / "dashboard.log"
    argv = [str(BIN / "roost"), "--kubeconfig", str(fleet.cluster.kubeconfig), "dashboard"]
    argv += ["--read-only", "--port", str(port)]
    with log.open("w") as out:
        dashboard = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
    try:
        vehicle = wait_until(
            "the dashboard showing the vehicle's live telemetry",
            lambda: _live(port, VEHICLE),
            WAIT_S,
            poll_s=1.0,
        )
        assert vehicle["active"] == "px4-a"
    finally:
        dashboard.terminate()
        dashboard.wait(timeout=30)
    assert "Traceback" not in log.read_text(), log.read_text()[-3000:]


def _live(port: int, name: str) -> dict[str, Any] | None:
    """The dashboard's fleet document entry of ``name`` once its telemetry is live."""
    try:
        with connect(f"ws://127.0.0.1:{port}/ws", open_timeout=2) as ws:
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                doc = json.loads(ws.recv(timeout=5))
                entry = next((v for v in doc.get("vehicles", []) if v.get("name") == name), None)
                if entry is not None and entry.get("telemetry") == "live":
                    return dict(entry)
    except (OSError, TimeoutError, WebSocketException):
        return None
    return None


def _at(stamp: str) -> datetime:
    return datetime.fromisoformat(stamp.replace("Z", "+00:00"))


def test_the_cut_outlasted_the_eviction_window(cut: partition.PartitionRun) -> None:
    assert cut.cut_s >= partition.CUT_S
    assert cut.cut_s > partition.GRACE_S + partition.EVICTION_S


def test_nothing_of_roost_is_evicted_restarted_or_replaced(
    fleet: RealFleet, cut: partition.PartitionRun
) -> None:
    keys = set(cut.before)
    assert any(k.startswith(f"{fleet.namespace}/{VEHICLE}-vicon") for k in keys), keys
    assert any(k.startswith(f"{partition.MISSION_NAMESPACE}/{partition.MISSION}") for k in keys)
    assert any("roost-agent" in k for k in keys), keys
    assert cut.pods_replaced == 0, (cut.before, cut.after)
    assert cut.pod_restarts == 0, (cut.before, cut.after)


def test_the_vehicle_said_since_when_its_node_was_unreachable(
    cut: partition.PartitionRun,
) -> None:
    bound = cut.vehicle_node_bound
    assert (bound["status"], bound["reason"]) == ("False", "NodeUnreachable")
    since = _at(bound["lastTransitionTime"])
    # The node controller notices within its grace period (and its next look).
    assert cut.cut_at - timedelta(seconds=1) <= since <= cut.restored_at
    assert "unreachable since" in bound["message"]


def test_the_mission_showed_the_vehicle_unreachable_and_flew_on(
    fleet: RealFleet, cut: partition.PartitionRun
) -> None:
    entry = cut.mission_vehicle
    assert entry["phase"] == "Running" and entry["unreachableSince"]
    mission = json.loads(
        fleet.cluster.kubectl(
            "get", "mission", partition.MISSION, "-n", partition.MISSION_NAMESPACE, "-o", "json"
        ).stdout
    )
    assert mission["status"]["phase"] == "Running"
    # The Mission's own view catches up with the Vehicle's on its next reconcile.
    wait_until(
        "the Mission's vehicle reachable again",
        lambda: not partition.mission_vehicle(fleet).get("unreachableSince"),
        WAIT_S,
    )


def test_the_failover_in_the_cut_is_recorded_with_its_true_time(
    cut: partition.PartitionRun,
) -> None:
    last = cut.last_failover
    assert (last["from"], last["to"]) == ("px4-a", "px4-b")
    happened = _at(last["time"])
    # Made by the agent during the cut (whole seconds in the API), not when reported.
    assert cut.silenced_at - timedelta(seconds=1) <= happened <= cut.restored_at
    assert cut.catchup_s > 0


@pytest.fixture(scope="module")
def reboot(fleet: RealFleet, cut: partition.PartitionRun) -> partition.RebootRun:
    # The Mission's onboard pod is a Job's (restartPolicy Never): a reboot ends it and
    # the Job controller starts another (one of its attempts). It has made its point.
    partition.stop_workloads(fleet)
    return partition.power_cycle(fleet)


def test_a_reboot_mid_routine_resumes_from_the_state_directory(
    reboot: partition.RebootRun,
) -> None:
    """The safety routine of the failover in the cut (a 120 s hold) still ran when the
    power went; the agent pod came back (same pod, new containers) and resumed it from
    its state directory, on the autopilot it had switched to."""
    assert reboot.routine_before in ("Started", "ConfirmingHold", "Holding"), reboot
    assert reboot.agent_after.uid == reboot.agent_before.uid
    assert (reboot.active_before, reboot.active_after) == ("px4-b", "px4-b"), "no switch back"
    resumed = [m for m in reboot.resumed if m.startswith("px4-b: resuming the safety routine")]
    assert resumed, reboot.log_tail
    assert reboot.restart_to_report_s > 0


def test_a_reboot_loop_ends_with_the_same_pods_reporting_and_nothing_left(
    fleet: RealFleet, reboot: partition.RebootRun
) -> None:
    """Three power cuts in a row, each before the node came up: in the end the same pods
    run their containers once each, and the agent reports, still on px4-b."""
    assert fleet.vehicle_node is not None
    node = fleet.vehicle_node.name
    before = partition.marks(fleet)
    for _ in range(3):
        fleet.pool.power_off(node)
        fleet.pool.power_on(node, wait_ready=False)
    booted_at = datetime.now(UTC)
    status = wait_until(
        "the agent's first report after the last boot",
        lambda: partition.reported_since(fleet, booted_at),
        WAIT_S,
    )
    assert status["activeAutopilot"] == "px4-b"
    wait_until("every pod on the vehicle node Ready", lambda: partition.all_ready(fleet), WAIT_S)
    after = partition.marks(fleet)
    assert {k: m.uid for k, m in after.items()} == {k: m.uid for k, m in before.items()}
    for key in after:
        name = key.split("/", 1)[1]
        assert partition.running_tasks(fleet, name) == 2, f"{key}: one sandbox, one container"
    bound = partition.node_bound(fleet)
    assert bound.get("status") == "True", bound


def test_a_vehicle_deleted_while_its_node_never_returns_leaves_nothing(
    fleet: RealFleet, cut: partition.PartitionRun
) -> None:
    assert fleet.vehicle_node is not None
    node = fleet.vehicle_node.name
    partition.stop_workloads(fleet)  # the mission first: its pods are the Job controller's
    vicon = f"{VEHICLE}-vicon"
    fleet.pool.set_link(node, up=False)
    try:
        wait_until(
            "the Vehicle's NodeBound to say NodeUnreachable",
            lambda: partition.node_bound(fleet).get("reason") == "NodeUnreachable",
            partition.GRACE_S + WAIT_S,
        )
        fleet.cluster.kubectl("delete", "redundantautopilot,vehicle", VEHICLE, "--wait=false")

        def pod_gone() -> bool:
            found = fleet.cluster.kubectl(
                "get", "pod", vicon, "-n", fleet.namespace, "--ignore-not-found", "-o", "name"
            )
            return not found.stdout.strip()

        wait_until("the vicon pod removed without its kubelet", pod_gone, WAIT_S)
        wait_until(
            "the Vehicle gone",
            lambda: (
                not fleet.cluster.kubectl(
                    "get", "vehicle", VEHICLE, "--ignore-not-found", "-o", "name"
                ).stdout.strip()
            ),
            WAIT_S,
        )
        labels = fleet.get("node", node)["metadata"].get("labels", {})
        assert LABEL_VEHICLE not in labels
    finally:
        fleet.pool.set_link(node, up=True)
    wait_until(
        "the kubelet back to stop the removed pod's containers",
        lambda: not partition.pod_containers(fleet, vicon),
        WAIT_S,
    )
