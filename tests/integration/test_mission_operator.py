"""Missions on the real control plane, with ``roost-operator`` running as a process.

kube-apiserver and etcd store the objects (CRD validation and CEL included), the
controller manager runs the Jobs, the scheduler places their pods on the fake vehicle
nodes and kwok plays the kubelets. The vehicle half of the operator labels and taints
the nodes and writes each vehicle's config, exactly as in production.

Two stand-ins, both because the real part is not wired up here yet:

* **The node agent.** :class:`~tests.support.fakeagents.FakeAgents` writes each
  RedundantAutopilot's status the way the agent does (conditions
  ActiveHealthy/Redundant/FailedOver/Ready, per-autopilot health with landed state and
  armed flag, lastFailover, reportedAt, nodeName) and executes commands from
  ``spec.command`` as the agent would (the safety routine ends on the ground and
  disarmed, an e-stop disarms; the result goes to ``status.lastCommand``).
  Agent-driven end-to-end tests with simulated autopilots come separately.
  The operator's autopilot handlers turn these reports into the Vehicle's
  ``AgentConnected`` and ``AutopilotsHealthy``, as they would for the real agent.

Workload timing: kwok v0.7's default "fast" pod stages complete every pod owned by a Job
the moment it runs (stage ``pod-complete``: phase Running + ownerReference kind Job →
Succeeded). To hold a mission in Running, the onboard template carries a scheduling gate
(``schedulingGates``); a gated pod stays Pending and unscheduled, so its Job stays
active. A test lets the workloads finish by removing the gates (as a scheduler plugin
would); kwok then runs and completes the pods. A failed pod is produced by writing the
pod's status phase Failed, which is what a kubelet reports for a failed container.

The cluster is shared by the session: every test uses unique names and its own vehicle
label, and removes its Missions before its Vehicles (their finalizers need the
operator).
"""

from __future__ import annotations

import json
import subprocess
import threading
from collections.abc import Iterator
from datetime import UTC, datetime

import pytest

from roost_api.wellknown import ANNOTATION_PAUSE_FAILOVER_ACTIONS, LABEL_MISSION, LABEL_VEHICLE
from roost_kube.client import Kube
from roost_kube.errors import ConflictError
from roost_kube.patches import Obj
from roost_kube.resources import (
    CONFIGMAPS,
    JOBS,
    LEASES,
    MISSIONS,
    PODS,
    REDUNDANT_AUTOPILOTS,
    VEHICLES,
)
from roost_localcluster.cluster import Cluster
from roost_operator.claims import claim_of, lease_name, release_options
from roost_operator.missions.cluster import claim_vehicle, release_vehicle
from roost_operator.missions.observed import MissionRef, VehicleView
from roost_operator.missions.workloads import (
    ENV_MISSION_VEHICLES,
    bounded_name,
    onboard_job_name,
)
from tests.support.fakeagents import FakeAgents
from tests.support.missionfleet import (
    FLIGHTS,
    WAIT_S,
    AddNode,
    Fleet,
    mission_manifest,
    mission_status,
    pods_of,
    release_holds,
    vehicle_condition,
    wait_phase,
)
from tests.support.operator import OperatorProcess
from tests.support.waiting import unique, wait_until

pytestmark = pytest.mark.cluster

OPERATOR_NAMESPACE = "roost-it-missions"


# -- fixtures ------------------------------------------------------------------------------


@pytest.fixture(scope="module", autouse=True)
def flights_namespace(roost_crds: Cluster) -> None:
    """The namespace the module's Missions live in (the operator's own is another)."""
    roost_crds.kubectl("create", "namespace", FLIGHTS, check=False)


@pytest.fixture
def agents(roost_crds: Cluster) -> Iterator[FakeAgents]:
    with FakeAgents(roost_crds) as running:
        yield running


@pytest.fixture
def fleet(
    roost_crds: Cluster,
    operator: OperatorProcess,
    kube: Kube,
    agents: FakeAgents,
    fake_nodes: AddNode,
) -> Iterator[Fleet]:
    created = Fleet(roost_crds, kube, agents, fake_nodes)
    yield created
    if not operator.process.alive():
        operator.start()
    created.cleanup()


