"""Agent ↔ cluster on the real control plane: failover reported, followed and guarded.

Every part is real: ``roost-agent`` processes (chart-style: ``NODE_NAME`` and a
kubeconfig, no config file) supervise simulated autopilots (``roost_sim``, in this test
process) over UDP; a ``roost-operator`` process reconciles Vehicles and the cluster side
of failover; kube-apiserver/etcd store everything, the operator replaces the mavros
Pods (bound to the vehicle's node) and kwok runs them on fake vehicle nodes. The API
server is stopped and started for the partition tests.

Each test flies a fresh vehicle (its own node, sims, agent, Vehicle and
RedundantAutopilot). The agents report every 2 s and the operator calls a report stale
after 6 s, so staleness shows within a test's patience.
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from roost_api.autopilot import AssignedFence, CommandAction, Fence, FenceCircle
from roost_api.commands import command_patch, new_command
from roost_kube.client import Kube
from roost_kube.patches import Obj
from roost_kube.resources import CONFIGMAPS, EVENTS, PODS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_localcluster.cluster import Cluster
from roost_operator.missions.fence import fence_patch
from roost_operator.vehicles.config import config_map_name
from roost_operator.vehicles.manifests import workload_name
from roost_operator.vehicles.pods import mavros_follows
from roost_sim import SimConfig, SimulatedAutopilot, autopilot_specs, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.apiwrites import write_requests
from tests.support.flight import SIM_THRESHOLDS, land
from tests.support.operator import OperatorProcess
from tests.support.waiting import unique, wait_until

pytestmark = pytest.mark.cluster

NAMESPACE = "roost-it-failover"
REPORT_INTERVAL_S = 2.0
STALE_S = 6.0
OPERATOR_NAMESPACE = NAMESPACE
OPERATOR_ENV = {"ROOST_AGENT_STALE_SECONDS": str(STALE_S)}
WAIT_S = 60.0
FakeNodes = Callable[..., dict[str, Any]]


def until(what: str, check: Callable[[], Any], timeout_s: float = WAIT_S) -> Any:
    return wait_until(what, check, timeout_s, poll_s=0.1)


def spec_observed(rig: Rig) -> bool:
    """The agent reported on the RedundantAutopilot's current generation (it read it)."""
    obj = rig.kube.get(REDUNDANT_AUTOPILOTS, rig.name) or {}
    generation = obj.get("metadata", {}).get("generation")
    conditions = (obj.get("status") or {}).get("conditions") or []
    return bool(conditions) and all(c.get("observedGeneration") == generation for c in conditions)


@dataclass
class Rig:
    """One flying vehicle: its objects' name, node, simulated autopilots and agent."""

    name: str
    node: str
    sims: list[SimulatedAutopilot]
    agent: AgentProcess
    kube: Kube

    def autopilots(self) -> Obj:
        obj = self.kube.get(REDUNDANT_AUTOPILOTS, self.name)
        assert obj is not None
        return obj

    def ra_status(self) -> Obj:
        return self.autopilots().get("status") or {}

    def vehicle_status(self) -> Obj:
        obj = self.kube.get(VEHICLES, self.name) or {}
        return obj.get("status") or {}

    def url(self, index: int) -> str:
        return self.sims[index].connection

    def mavros(self) -> Obj | None:
        return self.kube.get(PODS, workload_name(self.name, "mavros"), NAMESPACE)

    def mavros_on(self, index: int) -> bool:
        config = self.kube.get(CONFIGMAPS, config_map_name(self.name), NAMESPACE)
        return mavros_follows(self.url(index), config, self.mavros())

    def command(self, action: CommandAction, **kwargs: Any) -> str:
        command = new_command(action, **kwargs)
        self.kube.merge_patch(REDUNDANT_AUTOPILOTS, self.name, command_patch(command))
        return command.id


FLIGHT_ORDERS = frozenset(
    {
        "MAV_CMD_DO_SET_MODE",
        "MAV_CMD_NAV_LAND",
        "MAV_CMD_NAV_RETURN_TO_LAUNCH",
        "MAV_CMD_COMPONENT_ARM_DISARM",
    }
)


def orders(sim: SimulatedAutopilot) -> int:
    """Commands the agent sent this autopilot that change how it flies (hold, land, disarm)."""
    return sum(1 for c in sim.commands if c.source != (0, 0) and c.name in FLIGHT_ORDERS)


