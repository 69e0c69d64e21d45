"""A Vehicle's autopilots, workloads and component Pods, computed without a cluster."""

from __future__ import annotations

from typing import Any

from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.meta import Stack
from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import (
    ANNOTATION_CONFIG_HASH,
    ANNOTATION_POD_HASH,
    LABEL_MISSION,
    LABEL_VEHICLE,
    TAINT_VEHICLE,
)
from roost_operator.vehicles.config import vehicle_config
from roost_operator.vehicles.manifests import (
    DEFAULT_IMAGES,
    Autopilot,
    active_autopilot,
    autopilots_of,
    component_pod,
    component_workloads,
    is_component_pod,
    pod_hash,
)


def spec(**overrides: object) -> VehicleSpec:
    return VehicleSpec.model_validate({"nodeName": "node-a", "sysid": 12, **overrides})


def redundant(
    primary: str = "fc1", stacks: tuple[str, str] = ("px4", "px4")
) -> RedundantAutopilotSpec:
    return RedundantAutopilotSpec.model_validate(
        {
            "vehicleName": "drone1",
            "primary": primary,
            "autopilots": [
                {
                    "name": "fc1",
                    "stack": stacks[0],
                    "connection": "udp://127.0.0.1:14540",
                    "sysid": 1,
                    "bridgeChannel": 0,
                },
                {
                    "name": "fc2",
                    "stack": stacks[1],
                    "connection": "udp://127.0.0.1:14541",
                    "fcuUrl": "udp://127.0.0.1:14641@",
                    "sysid": 2,
                    "bridgeChannel": 1,
                },
            ],
        }
    )


# -- autopilots ---------------------------------------------------------------------


def test_autopilots_come_from_the_redundant_autopilot_with_fcu_url_defaulting_to_connection() -> (
    None
):
    aps = autopilots_of(spec(simulation={"stack": "px4"}), redundant())
    assert [(a.name, a.sysid, a.fcu_url) for a in aps] == [
        ("fc1", 1, "udp://127.0.0.1:14540"),
        ("fc2", 2, "udp://127.0.0.1:14641@"),
    ]


def test_a_simulated_vehicle_without_redundant_autopilot_gets_one_derived_sitl() -> None:
    (only,) = autopilots_of(spec(simulation={"stack": "ardupilot", "instance": 2}), None)
    assert only.stack is Stack.ARDUPILOT
    assert only.sysid == 12
    assert only.connection == only.fcu_url == "udp://127.0.0.1:14548"


def test_a_real_vehicle_without_redundant_autopilot_has_no_known_autopilot() -> None:
    assert autopilots_of(spec(), None) == []
    assert active_autopilot([], reported_active=None, primary=None) is None


def test_active_autopilot_prefers_the_reported_one_then_the_primary() -> None:
    aps = autopilots_of(spec(), redundant(primary="fc1"))
    assert active_autopilot(aps, reported_active="fc2", primary="fc1") == aps[1]
    assert active_autopilot(aps, reported_active=None, primary="fc1") == aps[0]
    assert active_autopilot(aps, reported_active="gone", primary="fc2") == aps[1]
    assert active_autopilot(aps, reported_active=None, primary=None) == aps[0]


# -- workloads ----------------------------------------------------------------------


def test_default_components_are_mavros_only_and_overrides_pick_images() -> None:
    assert [w.component for w in component_workloads(spec(), [], vehicle_name="drone1")] == [
        "mavros"
    ]
    s = spec(
        components={
            "mavros": {"enabled": False},
            "vicon": {"enabled": True, "image": "example/vicon:1"},
            "hardware": {"enabled": True},
        }
    )
    workloads = {w.component: w for w in component_workloads(s, [], vehicle_name="drone1")}
    assert set(workloads) == {"vicon", "hardware"}
    assert workloads["vicon"].image == "example/vicon:1"
    assert workloads["hardware"].image == DEFAULT_IMAGES["hardware"]


def test_one_sitl_per_autopilot_and_no_two_share_a_port_or_sysid() -> None:
    s = spec(simulation={"stack": "px4", "instance": 1})
    sitls = [
        w
        for w in component_workloads(s, autopilots_of(s, redundant()), vehicle_name="drone1")
        if w.component.startswith("sitl-")
    ]
    assert [w.component for w in sitls] == ["sitl-fc1", "sitl-fc2"]
    envs = [{e["name"]: e["value"] for e in w.container["env"]} for w in sitls]
    ports = [(e["ROOST_SITL_AGENT_PORT"], e["ROOST_SITL_AUTOPILOT_PORT"]) for e in envs]
    assert len({p for pair in ports for p in pair}) == 4
    assert [e["ROOST_SITL_SYSID"] for e in envs] == ["1", "2"]
    assert all(w.image == DEFAULT_IMAGES["sitl-px4"] for w in sitls)


