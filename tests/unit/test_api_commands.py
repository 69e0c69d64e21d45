"""How the cluster reads the fate of a command it wrote to a RedundantAutopilot."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from pydantic import ValidationError

from roost_api.autopilot import CommandAction, CommandResult
from roost_api.commands import CommandOutcome, command_outcome, new_command

T0 = datetime(2026, 1, 1, tzinfo=UTC)


def _result(command_id: str, result: str) -> CommandResult:
    return CommandResult(id=command_id, result=result, time=T0)


def test_a_given_command_id_is_kept_so_a_repeated_request_is_the_same_request() -> None:
    first = new_command(CommandAction.SAFETY_ROUTINE, command_id="abort-x-1", issued_at=T0)
    again = new_command(CommandAction.SAFETY_ROUTINE, command_id="abort-x-1")
    assert first.id == again.id == "abort-x-1"
    assert (
        new_command(CommandAction.SAFETY_ROUTINE).id != new_command(CommandAction.SAFETY_ROUTINE).id
    )


def test_a_command_still_in_spec_and_not_reported_is_pending() -> None:
    cmd = new_command(CommandAction.SAFETY_ROUTINE, command_id="a-1", issued_at=T0)
    assert command_outcome(cmd, cmd, None) is CommandOutcome.PENDING
    assert command_outcome(cmd, cmd, _result("older", "Executed")) is CommandOutcome.PENDING


@pytest.mark.parametrize(
    ("result", "outcome"),
    [
        ("Executed", CommandOutcome.EXECUTED),
        ("Rejected", CommandOutcome.REJECTED),
        ("Expired", CommandOutcome.EXPIRED),
    ],
)
def test_the_agents_result_for_this_id_decides(result: str, outcome: CommandOutcome) -> None:
    cmd = new_command(CommandAction.EMERGENCY_STOP, command_id="e-1", issued_at=T0)
    other = new_command(CommandAction.SAFETY_ROUTINE, command_id="b-1", issued_at=T0)
    assert command_outcome(cmd, other, _result("e-1", result)) is outcome


def test_a_command_replaced_before_the_agent_saw_it_is_superseded() -> None:
    cmd = new_command(CommandAction.SAFETY_ROUTINE, command_id="a-1", issued_at=T0)
    other = new_command(CommandAction.SWITCH, target="fc2", issued_at=T0)
    assert command_outcome(cmd, other, None) is CommandOutcome.SUPERSEDED
    assert command_outcome(cmd, None, _result(other.id, "Executed")) is CommandOutcome.SUPERSEDED


def test_a_result_outside_the_contract_is_refused() -> None:
    """The value set is an enum in the API (and in the CRD): no agent can report another."""
    with pytest.raises(ValidationError, match="Executed"):
        _result("e-1", "SomethingNew")
