"""Carrying out what the arbiter decided: the bridge switch, the safety routine, landing
orders, the emergency stop and command results.

Why this module exists apart from the decision loop (:mod:`roost_agent.agent`): the loop
judges and steps the pure arbiter; this is what its actions do to the world. The switch
path stays local and immediate (bridge write, then the hub's route, with no logging,
network or disk before it); everything slow runs on :class:`SafetyWorker`, one job at a
time (a newer job supersedes an older one, nothing supersedes an emergency stop), so the
decision loop never waits for an autopilot to answer. Each step is made durable
(:mod:`roost_agent.state`) before it goes on, so a restarted agent resumes a routine
where it was.

:class:`Actions` is a part of :class:`roost_agent.agent.Agent` (its methods work on the
agent's state under its lock); it is kept here so the loop, its actions and spec changes
can each be read on their own.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

from roost_agent.arbiter import (
    Action,
    ArbiterState,
    CommandDone,
    Decision,
    ForceDisarm,
    LandInPlace,
    NoHealthyStandby,
    RunSafetyRoutine,
    SafetyPlan,
    SwitchBridge,
    Trigger,
)
from roost_agent.bridge import Bridge, BridgeError
from roost_agent.events import EventKind, FailoverEvent
from roost_agent.link import AutopilotLink
from roost_agent.parts import AgentParts, Running
from roost_agent.safety import (
    TERMINAL_PHASES,
    WARNING_PHASES,
    Phase,
    Progress,
    SafetyRunner,
    Timing,
)
from roost_agent.state import MAX_REMEMBERED_COMMANDS, SafetyProgress
from roost_api.autopilot_enums import CommandResultKind, FinalAction, SafetyRoutinePhase
from roost_api.plain import CommandResult, FailoverRecord

log = logging.getLogger(__name__)


@dataclass
class Job:
    """One unit of work for the safety worker."""

    title: str
    run: Callable[[threading.Event], None]
    emergency: bool = False
    cancel: threading.Event = field(default_factory=threading.Event)


class SafetyWorker:
    """Runs one job at a time. A new job cancels the running one and replaces a pending
    one, except that nothing but another emergency stop cancels or replaces an emergency
    stop."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._pending: Job | None = None
        self._current: Job | None = None
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="safety-worker", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, job: Job) -> None:
        with self._cond:
            current, pending = self._current, self._pending
            if current is not None and (job.emergency or not current.emergency):
                current.cancel.set()
            if pending is not None and pending.emergency and not job.emergency:
                log.warning("dropping %s: an emergency stop is pending", job.title)
                return
            self._pending = job
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stopping = True
            if self._current is not None:
                self._current.cancel.set()
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                job, self._pending = self._pending, None
                assert job is not None
                self._current = job
            try:
                job.run(job.cancel)
            except Exception:
                log.exception("%s failed", job.title)
            finally:
                with self._cond:
                    self._current = None


