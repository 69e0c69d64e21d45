"""Timed trajectories: CSV files of tasks, and linear interpolation between them.

A trajectory file has one row per task, ``time_s,north_m,east_m,down_m`` (a header row
is allowed), in the local NED frame of the vehicle's home, times from the mission start,
increasing. Between two tasks the setpoint moves in a straight line at constant speed.
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

Point = tuple[float, float, float]


@dataclass(frozen=True)
class Task:
    """Be at ``point`` (north, east, down; metres) ``time_s`` after the start."""

    time_s: float
    point: Point


class TrajectoryError(ValueError):
    """A trajectory file that cannot be flown (says which row and why)."""


def parse(rows: Iterable[Sequence[str]], source: str = "trajectory") -> list[Task]:
    """Tasks from CSV rows; the first row may be a header."""
    tasks: list[Task] = []
    for number, row in enumerate(rows, start=1):
        if not row or not "".join(row).strip():
            continue
        try:
            values = [float(v) for v in row]
        except ValueError:
            if number == 1:
                continue  # the header
            raise TrajectoryError(f"{source} row {number}: not numbers: {row}") from None
        if len(values) != 4 or not all(math.isfinite(v) for v in values):
            raise TrajectoryError(f"{source} row {number}: want time_s,north_m,east_m,down_m")
        if tasks and values[0] <= tasks[-1].time_s:
            raise TrajectoryError(f"{source} row {number}: time {values[0]} does not increase")
        tasks.append(Task(values[0], (values[1], values[2], values[3])))
    if len(tasks) < 2:
        raise TrajectoryError(f"{source}: a trajectory needs at least two tasks")
    return tasks


def load(path: Path) -> list[Task]:
    with path.open(newline="") as f:
        return parse(csv.reader(f), str(path))


def setpoint(tasks: Sequence[Task], t: float) -> Point:
    """Where the plan is ``t`` seconds after the start (held at the ends)."""
    if t <= tasks[0].time_s:
        return tasks[0].point
    for before, after in itertools.pairwise(tasks):
        if t <= after.time_s:
            share = (t - before.time_s) / (after.time_s - before.time_s)
            return (
                before.point[0] + share * (after.point[0] - before.point[0]),
                before.point[1] + share * (after.point[1] - before.point[1]),
                before.point[2] + share * (after.point[2] - before.point[2]),
            )
    return tasks[-1].point