def conditions(status: Obj) -> dict[str, tuple[str, str]]:
    return {c["type"]: (c["status"], c["reason"]) for c in status.get("conditions", [])}


def events(kube: Kube, kind: str, name: str) -> list[tuple[str, str]]:
    """(reason, message) of the Events about one object (Roost records them in ``default``)."""
    selector = f"involvedObject.kind={kind},involvedObject.name={name}"
    found = kube.list_objects(EVENTS, namespace="default", field_selector=selector)
    return [(e["reason"], e.get("message", "")) for e in found]


def reasons(kube: Kube, kind: str, name: str) -> list[str]:
    """Reasons of the Events about one object."""
    return [reason for reason, _ in events(kube, kind, name)]


@pytest.fixture
def rig(
    roost_crds: Cluster,
    operator: OperatorProcess,
    kube: Kube,
    fake_nodes: FakeNodes,
    tmp_path: Path,
) -> Iterator[Rig]:
    """A vehicle flying on two PX4 sims, its agent reporting, the Vehicle Ready."""
    name = unique("fo")
    node = f"{name}-node"
    fake_nodes(node)
    sims = start_vehicle_sims(["px4", "px4"], config=SimConfig.fast())
    agent = AgentProcess.in_cluster(roost_crds, node, tmp_path, report_interval_s=REPORT_INTERVAL_S)
    try:
        for sim in sims:
            sim.wait_ready()
            sim.fly(altitude_m=5)
        for sim in sims:
            sim.wait_until(lambda s: s.landed_state == "InAir", timeout=30)
        specs = [a.to_api() for a in autopilot_specs(sims)]
        for manifest in (
            {
                "apiVersion": "roost.dev/v1alpha1",
                "kind": "Vehicle",
                "metadata": {"name": name},
                "spec": {"nodeName": node, "sysid": 42},
            },
            {
                "apiVersion": "roost.dev/v1alpha1",
                "kind": "RedundantAutopilot",
                "metadata": {"name": name},
                "spec": {
                    "vehicleName": name,
                    "primary": "fc1",
                    "autopilots": specs,
                    "failoverPolicy": {"thresholds": SIM_THRESHOLDS.to_api()},
                },
            },
        ):
            roost_crds.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
        agent.start()
        result = Rig(name, node, sims, agent, kube)

        def reporting() -> bool:
            got = conditions(result.vehicle_status())
            ready = got.get("Ready", ("",))[0] == "True"
            connected = got.get("AgentConnected", ("",))[0] == "True"
            return ready and connected and result.mavros_on(0)

        until(f"Vehicle {name} Ready with its agent reporting", reporting)
        yield result
    finally:
        agent.stop()
        stop_sims(sims)
        if not operator.process.alive():
            operator.start()
        for kind in ("redundantautopilot", "vehicle"):
            roost_crds.kubectl("delete", kind, name, "--ignore-not-found", "--wait=false")
        until(f"Vehicle {name} gone", lambda: kube.get(VEHICLES, name) is None)


def failed_over(rig: Rig, count: int = 1) -> Obj | None:
    status = rig.ra_status()
    if status.get("activeAutopilot") == "fc2" and status.get("failoverCount") == count:
        return status
    return None


def test_killing_the_active_autopilot_switches_locally_and_the_cluster_follows(
    rig: Rig, kube: Kube
) -> None:
    rig.sims[0].inject("silence")

    status = until("the agent to report the switch to fc2", lambda: failed_over(rig))
    assert status["lastFailover"]["from"] == "fc1" and status["lastFailover"]["to"] == "fc2"
    assert status["lastFailover"]["trigger"] == "Automatic" and status["latched"] is True
    got = conditions(status)
    assert got["ActiveHealthy"] == ("True", "Healthy")
    assert got["FailedOver"] == ("True", "AutomaticFailover")
    assert got["Redundant"][0] == "False" and got["Ready"][0] == "False"
    # the safety routine ran on the new active autopilot: hold, then land
    rig.sims[1].wait_until(lambda s: s.landed_state == "OnGround", timeout=30)
    assert "AUTO.LOITER" in [m.mode for m in rig.sims[1].mode_history]

    def vehicle_followed() -> Obj | None:
        vehicle = rig.vehicle_status()
        failover = vehicle.get("failover") or {}
        done = rig.mavros_on(1) and not failover.get("action")
        return vehicle if done and vehicle.get("fcuUrl") == rig.url(1) else None

    vehicle = until("mavros re-pointed at fc2 and the action finished", vehicle_followed)
    assert vehicle["activeAutopilot"] == "fc2"
    assert vehicle["failover"]["followedAutopilot"] == "fc2"
    got = conditions(vehicle)
    assert got["AgentConnected"] == ("True", "Reporting")
    assert got["AutopilotsHealthy"] == ("False", "FailedOver")
    assert got["Ready"][0] == "False"
    assert "FailedOver" in reasons(kube, "RedundantAutopilot", rig.name)
    vehicle_events = reasons(kube, "Vehicle", rig.name)
    assert {"FailedOver", "RepointingMavros", "MavrosRepointed"} <= set(vehicle_events)


