"""The sandbox's script: take off when the mission runs, then break an autopilot on cue.

Runs in a background thread beside the live view and narrates what it does (and what the
cluster does in answer) through :class:`Script`, which the view draws under the tables:

1. wait for the Mission to be Running, then take every vehicle off (kwok only pretends to
   run the onboard pod, so the director stands in for the mission's controller);
2. wait until the fault vehicle's agent reports its active autopilot and the Vehicle is
   Ready, let the fleet fly
   for ``fault_after_s``, then inject the fault on that active autopilot;
3. wait for the agent's record of the failover and the operator's reaction (Events,
   Vehicle and Mission status) and report them.

It only reads the cluster and talks to simulators; it starts no processes (those must be
started on the main thread, see :mod:`.processes`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from pydantic import ValidationError
from rich.console import Group, RenderableType
from rich.text import Text

from roost_api.autopilot import FailoverRecord, RedundantAutopilotStatus, SafetyRoutinePhase
from roost_api.meta import now
from roost_api.mission import MissionPhase, MissionStatus
from roost_cli.cluster import Fleet
from roost_cli.errors import CliError
from roost_cli.sandbox import plan, sims, state
from roost_cli.tables import format_latency

TAKEOFF_WAIT_S = 90.0
AGENT_WAIT_S = 60.0
VEHICLE_READY_WAIT_S = 600.0
"""The fault waits for its Vehicle to be Ready (a failover of a vehicle that never was
is no demonstration); 25 vehicles on two cores take minutes to get there."""
FAILOVER_WAIT_S = 60.0
SAFETY_ROUTINE_WAIT_S = 60.0
POLL_S = 0.5
DEFAULT_FAULT = "silence"
FAULT_STORY = {
    "silence": "stops sending MAVLink (a dead flight controller)",
    "freeze": "keeps streaming the same frozen values (a hung main loop)",
    "sensor": "reports a failed gyro",
    "state": "reports MAV_STATE CRITICAL",
    "reboot": "reboots in flight",
}


class Script:
    """What the sandbox tells the user under the live view: its plan and what happened."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lines: list[tuple[str, str]] = []

    def say(self, message: str, style: str = "") -> None:
        with self._lock:
            self._lines.append((message, style))

    def warn(self, message: str) -> None:
        """Say it in red, once (repeats of the same warning are dropped)."""
        self.once(message, "bold red")

    def once(self, message: str, style: str = "") -> None:
        """Say it unless it was said already (with this style)."""
        with self._lock:
            if (message, style) not in self._lines:
                self._lines.append((message, style))

    def lines(self) -> list[tuple[str, str]]:
        """Every (message, style) so far, oldest first."""
        with self._lock:
            return list(self._lines)

    def renderable(self, last: int = 8) -> RenderableType | None:
        lines = self.lines()[-last:]
        if not lines:
            return None
        return Group(*(Text(message, style=style) for message, style in lines))


def _parse_ra_status(obj: Mapping[str, Any]) -> RedundantAutopilotStatus | None:
    try:
        return RedundantAutopilotStatus.model_validate(obj.get("status") or {})
    except ValidationError:
        return None


def failover_since(obj: Mapping[str, Any], since: datetime) -> FailoverRecord | None:
    """The RedundantAutopilot's last failover if it happened at or after ``since``.

    Kubernetes times have whole seconds, so ``since`` is compared truncated the same way.
    """
    status = _parse_ra_status(obj)
    record = status.last_failover if status else None
    if record is None or record.time < since.replace(microsecond=0):
        return None
    return record


def active_autopilot(obj: Mapping[str, Any]) -> str | None:
    """The autopilot the agent reports as driving the motors (None before it reports)."""
    status = _parse_ra_status(obj)
    return status.active_autopilot if status else None


def vehicle_ready(obj: Mapping[str, Any]) -> bool:
    """Whether a Vehicle's ``Ready`` condition is True."""
    conditions = (obj.get("status") or {}).get("conditions") or []
    return any(c.get("type") == "Ready" and c.get("status") == "True" for c in conditions)


def routine_done(phase: str | None) -> bool:
    """True once the safety routine has finished or was skipped (a pilot in manual mode)."""
    return phase in _FINAL_PHASES


_FINAL_PHASES = frozenset(p.value for p in SafetyRoutinePhase if p.final)


def mission_phase(obj: Mapping[str, Any]) -> str:
    try:
        return str(MissionStatus.model_validate(obj.get("status") or {}).phase)
    except ValidationError:
        return MissionPhase.PENDING.value


@dataclass(frozen=True)
class Cue:
    """The fault to inject: on which vehicle, what kind, after how long in the air."""

    vehicle: str
    kind: str = DEFAULT_FAULT
    after_s: float = 15.0