# -- manifests and reads -------------------------------------------------------------------


def condition_of(status: Obj, type_: str) -> Obj | None:
    return next((c for c in status.get("conditions") or [] if c["type"] == type_), None)


def jobs_of(kube: Kube, mission: str) -> dict[str, Obj]:
    return {
        j["metadata"]["name"]: j
        for j in kube.list_objects(
            JOBS, namespace=FLIGHTS, labels={LABEL_MISSION: bounded_name(mission)}
        )
        if not j["metadata"].get("deletionTimestamp")
    }


def claimed_by(kube: Kube, vehicle: str) -> str | None:
    """``namespace/name`` of the Mission whose claim Lease holds ``vehicle``, if any."""
    claim = claim_of(kube.get(LEASES, lease_name(vehicle), OPERATOR_NAMESPACE) or {})
    return claim.holder_key if claim else None


def command_of(kube: Kube, vehicle: str) -> Obj | None:
    """The command on the vehicle's RedundantAutopilot (spec.command), if any."""
    body = kube.get(REDUNDANT_AUTOPILOTS, vehicle) or {}
    command: Obj | None = (body.get("spec") or {}).get("command")
    return command


def assigned(status: Obj) -> list[str]:
    return [v["name"] for v in status.get("vehicles") or []]


def events_for(cluster: Cluster, mission: str) -> list[str]:
    out = cluster.kubectl(
        "get",
        "events",
        "-n",
        FLIGHTS,
        "--field-selector",
        f"involvedObject.name={mission}",
        "-o",
        "jsonpath={range .items[*]}{.reason}{'\\n'}{end}",
    ).stdout
    return out.split()


# -- tests ---------------------------------------------------------------------------------


def test_three_vehicles_fly_to_succeeded_with_an_offboard_monitor(
    fleet: Fleet, kube: Kube, fake_nodes: AddNode, roost_crds: Cluster
) -> None:
    ground = unique("ground")
    fake_nodes(ground)
    vehicles = fleet.add(3)
    name = fleet.mission(
        unique("happy"), selector={"fleet": fleet.label}, count=3, hold=False, offboard=True
    )
    # the offboard monitor's Job ends with the Mission: its pod is seen, placed, while it runs
    (monitor,) = wait_until(
        "the offboard monitor's pod on a node",
        lambda: [
            p
            for p in pods_of(kube, name)
            if not p["metadata"]["labels"].get(LABEL_VEHICLE) and p["spec"].get("nodeName")
        ],
    )

    status = wait_phase(kube, name, "Succeeded")
    assert sorted(assigned(status)) == sorted(vehicles)
    assert all(v["phase"] == "Succeeded" for v in status["vehicles"])
    assert status["assignedCount"] == 3
    assert condition_of(status, "Complete")["status"] == "True"  # type: ignore[index]

    pods = pods_of(kube, name)
    onboard = {p["spec"]["nodeName"]: p for p in pods if p["metadata"]["labels"].get(LABEL_VEHICLE)}
    assert set(onboard) == {f"{v}-node" for v in vehicles}, "one onboard pod on each vehicle"
    pod = next(iter(onboard.values()))
    container = pod["spec"]["containers"][0]
    env = {e["name"]: e for e in container["env"]}
    assert env[ENV_MISSION_VEHICLES]["value"] == ",".join(assigned(status))
    assert "configMapKeyRef" in env["VEHICLE_NAME"]["valueFrom"]
    assert {m["mountPath"] for m in container["volumeMounts"]} >= {"/etc/roost", "/etc/starling"}
    assert monitor["spec"]["nodeName"] not in {f"{v}-node" for v in vehicles}

    wait_until(
        "vehicles released", lambda: all(claimed_by(kube, v) is None for v in vehicles), WAIT_S
    )
    columns = roost_crds.kubectl("get", "missions", name, "-n", FLIGHTS).stdout
    assert "Succeeded" in columns and "3" in columns
    reasons = events_for(roost_crds, name)
    assert "Started" in reasons and "Completed" in reasons


