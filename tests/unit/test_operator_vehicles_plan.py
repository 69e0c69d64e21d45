"""The Vehicle controller's whole decision (roost_operator.vehicles.plan), without a cluster.

Covers what the controller decides in one place: the node binding, which autopilot the
vehicle's workloads follow (with and without a RedundantAutopilot, with a fleet guard
holding a re-point back), the claim mirrored into status, how refusals of the API
server become conditions, and when a new Vehicle's first report may wait for its pods.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest

from roost_api.autopilot import RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.meta import ObjectReference, find_condition
from roost_api.vehicle import VehicleFailover, VehicleSpec, VehicleStatus
from roost_kube.errors import error_for_status
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.vehicles.manifests import DEFAULT_FCU_URL
from roost_operator.vehicles.placement import NodeClaim
from roost_operator.vehicles.plan import (
    Context,
    Observed,
    node_binding,
    plan_vehicle,
    relevant_autopilot,
)
from roost_operator.vehicles.pods import ComponentState, pod_state
from roost_operator.vehicles.status import (
    REFUSED_AUTOPILOT_LABEL,
    REFUSED_CONFIG,
    Applied,
    first_report_due,
    refusal_time,
    report,
)

NOW = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)
URL1, URL2 = "udp://127.0.0.1:14540", "udp://127.0.0.1:14641@"
CTX = Context(namespace="roost-system", guards=FleetGuards())


def node(ready: bool = True) -> dict[str, Any]:
    return {
        "metadata": {"name": "node-a", "resourceVersion": "1"},
        "status": {"conditions": [{"type": "Ready", "status": "True" if ready else "False"}]},
    }


LOST_AT = "2026-05-01T11:58:20Z"


def unreachable(*, condition: bool = True, taint: bool = True) -> dict[str, Any]:
    """node-a as the node controller leaves it when the kubelet's link is lost."""
    body = node()
    if condition:
        body["status"]["conditions"] = [
            {
                "type": "Ready",
                "status": "Unknown",
                "reason": "NodeStatusUnknown",
                "message": "Kubelet stopped posting node status.",
                "lastTransitionTime": LOST_AT,
            }
        ]
    if taint:
        key = "node.kubernetes.io/unreachable"
        body["spec"] = {"taints": [{"key": key, "effect": "NoExecute", "timeAdded": LOST_AT}]}
    return body


def ra_spec() -> RedundantAutopilotSpec:
    return RedundantAutopilotSpec.model_validate(
        {
            "vehicleName": "drone1",
            "primary": "fc1",
            "autopilots": [
                {"name": "fc1", "stack": "px4", "connection": URL1, "sysid": 1, "bridgeChannel": 0},
                {
                    "name": "fc2",
                    "stack": "px4",
                    "connection": "udp://127.0.0.1:14541",
                    "fcuUrl": URL2,
                    "sysid": 2,
                    "bridgeChannel": 1,
                },
            ],
        }
    )


def observed(**overrides: Any) -> Observed:
    base = Observed(
        name="drone1",
        uid="uid-1",
        generation=3,
        created="2026-05-01T10:00:00Z",
        annotations={},
        spec=VehicleSpec.model_validate({"nodeName": "node-a", "sysid": 12}),
        status=VehicleStatus(),
        autopilot_spec=None,
        autopilot_status=None,
        node=node(),
        node_claims=[],
        claimed_by=None,
        actions_elsewhere=0,
        now=NOW,
        context=CTX,
    )
    return replace(base, **overrides)


def with_agent(active: str, **status: Any) -> dict[str, Any]:
    return {
        "autopilot_spec": ra_spec(),
        "autopilot_status": RedundantAutopilotStatus.model_validate(
            {"activeAutopilot": active, "reportedAt": NOW, "nodeName": "node-a", **status}
        ),
    }


# -- node binding ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "reason", "bound"),
    [
        ({}, "NodeLabeled", True),
        ({"node": None}, "NodeNotFound", False),
        ({"node": node(ready=False)}, "NodeNotReady", False),
        ({"node": unreachable()}, "NodeUnreachable", False),
        ({"node": unreachable(taint=False)}, "NodeUnreachable", False),
        ({"node": unreachable(condition=False)}, "NodeUnreachable", False),
        ({"name": "d" * 64}, "InvalidVehicleName", False),
        (
            {"node_claims": [NodeClaim("older", "2026-05-01T09:00:00Z")]},
            "NodeClaimedByOtherVehicle",
            False,
        ),
        ({"node_claims": [NodeClaim("younger", "2026-05-01T11:00:00Z")]}, "NodeLabeled", True),
    ],
)
def test_node_binding_decision_table(
    overrides: dict[str, Any], reason: str, *, bound: bool
) -> None:
    binding = node_binding(observed(**overrides))
    assert (binding.reason, binding.bound) == (reason, bound)