class Actions(AgentParts):
    """The agent's side that performs the arbiter's actions (see the module docstring)."""

    # What the actions touch of the agent besides its shared parts (set by Agent).
    _bridge: Bridge
    _timing: Timing
    _worker: SafetyWorker
    _failovers: deque[FailoverEvent]
    _last_command: CommandResult | None
    _pending: dict[str, Future[CommandResult]]

    def _execute(self, cfg: Running, decision: Decision) -> None:
        before = self._state
        self._state = decision.state
        for action in decision.actions:
            self._perform(cfg, before, action)
        after = self._state
        durable = (after.active, after.latched, after.failed_from, after.failover_count)
        if durable != (before.active, before.latched, before.failed_from, before.failover_count):
            self._persist()

    def _perform(self, cfg: Running, before: ArbiterState, action: Action) -> None:
        if isinstance(action, SwitchBridge):
            self._switch(cfg, before, action)
        elif isinstance(action, RunSafetyRoutine):
            self._start_routine(cfg, action.autopilot)
        elif isinstance(action, LandInPlace):
            self._start_landing(cfg, action)
        elif isinstance(action, NoHealthyStandby):
            self._emit(
                EventKind.NO_HEALTHY_STANDBY,
                "NoHealthyStandby",
                f"{action.reason}; pilot flies manually, no landing ordered",
                warning=True,
                autopilot=action.autopilot,
            )
        elif isinstance(action, ForceDisarm):
            self._emergency_stop(cfg, action)
        else:
            self._command_done(action)

    def _switch(self, cfg: Running, before: ArbiterState, action: SwitchBridge) -> None:
        hub = self._hub
        try:
            self._bridge.select(cfg.channels[action.to_autopilot])
            if hub is not None:  # the clients' route moves with the motors, same tick
                hub.set_active(action.to_autopilot)
        except BridgeError as exc:
            # The motors stay where they were: undo the decision, the next tick retries.
            self._state = replace(
                self._state,
                active=before.active,
                latched=before.latched,
                failed_from=before.failed_from,
                failover_count=before.failover_count,
            )
            self._emit(
                EventKind.BRIDGE_ERROR,
                "BridgeSwitchFailed",
                f"could not switch to {action.to_autopilot}: {exc}",
                warning=True,
                autopilot=action.to_autopilot,
            )
            return
        switched_at = self._clock()
        record = FailoverRecord(
            time=self._wall_clock().replace(microsecond=0),
            from_autopilot=action.from_autopilot,
            to_autopilot=action.to_autopilot,
            reason=action.reason,
            latency_ms=round((switched_at - action.detected_at) * 1000, 3),
            trigger=action.trigger,
            safety_routine=None
            if action.safety == SafetyPlan.NONE
            else SafetyRoutinePhase(action.safety.value),
            standby_in_step=action.in_step,
        )
        event = FailoverEvent(record, action.detected_at, switched_at, action.onset)
        with self._lock:
            self._last_failover = record
            self._failovers.append(event)
        if action.safety == SafetyPlan.RUN:
            self._start_routine(cfg, action.to_autopilot)
        if hub is not None:
            hub.aux_standby(action.to_autopilot)
        onset = event.onset_to_switch_ms
        timing = f"switched {event.latency_ms:.3f} ms after detection" + (
            f", {onset:.0f} ms after onset" if onset is not None else ""
        )
        reasons = {
            Trigger.AUTOMATIC: "FailedOver",
            Trigger.COMMAND: "SwitchedByCommand",
            Trigger.FAILBACK: "FailedBack",
        }
        self._emit(
            EventKind.FAILOVER,
            reasons[action.trigger],
            f"{action.from_autopilot} -> {action.to_autopilot}: {action.reason} ({timing})",
            warning=action.trigger == Trigger.AUTOMATIC,
            autopilot=action.to_autopilot,
            failover=event,
        )

    def _command_done(self, done: CommandDone) -> None:
        result = CommandResult(
            id=done.command_id,
            result=done.result,
            message=done.message,
            time=self._wall_clock().replace(microsecond=0),
        )
        with self._lock:
            self._processed[done.command_id] = result
            while len(self._processed) > MAX_REMEMBERED_COMMANDS:
                self._processed.popitem(last=False)
            self._last_command = result
            future = self._pending.pop(done.command_id, None)
        self._persist()
        if future is not None:
            future.set_result(result)
        self._emit(
            EventKind.COMMAND,
            f"Command{done.result.value}",
            f"{done.command_id}: {done.message}",
            warning=done.result != CommandResultKind.EXECUTED,
            command=result,
        )

    # -- safety jobs ---------------------------------------------------------------------

    def _reporter(self, autopilot: str) -> Callable[[Phase, str], None]:
        def report(phase: Phase, message: str) -> None:
            with self._lock:
                record = self._last_failover
                if record is not None and record.to_autopilot == autopilot:
                    self._last_failover = replace(record, safety_routine=phase)
            self._persist()
            self._emit(
                EventKind.SAFETY,
                f"SafetyRoutine{phase.value}",
                message,
                warning=phase in WARNING_PHASES,
                autopilot=autopilot,
            )

        return report

    def _runner(self, link: AutopilotLink, cancel: threading.Event) -> SafetyRunner:
        return SafetyRunner(
            link,
            cancel,
            self._reporter(link.name),
            self._timing,
            self._clock,
            progress=self._record_progress,
        )

    def _record_progress(self, progress: Progress) -> None:
        """Keep the routine's progress in the state file (written before it goes on)."""
        with self._lock:
            self._safety = SafetyProgress(
                autopilot=progress.autopilot,
                phase=progress.phase.value,
                final_action=progress.final_action,
                hold_seconds=progress.hold_seconds,
                hold_started=progress.hold_started,
                land_started=progress.land_started,
                holds=progress.holds,
            )

    def _start_routine(self, cfg: Running, autopilot: str) -> None:
        link = cfg.links[autopilot]
        routine = cfg.spec.failover_policy.safety_routine
        # Durable before the worker starts: an agent killed right after the switch still
        # finds the routine to run in its state file.
        self._record_progress(
            Progress(autopilot, Phase.STARTED, routine.final_action, routine.hold_seconds)
        )
        self._persist()

        def run(cancel: threading.Event) -> None:
            self._runner(link, cancel).run(routine)

        self._worker.submit(Job(f"safety routine on {autopilot}", run))

    def _resume_safety(self, cfg: Running) -> None:
        """After a restart: continue a safety routine or landing the last run left open."""
        saved = self._safety
        if saved is None or Phase(saved.phase) in TERMINAL_PHASES:
            return
        link = cfg.links.get(saved.autopilot)
        if link is None:
            return
        progress = Progress(
            saved.autopilot,
            Phase(saved.phase),
            saved.final_action,
            saved.hold_seconds,
            saved.hold_started,
            saved.land_started,
            saved.holds,
        )
        self._emit(
            EventKind.SAFETY,
            "SafetyRoutineResumed",
            f"{saved.autopilot}: resuming the safety routine from {saved.phase} after a restart",
            warning=True,
            autopilot=saved.autopilot,
        )

        def run(cancel: threading.Event) -> None:
            self._runner(link, cancel).resume(progress)

        self._worker.submit(Job(f"resumed safety routine on {saved.autopilot}", run))

    def _start_landing(self, cfg: Running, action: LandInPlace) -> None:
        self._emit(
            EventKind.LAND_ORDERED,
            "LandOrdered",
            f"{action.autopilot}: {action.reason}",
            warning=True,
            autopilot=action.autopilot,
        )
        link = cfg.links[action.autopilot]
        self._record_progress(
            Progress(action.autopilot, Phase.STARTED, FinalAction.LAND, 0.0, holds=False)
        )
        self._persist()

        def run(cancel: threading.Event) -> None:
            self._runner(link, cancel).land_now()

        self._worker.submit(Job(f"landing {action.autopilot}", run))

    def _emergency_stop(self, cfg: Running, action: ForceDisarm) -> None:
        self._emit(EventKind.EMERGENCY_STOP, "EmergencyStop", action.reason, warning=True)
        active = self._state.active
        order = sorted(action.autopilots, key=lambda n: n != active)
        links = [cfg.links[n] for n in order]

        def run(cancel: threading.Event) -> None:
            threads = [
                threading.Thread(target=self._runner(link, cancel).force_disarm, daemon=True)
                for link in links
            ]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()

        self._worker.submit(Job("emergency stop", run, emergency=True))
