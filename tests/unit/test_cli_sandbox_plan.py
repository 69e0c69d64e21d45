"""The sandbox's fleet on paper: unique identities, manifests the API accepts.

Manifests are checked against the API models and the generated CRD schemas (offline); the
e2e sandbox test applies them to a real API server, where the CEL rules run too.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jsonschema
import psutil
import pytest
import yaml

from roost_api import crd
from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.mission import MissionSpec
from roost_api.resources import KINDS
from roost_api.vehicle import VehicleSpec
from roost_cli.sandbox import kwok, missionrun, plan, state

ROOT = Path(__file__).resolve().parents[2]


def _fleet(count: int) -> tuple[plan.VehiclePlan, ...]:
    return plan.plan_fleet(count)


def _connections(vehicle: plan.VehiclePlan) -> dict[str, str]:
    """What the vehicle's simulators would report: each the port it bound itself."""
    return {
        a.name: f"udpout://127.0.0.1:{40000 + 10 * vehicle.index + i}"
        for i, a in enumerate(vehicle.autopilots)
    }


def _schema(kind: str) -> dict[str, Any]:
    resource = next(k for k in KINDS if k.kind == kind)
    document = yaml.safe_load((ROOT / "crds" / crd.file_name(resource)).read_text())
    schema: dict[str, Any] = document["spec"]["versions"][0]["schema"]["openAPIV3Schema"]
    return schema


def test_vehicles_alternate_stacks_and_never_share_a_sysid() -> None:
    fleet = _fleet(plan.MAX_VEHICLES)
    assert [v.name for v in fleet[:3]] == ["drone-1", "drone-2", "drone-3"]
    assert [v.stack.value for v in fleet[:3]] == ["px4", "ardupilot", "px4"]
    autopilots = [a for v in fleet for a in v.autopilots]
    assert len(autopilots) == plan.MAX_VEHICLES * plan.AUTOPILOTS_PER_VEHICLE
    assert len({a.sysid for a in autopilots}) == len(autopilots)
    assert len({v.sysid for v in fleet}) == len(fleet)
    assert all(1 <= a.sysid <= 255 for a in autopilots)


def test_each_vehicle_has_two_autopilots_of_its_stack_on_distinct_bridge_channels() -> None:
    drone = _fleet(2)[1]
    assert [(a.name, a.stack.value, a.bridge_channel) for a in drone.autopilots] == [
        ("apm-a", "ardupilot", 0),
        ("apm-b", "ardupilot", 1),
    ]
    assert drone.primary.name == "apm-a"


@pytest.mark.parametrize("count", [0, plan.MAX_VEHICLES + 1])
def test_fleet_size_is_bounded(count: int) -> None:
    with pytest.raises(ValueError, match="1 to"):
        _fleet(count)


def test_manifests_fit_the_models_and_the_crd_schemas() -> None:
    fleet = _fleet(3)
    for vehicle in fleet:
        v = plan.vehicle_manifest(vehicle)
        hub = f"127.0.0.1:{plan.HUB_PORT_BASE + vehicle.index}"
        ra = plan.autopilot_manifest(vehicle, _connections(vehicle), hub)
        spec = VehicleSpec.model_validate(v["spec"])
        assert spec.node_name == vehicle.node
        ra_spec = RedundantAutopilotSpec.model_validate(ra["spec"])
        assert ra_spec.vehicle_name == vehicle.name
        assert ra_spec.primary == vehicle.primary.name
        assert [a.connection for a in ra_spec.autopilots] == list(_connections(vehicle).values())
        assert ra_spec.hub is not None
        assert ra_spec.hub.udp == hub
        # simulators sharing the cores: a fixed silence threshold, not the learnt default
        th = ra_spec.failover_policy.thresholds
        assert th.message_error_min_ms == th.message_error_ms
        jsonschema.Draft4Validator(_schema("Vehicle")).validate(v)
        jsonschema.Draft4Validator(_schema("RedundantAutopilot")).validate(ra)
    mission = plan.mission_manifest(len(fleet))
    assert MissionSpec.model_validate(mission["spec"]).vehicles.count == 3
    jsonschema.Draft4Validator(_schema("Mission")).validate(mission)


