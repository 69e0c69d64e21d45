"""The reason value sets of every status condition and phase, owned by ``roost_api``.

Each reason must pass the Condition's CRD pattern (a reason the API server refuses would
lose the whole status write), be spelled once (no two members with one value), and the
composed reasons must stay inside the same pattern for every value they are built from.
"""

from __future__ import annotations

import re
from enum import StrEnum

import pytest

from roost_api.autopilot import (
    AutopilotConditionReason,
    CommandAction,
    FenceReason,
    ParametersReason,
    StandbyInStepReason,
)
from roost_api.commands import CommandOutcome
from roost_api.meta import Condition
from roost_api.mission import (
    MissionReason,
    MissionVehicleReason,
    abort_command_reason,
    failover_action_held_reason,
)
from roost_api.vehicle import FailoverGuard, VehicleConditionReason

REASONS: list[type[StrEnum]] = [
    AutopilotConditionReason,
    StandbyInStepReason,
    ParametersReason,
    FenceReason,
    VehicleConditionReason,
    MissionReason,
    MissionVehicleReason,
]
PATTERN = re.compile(Condition.model_fields["reason"].metadata[-1].pattern)


@pytest.mark.parametrize("enum", REASONS, ids=lambda e: e.__name__)
def test_every_reason_is_a_camel_case_identifier_spelled_once(enum: type[StrEnum]) -> None:
    values = [member.value for member in enum]
    assert len(values) == len(set(values))
    for value in values:
        assert PATTERN.match(value), value
        assert value[0].isupper(), value


def test_composed_reasons_fit_the_pattern_for_every_input() -> None:
    for guard in FailoverGuard:
        if guard is not FailoverGuard.ALLOWED:
            assert PATTERN.match(failover_action_held_reason(guard.value))
    for action in CommandAction:
        for outcome in CommandOutcome:
            assert PATTERN.match(abort_command_reason(action.value, outcome.value))
    assert failover_action_held_reason("Paused") == "FailoverActionPaused"
    assert abort_command_reason("SafetyRoutine", "Pending") == "SafetyRoutinePending"


def test_a_condition_built_from_an_enum_member_serialises_as_its_value() -> None:
    condition = Condition(
        type="Ready",
        status="True",
        reason=VehicleConditionReason.VEHICLE_READY,
        last_transition_time="2026-01-01T00:00:00Z",
    )
    assert condition.to_api()["reason"] == "VehicleReady"
