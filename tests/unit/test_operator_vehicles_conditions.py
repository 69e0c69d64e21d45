"""A Vehicle's conditions (NodeBound, ComponentsReady, Ready) and which changes are worth
an Event, computed without a cluster."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from functools import partial

import pytest

from roost_api.meta import find_condition, set_condition
from roost_operator.vehicles.conditions import (
    NodeBinding,
    components_condition,
    ready_condition,
    transitions,
    vehicle_conditions,
)
from roost_operator.vehicles.pods import (
    ComponentState,
)
from tests.support.conditions import cond as support_cond


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
        at=AT + timedelta(minutes=1),
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
        at=AT,
    )
    ready = find_condition(after, "Ready")
    assert ready is not None
    assert (ready.status, ready.reason) == ("False", "NodeNotFound")