def test_a_mission_waits_for_vehicles_and_starts_when_they_are_freed(
    fleet: Fleet, kube: Kube
) -> None:
    vehicles = fleet.add(2)
    first = fleet.mission(unique("first"), names=vehicles[:1], count=1)
    wait_phase(kube, first, "Running")
    second = fleet.mission(unique("second"), selector={"fleet": fleet.label}, count=2)

    status = wait_phase(kube, second, "Pending")
    wait_until(
        "the shortage message",
        lambda: "1 missing" in (mission_status(kube, second).get("message") or ""),
        WAIT_S,
    )
    status = mission_status(kube, second)
    assert status["reason"] == "InsufficientVehicles"
    assert f"{FLIGHTS}/{first}" in status["message"]
    assert claimed_by(kube, vehicles[1]) is None, "a waiting mission holds no partial set"

    release_holds(kube, first)
    wait_phase(kube, first, "Succeeded")
    status = wait_phase(kube, second, "Running")
    assert sorted(assigned(status)) == sorted(vehicles)


def test_preflight_holds_the_mission_until_the_autopilot_is_healthy(
    fleet: Fleet, kube: Kube, agents: FakeAgents
) -> None:
    good, bad = fleet.add(2)
    agents.set(bad, healthy=False)
    # The unhealthy report must have reached the Vehicle (agent connected, autopilots
    # unhealthy) before the mission looks, or preflight may name an earlier state.
    wait_until(
        "the unhealthy report on the Vehicle",
        lambda: (
            vehicle_condition(kube, bad, "AgentConnected") == "True"
            and vehicle_condition(kube, bad, "AutopilotsHealthy") == "False"
        ),
        WAIT_S,
    )
    name = fleet.mission(unique("preflight"), selector={"fleet": fleet.label}, count=2)

    status = wait_phase(kube, name, "Preflight")
    by_name = {v["name"]: v for v in status["vehicles"]}
    assert by_name[bad]["phase"] == "Preflight"
    assert by_name[bad]["reason"] == "ActiveAutopilotUnhealthy"
    assert by_name[good]["phase"] == "Claimed"
    assert condition_of(status, "PreflightPassed")["status"] == "False"  # type: ignore[index]
    assert jobs_of(kube, name) == {}, "nothing starts before every vehicle passes"

    agents.set(bad, healthy=True)
    wait_phase(kube, name, "Running")
    wait_until("both Jobs", lambda: len(jobs_of(kube, name)) == 2, WAIT_S)


def test_a_fence_every_autopilot_must_hold_before_the_start_and_lose_after(
    fleet: Fleet, kube: Kube, agents: FakeAgents, roost_crds: Cluster
) -> None:
    (drone,) = fleet.add(1, fence_refused=("fc2",))
    fence = {
        "circle": {"latitude": 47.3977, "longitude": 8.5456, "radiusM": 80},
        "maxAltitudeM": 30,
    }
    name = fleet.mission(unique("fenced"), names=[drone], count=1, fence=fence)

    wait_phase(kube, name, "Preflight")
    # the phase and the fence are separate writes: under load the phase may show first
    written = wait_until(
        "the fence in the RedundantAutopilot",
        lambda: (kube.get(REDUNDANT_AUTOPILOTS, drone) or {})["spec"].get("fence"),
        WAIT_S,
    )
    assert written["mission"] == f"{FLIGHTS}/{name}"
    assert written["fence"]["maxAltitudeM"] == 30
    wait_until(
        "preflight names fc2",
        lambda: (
            "fc2: UploadRefused" in (mission_status(kube, name)["vehicles"][0].get("message") or "")
        ),
        WAIT_S,
    )
    status = mission_status(kube, name)
    assert status["vehicles"][0]["reason"] == "FenceNotHeld"
    assert "fc1" not in status["vehicles"][0]["message"].split("autopilot: ", 1)[1]
    assert jobs_of(kube, name) == {}, "a vehicle without the fence on every autopilot stays"

    agents.set(drone, fence_refused=())
    wait_phase(kube, name, "Running")
    roost_crds.kubectl("delete", "mission", name, "-n", FLIGHTS)
    assert (kube.get(REDUNDANT_AUTOPILOTS, drone) or {})["spec"].get("fence") is None


