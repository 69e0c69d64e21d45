"""The safety routine on the new active autopilot, and the emergency stop.

After a failover the thesis held the vehicle for 3 s, then landed it. Roost does the
same with stack-correct encodings from :mod:`roost_mavlink` (PX4 AUTO.LOITER, ArduCopter
LOITER with BRAKE as second choice), and trusts nothing it has not seen confirmed: a
mode counts as entered only when the COMMAND_ACK accepted it AND a heartbeat received
after the request reports that ``custom_mode``. A heartbeat showing the mode is enough
on its own (the ack may be lost on a lossy link).

Retries follow the MAVLink command protocol: no ack or MAV_RESULT_TEMPORARILY_REJECTED
is retried a few times 0.3-0.5 s apart with ``confirmation`` incremented; DENIED,
UNSUPPORTED or FAILED is a refusal. A refused hold falls back to landing; a refused
NAV_LAND falls back to DO_SET_MODE(LAND); a refused RTL falls back to landing.

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
from dataclasses import dataclass
from typing import Protocol

from roost_api.autopilot import FinalAction, SafetyRoutine, SafetyRoutinePhase
from roost_api.meta import Stack
from roost_mavlink import (
    FORCE_DISARM_MAGIC,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_MODE_FLAG_SAFETY_ARMED,
    LandedState,
    MavResult,
    ModeIntent,
    custom_mode,
    intent_mode,
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


@dataclass(frozen=True)
class Timing:
    """How patient the routine is; defaults follow the MAVLink health reference."""

    ack_timeout_s: float = 0.4
    retry_gap_s: float = 0.35
    attempts: int = 3
    mode_confirm_s: float = 1.5
    landed_watch_s: float = 120.0
    poll_s: float = 0.02


Phase = SafetyRoutinePhase
"""Progress of a routine, as FailoverRecord.safetyRoutine shows it (the API's value set)."""


@dataclass(frozen=True)
class Outcome:
    """How a mode request ended."""

    confirmed: bool
    result: int | None  # last COMMAND_ACK result, None when none came
    attempts: int

    def describe(self) -> str:
        """Short text for logs and events."""
        if self.confirmed:
            return f"confirmed after {self.attempts} attempt(s)"
        answer = "no ack" if self.result is None else f"MAV_RESULT {self.result}"
        return f"not confirmed after {self.attempts} attempt(s) ({answer})"


Report = Callable[[Phase, str], None]

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
    ) -> None:
        self.link = link
        self.cancel = cancel
        self.report = report
        self.timing = timing
        self.clock = clock

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
        for attempt in range(self.timing.attempts):
            if self.cancel.is_set():
                return Outcome(False, result, attempt)
            sent_at = self.clock()
            result = self.link.command(
                command, params, confirmation=attempt, timeout_s=self.timing.ack_timeout_s
            )
            if result in _REFUSALS:
                return Outcome(self._mode_seen(expected_mode, sent_at), result, attempt + 1)
            if result == MavResult.ACCEPTED:
                seen = self._await(
                    functools.partial(self._mode_seen, expected_mode, sent_at),
                    self.timing.mode_confirm_s,
                )
                if seen:
                    return Outcome(True, result, attempt + 1)
            elif self._mode_seen(expected_mode, sent_at):
                return Outcome(True, result, attempt + 1)  # the ack got lost, the mode did not
            self.cancel.wait(self.timing.retry_gap_s)
        return Outcome(False, result, self.timing.attempts)

    def set_mode(self, name: str) -> Outcome:
        """DO_SET_MODE to the named mode of this link's stack, confirmed by heartbeat."""
        stack = self.link.stack
        return self.request(
            MAV_CMD_DO_SET_MODE, set_mode_params(stack, name), custom_mode(stack, name)
        )

    def hold(self) -> Outcome:
        """Enter the stack's hold mode (ArduCopter: LOITER, else BRAKE)."""
        outcome = self.set_mode(intent_mode(self.link.stack, ModeIntent.HOLD))
        if (
            not outcome.confirmed
            and self.link.stack == Stack.ARDUPILOT
            and not self.cancel.is_set()
        ):
            return self.set_mode("BRAKE")
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

    # -- the routines ------------------------------------------------------------------

    def run(self, routine: SafetyRoutine) -> Phase:
        """Hold for ``hold_seconds``, then the final action; returns the last phase."""
        held = self.hold()
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while requesting hold")
        if held.confirmed:
            self.report(Phase.HOLDING, f"{self.link.name} holding: {held.describe()}")
            if self.cancel.wait(routine.hold_seconds):
                return self._finish(Phase.CANCELLED, "superseded while holding")
            final = FinalAction(routine.final_action)
        else:
            self.report(Phase.HOLD_REFUSED, f"{self.link.name} hold {held.describe()}; landing")
            final = FinalAction.LAND
        if final == FinalAction.HOLD:
            return self._finish(Phase.HELD, f"{self.link.name} stays in hold")
        if final == FinalAction.RETURN_TO_LAUNCH:
            rtl = self.return_to_launch()
            if rtl.confirmed:
                return self._finish(
                    Phase.RETURNING, f"{self.link.name} returning: {rtl.describe()}"
                )
            if self.cancel.is_set():
                return self._finish(Phase.CANCELLED, "superseded while requesting RTL")
            self.report(Phase.LANDING, f"{self.link.name} RTL {rtl.describe()}; landing instead")
        return self._land_and_watch()

    def land_now(self) -> Phase:
        """Land at once (no healthy standby) and watch for touchdown."""
        return self._land_and_watch()

    def _land_and_watch(self) -> Phase:
        landing = self.land()
        if self.cancel.is_set():
            return self._finish(Phase.CANCELLED, "superseded while requesting land")
        if not landing.confirmed:
            return self._finish(Phase.FAILED, f"{self.link.name} land {landing.describe()}")
        self.report(Phase.LANDING, f"{self.link.name} landing: {landing.describe()}")
        touched = self._await(
            lambda: self.link.landed_state() == LandedState.ON_GROUND, self.timing.landed_watch_s
        )
        if touched:
            return self._finish(Phase.LANDED, f"{self.link.name} landed")
        if self.cancel.is_set():
            return Phase.CANCELLED
        return Phase.LANDING  # still descending when the watch ended; the autopilot goes on

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

    def _finish(self, phase: Phase, message: str) -> Phase:
        self.report(phase, message)
        return phase
