"""The safety routine on the new active autopilot, and the emergency stop.

After a failover the thesis held the vehicle for 3 s, then landed it. Roost does the
same with stack-correct encodings from :mod:`roost_mavlink`, and trusts nothing it has
not seen: a mode counts as entered only when the COMMAND_ACK accepted it AND a heartbeat
received after the request reports that ``custom_mode``. A heartbeat showing the mode is
enough on its own (the ack may be lost on a lossy link).

A hold that holds. The hold is one that needs no pilot input: PX4 AUTO.LOITER, ArduCopter
BRAKE with GUIDED (position hold at the stopping point) as second choice — never
ArduCopter LOITER, which follows the throttle stick and, with no radio, descends into the
ground (measured 2.45 m/s) while its mode reads "accepted". So a hold is confirmed by
telemetry, not by the mode: for :attr:`Timing.hold_confirm_s` the vehicle does not
descend faster than :attr:`Timing.hold_max_vspeed_mps` and stays within
:attr:`Timing.hold_band_m` below where the hold began (GLOBAL_POSITION_INT). Climbing is
not held against it: a hold entered during a climb brakes it (ArduCopter BRAKE entered
at 4.8 m while climbing rose to 5.5 m on real firmware), which endangers nothing. The watch goes
on for the whole hold; a hold that is not holding (or cannot be seen) escalates to the
final action at once, and says so (phase ``HoldFailed``). A final action of Hold cannot
be escalated to, so it becomes Land.

Landing. Landed is what the vehicle reports: EXTENDED_SYS_STATE ON_GROUND, a disarmed
heartbeat after the land order, or (ArduCopter, which reports MAV_STATE STANDBY once its
land detector fires, still armed) STANDBY in the land mode. A landing that has not ended
after :attr:`Timing.land_timeout_s` is reported (``LandTimedOut``, a warning) and ordered
again; a second timeout is a failure.

Retries follow the MAVLink command protocol: no ack or MAV_RESULT_TEMPORARILY_REJECTED
is retried a few times 0.3-0.5 s apart with ``confirmation`` incremented; DENIED,
UNSUPPORTED or FAILED is a refusal. A refused hold falls back to the next hold mode, then
to landing; a refused NAV_LAND falls back to DO_SET_MODE(LAND); a refused RTL to landing.

Crash consistency. Every step reports a :class:`Progress` (phase, the final action it is
heading for, when the hold and the landing began, in wall-clock seconds) which the agent
writes to its state file before going on; :meth:`SafetyRunner.resume` continues a
routine from such a record after an agent restart: a hold whose time has passed goes
straight to the final action, a landing in progress is confirmed, not restarted.

The routine runs on its own worker thread, after the bridge has switched; it can be
cancelled (a newer routine or an emergency stop supersedes it) and it never blocks the
decision loop. Everything it needs from the link is the small :class:`CommandLink`
protocol, so its decision table is unit-testable with a scripted autopilot.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

from roost_agent.health import Motion
from roost_api.autopilot_enums import FinalAction, SafetyRoutinePhase
from roost_api.core import Stack
from roost_api.plain import SafetyRoutine
from roost_mavlink import (
    FORCE_DISARM_MAGIC,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MavLandedState,
    MavResult,
    MavState,
    ModeIntent,
    custom_mode,
    hold_modes,
    intent_mode,
    mode_name,
    set_mode_params,
)

Params = tuple[float, float, float, float, float, float, float]
NO_PARAMS: Params = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

_REFUSALS = {MavResult.DENIED, MavResult.UNSUPPORTED, MavResult.FAILED}


class CommandLink(Protocol):
    """What the routine needs from an autopilot link (AutopilotLink implements it)."""

    name: str
    stack: Stack

    def command(
        self, command: int, params: Params, *, confirmation: int, timeout_s: float
    ) -> int | None:
        """Send COMMAND_LONG and return the COMMAND_ACK result, None when none came."""

    def heartbeat(self) -> tuple[int, int, float] | None:
        """(custom_mode, base_mode, received_at) of the last heartbeat."""

    def landed_state(self) -> int | None:
        """Last EXTENDED_SYS_STATE landed_state."""

    def system_status(self) -> int | None:
        """Last heartbeat MAV_STATE."""

    def motion(self) -> Motion | None:
        """Last altitude and vertical speed (GLOBAL_POSITION_INT)."""


@dataclass(frozen=True)
class Timing:
    """How patient the routine is; defaults follow the MAVLink health reference."""

    ack_timeout_s: float = 0.4
    retry_gap_s: float = 0.35
    attempts: int = 3
    mode_confirm_s: float = 1.5
    hold_confirm_s: float = 1.0  # telemetry window that confirms a hold
    hold_max_vspeed_mps: float = 0.5  # descent speed allowed while holding
    hold_band_m: float = 0.5  # altitude allowed below where the hold began
    hold_violation_s: float = 0.2  # a vertical speed beyond the limit must last this long
    telemetry_max_age_s: float = 0.5  # older GLOBAL_POSITION_INT is no evidence
    land_timeout_s: float = 90.0
    resume_wait_s: float = 5.0  # after a restart: wait this long to hear the autopilot
    poll_s: float = 0.02


Phase = SafetyRoutinePhase
"""Progress of a routine, as FailoverRecord.safetyRoutine shows it (the API's value set)."""


# Phases after which nothing is left to do (no resume after a restart).
TERMINAL_PHASES = frozenset(
    {Phase.LANDED, Phase.RETURNING, Phase.HELD, Phase.CANCELLED, Phase.FAILED, Phase.DISARMED}
)
# Phases worth a warning Event.
WARNING_PHASES = frozenset(
    {Phase.FAILED, Phase.HOLD_REFUSED, Phase.HOLD_FAILED, Phase.LAND_TIMED_OUT}
)


@dataclass(frozen=True)
class Progress:
    """Where a routine is, durable enough to resume from (wall-clock seconds)."""

    autopilot: str
    phase: Phase
    final_action: FinalAction
    hold_seconds: float
    hold_started: float | None = None
    land_started: float | None = None
    holds: bool = True  # False: a landing order (no hold first)


@dataclass(frozen=True)
class Outcome:
    """How a mode request ended."""

    confirmed: bool
    result: int | None  # last COMMAND_ACK result, None when none came
    attempts: int
    mode: str = ""

    def describe(self) -> str:
        """Short text for logs and events."""
        what = f"{self.mode} " if self.mode else ""
        if self.confirmed:
            return f"{what}confirmed after {self.attempts} attempt(s)"
        answer = "no ack" if self.result is None else f"MAV_RESULT {self.result}"
        return f"{what}not confirmed after {self.attempts} attempt(s) ({answer})"


@dataclass(frozen=True)
class HoldVerdict:
    """What telemetry says about a hold: holding, or why not."""

    holding: bool
    reason: str


def judge_hold(
    samples: list[Motion], reference_m: float, now: float, timing: Timing
) -> HoldVerdict | None:
    """Judge a hold from the GLOBAL_POSITION_INT samples seen since it began.

    Returns a failing verdict as soon as the altitude leaves the band below
    ``reference_m`` or the descent speed stays beyond the limit for
    ``hold_violation_s``, or when the newest sample is older than
    ``telemetry_max_age_s`` (no evidence); None while nothing speaks against the hold.
    """
    if not samples or now - samples[-1].at > timing.telemetry_max_age_s:
        age = "none received" if not samples else f"last {now - samples[-1].at:.1f} s ago"
        return HoldVerdict(False, f"no altitude telemetry ({age})")
    last = samples[-1]
    lost = reference_m - last.altitude_m
    if lost > timing.hold_band_m:
        return HoldVerdict(
            False, f"lost {lost:.2f} m of altitude (band {timing.hold_band_m:.2f} m)"
        )
    fast_since: float | None = None
    for sample in samples:
        if -sample.climb_mps > timing.hold_max_vspeed_mps:
            fast_since = sample.at if fast_since is None else fast_since
        else:
            fast_since = None
    if fast_since is not None and last.at - fast_since >= timing.hold_violation_s:
        return HoldVerdict(
            False,
            f"descending at {-last.climb_mps:.2f} m/s (limit {timing.hold_max_vspeed_mps:.2f} m/s)",
        )
    return None


Report = Callable[[Phase, str], None]
ProgressSink = Callable[[Progress], None]

DEFAULT_TIMING = Timing()


class SafetyRunner:
    """Runs the routine and the emergency stop against one :class:`CommandLink`."""

    def __init__(
        self,
        link: CommandLink,
        cancel: threading.Event,
        report: Report,
        timing: Timing = DEFAULT_TIMING,
        clock: Callable[[], float] = time.monotonic,
        *,
        progress: ProgressSink | None = None,
        wall: Callable[[], float] = time.time,
        hold_modes_override: tuple[str, ...] | None = None,
    ) -> None:
        self.link = link
        self.cancel = cancel
        self.report = report
        self.timing = timing
        self.clock = clock
        self.wall = wall
        self._progress_sink = progress
        self._hold_modes = hold_modes_override or hold_modes(link.stack)
        self._progress: Progress | None = None

    # -- building blocks ---------------------------------------------------------------

    def _mode_seen(self, expected: int, since: float) -> bool:
        beat = self.link.heartbeat()
        return beat is not None and beat[2] >= since and beat[0] == expected

    def _await(self, condition: Callable[[], bool], timeout_s: float) -> bool:
        deadline = self.clock() + timeout_s
        while not self.cancel.is_set():
            if condition():
                return True
            if self.clock() >= deadline:
                return False
            self.cancel.wait(self.timing.poll_s)
        return False

    def request(self, command: int, params: Params, expected_mode: int) -> Outcome:
        """Send ``command`` until the heartbeat shows ``expected_mode`` or it is refused."""
        result: int | None = None
        name = mode_name(self.link.stack, expected_mode)
        for attempt in range(self.timing.attempts):
            if self.cancel.is_set():
                return Outcome(False, result, attempt, name)
            sent_at = self.clock()
            result = self.link.command(
                command, params, confirmation=attempt, timeout_s=self.timing.ack_timeout_s
            )
            if result in _REFUSALS:
                return Outcome(self._mode_seen(expected_mode, sent_at), result, attempt + 1, name)
            if result == MavResult.ACCEPTED:
                seen = self._await(
                    functools.partial(self._mode_seen, expected_mode, sent_at),
                    self.timing.mode_confirm_s,
                )
                if seen:
                    return Outcome(True, result, attempt + 1, name)
            elif self._mode_seen(expected_mode, sent_at):
                return Outcome(True, result, attempt + 1, name)  # the ack got lost, the mode not
            self.cancel.wait(self.timing.retry_gap_s)
        return Outcome(False, result, self.timing.attempts, name)

    def set_mode(self, name: str) -> Outcome:
        """DO_SET_MODE to the named mode of this link's stack, confirmed by heartbeat."""
        stack = self.link.stack
        return self.request(
            MAV_CMD_DO_SET_MODE, set_mode_params(stack, name), custom_mode(stack, name)
        )

    def hold(self) -> Outcome:
        """Enter the first hold mode the autopilot accepts (ArduCopter: BRAKE, GUIDED)."""
        outcome = Outcome(False, None, 0)
        for name in self._hold_modes:
            outcome = self.set_mode(name)
            if outcome.confirmed or self.cancel.is_set():
                return outcome
        return outcome

    def land(self) -> Outcome:
        """MAV_CMD_NAV_LAND, falling back to DO_SET_MODE(LAND) when refused."""
        stack = self.link.stack
        land_mode = custom_mode(stack, intent_mode(stack, ModeIntent.LAND))
        outcome = self.request(MAV_CMD_NAV_LAND, NO_PARAMS, land_mode)
        if outcome.confirmed or self.cancel.is_set():
            return outcome
        return self.set_mode(intent_mode(stack, ModeIntent.LAND))

    def return_to_launch(self) -> Outcome:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH, confirmed by the RTL mode in the heartbeat."""
        stack = self.link.stack
        rtl_mode = custom_mode(stack, intent_mode(stack, ModeIntent.RETURN_TO_LAUNCH))
        return self.request(MAV_CMD_NAV_RETURN_TO_LAUNCH, NO_PARAMS, rtl_mode)

    def landed(self, since: float) -> str | None:
        """How the vehicle says it is on the ground (None while it does not)."""
        if self.link.landed_state() == MavLandedState.ON_GROUND:
            return "landed state ON_GROUND"
        beat = self.link.heartbeat()
        if beat is None or beat[2] < since:
            return None
        if not beat[1] & MAV_MODE_FLAG_SAFETY_ARMED:
            return "disarmed"
        stack = self.link.stack
        in_land_mode = beat[0] == custom_mode(stack, intent_mode(stack, ModeIntent.LAND))
        if (
            stack is Stack.ARDUPILOT
            and in_land_mode
            and self.link.system_status() == MavState.STANDBY
        ):
            return "MAV_STATE STANDBY in LAND (land detector)"
        return None

    # -- progress ----------------------------------------------------------------------

    def _note(
        self,
        phase: Phase,
        message: str,
        *,
        hold_started: float | None = None,
        land_started: float | None = None,
    ) -> None:
        """Record progress durably (through the sink), then report the phase."""
        if self._progress is not None:
            progress = replace(self._progress, phase=phase)
            if hold_started is not None:
                progress = replace(progress, hold_started=hold_started)
            if land_started is not None:
                progress = replace(progress, land_started=land_started)
            self._progress = progress
            if self._progress_sink is not None:
                self._progress_sink(self._progress)
        self.report(phase, message)

    def _finish(self, phase: Phase, message: str) -> Phase:
        self._note(phase, message)
        return phase

    # -- the routines ------------------------------------------------------------------

    def run(self, routine: SafetyRoutine) -> Phase:
        """Hold for ``hold_seconds``, then the final action; returns the last phase."""
        final = FinalAction(routine.final_action)
        self._progress = Progress(self.link.name, Phase.STARTED, final, routine.hold_seconds)
        self._note(Phase.STARTED, f"{self.link.name}: safety routine started")
        return self._hold_then_final(routine.hold_seconds, final)

    def resume(self, progress: Progress) -> Phase:
        """Continue a routine recorded before an agent restart (see module docstring)."""
        self._progress = progress
        name = self.link.name
        final = FinalAction(progress.final_action)
        phase = Phase(progress.phase)
        if phase in TERMINAL_PHASES:
            return phase
        # A restarted agent's link has heard nothing yet; commands sent now would be lost.
        self._await(lambda: self.link.heartbeat() is not None, self.timing.resume_wait_s)
        if phase in (Phase.LANDING, Phase.LAND_TIMED_OUT):
            return self._confirm_landing(progress)
        if not progress.holds:
            self.report(Phase.STARTED, f"{name}: resuming the landing order")
            return self._land_and_watch()
        if phase in (Phase.HOLD_FAILED, Phase.HOLD_REFUSED):
            self.report(phase, f"{name}: resuming the escalation to {final.value}")
            return self._final(_escalation(final))
        started = progress.hold_started
        remaining = progress.hold_seconds - (self.wall() - started) if started else None
        if remaining is not None and remaining <= 0:
            self._note(
                Phase.HOLDING,
                f"{name}: the hold ended while the agent was down; {final.value} now",
            )
            return self._final(final)
        return self._hold_then_final(
            progress.hold_seconds if remaining is None else remaining, final
        )

    def _hold_then_final(self, hold_seconds: float, final: FinalAction) -> Phase:
        name = self.link.name
        held = self.hold()
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while requesting hold")
        if not held.confirmed:
            escalation = _escalation(final)
            self._note(
                Phase.HOLD_REFUSED,
                f"{name} hold {held.describe()}; {escalation.value} at once",
            )
            return self._final(escalation)
        hold_started = self.wall()
        if self._progress is not None and self._progress.hold_started is not None:
            hold_started = self._progress.hold_started  # resumed: the hold began earlier
        self._note(
            Phase.CONFIRMING_HOLD,
            f"{name} hold {held.describe()}; confirming by telemetry",
            hold_started=hold_started,
        )
        verdict = self._watch_hold(hold_seconds)
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while holding")
        if verdict is not None and not verdict.holding:
            escalation = _escalation(final)
            self._note(
                Phase.HOLD_FAILED,
                f"{name} not holding in {held.mode}: {verdict.reason}; {escalation.value} at once",
            )
            return self._final(escalation)
        return self._final(final)

    def _watch_hold(self, hold_seconds: float) -> HoldVerdict | None:
        """Watch the hold for ``hold_seconds`` (at least the confirmation window).

        Reports HOLDING once the confirmation window passed with nothing against it;
        returns the failing verdict as soon as there is one, else None.
        """
        name = self.link.name
        began = self.clock()
        first = self.link.motion()
        reference = first.altitude_m if first is not None else None
        samples: list[Motion] = []
        confirmed = False
        while not self.cancel.is_set():
            now = self.clock()
            motion = self.link.motion()
            if motion is not None and (not samples or motion.at > samples[-1].at):
                if reference is None:
                    reference = motion.altitude_m
                samples.append(motion)
                del samples[:-200]
            elapsed = now - began
            if samples or elapsed >= self.timing.telemetry_max_age_s:
                verdict = judge_hold(samples, reference or 0.0, now, self.timing)
                if verdict is not None:
                    return verdict
            if not confirmed and elapsed >= self.timing.hold_confirm_s:
                confirmed = True
                alt = samples[-1].altitude_m if samples else float("nan")
                self._note(
                    Phase.HOLDING,
                    f"{name} holding: altitude {alt:.2f} m within "
                    f"{self.timing.hold_band_m:.2f} m for {self.timing.hold_confirm_s:.1f} s",
                )
            if confirmed and elapsed >= hold_seconds:
                return None
            self.cancel.wait(self.timing.poll_s)
        return None

    def _final(self, final: FinalAction) -> Phase:
        name = self.link.name
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded before the final action")
        if final == FinalAction.HOLD:
            return self._finish(Phase.HELD, f"{name} stays in hold")
        if final == FinalAction.RETURN_TO_LAUNCH:
            rtl = self.return_to_launch()
            if rtl.confirmed:
                return self._finish(Phase.RETURNING, f"{name} returning: {rtl.describe()}")
            if self.cancel.is_set():
                return self._finish(Phase.CANCELLED, "superseded while requesting RTL")
            self.report(Phase.LANDING, f"{name} RTL {rtl.describe()}; landing instead")
        return self._land_and_watch()

    def land_now(self) -> Phase:
        """Land at once (no healthy standby) and watch for touchdown."""
        self._progress = Progress(self.link.name, Phase.STARTED, FinalAction.LAND, 0.0, holds=False)
        return self._land_and_watch()

    def _land_and_watch(self) -> Phase:
        name = self.link.name
        landing = self.land()
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while requesting land")
        if not landing.confirmed:
            return self._finish(Phase.FAILED, f"{name} land {landing.describe()}")
        started = self.wall()
        self._note(Phase.LANDING, f"{name} landing: {landing.describe()}", land_started=started)
        return self._watch_landing(self.clock() - self.timing.mode_confirm_s, retried=False)

    def _confirm_landing(self, progress: Progress) -> Phase:
        """After a restart: is it down, still landing, or no longer landing?"""
        name = self.link.name
        since = self.clock()
        stack = self.link.stack
        land_mode = custom_mode(stack, intent_mode(stack, ModeIntent.LAND))
        how = self.landed(0.0)
        if how is not None:
            return self._finish(Phase.LANDED, f"{name} landed ({how}), confirmed after restart")
        beat = self.link.heartbeat()
        if beat is not None and beat[0] == land_mode:
            self.report(Phase.LANDING, f"{name} still landing after restart; watching")
            return self._watch_landing(since, retried=progress.phase == Phase.LAND_TIMED_OUT)
        self.report(Phase.LANDING, f"{name} not in its land mode after restart; landing again")
        return self._land_and_watch()

    def _watch_landing(self, since: float, *, retried: bool) -> Phase:
        name = self.link.name
        how: list[str] = []

        def down() -> bool:
            found = self.landed(since)
            if found is not None:
                how.append(found)
            return found is not None

        if self._await(down, self.timing.land_timeout_s):
            return self._finish(Phase.LANDED, f"{name} landed ({how[-1]})")
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while landing")
        motion = self.link.motion()
        where = "" if motion is None else f" at {motion.altitude_m:.1f} m"
        if retried:
            return self._finish(
                Phase.FAILED,
                f"{name} not landed{where} after two land orders "
                f"({self.timing.land_timeout_s:.0f} s each)",
            )
        self._note(
            Phase.LAND_TIMED_OUT,
            f"{name} not landed{where} after {self.timing.land_timeout_s:.0f} s; "
            "land ordered again",
        )
        landing = self.land()
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while requesting land")
        if not landing.confirmed:
            return self._finish(Phase.FAILED, f"{name} land {landing.describe()}")
        return self._watch_landing(self.clock() - self.timing.mode_confirm_s, retried=True)

    def force_disarm(self) -> Phase:
        """Emergency stop: COMPONENT_ARM_DISARM(0, 21196), confirmed by a disarmed heartbeat."""

        def disarmed_since(at: float) -> bool:
            beat = self.link.heartbeat()
            return beat is not None and beat[2] >= at and not beat[1] & MAV_MODE_FLAG_SAFETY_ARMED

        params: Params = (0.0, float(FORCE_DISARM_MAGIC), 0.0, 0.0, 0.0, 0.0, 0.0)
        result: int | None = None
        for attempt in range(self.timing.attempts):
            sent_at = self.clock()
            result = self.link.command(
                MAV_CMD_COMPONENT_ARM_DISARM,
                params,
                confirmation=attempt,
                timeout_s=self.timing.ack_timeout_s,
            )
            if self._await(functools.partial(disarmed_since, sent_at), self.timing.mode_confirm_s):
                return self._finish(Phase.DISARMED, f"{self.link.name} disarmed")
            if result in _REFUSALS:
                break
        answer = "no ack" if result is None else f"MAV_RESULT {result}"
        return self._finish(Phase.FAILED, f"{self.link.name} force disarm not confirmed ({answer})")


def _escalation(final: FinalAction) -> FinalAction:
    """The final action a failed hold escalates to: Hold cannot be it, Land is."""
    return FinalAction.LAND if final == FinalAction.HOLD else final
