"""Node labels, taint and claims: NFD-style bookkeeping that never touches others' keys."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from roost_api.vehicle import VehicleSpec
from roost_api.wellknown import (
    ANNOTATION_MANAGED_LABELS,
    LABEL_SIMULATED,
    LABEL_STACK,
    LABEL_VEHICLE,
    LABEL_VEHICLE_CLASS,
    STARLING_LABEL_TYPE,
    TAINT_VEHICLE,
)
from roost_operator.vehicles.placement import (
    LINK_TOLERATIONS,
    NodeClaim,
    NodeState,
    claim_winner,
    desired_node_labels,
    managed_keys,
    managed_label_keys,
    node_reachability,
    node_readiness,
    place_on_vehicle,
    plan_node,
    vehicle_name_problem,
)


def spec(**overrides: object) -> VehicleSpec:
    return VehicleSpec.model_validate({"nodeName": "node-a", "sysid": 12, **overrides})


def node(
    labels: dict[str, str] | None = None,
    annotations: dict[str, str] | None = None,
    taints: list[dict[str, str]] | None = None,
) -> dict[str, Any]:
    return {
        "metadata": {
            "name": "node-a",
            "resourceVersion": "41",
            "labels": labels or {},
            "annotations": annotations or {},
        },
        "spec": {"taints": taints} if taints is not None else {},
    }


def apply_patch(obj: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """JSON merge patch (RFC 7386), as the API server applies it."""
    result = dict(obj)
    for key, value in patch.items():
        if value is None:
            result.pop(key, None)
        elif isinstance(value, dict) and isinstance(result.get(key), dict):
            result[key] = apply_patch(result[key], value)
        elif isinstance(value, dict):
            result[key] = apply_patch({}, value)
        else:
            result[key] = value
    return result


def converge(n: dict[str, Any], want: NodeState) -> dict[str, Any]:
    patch = plan_node(n, want)
    return n if patch is None else apply_patch(n, patch)


OTHER_TAINT = {"key": "dedicated", "value": "gpu", "effect": "NoExecute"}


def test_labels_of_a_simulated_vehicle_with_starling_compatibility() -> None:
    labels = desired_node_labels("drone1", spec(simulation={"stack": "ardupilot"}))
    assert labels[LABEL_VEHICLE] == "drone1"
    assert labels[LABEL_SIMULATED] == "true"
    assert labels[LABEL_STACK] == "ardupilot"
    assert labels[STARLING_LABEL_TYPE] == "vehicle"
    assert labels["starling.dev/vehicle-class"] == "rotary"
    assert labels["starling.dev/vehicle-type"] == "quadrotor"


def test_no_starling_labels_without_compatibility_and_no_stack_for_real_vehicles() -> None:
    labels = desired_node_labels("drone1", spec(starlingCompatibility=False))
    assert not any(k.startswith("starling.dev/") for k in labels)
    assert LABEL_STACK not in labels
    assert labels[LABEL_SIMULATED] == "false"


def test_binding_a_bare_node_sets_labels_taint_and_records_them_under_lock() -> None:
    bare = node(labels={"kubernetes.io/hostname": "node-a"}, taints=[OTHER_TAINT])
    patch = plan_node(bare, NodeState.of_vehicle("drone1", spec()))
    assert patch is not None
    assert patch["metadata"]["resourceVersion"] == "41"
    bound = apply_patch(bare, patch)
    assert bound["metadata"]["labels"]["kubernetes.io/hostname"] == "node-a"
    assert bound["metadata"]["labels"][LABEL_VEHICLE] == "drone1"
    assert bound["spec"]["taints"] == [
        OTHER_TAINT,
        {"key": TAINT_VEHICLE, "value": "drone1", "effect": "NoSchedule"},
    ]
    assert managed_keys(bound) == {*desired_node_labels("drone1", spec()), f"taint:{TAINT_VEHICLE}"}
    assert managed_label_keys(bound) == sorted(desired_node_labels("drone1", spec()))


def test_a_bound_node_needs_no_write() -> None:
    bound = converge(node(), NodeState.of_vehicle("drone1", spec()))
    assert plan_node(bound, NodeState.of_vehicle("drone1", spec())) is None


def test_releasing_removes_only_recorded_keys() -> None:
    others = {"team": "blue", "roost.dev/hand-set": "keep"}
    bound = converge(
        node(labels=dict(others), taints=[OTHER_TAINT]), NodeState.of_vehicle("drone1", spec())
    )
    released = converge(bound, NodeState.released())
    assert released["metadata"]["labels"] == others
    assert released["spec"]["taints"] == [OTHER_TAINT]
    assert ANNOTATION_MANAGED_LABELS not in released["metadata"]["annotations"]
    assert plan_node(released, NodeState.released()) is None


def test_releasing_a_node_roost_never_touched_changes_nothing() -> None:
    foreign = node(
        labels={LABEL_VEHICLE: "someone-elses"},
        taints=[{"key": TAINT_VEHICLE, "value": "x", "effect": "NoSchedule"}],
    )
    assert plan_node(foreign, NodeState.released()) is None


def test_spec_change_patches_only_the_changed_label_and_drops_the_unwanted_ones() -> None:
    bound = converge(node(), NodeState.of_vehicle("drone1", spec()))
    want = NodeState.of_vehicle(
        "drone1", spec(vehicleClass="fixed-wing", starlingCompatibility=False)
    )
    patch = plan_node(bound, want)
    assert patch is not None
    assert patch["metadata"]["labels"] == {
        LABEL_VEHICLE_CLASS: "fixed-wing",
        STARLING_LABEL_TYPE: None,
        "starling.dev/vehicle-class": None,
        "starling.dev/vehicle-type": None,
    }
    assert "spec" not in patch


def test_a_hand_removed_roost_label_is_put_back() -> None:
    bound = converge(node(), NodeState.of_vehicle("drone1", spec()))
    edited = {
        **bound,
        "metadata": {
            **bound["metadata"],
            "labels": {k: v for k, v in bound["metadata"]["labels"].items() if k != LABEL_VEHICLE},
        },
    }
    patch = plan_node(edited, NodeState.of_vehicle("drone1", spec()))
    assert patch is not None
    assert patch["metadata"]["labels"] == {LABEL_VEHICLE: "drone1"}


@given(
    others=st.dictionaries(
        st.sampled_from(["a", "b", "roost.dev/x", "starling.dev/y", LABEL_VEHICLE_CLASS]),
        st.sampled_from(["1", "2"]),
    ),
    vehicle_class=st.sampled_from(["rotary", "fixed-wing"]),
    compat=st.booleans(),
)
def test_bind_then_release_restores_every_label_roost_did_not_set(
    others: dict[str, str], vehicle_class: str, compat: bool
) -> None:
    start = node(labels=dict(others))
    want = NodeState.of_vehicle(
        "drone1", spec(vehicleClass=vehicle_class, starlingCompatibility=compat)
    )
    bound = converge(start, want)
    assert plan_node(bound, want) is None
    released = converge(bound, NodeState.released())
    taken = set(want.labels)
    assert {k: v for k, v in released["metadata"]["labels"].items()} == {
        k: v for k, v in others.items() if k not in taken
    }


def test_the_oldest_claim_wins_and_ties_go_by_name() -> None:
    a = NodeClaim("b-vehicle", "2024-01-01T00:00:00Z")
    b = NodeClaim("a-vehicle", "2024-01-02T00:00:00Z")
    c = NodeClaim("c-vehicle", "2024-01-01T00:00:00Z")
    assert claim_winner([b, a, c]) == a
    assert claim_winner([c, NodeClaim("a", "2024-01-01T00:00:00Z")]) == NodeClaim(
        "a", "2024-01-01T00:00:00Z"
    )
    assert claim_winner([]) is None


def test_placement_selects_the_vehicle_label_and_tolerates_only_its_taint() -> None:
    pod = place_on_vehicle(
        {"nodeSelector": {"arch": "arm64"}, "tolerations": [{"key": "other"}]}, "drone1"
    )
    assert pod["nodeSelector"] == {"arch": "arm64", LABEL_VEHICLE: "drone1"}
    assert pod["tolerations"] == [
        {"key": "other"},
        {"key": TAINT_VEHICLE, "operator": "Equal", "value": "drone1", "effect": "NoSchedule"},
        *LINK_TOLERATIONS,
    ]
    assert place_on_vehicle(pod, "drone1") == pod


def test_pods_on_a_vehicle_tolerate_a_lost_link_for_as_long_as_they_exist() -> None:
    """No tolerationSeconds: the taint manager never evicts them; a template's own
    toleration of a lost link (with a deadline) is replaced."""
    template = {
        "tolerations": [
            {
                "key": "node.kubernetes.io/unreachable",
                "operator": "Exists",
                "effect": "NoExecute",
                "tolerationSeconds": 300,
            }
        ]
    }
    lost_link = [
        t for t in place_on_vehicle(template, "drone1")["tolerations"] if t["effect"] == "NoExecute"
    ]
    assert {t["key"] for t in lost_link} == {
        "node.kubernetes.io/unreachable",
        "node.kubernetes.io/not-ready",
    }
    assert all(t["operator"] == "Exists" and "tolerationSeconds" not in t for t in lost_link)


@pytest.mark.parametrize(
    ("ready", "taints", "unreachable", "since"),
    [
        # Ready condition             taints                  → unreachable  since
        (("True", None), [], False, None),
        (("False", None), [], False, None),  # the kubelet's own NotReady: heard from
        (("Unknown", "2026-05-01T10:00:00Z"), [], True, "2026-05-01T10:00:00+00:00"),
        (
            None,
            [("node.kubernetes.io/unreachable", "2026-05-01T10:00:05Z")],
            True,
            "2026-05-01T10:00:05+00:00",
        ),
        (
            ("Unknown", "2026-05-01T10:00:00Z"),
            [("node.kubernetes.io/unreachable", "2026-05-01T10:00:05Z")],
            True,
            "2026-05-01T10:00:00+00:00",
        ),
        (("Unknown", None), [], True, None),
    ],
)
def test_node_reachability_decision_table(
    ready: tuple[str, str | None] | None,
    taints: list[tuple[str, str]],
    *,
    unreachable: bool,
    since: str | None,
) -> None:
    conditions = []
    if ready is not None:
        conditions.append({"type": "Ready", "status": ready[0], "lastTransitionTime": ready[1]})
    node = {
        "status": {"conditions": conditions},
        "spec": {"taints": [{"key": k, "effect": "NoExecute", "timeAdded": t} for k, t in taints]},
    }
    found = node_reachability(node)
    assert (found is not None) == unreachable
    if found is not None:
        assert (found.since.isoformat() if found.since else None) == since


def test_node_readiness_quotes_the_kubelet() -> None:
    ready = {"status": {"conditions": [{"type": "Ready", "status": "True"}]}}
    down = {
        "status": {
            "conditions": [
                {"type": "Ready", "status": "Unknown", "message": "Kubelet stopped posting"}
            ]
        }
    }
    assert node_readiness(ready) == (True, "")
    assert node_readiness(down) == (False, "Ready=Unknown: Kubelet stopped posting")
    assert node_readiness({})[0] is False


def test_names_too_long_for_a_label_value_are_reported() -> None:
    assert vehicle_name_problem("a" * 63) is None
    problem = vehicle_name_problem("a" * 64)
    assert problem is not None
    assert "64 characters" in problem