@pytest.mark.parametrize("action", ["SafetyRoutine", "EmergencyStop"])
def test_abort_lands_every_vehicle_and_stops_the_workloads(
    fleet: Fleet, kube: Kube, agents: FakeAgents, roost_crds: Cluster, action: str
) -> None:
    vehicles = fleet.add(2, execute_commands=False)
    name = fleet.mission(
        unique("abort"), selector={"fleet": fleet.label}, count=2, abortAction=action
    )
    wait_phase(kube, name, "Running")
    wait_until("both Jobs", lambda: len(jobs_of(kube, name)) == 2, WAIT_S)

    roost_crds.kubectl(
        "patch", "mission", name, "-n", FLIGHTS, "--type=merge", "-p", '{"spec":{"abort":true}}'
    )
    status = wait_phase(kube, name, "Aborting")
    assert status["reason"] == "AbortRequested"

    def all_commanded() -> list[Obj] | None:
        found = [command_of(kube, v) for v in vehicles]
        return [c for c in found if c is not None] if all(found) else None

    commands = wait_until("commands on every vehicle", all_commanded, WAIT_S)
    assert {c["action"] for c in commands} == {action}
    assert len({c["id"] for c in commands}) == 2
    wait_until("the Jobs to be stopped", lambda: jobs_of(kube, name) == {}, WAIT_S)
    assert mission_status(kube, name)["phase"] == "Aborting", "not Aborted before they land"
    assert all(claimed_by(kube, v) == f"{FLIGHTS}/{name}" for v in vehicles)

    for vehicle in vehicles:
        agents.set(vehicle, execute_commands=True)
    status = wait_phase(kube, name, "Aborted")
    assert {v["reason"] for v in status["vehicles"]} == {
        "Disarmed" if action == "EmergencyStop" else "Landed"
    }
    for vehicle in vehicles:
        body = kube.get(REDUNDANT_AUTOPILOTS, vehicle) or {}
        assert body["status"]["lastCommand"]["result"] == "Executed"
    wait_until(
        "vehicles released", lambda: all(claimed_by(kube, v) is None for v in vehicles), WAIT_S
    )
    assert jobs_of(kube, name) == {}, "nothing is started after an abort"
    with pytest.raises(subprocess.CalledProcessError) as undo:
        roost_crds.kubectl(
            "patch",
            "mission",
            name,
            "-n",
            FLIGHTS,
            "--type=merge",
            "-p",
            '{"spec":{"abort":false}}',
        )
    assert "abort cannot be undone" in undo.value.stderr


@pytest.mark.parametrize("policy", ["Continue", "AbortVehicle", "AbortMission"])
def test_a_failover_mid_mission_follows_the_policy(
    fleet: Fleet, kube: Kube, agents: FakeAgents, policy: str
) -> None:
    fleet.add(2)
    name = fleet.mission(
        unique("failover"), selector={"fleet": fleet.label}, count=2, onFailover=policy
    )
    status = wait_phase(kube, name, "Running")
    hit, other = assigned(status)

    agents.fail_over(hit)

    if policy == "AbortMission":
        status = wait_phase(kube, name, "Aborted")
        assert status["reason"] == "VehicleFailedOver"
        assert all(v["phase"] == "Aborted" for v in status["vehicles"])
        return
    degraded = wait_until(
        "Degraded=True",
        lambda: (
            (c := condition_of(mission_status(kube, name), "Degraded")) and c["status"] == "True"
        ),
        WAIT_S,
    )
    assert degraded
    if policy == "AbortVehicle":
        wait_until(
            f"{hit} aborted",
            lambda: (
                {v["name"]: v["phase"] for v in mission_status(kube, name)["vehicles"]}[hit]
                == "Aborted"
            ),
            WAIT_S,
        )
        assert (command_of(kube, hit) or {})["action"] == "SafetyRoutine"
        assert command_of(kube, other) is None
        wait_until(f"{hit}'s Job stopped", lambda: len(jobs_of(kube, name)) == 1, WAIT_S)
    else:
        assert len(jobs_of(kube, name)) == 2
    assert mission_status(kube, name)["phase"] == "Running"
    release_holds(kube, name)
    status = wait_phase(kube, name, "Succeeded")
    assert condition_of(status, "Degraded")["status"] == "True"  # type: ignore[index]