def test_without_a_hub_port_the_autopilot_has_no_hub() -> None:
    vehicle = _fleet(1)[0]
    assert "hub" not in plan.autopilot_manifest(vehicle, _connections(vehicle))["spec"]


def test_hub_ports_skip_taken_ones_and_stay_below_the_ephemeral_range() -> None:
    taken = {plan.HUB_PORT_BASE + 1}
    ports = plan.hub_ports(3, lambda port: port not in taken, below=32768)
    assert ports == (plan.HUB_PORT_BASE, plan.HUB_PORT_BASE + 2, plan.HUB_PORT_BASE + 3)
    with pytest.raises(ValueError, match="no 3 free UDP ports"):
        plan.hub_ports(3, lambda port: port not in taken, below=plan.HUB_PORT_BASE + 3)


def test_the_reference_missions_manifest_fits_and_selects_the_sandbox_vehicles() -> None:
    runtime = {kwok.RUNTIME_ANNOTATION: plan.MISSION_RUNTIME}
    mission = missionrun.mission_manifests(missionrun.SYNC_PATHS, 2, runtime)[0]
    assert MissionSpec.model_validate(mission["spec"]).vehicles.count == 2
    jsonschema.Draft4Validator(_schema("Mission")).validate(mission)
    selector = mission["spec"]["vehicles"]["selector"]["matchLabels"]
    for vehicle in _fleet(2):
        labels = plan.vehicle_manifest(vehicle)["metadata"]["labels"]
        assert selector.items() <= labels.items()


def test_the_mission_selects_exactly_the_sandbox_vehicles() -> None:
    selector = plan.mission_manifest(2)["spec"]["vehicles"]["selector"]["matchLabels"]
    for vehicle in _fleet(2):
        labels = plan.vehicle_manifest(vehicle)["metadata"]["labels"]
        assert selector.items() <= labels.items()


def test_state_round_trips_and_finds_vehicles(tmp_path: Path) -> None:
    recorded = state.SandboxState(
        pid=1,
        create_time=2.5,
        directory=str(tmp_path),
        vehicles=[
            state.SandboxVehicle(
                name="drone-1",
                node="drone-1",
                stack="px4",
                autopilots=[
                    state.SimulatedAutopilot(
                        name="px4-a",
                        stack="px4",
                        sysid=1,
                        connection="udpout://127.0.0.1:40000",
                        control="/tmp/x.sock",
                        bridge_channel=0,
                    )
                ],
            )
        ],
    )
    state.save(recorded)
    loaded = state.load(tmp_path)
    assert loaded == recorded
    assert loaded.vehicle("drone-1") is not None
    assert loaded.vehicle("drone-9") is None
    assert loaded.cluster_dir == tmp_path / "cluster"
    state.remove(tmp_path)
    assert state.load(tmp_path) is None


def test_a_sandbox_whose_process_is_gone_is_not_running(tmp_path: Path) -> None:
    me = psutil.Process()
    state.save(
        state.SandboxState(pid=me.pid, create_time=me.create_time(), directory=str(tmp_path))
    )
    assert state.running(tmp_path) is not None
    # Same pid, different start time: a recycled pid is not our sandbox.
    state.save(state.SandboxState(pid=me.pid, create_time=1.0, directory=str(tmp_path)))
    assert state.running(tmp_path) is None


def test_kwok_keeps_the_missions_pods_running_for_the_annotated_runtime() -> None:
    stages = {stage["metadata"]["name"]: stage["spec"] for stage in kwok.pod_stages()}
    assert set(stages) == {"roost-pod-ready", "roost-pod-complete", "roost-pod-delete"}
    assert all(spec["resourceRef"] == {"apiGroup": "v1", "kind": "Pod"} for spec in stages.values())
    delay = stages["roost-pod-complete"]["delay"]["durationFrom"]["expressionFrom"]
    onboard = plan.mission_manifest(1)["spec"]["onboard"]["metadata"]["annotations"]
    assert delay == f'.metadata.annotations["{kwok.RUNTIME_ANNOTATION}"]'
    assert onboard == {kwok.RUNTIME_ANNOTATION: plan.MISSION_RUNTIME}
    # Round-trips through YAML as the sandbox writes it for kwok's --config.
    assert list(yaml.safe_load_all(yaml.safe_dump_all(kwok.pod_stages()))) == kwok.pod_stages()
