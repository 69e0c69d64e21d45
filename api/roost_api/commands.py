"""Building the requests the cluster makes of a node agent (``RedundantAutopilot.spec.command``).

One place for the shape of a command and of the patch that delivers it, shared by the
operator (mission abort, failover policy) and the ``roost`` CLI (``roost estop``), so
both issue commands the agent treats the same way. Pure: no API calls here.

A command is executed at most once, identified by its ``id``; a new request therefore
always gets a fresh id, even when it repeats the previous action. The agent ignores a
command it first sees more than ``deadlineSeconds`` after ``issuedAt`` (e.g. after a
network partition), so an old e-stop never fires when a vehicle reconnects.
"""

from __future__ import annotations

import secrets
from datetime import datetime
from enum import StrEnum
from typing import Any

from roost_api.autopilot import AutopilotCommand, CommandAction, CommandResult
from roost_api.meta import now

DEFAULT_DEADLINE_SECONDS = 10


def new_command(
    action: CommandAction,
    *,
    target: str | None = None,
    deadline_seconds: int = DEFAULT_DEADLINE_SECONDS,
    issued_at: datetime | None = None,
    command_id: str | None = None,
) -> AutopilotCommand:
    """A command with a fresh unique id (action name, time and random suffix).

    ``target`` is required for ``Switch`` and refused for every other action, mirroring
    the CRD's CEL rule so a bad request fails here rather than at the API server.
    A caller that may repeat itself (an operator restarted between writing a command
    and recording it) passes a ``command_id`` derived from what the request is about,
    so the repeat carries the same id and the agent does not act twice.
    """
    action = CommandAction(action)
    if (action is CommandAction.SWITCH) != (target is not None):
        raise ValueError("a Switch command needs a target; other commands take none")
    at = issued_at or now()
    if command_id is None:
        command_id = f"{action.value.lower()}-{at:%Y%m%d%H%M%S}-{secrets.token_hex(4)}"
    return AutopilotCommand(
        id=command_id,
        action=action,
        target=target,
        issued_at=at,
        deadline_seconds=deadline_seconds,
    )


def command_patch(command: AutopilotCommand) -> dict[str, Any]:
    """The merge patch that sets ``spec.command`` on a RedundantAutopilot."""
    return {"spec": {"command": command.to_api()}}


class CommandOutcome(StrEnum):
    """Where a command the cluster wrote stands, as the RedundantAutopilot shows it."""

    PENDING = "Pending"
    """Still in ``spec.command``; the agent has not processed it yet."""
    EXECUTED = "Executed"
    REJECTED = "Rejected"
    EXPIRED = "Expired"
    """The agent saw it later than ``deadlineSeconds`` after ``issuedAt`` and ignored it."""
    SUPERSEDED = "Superseded"
    """Another request replaced it in ``spec.command`` before the agent processed it."""


def command_outcome(
    command: AutopilotCommand,
    spec_command: AutopilotCommand | None,
    last_command: CommandResult | None,
) -> CommandOutcome:
    """The outcome of ``command`` given the object's ``spec.command`` and ``status.lastCommand``.

    The agent's result (:class:`~roost_api.autopilot.CommandResultKind`, an enum the CRD
    enforces) is the outcome. Expired and Superseded requests never ran: a caller that
    still wants the effect issues a new command (with a new id).
    """
    if last_command is not None and last_command.id == command.id:
        return CommandOutcome(last_command.result)
    if spec_command is not None and spec_command.id == command.id:
        return CommandOutcome.PENDING
    return CommandOutcome.SUPERSEDED
