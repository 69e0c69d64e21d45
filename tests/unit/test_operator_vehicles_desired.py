"""Desired workloads and conditions of a Vehicle, computed without a cluster."""

from __future__ import annotations

from datetime import UTC, datetime
from functools import partial
from typing import Any

import pytest

from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.meta import Stack, find_condition, set_condition
from roost_api.vehicle import VehicleSpec, VehicleStatus
from roost_api.wellknown import (
    ANNOTATION_CONFIG_HASH,
    ANNOTATION_POD_HASH,
    LABEL_MISSION,
    LABEL_VEHICLE,
    TAINT_VEHICLE,
)
from roost_operator.vehicles.config import vehicle_config
from roost_operator.vehicles.desired import (
    DEFAULT_IMAGES,
    Autopilot,
    ComponentState,
    NodeBinding,
    PodStep,
    ReleaseStep,
    active_autopilot,
    autopilots_of,
    component_pod,
    component_workloads,
    components_condition,
    is_component_pod,
    pod_hash,
    pod_node,
    pod_state,
    pod_step,
    ready_condition,
    release_step,
    transitions,
    vehicle_conditions,
)
from roost_operator.vehicles.status import status_patch
from tests.support.conditions import cond as support_cond


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


# -- replacing pods --------------------------------------------------------------------

DESIRED: dict[str, Any] = {"metadata": {"annotations": {ANNOTATION_POD_HASH: "new"}}}


def live_pod(
    hash_: str = "new", phase: str = "Running", *, deleting: bool = False
) -> dict[str, Any]:
    meta: dict[str, Any] = {"annotations": {ANNOTATION_POD_HASH: hash_}}
    if deleting:
        meta["deletionTimestamp"] = "2024-01-01T00:00:00Z"
    return {"metadata": meta, "status": {"phase": phase}}


@pytest.mark.parametrize(
    ("live", "node_exists", "step"),
    [
        # no pod: create it, once its node exists
        (None, True, PodStep.CREATE),
        (None, False, PodStep.WAIT),
        # the desired pod: keep it, whatever its phase short of an end
        (live_pod(), True, PodStep.KEEP),
        (live_pod(phase="Pending"), True, PodStep.KEEP),
        (live_pod(), False, PodStep.KEEP),
        # an outdated pod: delete it first (its successor follows its deletion)
        (live_pod("old"), True, PodStep.REPLACE),
        (live_pod("old", "Failed"), True, PodStep.REPLACE),
        ({"metadata": {}, "status": {"phase": "Running"}}, True, PodStep.REPLACE),
        # an ended pod (evicted, failed, succeeded): delete it, then recreate it
        (live_pod(phase="Failed"), True, PodStep.RESTART),
        (live_pod(phase="Succeeded"), True, PodStep.RESTART),
        # a pod on its way out: never a second one beside it
        (live_pod(deleting=True), True, PodStep.WAIT),
        (live_pod("old", deleting=True), True, PodStep.WAIT),
        (live_pod(phase="Failed", deleting=True), True, PodStep.WAIT),
    ],
)
def test_pod_replacement_decision_table(
    live: dict[str, Any] | None, node_exists: bool, step: PodStep
) -> None:
    assert pod_step(live, DESIRED, node_exists=node_exists) is step


# -- readiness and conditions --------------------------------------------------------


def pod(
    phase: str = "Running", ready: str = "True", hash_: str = "new", *, deleting: bool = False
) -> dict[str, Any]:
    body = live_pod(hash_, phase, deleting=deleting)
    body["status"]["conditions"] = [{"type": "Ready", "status": ready}]
    return body


@pytest.mark.parametrize(
    ("live", "ready", "detail"),
    [
        (None, False, "does not exist"),
        (pod(deleting=True), False, "terminating"),
        (pod(hash_="old"), False, "outdated"),
        (pod("Pending", "False"), False, "Pending"),
        (pod("Failed", "False"), False, "ended (Failed"),
        (pod("Running", "False"), False, "not Ready"),
        (pod(), True, ""),
    ],
)
def test_pod_state_says_what_is_missing(
    live: dict[str, Any] | None, ready: bool, detail: str
) -> None:
    state = pod_state("mavros", live, "new")
    assert state.ready is ready
    assert detail in state.detail
    assert bool(state.detail) is not ready


def test_pod_state_names_a_container_that_cannot_start() -> None:
    live = pod("Pending", "False")
    live["status"]["containerStatuses"] = [
        {"state": {"waiting": {"reason": "ImagePullBackOff", "message": "no such image"}}}
    ]
    assert "ImagePullBackOff: no such image" in pod_state("mavros", live, "new").detail


def test_components_condition_names_each_component_that_is_not_ready() -> None:
    status, reason, message = components_condition(
        [ComponentState("mavros", True, ""), ComponentState("vicon", False, "0/1 pods available")]
    )
    assert (status, reason) == ("False", "ComponentsNotReady")
    assert message == "component vicon not ready: 0/1 pods available"
    assert components_condition([])[:2] == ("True", "NoComponents")
    assert components_condition([], blocked="node taken")[:2] == ("False", "WaitingForNode")


AT = datetime(2024, 1, 1, tzinfo=UTC)


cond = partial(support_cond, at=AT)