def test_a_silent_agent_turns_agent_connected_unknown_and_back(rig: Rig) -> None:
    rig.agent.crash()

    def stale() -> Obj | None:
        got = conditions(rig.vehicle_status())
        return got if got.get("AgentConnected") == ("Unknown", "ReportsStale") else None

    got = until("AgentConnected Unknown", stale, timeout_s=STALE_S * 6)
    assert got["AutopilotsHealthy"] == ("Unknown", "AgentNotConnected")
    assert got["Ready"][0] == "Unknown"
    rig.agent.start()
    until(
        "AgentConnected True again",
        lambda: conditions(rig.vehicle_status()).get("AgentConnected", ("",))[0] == "True",
    )


def test_a_failover_during_an_api_outage_happens_and_the_status_catches_up(
    rig: Rig, roost_crds: Cluster, kube: Kube
) -> None:
    plane = roost_crds.control_plane
    assert plane is not None, "partition tests need the harness's own control plane"
    plane.stop_apiserver()
    try:
        rig.sims[0].inject("silence")
        switched = until("the local switch (agent output)", lambda: rig.agent.events("Failover"))
        assert switched[0]["failover"]["to"] == "fc2"
        rig.sims[1].wait_until(lambda s: s.mode == "AUTO.LOITER", timeout=20)
    finally:
        plane.start_apiserver()

    status = until("the switch in the API after the outage", lambda: failed_over(rig))
    assert status["lastFailover"]["time"] == switched[0]["failover"]["time"]
    assert conditions(status)["FailedOver"] == ("True", "AutomaticFailover")
    until(
        "the failover Event posted after the outage",
        lambda: "FailedOver" in reasons(kube, "RedundantAutopilot", rig.name),
    )
    until("mavros re-pointed after the outage", lambda: rig.mavros_on(1))


def test_a_command_issued_before_a_partition_expires_instead_of_running_late(
    rig: Rig, roost_crds: Cluster
) -> None:
    assert (rig.agent.state_dir / "agent-state.json").exists()
    rig.agent.crash()  # the agent is cut off: it cannot see the command in time
    sent = orders(rig.sims[0])
    command_id = rig.command(CommandAction.SAFETY_ROUTINE, deadline_seconds=2)
    plane = roost_crds.control_plane
    assert plane is not None, "partition tests need the harness's own control plane"
    plane.stop_apiserver()
    try:
        rig.agent.start()  # API down: it flies on with the spec saved on disk
        until("the agent running on its saved spec", lambda: rig.agent.events("Started"))
        issued = time.time()  # the command was issued before this instant
        wait_until("the command's 2 s deadline to pass", lambda: time.time() > issued + 2.5)
    finally:
        plane.start_apiserver()

    def recorded() -> Obj | None:
        last = rig.ra_status().get("lastCommand") or {}
        return last if last.get("id") == command_id else None

    last = until("the agent to record the stale command", recorded)
    assert last["result"] == "Expired"
    assert orders(rig.sims[0]) == sent
    assert rig.ra_status()["activeAutopilot"] == "fc1"


