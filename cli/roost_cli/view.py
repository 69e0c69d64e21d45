"""The fleet view: one snapshot of vehicles, missions and events, or a live-refreshing one.

``roost status`` prints one snapshot; ``roost status --watch`` and the sandbox keep it on
screen with rich's ``Live``, re-reading the cluster every interval. A failed read (the API
server restarting, say) is shown in place of the tables and retried: a live view must not
die on one bad poll.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.panel import Panel
from rich.text import Text

from roost_cli import render, tables
from roost_cli.cluster import Fleet
from roost_cli.errors import CliError

DEFAULT_EVENTS = 8
MAX_EVENTS = 500
"""The most Events ``roost status --events`` shows: what one list call returns."""


@dataclass(frozen=True)
class Snapshot:
    """The rows of one read of the cluster."""

    fleet: list[tables.FleetRow]
    missions: list[tables.MissionRow]
    events: list[tables.EventRow]


def read(fleet: Fleet, events: int = DEFAULT_EVENTS) -> Snapshot:
    """Read vehicles, autopilots, missions (and events when ``events`` > 0) once."""
    now = datetime.now(UTC)
    missions = fleet.missions()
    return Snapshot(
        fleet=tables.fleet_rows(fleet.vehicles(), fleet.autopilots(), missions, now),
        missions=tables.mission_rows(missions, now),
        events=tables.event_rows(fleet.events(), now, events) if events > 0 else [],
    )


def renderable(snapshot: Snapshot, title: str, story: RenderableType | None = None) -> Group:
    """The fleet table, then ``story`` (if any), missions and events."""
    parts: list[RenderableType] = [render.fleet_table(snapshot.fleet, title=title)]
    if story is not None:
        parts.append(story)
    if snapshot.missions:
        parts.append(render.missions_table(snapshot.missions))
    if snapshot.events:
        parts.append(render.events_table(snapshot.events))
    return Group(*parts)


def title_for(fleet: Fleet) -> str:
    return f"Roost fleet · {fleet.server} ({fleet.target.source})"


def live(
    console: Console,
    fleet: Fleet,
    *,
    interval_s: float,
    events: int = DEFAULT_EVENTS,
    story: Callable[[], RenderableType | None] = lambda: None,
    stop: threading.Event | None = None,
) -> None:
    """Refresh the view every ``interval_s`` until ``stop`` is set or Ctrl-C.

    ``story`` is drawn right under the fleet table on every refresh, where it stays
    visible on a small terminal (the sandbox narrates its script there).
    """
    stop = stop or threading.Event()

    def frame() -> RenderableType:
        narration = story()
        try:
            return renderable(read(fleet, events), title_for(fleet), narration)
        except CliError as error:
            failed = Panel(Text(str(error), style="red"), title="cannot read the fleet")
            return Group(failed, narration) if narration is not None else failed

    with Live(frame(), console=console, refresh_per_second=4, transient=False) as screen:
        while not stop.wait(interval_s):
            screen.update(frame())