def test_two_simulated_vehicles_on_distinct_instances_never_collide() -> None:
    ports: set[str] = set()
    for instance in range(3):
        s = spec(simulation={"stack": "px4", "instance": instance})
        for w in component_workloads(s, autopilots_of(s, redundant()), vehicle_name="drone1"):
            env = {e["name"]: e["value"] for e in w.container.get("env", [])}
            if "ROOST_SITL_AGENT_PORT" in env:
                new = {env["ROOST_SITL_AGENT_PORT"], env["ROOST_SITL_AUTOPILOT_PORT"]}
                assert not new & ports
                ports |= new


def test_ardupilot_sitl_gets_a_tcp_readiness_probe_px4_none() -> None:
    s = spec(simulation={"stack": "px4"})
    workloads = component_workloads(
        s, autopilots_of(s, redundant(stacks=("px4", "ardupilot"))), vehicle_name="drone1"
    )
    by = {w.component: w for w in workloads}
    assert "readinessProbe" not in by["sitl-fc1"].container
    probe = by["sitl-fc2"].container["readinessProbe"]
    assert probe["tcpSocket"]["port"] == by["sitl-fc2"].container["ports"][0]["containerPort"]
    assert by["sitl-fc2"].image == DEFAULT_IMAGES["sitl-ardupilot"]


def test_simulation_image_override_applies_to_every_sitl() -> None:
    s = spec(simulation={"stack": "px4", "image": "example/sitl:2"})
    images = {
        w.image
        for w in component_workloads(s, autopilots_of(s, redundant()), vehicle_name="drone1")
        if "sitl" in w.component
    }
    assert images == {"example/sitl:2"}


def config_for(s: VehicleSpec, active: Autopilot | None) -> dict[str, str]:
    return vehicle_config(
        name="drone1",
        spec=s,
        fcu_url=active.fcu_url if active else "",
        firmware=active.stack if active else None,
        active_autopilot=active.name if active else None,
    )


def manifests(reported_active: str | None) -> dict[str, dict[str, Any]]:
    s = spec(simulation={"stack": "px4"})
    aps = autopilots_of(s, redundant())
    values = config_for(s, active_autopilot(aps, reported_active=reported_active, primary="fc1"))
    return {
        w.component: component_pod(
            "drone1", "node-a", w, values, namespace="roost-system", owners=[{"uid": "v"}]
        )
        for w in component_workloads(s, aps, vehicle_name="drone1")
    }


def test_a_component_is_one_pod_bound_to_the_vehicles_node() -> None:
    p = manifests(None)["mavros"]
    assert (p["apiVersion"], p["kind"]) == ("v1", "Pod")
    assert p["metadata"]["name"] == "drone1-mavros"
    assert p["metadata"]["namespace"] == "roost-system"
    assert p["metadata"]["ownerReferences"] == [{"uid": "v"}]
    assert is_component_pod(p)
    pod = p["spec"]
    assert pod["nodeName"] == "node-a"  # no scheduler
    assert pod["restartPolicy"] == "Always"
    assert pod["nodeSelector"] == {LABEL_VEHICLE: "drone1"}  # the kubelet still checks it
    assert pod["tolerations"][0]["key"] == TAINT_VEHICLE
    container = pod["containers"][0]
    assert container["resources"]["requests"]["cpu"] == "100m"
    env = {e["name"] for e in container["env"]}
    assert {"VEHICLE_NAME", "VEHICLE_FCU_URL"} <= env
    assert pod_hash(p)


def test_a_missions_onboard_pod_is_not_a_component_pod() -> None:
    p = manifests(None)["mavros"]
    labels = {**p["metadata"]["labels"], LABEL_MISSION: "survey"}
    assert not is_component_pod({"metadata": {"labels": labels}})


def test_a_failover_changes_mavros_but_not_the_simulated_autopilots() -> None:
    before, after = manifests(None), manifests("fc2")

    def annotation(p: dict[str, Any], key: str) -> str:
        return str(p["metadata"]["annotations"][key])

    for key in (ANNOTATION_CONFIG_HASH, ANNOTATION_POD_HASH):
        assert annotation(before["mavros"], key) != annotation(after["mavros"], key)
    for sitl in ("sitl-fc1", "sitl-fc2"):
        assert before[sitl] == after[sitl]


def test_a_node_change_replaces_every_workload() -> None:
    s = spec()
    (mavros,) = component_workloads(s, [], vehicle_name="drone1")
    values = config_for(s, None)
    a = component_pod("drone1", "node-a", mavros, values, namespace="n", owners=[])
    b = component_pod("drone1", "node-b", mavros, values, namespace="n", owners=[])
    assert pod_hash(a) != pod_hash(b)
    assert a["metadata"]["name"] == b["metadata"]["name"]