def test_an_operator_restarted_mid_failover_acts_once(
    rig: Rig, operator: OperatorProcess, kube: Kube
) -> None:
    before = rig.mavros()
    assert before is not None
    operator.crash()
    rig.sims[0].inject("silence")
    until("the agent to report the switch", lambda: failed_over(rig))
    operator.start()
    until(
        "the operator to start the re-point",
        lambda: (rig.vehicle_status().get("failover") or {}).get("followedAutopilot") == "fc2",
        timeout_s=WAIT_S,
    )
    operator.crash()  # in the middle: mavros rolling, the action not finished
    operator.start()

    until(
        "mavros on fc2 and the action finished",
        lambda: rig.mavros_on(1) and not (rig.vehicle_status()["failover"].get("action")),
    )
    time.sleep(REPORT_INTERVAL_S * 2)  # nothing more happens over two reports and reconciles
    after = rig.mavros()
    assert after is not None and after["metadata"]["uid"] != before["metadata"]["uid"]
    failover = rig.vehicle_status()["failover"]
    assert failover["observedFailoverCount"] == 1 and len(failover["recent"]) == 1
    vehicle_events = events(kube, "Vehicle", rig.name)
    assert [r for r, _ in vehicle_events].count("RepointingMavros") == 1
    observed = [m for r, m in vehicle_events if r == "FailedOver" and m.startswith("fc1 -> fc2")]
    assert len(observed) == 1, vehicle_events  # (conditions' transitions say "... is False")


def test_manual_switch_and_safety_routine_run_once_even_when_replayed(rig: Rig) -> None:
    switch_id = f"switch-{uuid.uuid4().hex[:8]}"
    rig.command(CommandAction.SWITCH, target="fc2", command_id=switch_id)

    def executed(command_id: str) -> Obj | None:
        status = rig.ra_status()
        last = status.get("lastCommand") or {}
        return status if last.get("id") == command_id and last["result"] == "Executed" else None

    status = until("the Switch executed", lambda: executed(switch_id))
    assert status["activeAutopilot"] == "fc2"
    switched = {k: status["lastFailover"][k] for k in ("time", "from", "to", "trigger")}
    assert switched["trigger"] == "Command" and switched["to"] == "fc2"
    assert conditions(status)["FailedOver"] == ("True", "SwitchedByCommand")

    routine_id = f"routine-{uuid.uuid4().hex[:8]}"
    rig.command(CommandAction.SAFETY_ROUTINE, command_id=routine_id)
    until("the SafetyRoutine executed", lambda: executed(routine_id))
    rig.sims[1].wait_until(lambda s: s.mode == "AUTO.LOITER", timeout=20)
    rig.sims[1].wait_until(lambda s: s.landed_state == "OnGround", timeout=30)
    sent = [orders(sim) for sim in rig.sims]

    # replay both requests (same ids, fresh issuedAt), then restart the agent on top
    rig.command(CommandAction.SWITCH, target="fc2", command_id=switch_id)
    rig.command(CommandAction.SAFETY_ROUTINE, command_id=routine_id)
    until("the agent to have read the replayed requests", lambda: spec_observed(rig))
    rig.agent.crash()
    rig.agent.start()
    stamp = rig.ra_status()["reportedAt"]
    until("a report from the restarted agent", lambda: rig.ra_status()["reportedAt"] != stamp)
    time.sleep(REPORT_INTERVAL_S)  # nothing happens over one more report: nothing re-run
    status = rig.ra_status()
    assert status["activeAutopilot"] == "fc2"
    assert {k: status["lastFailover"][k] for k in switched} == switched
    assert status["lastCommand"]["id"] == routine_id
    assert [orders(sim) for sim in rig.sims] == sent
    assert len(rig.agent.events("Failover")) == 1


def test_a_flapping_autopilot_does_not_cause_a_storm(
    rig: Rig, roost_crds: Cluster, kube: Kube
) -> None:
    rig.sims[0].inject("silence")
    until("the failover", lambda: failed_over(rig))
    rig.sims[1].wait_until(lambda s: s.landed_state == "OnGround", timeout=30)
    until("mavros on fc2", lambda: rig.mavros_on(1))
    time.sleep(REPORT_INTERVAL_S)  # a settled baseline: the failover's last writes land
    mavros = rig.mavros()
    assert mavros is not None
    status_writes = write_requests(roost_crds, [("redundantautopilots", "status")])
    vehicle_writes = write_requests(roost_crds, [("vehicles", "status")])
    agent_events = len(reasons(kube, "RedundantAutopilot", rig.name))
    vehicle_events = len(reasons(kube, "Vehicle", rig.name))

    window_s = 12.0
    started = time.monotonic()
    flips = 0
    while time.monotonic() - started < window_s:  # fc1 comes and goes, again and again
        rig.sims[0].clear()
        time.sleep(1.2)
        rig.sims[0].inject("silence")
        time.sleep(0.8)
        flips += 1
    rig.sims[0].clear()

    ra_writes = write_requests(roost_crds, [("redundantautopilots", "status")]) - status_writes
    v_writes = write_requests(roost_crds, [("vehicles", "status")]) - vehicle_writes
    # coalesced: at most one routine write per second plus the periodic refreshes
    assert ra_writes <= window_s / 1.0 + window_s / REPORT_INTERVAL_S + 2, ra_writes
    assert v_writes <= ra_writes + 1, (v_writes, ra_writes)
    status = rig.ra_status()
    assert status["failoverCount"] == 1 and status["activeAutopilot"] == "fc2"
    assert len(rig.agent.events("Failover")) == 1
    assert len(reasons(kube, "RedundantAutopilot", rig.name)) == agent_events
    assert len(reasons(kube, "Vehicle", rig.name)) == vehicle_events
    after = rig.mavros()
    assert after is not None and after["metadata"]["uid"] == mavros["metadata"]["uid"]  # kept
    assert flips >= 5


