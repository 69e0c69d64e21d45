"""Which vehicles a Mission may claim (roost_operator.missions.selection): label
selectors, preference order, availability and the claims that still count.

Every input is an API model built as the API server would return it
(:mod:`tests.support.missions`); the functions under test are pure: no mocks.
"""

from __future__ import annotations

from typing import Any

import pytest

from roost_api.meta import ObjectReference
from roost_api.mission import (
    LabelSelector,
    VehicleSelection,
)
from roost_operator.missions.selection import (
    availability,
    candidates,
    holding_missions,
    matches_selector,
    shortage_message,
)
from tests.support.missions import (
    ME,
    OTHER,
    vehicle,
)


@pytest.mark.parametrize(
    ("selector", "labels", "matches"),
    [
        ({"matchLabels": {"fleet": "a"}}, {"fleet": "a", "x": "y"}, True),
        ({"matchLabels": {"fleet": "a"}}, {"fleet": "b"}, False),
        (
            {"matchExpressions": [{"key": "k", "operator": "In", "values": ["1", "2"]}]},
            {"k": "2"},
            True,
        ),
        ({"matchExpressions": [{"key": "k", "operator": "In", "values": ["1"]}]}, {}, False),
        ({"matchExpressions": [{"key": "k", "operator": "NotIn", "values": ["1"]}]}, {}, True),
        (
            {"matchExpressions": [{"key": "k", "operator": "NotIn", "values": ["1"]}]},
            {"k": "1"},
            False,
        ),
        ({"matchExpressions": [{"key": "k", "operator": "Exists"}]}, {"k": ""}, True),
        ({"matchExpressions": [{"key": "k", "operator": "DoesNotExist"}]}, {"k": ""}, False),
        ({}, {"anything": "x"}, True),
    ],
)
def test_label_selectors_follow_kubernetes_semantics(
    selector: dict[str, Any], labels: dict[str, str], matches: bool
) -> None:
    assert matches_selector(labels, LabelSelector.model_validate(selector)) is matches


def test_named_vehicles_come_first_in_their_order_then_selector_matches_by_name() -> None:
    fleet = {v.name: v for v in [vehicle("c"), vehicle("a"), vehicle("b"), vehicle("z", labels={})]}
    selection = VehicleSelection.model_validate(
        {"names": ["z", "b", "ghost"], "selector": {"matchLabels": {"fleet": "a"}}, "count": 2}
    )
    assert candidates(selection, fleet) == ["z", "b", "a", "c"]


def test_availability_sorts_candidates_into_free_claimed_and_not_ready() -> None:
    fleet = {
        v.name: v
        for v in [
            vehicle("a"),
            vehicle("b", claimed_by=OTHER),
            vehicle("c", ready=False),
            vehicle("d", claimed_by=ObjectReference(namespace="gone", name="deleted")),
            vehicle("e", claimed_by=ME.reference),
            vehicle("f", deleting=True),
        ]
    }
    selection = VehicleSelection.model_validate(
        {"names": ["ghost"], "selector": {"matchLabels": {"fleet": "a"}}, "count": 5}
    )
    result = availability(selection, fleet, ME, frozenset({ME.key, "default/rival"}))
    assert result.free == ["a", "d"], "an orphaned claim (mission gone) counts as free"
    assert result.claimed_elsewhere == {"b": "default/rival"}
    assert set(result.not_ready) == {"c", "f"}
    assert result.unknown_names == ["ghost"]
    message = shortage_message(required=5, held=1, available=result)
    assert message.startswith("needs 5 vehicles, 3 available: 2 missing")
    assert "claimed by other missions (default/rival)" in message
    assert "ghost" in message


def test_claims_of_finished_missions_count_only_while_a_vehicle_is_landing() -> None:
    def body(name: str, status: dict[str, Any]) -> dict[str, Any]:
        return {"metadata": {"namespace": "ns", "name": name}, "status": status}

    landing = {"name": "a", "phase": "Aborting"}
    missions = [
        body("new", {}),
        body("running", {"phase": "Running"}),
        body("done", {"phase": "Succeeded", "vehicles": [{"name": "a", "phase": "Succeeded"}]}),
        body("failed-landing", {"phase": "Failed", "vehicles": [landing]}),
        body("aborted", {"phase": "Aborted"}),
    ]
    assert holding_missions(missions) == {"ns/new", "ns/running", "ns/failed-landing"}
