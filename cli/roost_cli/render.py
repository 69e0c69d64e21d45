"""Rich tables for the rows in :mod:`roost_cli.tables`.

Only presentation lives here: which colour a health level gets, how the active
autopilot is marked. Colour is a hint, never the only signal, so piping the output
(no colour) keeps every fact: the active autopilot carries a ``▸`` marker as well.
"""

from __future__ import annotations

from collections.abc import Sequence

from rich.table import Table
from rich.text import Text

from roost_cli.tables import EventRow, FleetRow, MissionRow

LEVEL_STYLES = {
    "OK": "green",
    "WARN": "yellow",
    "STARTING": "cyan",
    "ERROR": "bold red",
    "STALE": "magenta",
}
READY_STYLES = {"True": "green", "False": "red", "Unknown": "yellow"}
PHASE_STYLES = {
    "Pending": "dim",
    "Preflight": "cyan",
    "Running": "green",
    "Succeeded": "bold green",
    "Failed": "bold red",
    "Aborting": "yellow",
    "Aborted": "red",
}
ACTIVE_MARKER = "▸"
MESSAGE_LIMIT = 140
"""Longer messages are cut (``kubectl describe`` has the whole text): a live view must fit."""


def _shorten(message: str) -> str:
    return message if len(message) <= MESSAGE_LIMIT else message[: MESSAGE_LIMIT - 1] + "…"


def health_text(row: FleetRow) -> Text:
    """The HEALTH cell: each autopilot with its level, the active one marked and bold."""
    text = Text()
    for index, cell in enumerate(row.autopilots):
        if index:
            text.append(" · ", style="dim")
        marker = ACTIVE_MARKER if cell.active else ""
        text.append(f"{marker}{cell.name} ", style="bold" if cell.active else "")
        text.append(cell.level, style=LEVEL_STYLES.get(cell.level, "dim"))
        if cell.reason:
            text.append(f" ({cell.reason})", style="dim")
        if cell.params:
            text.append(f" [params {cell.params}]", style="yellow")
        if cell.fence:
            held = cell.fence.startswith("held ")
            text.append(f" [fence {cell.fence}]", style="green" if held else "yellow")
    return text if row.autopilots else Text("-", style="dim")


def _ready_text(row: FleetRow) -> Text:
    text = Text(row.ready, style=READY_STYLES.get(row.ready, "dim"))
    if row.ready_reason:
        text.append(f" {row.ready_reason}", style="dim")
    if row.flight_hold:
        text.append(f"\nin flight: {row.flight_hold}", style="yellow")
    return text


def _mission_text(value: str) -> Text:
    name, _, phase = value.partition(" ")
    text = Text(name)
    if phase:
        text.append(f" {phase}", style=PHASE_STYLES.get(phase, ""))
    return text


def fleet_table(rows: Sequence[FleetRow], title: str | None = "Roost fleet") -> Table:
    """``roost status``: vehicle, node, Ready, active autopilot, health, mission, failover."""
    table = Table(title=title, title_justify="left", expand=False, header_style="bold")
    table.add_column("VEHICLE", style="bold cyan", no_wrap=True)
    table.add_column("NODE", no_wrap=True)
    table.add_column("READY")
    table.add_column("ACTIVE", no_wrap=True)
    table.add_column("HEALTH")
    table.add_column("MISSION")
    table.add_column("LAST FAILOVER")
    for row in rows:
        failover = Text(row.last_failover, style="yellow" if row.failover_detail else "dim")
        if row.failover_detail:
            failover.append(f"\n{row.failover_detail}", style="dim")
        table.add_row(
            row.vehicle,
            row.node,
            _ready_text(row),
            Text(row.active, style="bold" if row.active != "-" else "dim"),
            health_text(row),
            _mission_text(row.mission),
            failover,
        )
    if not rows:
        table.caption = "no Vehicles yet: kubectl apply -f examples/vehicle-sim-px4.yaml"
    return table


def missions_table(rows: Sequence[MissionRow]) -> Table:
    """``roost missions``: phase, assignment, per-vehicle state, and why."""
    table = Table(title="Roost missions", title_justify="left", header_style="bold")
    table.add_column("MISSION", style="bold cyan", no_wrap=True)
    table.add_column("PHASE", no_wrap=True)
    table.add_column("ASSIGNED", justify="right", no_wrap=True)
    table.add_column("VEHICLES")
    table.add_column("DEGRADED", no_wrap=True)
    table.add_column("STARTED", justify="right", no_wrap=True)
    table.add_column("MESSAGE")
    for row in rows:
        phase = Text(row.phase, style=PHASE_STYLES.get(row.phase, ""))
        if row.abort and row.phase not in ("Aborting", "Aborted"):
            phase.append(" (abort requested)", style="yellow")
        table.add_row(
            row.name,
            phase,
            row.assigned,
            row.vehicles,
            Text(row.degraded, style="yellow" if row.degraded == "True" else "dim"),
            row.started,
            _shorten(row.message),
        )
    if not rows:
        table.caption = "no Missions yet: kubectl apply -f examples/mission.yaml"
    return table


def events_table(rows: Sequence[EventRow]) -> Table:
    """Recent Events about Roost objects: what the operator and the agents decided."""
    table = Table(title="Recent events", title_justify="left", header_style="bold", box=None)
    table.add_column("AGE", justify="right", no_wrap=True)
    table.add_column("TYPE", no_wrap=True)
    table.add_column("OBJECT", no_wrap=True)
    table.add_column("REASON", no_wrap=True)
    table.add_column("MESSAGE")
    for row in rows:
        table.add_row(
            row.age,
            Text(row.type, style="yellow" if row.type == "Warning" else "dim"),
            row.object,
            Text(row.reason, style="bold"),
            _shorten(row.message),
        )
    if not rows:
        table.caption = "no events yet"
    return table
