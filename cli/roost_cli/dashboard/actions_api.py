"""The dashboard's guarded actions: abort a Mission, e-stop vehicles — the CLI's semantics.

Each handler calls :mod:`roost_cli.actions`, exactly what ``roost abort`` and
``roost estop`` call, so a click means what the command means. What the dashboard adds is
the confirmation contract: the page shows a dialog listing every target, and the request
carries that list (``confirmed``). The server works the targets out again from the
cluster and acts only when they are the very ones the user confirmed; if the fleet
changed in between (a vehicle joined, a mission assigned another), it refuses (409) and
the page asks again with the new list. Nothing is ever done to a target nobody saw.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from roost_api.autopilot import CommandAction
from roost_cli import actions
from roost_cli.cluster import Fleet
from roost_cli.dashboard.model import FleetModel
from roost_cli.errors import CliError


class RefusedError(Exception):
    """A request the server will not carry out; ``status`` is the HTTP status."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


def _confirmed(body: dict[str, Any]) -> list[str]:
    confirmed = body.get("confirmed")
    if not isinstance(confirmed, list) or not all(isinstance(n, str) for n in confirmed):
        raise RefusedError("say which targets were confirmed: confirmed = [names]")
    return sorted(confirmed)


def _check(targets: list[str], confirmed: list[str]) -> None:
    if sorted(targets) != confirmed:
        raise RefusedError(
            f"the targets changed since you confirmed them: now {', '.join(sorted(targets))}"
            " — confirm again",
            status=409,
        )


def abort_targets(model: FleetModel, mission: str) -> tuple[str, str, list[str]]:
    """(namespace, name, vehicles it reaches) of ``namespace/name``."""
    namespace, name = actions.split_mission_ref(mission, "default")
    return namespace, name, sorted(model.mission_vehicles(namespace, name))


def abort(fleet: Fleet, model: FleetModel, body: dict[str, Any]) -> dict[str, Any]:
    """``roost abort``: set ``spec.abort`` on the Mission; the operator does the rest."""
    mission = body.get("mission")
    if not isinstance(mission, str):
        raise RefusedError("which mission? mission = NAMESPACE/NAME")
    try:
        namespace, name, vehicles = abort_targets(model, mission)
        _check([f"{namespace}/{name}", *vehicles], _confirmed(body))
        actions.request_abort(fleet, namespace, name)
    except CliError as error:
        raise RefusedError(str(error)) from None
    return {
        "mission": f"{namespace}/{name}",
        "vehicles": vehicles,
        "message": f"abort requested: the operator asks {len(vehicles)} vehicle(s) to run "
        "their safety routine",
    }


def estop(fleet: Fleet, model: FleetModel, body: dict[str, Any]) -> dict[str, Any]:
    """``roost estop``: force-disarm, then wait for every agent's acknowledgement."""
    vehicles = body.get("vehicles") or []
    everything = bool(body.get("all"))
    if not isinstance(vehicles, list) or not all(isinstance(v, str) for v in vehicles):
        raise RefusedError("vehicles must be a list of names")
    try:
        targets = actions.select_targets(
            actions.autopilots_by_vehicle(fleet.autopilots()), vehicles, everything
        )
        _check(list(targets), _confirmed(body))
        sent = actions.send_command(fleet, targets, CommandAction.EMERGENCY_STOP)
        acks = actions.await_acknowledgements(fleet, targets, sent)
    except CliError as error:
        raise RefusedError(str(error)) from None
    return {
        "vehicles": list(targets),
        "acknowledgements": [asdict(ack) for ack in acks],
        "executed": all(ack.result == "Executed" for ack in acks),
    }