class Director(threading.Thread):
    """Runs the script once; :meth:`stop` ends it early (the sandbox is shutting down)."""

    def __init__(
        self,
        fleet_factory: Callable[[], Fleet],
        recorded: state.SandboxState,
        script: Script,
        cue: Cue | None,
    ) -> None:
        super().__init__(name="sandbox-director", daemon=True)
        self._fleet_factory = fleet_factory
        self._recorded = recorded
        self._script = script
        self._cue = cue
        self._stopping = threading.Event()

    def stop(self) -> None:
        self._stopping.set()

    def run(self) -> None:
        try:
            fleet = self._fleet_factory()
            self._take_off(fleet)
            if self._cue is not None:
                self._break_an_autopilot(fleet, self._cue)
        except CliError as error:
            self._script.warn(str(error))
        except _StoppedError:
            return

    # ---- steps -------------------------------------------------------------------------
    def _wait(self, what: Callable[[], bool], timeout_s: float) -> bool:
        """Poll ``what`` until true (True) or ``timeout_s`` passes (False).

        An API server too busy to answer one poll (a big sandbox on two cores) is asked
        again at the next; only the timeout ends the wait.
        """
        deadline = time.monotonic() + timeout_s
        while not self._answers(what):
            if time.monotonic() > deadline:
                return False
            if self._stopping.wait(POLL_S):
                raise _StoppedError
        return True

    def _answers(self, what: Callable[[], bool]) -> bool:
        try:
            return what()
        except CliError as error:
            self._script.once(f"(retrying) {error}", "dim")
            return False

    def _mission(self, fleet: Fleet) -> dict[str, Any] | None:
        for mission in fleet.missions(plan.MISSION_NAMESPACE):
            if mission.get("metadata", {}).get("name") == plan.MISSION_NAME:
                return mission
        return None

    def _take_off(self, fleet: Fleet) -> None:
        name = f"{plan.MISSION_NAMESPACE}/{plan.MISSION_NAME}"
        self._script.say(f"Waiting for Mission {name} to start…", "dim")

        def started() -> bool:
            mission = self._mission(fleet)
            return (
                mission is not None
                and mission_phase(mission) != MissionPhase.PENDING
                and (mission_phase(mission) != MissionPhase.PREFLIGHT)
            )

        if self._wait(started, TAKEOFF_WAIT_S):
            mission = self._mission(fleet)
            phase = mission_phase(mission) if mission else "missing"
            self._script.say(f"Mission {name} is {phase}: the fleet takes off.", "bold")
        else:
            self._script.warn(
                f"Mission {name} has not started after {TAKEOFF_WAIT_S:.0f} s "
                "(`roost missions` says why); taking off anyway."
            )
        for vehicle in self._recorded.vehicles:
            sims.fly(vehicle)

    def _break_an_autopilot(self, fleet: Fleet, cue: Cue) -> None:
        ra_name = cue.vehicle  # the sandbox names each RedundantAutopilot after its vehicle
        reported: list[str] = []

        def agent_reports() -> bool:
            active = active_autopilot(fleet.autopilot(ra_name))
            if active:
                reported.append(active)
            return bool(active)

        if not self._wait(agent_reports, AGENT_WAIT_S):
            self._script.warn(
                f"the agent of {cue.vehicle} has not reported an active autopilot after "
                f"{AGENT_WAIT_S:.0f} s; see its log in the sandbox's logs directory. "
                "Injecting the fault on the primary anyway."
            )

        def vehicle_is_ready() -> bool:
            return any(
                v.get("metadata", {}).get("name") == cue.vehicle and vehicle_ready(v)
                for v in fleet.vehicles()
            )

        if not self._wait(vehicle_is_ready, VEHICLE_READY_WAIT_S):
            self._script.warn(
                f"Vehicle {cue.vehicle} is not Ready after {VEHICLE_READY_WAIT_S:.0f} s "
                "(`roost status` says why); breaking it anyway."
            )
        vehicle = self._recorded.vehicle(cue.vehicle)
        assert vehicle is not None, "the cue names a sandbox vehicle"
        target = reported[-1] if reported else vehicle.autopilots[0].name
        self._script.say(
            f"In {cue.after_s:.0f} s: fault '{cue.kind}' on {cue.vehicle}/{target}.", "yellow"
        )
        if self._stopping.wait(cue.after_s):
            raise _StoppedError
        injected_at = now()
        sims.control(self._recorded, cue.vehicle, target, sims.fault_message(cue.kind, None))
        story = FAULT_STORY.get(cue.kind, "is faulty")
        self._script.say(
            f"💥 {cue.vehicle}/{target} {story}. Watch {cue.vehicle} fail over.", "bold yellow"
        )
        records: list[FailoverRecord] = []

        def failed_over() -> bool:
            record = failover_since(fleet.autopilot(ra_name), injected_at)
            if record is not None:
                records.append(record)
            return record is not None

        if not self._wait(failed_over, FAILOVER_WAIT_S):
            self._script.warn(
                f"no failover recorded on {cue.vehicle} within {FAILOVER_WAIT_S:.0f} s of the "
                "fault; see the agent's log in the sandbox's logs directory."
            )
            return
        record = records[-1]
        self._script.say(
            f"✓ {cue.vehicle} failed over {record.from_autopilot} → {record.to_autopilot} in "
            f"{format_latency(record.latency_ms)} ({record.reason}); the safety routine holds "
            f"on {record.to_autopilot}, then lands.",
            "bold green",
        )

        def routine_finished() -> bool:
            latest = failover_since(fleet.autopilot(ra_name), injected_at)
            if latest is not None:
                records.append(latest)
            return latest is not None and routine_done(latest.safety_routine)

        finished = self._wait(routine_finished, SAFETY_ROUTINE_WAIT_S)
        outcome = records[-1].safety_routine or "not reported"
        self._script.say(
            f"{'✓' if finished else '…'} safety routine on {record.to_autopilot}: {outcome}. "
            f"`kubectl get events` and `kubectl describe redundantautopilot {ra_name}` show "
            "the details.",
            "bold green" if finished else "yellow",
        )
        self._script.say(
            f"Clear the fault with `roost fault {cue.vehicle} {target} clear`; Ctrl-C stops "
            "the sandbox.",
            "dim",
        )


class _StoppedError(Exception):
    """The sandbox is shutting down: end the script quietly."""