def test_a_vehicle_that_cannot_have_its_node_labels_nothing_and_runs_nothing() -> None:
    plan = plan_vehicle(observed(node_claims=[NodeClaim("older", "2026-05-01T09:00:00Z")]))
    assert plan.node_state is None and plan.pods == {}
    assert plan.status.node_name is None and plan.status.managed_labels == []


def test_a_missing_node_still_gets_its_workloads_declared_and_the_controller_waits() -> None:
    plan = plan_vehicle(observed(node=None))
    assert plan.runs_workloads and "mavros" in plan.pods
    assert plan.node_state is None, "no node to label"


def test_an_unreachable_node_keeps_every_pod_and_says_since_when_in_ready() -> None:
    """A lost link changes nothing Roost runs on the vehicle: same pods (same hashes),
    the node keeps its labels; NodeBound and Ready say since when it is unreachable."""
    reachable = plan_vehicle(observed())
    lost = plan_vehicle(observed(node=unreachable()))
    assert lost.runs_workloads and lost.node_state == reachable.node_state
    assert lost.pods == reachable.pods
    status = report(lost, Applied(live={}, refused={}))
    bound = find_condition(status.conditions, "NodeBound")
    ready = find_condition(status.conditions, "Ready")
    assert bound is not None and ready is not None
    assert (bound.status, bound.reason) == ("False", "NodeUnreachable")
    assert bound.last_transition_time == datetime(2026, 5, 1, 11, 58, 20, tzinfo=UTC)
    assert f"unreachable since {LOST_AT}" in bound.message
    assert (ready.status, ready.reason) == ("False", "NodeUnreachable")
    assert f"unreachable since {LOST_AT}" in ready.message


# -- which autopilot mavros follows ------------------------------------------------------


def test_without_a_redundant_autopilot_a_real_vehicle_follows_its_serial_link() -> None:
    plan = plan_vehicle(observed())
    assert plan.fcu_url == DEFAULT_FCU_URL
    assert plan.failover is None and plan.status.active_autopilot is None


def test_the_first_pointing_follows_the_agents_active_autopilot() -> None:
    plan = plan_vehicle(observed(**with_agent("fc2")))
    assert plan.followed is not None and plan.followed.name == "fc2"
    assert plan.fcu_url == URL2 == plan.status.fcu_url
    assert plan.config_map["data"]["VEHICLE_FCU_URL"] == URL2


def test_a_failover_repoints_mavros_unless_a_guard_holds_it_back() -> None:
    followed_fc1 = VehicleStatus(fcu_url=URL1, failover=VehicleFailover(followed_autopilot="fc1"))
    moved = plan_vehicle(observed(status=followed_fc1, **with_agent("fc2")))
    assert moved.fcu_url == URL2 and moved.failover is not None and moved.failover.acting
    paused = replace(CTX, guards=FleetGuards(paused=True))
    held = plan_vehicle(replace(observed(status=followed_fc1, **with_agent("fc2")), context=paused))
    assert held.fcu_url == URL1, "the workloads keep following fc1"
    assert held.status.failover is not None and held.status.failover.blocked == "Paused"
    assert held.config_map["data"]["VEHICLE_FCU_URL"] == URL1


def test_the_agents_conditions_go_when_the_redundant_autopilot_goes() -> None:
    with_ra = plan_vehicle(observed(**with_agent("fc1")))
    kinds = {c.type for c in with_ra.status.conditions}
    assert {"AgentConnected", "AutopilotsHealthy"} <= kinds
    without = plan_vehicle(observed(status=with_ra.status))
    assert not {"AgentConnected", "AutopilotsHealthy"} & {c.type for c in without.status.conditions}


# -- claim mirror and the status written -------------------------------------------------


def test_the_mission_claim_is_mirrored_into_status() -> None:
    survey = ObjectReference(namespace="flights", name="survey")
    assert plan_vehicle(observed(claimed_by=survey)).status.claimed_by == survey
    released = VehicleStatus(claimed_by=survey)
    assert plan_vehicle(observed(status=released)).status.claimed_by is None


def test_report_folds_component_states_and_readiness_into_the_status() -> None:
    plan = plan_vehicle(observed())
    status = report(plan, Applied(live={}, refused={}))
    components = find_condition(status.conditions, "ComponentsReady")
    assert components is not None and components.status == "False"
    ready = find_condition(status.conditions, "Ready")
    assert ready is not None and ready.status == "False"
    assert status.observed_generation == 3