def test_a_paused_failover_consequence_is_applied_once_the_pause_is_lifted(
    fleet: Fleet, kube: Kube, agents: FakeAgents, roost_crds: Cluster
) -> None:
    fleet.add(2)
    name = fleet.mission(
        unique("paused"), selector={"fleet": fleet.label}, count=2, onFailover="AbortVehicle"
    )
    hit, other = assigned(wait_phase(kube, name, "Running"))
    roost_crds.kubectl("annotate", "vehicle", hit, f"{ANNOTATION_PAUSE_FAILOVER_ACTIONS}=true")

    agents.fail_over(hit)

    def entry_of(vehicle: str) -> Obj:
        vehicles = mission_status(kube, name).get("vehicles") or []
        found: Obj = next(v for v in vehicles if v["name"] == vehicle)
        return found

    def held_back() -> Obj | None:
        entry = entry_of(hit)
        return entry if entry.get("failoverActionHeld") == "Paused" else None

    held = wait_until(f"{hit}'s consequence held back", held_back, WAIT_S)
    assert held["phase"] == "Running" and held["reason"] == "FailoverActionPaused"
    assert command_of(kube, hit) is None and len(jobs_of(kube, name)) == 2
    degraded = condition_of(mission_status(kube, name), "Degraded")
    assert degraded is not None and degraded["reason"] == "FailoverActionPaused"
    wait_until(
        "the FailoverActionPaused Event",
        lambda: "FailoverActionPaused" in events_for(roost_crds, name),
        WAIT_S,
    )

    roost_crds.kubectl("annotate", "vehicle", hit, f"{ANNOTATION_PAUSE_FAILOVER_ACTIONS}-")
    wait_until(f"{hit} aborted", lambda: entry_of(hit)["phase"] == "Aborted", WAIT_S)
    assert (command_of(kube, hit) or {})["action"] == "SafetyRoutine"
    assert command_of(kube, other) is None
    assert entry_of(hit).get("failoverActionHeld") is None


def test_a_failed_workload_fails_the_mission_and_stops_the_others(fleet: Fleet, kube: Kube) -> None:
    vehicles = fleet.add(2)
    name = fleet.mission(unique("fails"), selector={"fleet": fleet.label}, count=2, backoffLimit=0)
    status = wait_phase(kube, name, "Running")
    broken = assigned(status)[0]
    wait_until("both pods", lambda: len(pods_of(kube, name)) == 2, WAIT_S)
    (pod,) = [p for p in pods_of(kube, name) if p["metadata"]["labels"][LABEL_VEHICLE] == broken]
    kube.merge_patch(
        PODS,
        pod["metadata"]["name"],
        {"status": {"phase": "Failed", "reason": "Error", "message": "controller crashed"}},
        namespace=FLIGHTS,
        subresource="status",
    )
    status = wait_phase(kube, name, "Failed")
    assert status["reason"] == "VehicleWorkloadFailed"
    assert status["message"].startswith(f"{broken}: onboard Job")
    wait_until(
        "the other Job stopped",
        lambda: (
            jobs_of(kube, name) == {k: v for k, v in jobs_of(kube, name).items() if broken in k}
        ),
        WAIT_S,
    )
    wait_until(
        "vehicles released", lambda: all(claimed_by(kube, v) is None for v in vehicles), WAIT_S
    )


def test_competing_missions_never_share_a_vehicle(
    fleet: Fleet, kube: Kube, roost_crds: Cluster
) -> None:
    vehicles = fleet.add(5)
    names = [unique(f"rival{i}") for i in range(4)]
    fleet.missions.extend(names)
    manifests = "\n---\n".join(
        json.dumps(mission_manifest(n, selector={"fleet": fleet.label}, count=2)) for n in names
    )
    roost_crds.kubectl("apply", "-f", "-", input_text=manifests)

    def settled() -> dict[str, Obj] | None:
        statuses = {n: mission_status(kube, n) for n in names}
        running = [s for s in statuses.values() if s.get("phase") == "Running"]
        pending = [s for s in statuses.values() if s.get("reason") == "InsufficientVehicles"]
        return statuses if len(running) == 2 and len(pending) == 2 else None

    statuses = wait_until("two missions running and two waiting", settled, WAIT_S)
    flying = [assigned(s) for s in statuses.values() if s["phase"] == "Running"]
    taken = [v for group in flying for v in group]
    assert len(taken) == len(set(taken)) == 4, f"a vehicle was shared: {flying}"
    for mission, status in statuses.items():
        for vehicle in assigned(status) if status["phase"] == "Running" else []:
            assert claimed_by(kube, vehicle) == f"{FLIGHTS}/{mission}"
    free = set(vehicles) - set(taken)
    assert all(claimed_by(kube, v) is None for v in free), "waiting missions hold nothing"


