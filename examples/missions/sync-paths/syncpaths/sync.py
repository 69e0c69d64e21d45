"""The synchronisation rule, pure: a follower's schedule and the monitor's membership.

A vehicle's plan time runs ``now - start - offset``. Approaching task k, the setpoint
moves along the trajectory until plan time reaches the task's time, then stays on the
task's point until the vehicle is there (within ``arrive_radius_m``): its delay is
``d = arrival - (start + offset + t_k)``. It reports d and waits for every other live
vehicle's delay for task k; with ``D`` the largest, everyone leaves the task at
``start + offset + t_k + D`` (a vehicle waits ``w = D - d``) and adds ``D`` to its offset.
The next transit then takes the planned time again: the *corrected transit*
``arrival_k - arrival_(k-1) - wait_(k-1) - d_k`` (the paper's Table I) differs from the
plan only by how late a vehicle actually left, which this module records.

A vehicle that leaves (its mission workload stopped, e.g. after a failover with
``onFailover: AbortVehicle``) or falls silent is dropped from the members by the
monitor; nobody waits for its reports. ``max_wait_s`` bounds any wait regardless.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

from syncpaths.trajectory import Point, Task, setpoint


class Phase(StrEnum):
    APPROACHING = "Approaching"
    WAITING = "Waiting"
    DONE = "Done"


@dataclass(frozen=True)
class TaskRecord:
    """One row of the table: times in seconds from the mission start."""

    task: int
    delay_s: float
    wait_s: float
    arrival_s: float
    departure_s: float
    transit_s: float  # corrected transit from the previous task
    planned_transit_s: float


@dataclass
class Follower:
    """One vehicle's schedule; feed it the clock and the vehicle's position."""

    name: str
    tasks: Sequence[Task]
    start: float  # monotonic time of the mission start
    arrive_radius_m: float = 0.5
    max_wait_s: float = 60.0
    offset: float = 0.0
    task: int = 1
    phase: Phase = Phase.APPROACHING
    records: list[TaskRecord] = field(default_factory=list)
    _arrival: float | None = None
    _delay: float = 0.0
    _last_departure_s: float = 0.0
    _waited_since: float = 0.0

    def setpoint(self, now: float) -> Point:
        """Where the vehicle should be now."""
        if self.phase is Phase.DONE:
            return self.tasks[-1].point
        target = self.tasks[self.task]
        if self.phase is Phase.WAITING:
            return target.point
        return setpoint(self.tasks, min(now - self.start - self.offset, target.time_s))

    def planned_at(self, k: int) -> float:
        """Monotonic time task ``k`` is due under the current offset."""
        return self.start + self.offset + self.tasks[k].time_s

    def step(self, now: float, position: Point | None) -> float | None:
        """Advance; returns this vehicle's delay when it has just arrived at its task."""
        if self.phase is not Phase.APPROACHING or position is None:
            return None
        target = self.tasks[self.task]
        if now - self.start - self.offset < target.time_s:
            return None
        if math.dist(position, target.point) > self.arrive_radius_m:
            return None
        self._arrival = now
        self._delay = max(0.0, now - self.planned_at(self.task))
        self._waited_since = now
        self.phase = Phase.WAITING
        return self._delay

    def try_depart(self, now: float, delays: Mapping[str, float], members: Iterable[str]) -> bool:
        """Leave the task once every live member's delay is known (or ``max_wait_s``
        passed) and the slowest one's delay has elapsed. ``delays``: other vehicles'
        reports for this task."""
        if self.phase is not Phase.WAITING or self._arrival is None:
            return False
        waiting_for = [m for m in members if m != self.name and m not in delays]
        timed_out = now - self._waited_since >= self.max_wait_s
        if waiting_for and not timed_out:
            return False
        slowest = max([self._delay, *(delays[m] for m in delays if m != self.name)])
        leave_at = self.planned_at(self.task) + slowest
        if now < leave_at:
            return False
        arrival_s = self._arrival - self.start
        previous = self.records[-1] if self.records else None
        previous_arrival = previous.arrival_s if previous else self.tasks[self.task - 1].time_s
        previous_wait = previous.wait_s if previous else 0.0
        planned = self.tasks[self.task].time_s - self.tasks[self.task - 1].time_s
        self.records.append(
            TaskRecord(
                task=self.task,
                delay_s=self._delay,
                wait_s=now - self._arrival,
                arrival_s=arrival_s,
                departure_s=now - self.start,
                transit_s=arrival_s - previous_arrival - previous_wait - self._delay,
                planned_transit_s=planned,
            )
        )
        self.offset += slowest
        self._arrival = None
        if self.task + 1 >= len(self.tasks):
            self.phase = Phase.DONE
        else:
            self.task += 1
            self.phase = Phase.APPROACHING
        return True


@dataclass
class Membership:
    """The monitor's view of the live vehicles: heard within ``silent_after_s`` and not
    left."""

    silent_after_s: float = 3.0
    last_heard: dict[str, float] = field(default_factory=dict)
    left: set[str] = field(default_factory=set)

    def heard(self, vehicle: str, now: float) -> bool:
        """Record a message; True when ``vehicle`` is new (membership changed)."""
        if vehicle in self.left:
            return False
        new = vehicle not in self.last_heard
        self.last_heard[vehicle] = now
        return new

    def leave(self, vehicle: str) -> bool:
        """``vehicle`` leaves for good; True when it was a member."""
        was = vehicle in self.last_heard
        self.left.add(vehicle)
        self.last_heard.pop(vehicle, None)
        return was

    def expire(self, now: float) -> list[str]:
        """Drop the vehicles silent for too long; returns them."""
        gone = [v for v, at in self.last_heard.items() if now - at > self.silent_after_s]
        for vehicle in gone:
            self.leave(vehicle)
        return gone

    @property
    def members(self) -> list[str]:
        return sorted(self.last_heard)
