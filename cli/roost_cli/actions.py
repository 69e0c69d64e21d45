"""What ``roost abort`` and ``roost estop`` ask of the cluster, and how they confirm it.

Both only write spec fields (``Mission.spec.abort``, ``RedundantAutopilot.spec.command``);
the operator and the node agents do the work, exactly as if the user had used kubectl.
``estop`` then waits for each agent's acknowledgement (``status.lastCommand`` carrying
the command's id), because an e-stop nobody executed must be visible at once.

The pure parts (finding a vehicle's RedundantAutopilot, reading a mission reference,
judging an acknowledgement) are separate functions so they are tested without a cluster.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from roost_api.autopilot import (
    AutopilotCommand,
    CommandAction,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.commands import CommandOutcome, command_outcome, command_patch, new_command
from roost_cli.cluster import Fleet
from roost_cli.errors import CliError

ACK_TIMEOUT_S = 10.0
ACK_POLL_S = 0.25


def split_mission_ref(ref: str, default_namespace: str) -> tuple[str, str]:
    """``name`` or ``namespace/name`` → (namespace, name)."""
    namespace, sep, name = ref.rpartition("/")
    if sep and (not namespace or not name):
        raise CliError(f"mission {ref!r}: write NAME or NAMESPACE/NAME")
    return (namespace or default_namespace), name


def autopilots_by_vehicle(autopilots: Iterable[Mapping[str, Any]]) -> dict[str, str]:
    """Vehicle name → name of its RedundantAutopilot.

    Admission makes them 1:1 and equal (``metadata.name == spec.vehicleName``); reading
    ``spec.vehicleName`` keeps objects created before that rule mapped to their vehicle.
    """
    result: dict[str, str] = {}
    for ra in autopilots:
        name = str(ra.get("metadata", {}).get("name", ""))
        vehicle = str((ra.get("spec") or {}).get("vehicleName") or name)
        result[vehicle] = name
    return result


def select_targets(
    by_vehicle: Mapping[str, str], vehicles: Sequence[str], everything: bool
) -> dict[str, str]:
    """The (vehicle → RedundantAutopilot) pairs an e-stop addresses.

    Exactly one of ``vehicles`` and ``everything`` must be given; naming a vehicle that
    has no RedundantAutopilot is an error rather than a silent skip.
    """
    if everything == bool(vehicles):
        raise CliError("say which vehicles to stop: --vehicle NAME (repeatable) or --all")
    if everything:
        if not by_vehicle:
            raise CliError("no RedundantAutopilots in this cluster: nothing to stop")
        return dict(sorted(by_vehicle.items()))
    unknown = [v for v in vehicles if v not in by_vehicle]
    if unknown:
        known = ", ".join(sorted(by_vehicle)) or "none"
        raise CliError(
            f"no RedundantAutopilot for vehicle {', '.join(unknown)} (vehicles with "
            f"autopilots: {known}); `roost status` lists the fleet"
        )
    return {v: by_vehicle[v] for v in vehicles}


@dataclass(frozen=True)
class Acknowledgement:
    """How one agent answered a command (or that it has not yet)."""

    vehicle: str
    autopilot: str
    command_id: str
    result: str
    """A :class:`~roost_api.commands.CommandOutcome` (Executed, Rejected, Expired,
    Superseded), or ``NoAnswer`` when the agent did not answer in time."""
    message: str


def acknowledgement(
    vehicle: str, autopilot: Mapping[str, Any], command: AutopilotCommand
) -> Acknowledgement | None:
    """How the agent answered ``command`` on this RedundantAutopilot, None while pending.

    The outcome is :func:`roost_api.commands.command_outcome`'s, so a command another
    request replaced before the agent saw it reads ``Superseded``, exactly as the
    operator reads it.
    """
    try:
        spec = RedundantAutopilotSpec.model_validate(autopilot.get("spec") or {})
        status = RedundantAutopilotStatus.model_validate(autopilot.get("status") or {})
    except ValidationError:
        return None
    outcome = command_outcome(command, spec.command, status.last_command)
    if outcome is CommandOutcome.PENDING:
        return None
    last = status.last_command
    message = last.message if last is not None and last.id == command.id else ""
    name = str(autopilot.get("metadata", {}).get("name", ""))
    return Acknowledgement(vehicle, name, command.id, outcome.value, message)


def request_abort(fleet: Fleet, namespace: str, name: str) -> dict[str, Any]:
    """Set ``spec.abort`` on a Mission (the CRD refuses to unset it)."""
    return fleet.patch_mission(namespace, name, {"spec": {"abort": True}})


def send_command(
    fleet: Fleet, targets: Mapping[str, str], action: CommandAction
) -> dict[str, AutopilotCommand]:
    """Write one fresh command per vehicle; returns vehicle → command sent."""
    sent: dict[str, AutopilotCommand] = {}
    for vehicle, autopilot in targets.items():
        command = new_command(action)
        fleet.patch_autopilot(autopilot, command_patch(command))
        sent[vehicle] = command
    return sent


def await_acknowledgements(
    fleet: Fleet,
    targets: Mapping[str, str],
    sent: Mapping[str, AutopilotCommand],
    timeout_s: float = ACK_TIMEOUT_S,
) -> list[Acknowledgement]:
    """Poll until every agent answered or ``timeout_s`` passed; silent ones are NoAnswer."""
    answers: dict[str, Acknowledgement] = {}
    deadline = time.monotonic() + timeout_s
    while True:
        for vehicle, autopilot in targets.items():
            if vehicle not in answers:
                ack = acknowledgement(vehicle, fleet.autopilot(autopilot), sent[vehicle])
                if ack is not None:
                    answers[vehicle] = ack
        if len(answers) == len(targets) or time.monotonic() > deadline:
            break
        time.sleep(ACK_POLL_S)
    return [
        answers.get(vehicle)
        or Acknowledgement(
            vehicle,
            autopilot,
            sent[vehicle].id,
            "NoAnswer",
            f"the agent did not answer within {timeout_s:.0f} s: is roost-agent running "
            "on the vehicle's node and connected to the API server?",
        )
        for vehicle, autopilot in targets.items()
    ]