def test_a_claim_written_from_a_stale_read_loses(fleet: Fleet, kube: Kube) -> None:
    """The claim's exclusivity itself: two claims computed from one read, one wins; a
    takeover and a release computed from a stale read of the claim are refused too."""
    (name,) = fleet.add(1)
    view = VehicleView.from_body(kube.get(VEHICLES, name) or {})
    alpha = MissionRef(namespace=FLIGHTS, name=unique("alpha"), uid="uid-alpha")
    beta = MissionRef(namespace=FLIGHTS, name=unique("beta"), uid="uid-beta")
    results: list[VehicleView | None] = [None, None]
    now = datetime.now(UTC)

    def claim(index: int, mission: MissionRef) -> None:
        results[index] = claim_vehicle(kube, OPERATOR_NAMESPACE, view, mission, at=now)

    threads = [threading.Thread(target=claim, args=(i, m)) for i, m in enumerate((alpha, beta))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    winners = [r for r in results if r is not None]
    assert len(winners) == 1
    winner = winners[0]
    assert winner.claim is not None
    holder = claimed_by(kube, name)
    assert holder == winner.claim.holder_key
    loser = beta if holder == alpha.key else alpha
    assert not release_vehicle(kube, OPERATOR_NAMESPACE, name, loser), "not the loser's claim"

    # Two takeovers of the same claim judged orphaned at one version: exactly one wins.
    gamma = MissionRef(namespace=FLIGHTS, name=unique("gamma"), uid="uid-gamma")
    first = claim_vehicle(kube, OPERATOR_NAMESPACE, winner, gamma, at=now)
    second = claim_vehicle(kube, OPERATOR_NAMESPACE, winner, loser, at=now)
    assert first is not None and second is None
    assert claimed_by(kube, name) == gamma.key

    # A release carrying a stale resourceVersion is refused by the API server.
    assert winner.claim is not None
    with pytest.raises(ConflictError):
        kube.request(
            "DELETE",
            LEASES.object_path(lease_name(name), OPERATOR_NAMESPACE),
            body=release_options(winner.claim),
        )
    assert release_vehicle(kube, OPERATOR_NAMESPACE, name, gamma)
    assert claimed_by(kube, name) is None


def test_a_restarted_operator_resumes_without_duplicating_workloads(
    fleet: Fleet, kube: Kube, operator: OperatorProcess
) -> None:
    vehicles = fleet.add(3)
    name = fleet.mission(unique("restart"), selector={"fleet": fleet.label}, count=3)
    wait_phase(kube, name, "Running")
    wait_until("three Jobs", lambda: len(jobs_of(kube, name)) == 3, WAIT_S)
    before = {n: j["metadata"]["uid"] for n, j in jobs_of(kube, name).items()}
    pods_before = {p["metadata"]["uid"] for p in pods_of(kube, name)}

    operator.crash()
    lost = sorted(before)[0]
    kube.delete(JOBS, lost, FLIGHTS)
    operator.start()

    wait_until("the lost Job to be back", lambda: lost in jobs_of(kube, name), WAIT_S)
    after = {n: j["metadata"]["uid"] for n, j in jobs_of(kube, name).items()}
    assert set(after) == set(before)
    assert {n: u for n, u in after.items() if n != lost} == {
        n: u for n, u in before.items() if n != lost
    }
    assert after[lost] != before[lost]

    def settled() -> set[str] | None:
        """The pods once the job controller made the new Job's and the garbage
        collector took the lost one's (both after the Job is back, each in its time)."""
        uids = {p["metadata"]["uid"] for p in pods_of(kube, name)}
        return uids if len(uids) == 3 and len(pods_before & uids) == 2 else None

    wait_until(
        "the new Job's pod beside the two that survived",
        settled,
        WAIT_S,
        explain=lambda: f"pods: {[p['metadata']['name'] for p in pods_of(kube, name)]}",
    )
    release_holds(kube, name)
    status = wait_phase(kube, name, "Succeeded")
    assert sorted(assigned(status)) == sorted(vehicles)


def test_deleting_a_running_mission_lands_and_releases_its_vehicles(
    fleet: Fleet, kube: Kube, roost_crds: Cluster
) -> None:
    vehicles = fleet.add(2)
    name = fleet.mission(unique("deleted"), selector={"fleet": fleet.label}, count=2)
    wait_phase(kube, name, "Running")
    roost_crds.kubectl("delete", "mission", name, "-n", FLIGHTS)
    assert kube.get(MISSIONS, name, FLIGHTS) is None
    for vehicle in vehicles:
        assert claimed_by(kube, vehicle) is None
        assert (command_of(kube, vehicle) or {})["action"] == "SafetyRoutine"


def test_a_template_the_job_api_refuses_fails_the_mission_before_it_claims(
    fleet: Fleet, kube: Kube
) -> None:
    vehicles = fleet.add(1)
    manifest = mission_manifest(unique("badtemplate"), selector={"fleet": fleet.label}, count=1)
    manifest["spec"]["onboard"]["spec"]["containers"][0]["name"] = "Not_A_Valid_Name"
    fleet.missions.append(manifest["metadata"]["name"])
    fleet.apply(manifest)
    status = wait_phase(kube, manifest["metadata"]["name"], "Failed")
    assert status["reason"] == "InvalidTemplate"
    message = status["message"]
    assert message.startswith("spec.onboard is refused by the Job API: ")
    assert "Not_A_Valid_Name" in message and "{" not in message, "the API's words, not JSON"
    assert claimed_by(kube, vehicles[0]) is None, "nothing was claimed"
    assert jobs_of(kube, manifest["metadata"]["name"]) == {}
    # The broken Mission is deleted like any other.
    fleet.cluster.kubectl("delete", "mission", manifest["metadata"]["name"], "-n", FLIGHTS)
    assert kube.get(MISSIONS, manifest["metadata"]["name"], FLIGHTS) is None


def test_a_vehicle_deleted_mid_mission_leaves_it_at_once(
    fleet: Fleet, kube: Kube, roost_crds: Cluster
) -> None:
    doomed, staying = fleet.add(2)
    name = fleet.mission(unique("vdel"), names=[doomed, staying], count=2)
    wait_phase(kube, name, "Running")
    wait_until("both Jobs", lambda: len(jobs_of(kube, name)) == 2, WAIT_S)
    copy = f"roost-vehicle-{doomed}"
    assert kube.get(CONFIGMAPS, copy, FLIGHTS) is not None

    roost_crds.kubectl("delete", "vehicle", doomed, "--wait=false")

    def left() -> Obj | None:
        status = mission_status(kube, name)
        by_name = {v["name"]: v for v in status.get("vehicles") or []}
        return status if by_name[doomed].get("reason") == "VehicleDeleted" else None

    status = wait_until("the vehicle to leave the mission", left, WAIT_S)
    assert status["phase"] == "Running"
    degraded = condition_of(status, "Degraded") or {}
    assert (degraded.get("status"), degraded.get("reason")) == ("True", "VehicleDeleted")
    wait_until(
        "its Job stopped and its config copy gone",
        lambda: (
            onboard_job_name(name, doomed) not in jobs_of(kube, name)
            and kube.get(CONFIGMAPS, copy, FLIGHTS) is None
        ),
        WAIT_S,
    )
    assert (command_of(kube, doomed) or {}).get("action") == "SafetyRoutine"
    assert "VehicleDeleted" in events_for(roost_crds, name)
    release_holds(kube, name, staying)
    wait_phase(kube, name, "Succeeded")


def test_invalid_missions_are_rejected_with_a_clear_message(roost_crds: Cluster) -> None:
    manifest = mission_manifest(unique("bad"), names=["x"], count=2)
    result = roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(manifest), check=False)
    assert result.returncode != 0
    assert "count is larger than the number of names" in result.stderr