def test_refusals_become_conditions_that_say_what_to_change() -> None:
    plan = plan_vehicle(observed(**with_agent("fc1")))
    too_long = error_for_status(
        422, "PATCH", "/x", '{"message":"metadata.labels: must be no more than 63 bytes"}'
    )
    status = report(
        plan,
        Applied(live={}, refused={REFUSED_AUTOPILOT_LABEL: too_long, REFUSED_CONFIG: too_long}),
    )
    bound = find_condition(status.conditions, "NodeBound")
    assert bound is not None and bound.reason == "AutopilotLabelRefused"
    assert "at most 63 characters" in bound.message
    components = find_condition(status.conditions, "ComponentsReady")
    assert components is not None and components.reason == "ConfigRefused"
    assert "spec.config" in components.message
    when = refusal_time(status, {REFUSED_AUTOPILOT_LABEL: too_long})
    assert when == bound.last_transition_time, "the same refusal names the same Event"
    later = replace(observed(**with_agent("fc1")), now=NOW + timedelta(minutes=5))
    again = report(
        plan_vehicle(replace(later, status=status)),
        Applied(live={}, refused={REFUSED_AUTOPILOT_LABEL: too_long}),
    )
    assert refusal_time(again, {REFUSED_AUTOPILOT_LABEL: too_long}) == when


def test_agent_reports_that_only_tick_do_not_change_the_fingerprint() -> None:
    body = {"spec": {"vehicleName": "d"}, "status": {"reportedAt": "t1", "activeAutopilot": "fc1"}}
    later = {"spec": {"vehicleName": "d"}, "status": {"reportedAt": "t2", "activeAutopilot": "fc1"}}
    switched = {"spec": {"vehicleName": "d"}, "status": {"activeAutopilot": "fc2"}}
    assert relevant_autopilot(body) == relevant_autopilot(later)
    assert relevant_autopilot(body) != relevant_autopilot(switched)


# -- a new Vehicle's first report --------------------------------------------------------

HOLD = timedelta(seconds=5)
NEW = "2026-05-01T11:59:58Z"  # two seconds before NOW: inside the hold
STARTING = ComponentState("mavros", False, "its Pod is Pending", starting=True)
PULLING = ComponentState("mavros", False, "its Pod is Pending (ErrImagePull: no such image)")
READY = ComponentState("mavros", True, "")


def pending_pod(*waiting: str) -> dict[str, Any]:
    return {
        "metadata": {"name": "drone1-mavros"},
        "status": {
            "phase": "Pending",
            "containerStatuses": [{"state": {"waiting": {"reason": why}}} for why in waiting],
        },
    }


def first_report(
    states: list[ComponentState], hold: timedelta = HOLD, **overrides: Any
) -> datetime | None:
    """first_report_due of a Vehicle ``observed(**overrides)`` whose pods are ``states``."""
    obs = observed(
        **({"created": NEW, "context": replace(CTX, first_report_hold=hold)} | overrides)
    )
    plan = plan_vehicle(obs)
    status = report(plan, Applied(live={}, refused={}))
    return first_report_due(plan, status, states)


SURVEY = ObjectReference(namespace="flights", name="survey")


@pytest.mark.parametrize(
    ("case", "states", "overrides", "held"),
    [
        ("new, its pod only starting: held", [STARTING], {}, True),
        ("new, one pod Ready and one starting: held", [READY, STARTING], {}, True),
        ("new, every pod Ready already: written", [READY], {}, False),
        ("new, no components at all: written", [], {}, False),
        ("a pod waits for an image: written", [PULLING], {}, False),
        ("the node is missing: written", [STARTING], {"node": None}, False),
        ("the node is not Ready: written", [STARTING], {"node": node(ready=False)}, False),
        ("a status exists already: written", [STARTING], {"status": "written"}, False),
        (
            "created longer ago than the hold: written",
            [STARTING],
            {"created": "2026-05-01T11:59:55Z"},
            False,
        ),
        ("a RedundantAutopilot: written", [STARTING], with_agent("fc1"), False),
        ("a Mission's claim to mirror: written", [STARTING], {"claimed_by": SURVEY}, False),
        (
            "a creation time that does not parse: written",
            [STARTING],
            {"created": "yesterday"},
            False,
        ),
    ],
)
def test_first_report_due_decision_table(
    case: str, states: list[ComponentState], overrides: dict[str, Any], held: bool
) -> None:
    if overrides.get("status") == "written":
        earlier = report(plan_vehicle(observed()), Applied(live={}, refused={}))
        overrides = {"status": earlier}
    due = first_report(states, **overrides)
    assert (due is not None) is held, case
    if held:
        assert due == datetime(2026, 5, 1, 12, 0, 3, tzinfo=UTC), "creation + the hold"


def test_a_refused_config_is_written_at_once() -> None:
    obs = observed(created=NEW, context=replace(CTX, first_report_hold=HOLD))
    plan = plan_vehicle(obs)
    too_big = error_for_status(422, "PATCH", "/x", '{"message":"ConfigMap is too long"}')
    status = report(plan, Applied(live={}, refused={REFUSED_CONFIG: too_big}))
    assert first_report_due(plan, status, [STARTING]) is None