def test_a_guard_holds_the_repoint_until_a_human_lifts_it(rig: Rig, roost_crds: Cluster) -> None:
    roost_crds.kubectl(
        "annotate", "vehicle", rig.name, "roost.dev/pause-failover-actions=true", "--overwrite"
    )
    rig.sims[0].inject("silence")
    until("the switch", lambda: failed_over(rig))

    def held() -> Obj | None:
        vehicle = rig.vehicle_status()
        return vehicle if (vehicle.get("failover") or {}).get("blocked") == "Paused" else None

    vehicle = until("the re-point held back by the pause", held)
    assert vehicle["activeAutopilot"] == "fc2"  # the truth, from the agent
    assert vehicle["fcuUrl"] == rig.url(0)  # mavros stays until a human decides
    assert rig.mavros_on(0)
    roost_crds.kubectl("annotate", "vehicle", rig.name, "roost.dev/pause-failover-actions-")
    until("mavros re-pointed once the pause is lifted", lambda: rig.mavros_on(1))
    assert rig.vehicle_status()["failover"].get("blocked") is None


def test_a_fence_written_into_the_redundant_autopilot_reaches_both_autopilots_and_goes(
    rig: Rig,
) -> None:
    """What the operator writes for a Mission's fence (spec.fence), read by the real
    agent process from the API server: deferred while the vehicle flies, uploaded to both
    simulated autopilots once they landed and disarmed, reported per autopilot in the
    status, and the previous fence restored once it is removed."""
    home = SimConfig()
    fence = AssignedFence(
        mission="default/fenced",
        id="0123456789ab",
        fence=Fence(
            circle=FenceCircle(
                latitude=home.home_lat_deg, longitude=home.home_lon_deg, radius_m=60
            ),
            max_altitude_m=25,
        ),
    )
    before = [list(sim.fence.items) for sim in rig.sims]
    rig.kube.merge_patch(REDUNDANT_AUTOPILOTS, rig.name, fence_patch(fence))

    def fence_states() -> dict[str, tuple[str, str]]:
        return {
            h["name"]: (c["status"], c["message"])
            for h in rig.ra_status().get("autopilots", [])
            for c in h.get("conditions", [])
            if c["type"] == "FenceInSync"
        }

    def held() -> bool:
        states = fence_states()
        return len(states) == 2 and all(
            s == "True" and m.startswith("holds fence 0123456789ab") for s, m in states.values()
        )

    def deferred() -> bool:
        states = fence_states()
        return len(states) == 2 and all(
            m == "uploading the fence waits until disarmed" for _, m in states.values()
        )

    until("the fence deferred while the vehicle flies", deferred)
    assert all(sim.fence.uploads == 0 for sim in rig.sims)
    for sim in rig.sims:
        land(sim)
    until("both autopilots hold the fence", held)
    assert all(len(sim.fence.items) == 1 for sim in rig.sims)
    assert all(sim.params.get("GF_MAX_VER_DIST") == 25 for sim in rig.sims)
    rig.kube.merge_patch(REDUNDANT_AUTOPILOTS, rig.name, fence_patch(None))
    until("the fence condition gone", lambda: fence_states() == {})
    assert [list(sim.fence.items) for sim in rig.sims] == before
    assert all(sim.params.get("GF_MAX_VER_DIST") == 0 for sim in rig.sims)