def test_ready_reports_the_first_false_detail_before_unknowns() -> None:
    conditions = [
        cond("NodeBound", "True"),
        cond("ComponentsReady", "Unknown", "Waiting"),
        cond("AutopilotsHealthy", "False", "ActiveUnhealthy", "fc1 ERROR"),
    ]
    status, reason, message = ready_condition(conditions)
    assert (status, reason) == ("False", "ActiveUnhealthy")
    assert "AutopilotsHealthy: fc1 ERROR" in message


def test_ready_is_unknown_when_only_unknowns_fail_and_true_when_all_pass() -> None:
    assert ready_condition([cond("NodeBound", "True"), cond("AgentConnected", "Unknown")])[0] == (
        "Unknown"
    )
    assert ready_condition([cond("NodeBound", "True"), cond("ComponentsReady", "True")]) == (
        "True",
        "VehicleReady",
        "node bound, components ready",
    )


def test_conditions_keep_other_writers_types_and_transition_times() -> None:
    previous = set_condition(
        [cond("AutopilotsHealthy", "True")],
        type="NodeBound",
        status="True",
        reason="NodeLabeled",
        at=AT,
    )
    after = vehicle_conditions(
        previous,
        binding=NodeBinding(True, "NodeLabeled", "ok"),
        components=("True", "NoComponents", ""),
        generation=3,
    )
    node_bound = find_condition(after, "NodeBound")
    assert node_bound is not None
    assert node_bound.last_transition_time == AT
    assert node_bound.observed_generation == 3
    assert find_condition(after, "AutopilotsHealthy") == previous[0]
    ready = find_condition(after, "Ready")
    assert ready is not None and ready.status == "True"


@pytest.mark.parametrize(
    ("before", "after", "news"),
    [
        # a first appearance: news only when a detail condition is False from the start
        (None, ("NodeBound", "True"), False),
        (None, ("NodeBound", "False"), True),
        (None, ("AgentConnected", "Unknown"), False),
        (None, ("Ready", "False"), False),  # rolling out, or NodeBound's own Event says why
        (None, ("Ready", "True"), False),
        # a change of status is always news; the same status never is
        (("Ready", "False"), ("Ready", "True"), True),
        (("Ready", "True"), ("Ready", "False"), True),
        (("NodeBound", "True"), ("NodeBound", "Unknown"), True),
        (("NodeBound", "False"), ("NodeBound", "False"), False),
        # a type that is not chosen for Events never is
        (None, ("ComponentsReady", "False"), False),
        (("ComponentsReady", "False"), ("ComponentsReady", "True"), False),
    ],
)
def test_which_condition_changes_are_worth_an_event(
    before: tuple[str, str] | None, after: tuple[str, str], news: bool
) -> None:
    old = [cond(*before)] if before else []
    new = [cond(*after)]
    assert [c.type for c in transitions(old, new, ["Ready", "NodeBound", "AgentConnected"])] == (
        [after[0]] if news else []
    )


def test_losing_the_node_makes_ready_false_with_the_node_reason() -> None:
    after = vehicle_conditions(
        [],
        binding=NodeBinding(False, "NodeNotFound", "node node-a does not exist"),
        components=components_condition([], blocked=None),
        generation=1,
    )
    ready = find_condition(after, "Ready")
    assert ready is not None
    assert (ready.status, ready.reason) == ("False", "NodeNotFound")


def test_status_patch_sends_only_changed_owned_fields_with_nulls_for_removals() -> None:
    old = VehicleStatus.model_validate(
        {
            "nodeName": "node-a",
            "fcuUrl": "udp://a",
            "managedLabels": ["x"],
            "activeAutopilot": "fc1",
        }
    )
    new = VehicleStatus.model_validate(
        {"fcuUrl": "udp://a", "managedLabels": [], "activeAutopilot": "fc2"}
    )
    fields = ("nodeName", "fcuUrl", "managedLabels")
    assert status_patch(old, new, fields) == {"nodeName": None, "managedLabels": []}
    assert status_patch(new, new, fields) is None


# -- releasing a gone Vehicle's pods -------------------------------------------------------


def _node(ready: str) -> dict[str, Any]:
    return {"status": {"conditions": [{"type": "Ready", "status": ready}]}}


@pytest.mark.parametrize(
    ("terminating", "node", "step"),
    [
        # pod terminating  its node           → step
        (False, _node("True"), ReleaseStep.DELETE),
        (True, _node("True"), ReleaseStep.LEAVE),  # its kubelet is finishing it
        (False, _node("False"), ReleaseStep.DELETE),  # NotReady, yet heard from
        (False, _node("Unknown"), ReleaseStep.FORCE),  # unreachable: never confirmed
        (True, _node("Unknown"), ReleaseStep.FORCE),  # the garbage collector was first
        (False, None, ReleaseStep.FORCE),  # no node left to confirm it
    ],
)
def test_release_step_decision_table(
    *, terminating: bool, node: dict[str, Any] | None, step: ReleaseStep
) -> None:
    pod = manifests(None)["mavros"]
    if terminating:
        pod["metadata"]["deletionTimestamp"] = "2026-05-01T12:00:00Z"
    assert release_step(pod, node) is step
    assert pod_node(pod) == "node-a"