def test_no_hold_writes_every_first_report_at_once() -> None:
    assert first_report([STARTING], hold=timedelta(0)) is None


@pytest.mark.parametrize(
    ("waiting", "starting"),
    [
        ((), True),
        (("ContainerCreating",), True),
        (("PodInitializing", "ContainerCreating"), True),
        (("ImagePullBackOff",), False),
        (("ContainerCreating", "CreateContainerConfigError"), False),
    ],
)
def test_a_pending_pod_is_only_starting_while_its_containers_wait_for_their_start(
    waiting: tuple[str, ...], starting: bool
) -> None:
    state = pod_state("mavros", pending_pod(*waiting))
    assert not state.ready
    assert state.starting is starting


def test_an_ended_pod_is_not_starting() -> None:
    ended = {"metadata": {"name": "m"}, "status": {"phase": "Failed", "reason": "Evicted"}}
    assert not pod_state("mavros", ended).starting


# -- nothing changes under a vehicle in the air (roost_operator.vehicles.flight) ----------


def armed(*names: str, active: str = "fc1") -> dict[str, Any]:
    """The agent reporting ``names`` armed (the others disarmed)."""
    healths = [
        {"name": n, "level": "OK", "armed": n in names, "landedState": "InAir"}
        for n in ("fc1", "fc2")
    ]
    return with_agent(active, autopilots=healths)


def simulated(**status: Any) -> dict[str, Any]:
    return {
        "spec": VehicleSpec.model_validate(
            {"nodeName": "node-a", "sysid": 12, "simulation": {"stack": "px4"}}
        ),
        **status,
    }


@pytest.mark.parametrize(
    ("overrides", "holds", "budget", "reason"),
    [
        # (what the agent reports, ...) -> pods held, a budget, status.flightHold.reason
        ({}, False, False, None),  # no RedundantAutopilot: on the ground as far as we know
        (with_agent("fc1"), False, False, None),  # nobody said armed
        (armed(), False, False, None),
        (armed("fc2"), True, True, "autopilot fc2 is armed"),  # a standby armed counts
        (armed("fc1", "fc2"), True, True, "autopilot fc1, fc2 are armed"),
        ({**armed("fc1"), "node": None}, True, True, "autopilot fc1 is armed"),  # node gone
        ({**armed("fc1"), "name": "d" * 64}, False, False, None),  # runs nothing at all
    ],
)
def test_in_flight_decision_table(
    overrides: dict[str, Any], holds: bool, budget: bool, reason: str | None
) -> None:
    plan = plan_vehicle(observed(**overrides))
    assert plan.holds_pods is holds
    assert (plan.disruption_budget is not None) is budget
    hold = plan.status.flight_hold
    assert (hold.reason if hold else None) == reason
    if plan.disruption_budget is not None:
        assert hold is not None and hold.disruption_budget == "roost-vehicle-drone1-in-flight"
        assert plan.disruption_budget["metadata"]["name"] == hold.disruption_budget
        assert plan.disruption_budget["spec"]["maxUnavailable"] == 0
        assert plan.disruption_budget["spec"]["selector"]["matchLabels"] == {
            "app.kubernetes.io/managed-by": "roost",
            "roost.dev/vehicle": "drone1",
        }


def test_a_failover_consequence_is_not_held_in_the_air() -> None:
    followed_fc1 = VehicleStatus(fcu_url=URL1, failover=VehicleFailover(followed_autopilot="fc1"))
    plan = plan_vehicle(observed(status=followed_fc1, **armed("fc2", active="fc2")))
    assert plan.failover is not None and plan.failover.acting
    assert not plan.holds_pods  # mavros is re-pointed in flight
    assert plan.disruption_budget is not None  # but nothing is evicted


def test_in_the_air_an_outdated_pod_counts_as_it_runs_and_is_listed_as_deferred() -> None:
    plan = plan_vehicle(observed(**simulated(**armed("fc1"))))
    assert plan.pods, "a simulated vehicle has components"
    running = {"status": {"phase": "Running", "conditions": [{"type": "Ready", "status": "True"}]}}
    old = {"metadata": {"annotations": {"roost.dev/pod-hash": "old"}}, **running}
    live = {c: {**pod, **running} for c, pod in plan.pods.items()}
    live["mavros"] = old
    status = report(plan, Applied(live=live, refused={}))
    assert status.flight_hold is not None and status.flight_hold.deferred == ["mavros"]
    components = find_condition(status.conditions, "ComponentsReady")
    assert components is not None and components.status == "True"
    landed = plan_vehicle(observed(**simulated(**armed())))
    status = report(landed, Applied(live=live, refused={}))
    assert status.flight_hold is None
    components = find_condition(status.conditions, "ComponentsReady")
    assert components is not None and components.status == "False"  # now being replaced
