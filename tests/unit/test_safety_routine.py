"""The safety routine's decision table: confirmations, retries, fallbacks, cancellation.

A scripted autopilot stands in for the link here, because the answers this table needs
(temporarily rejected twice, a lost ack with the mode taken anyway, an accepted mode the
heartbeat never shows) cannot be produced on demand by the simulator. The routine against
the real simulator over UDP is in tests/integration/test_agent_failover.py.
"""

from __future__ import annotations

import threading
import time

import pytest

from roost_agent.safety import Phase, SafetyRunner, Timing
from roost_api.autopilot import FinalAction, SafetyRoutine
from roost_api.meta import Stack
from roost_mavlink import (
    FORCE_DISARM_MAGIC,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    LandedState,
    MavResult,
    custom_mode,
)
from roost_mavlink.modes import custom_mode_from_set_mode

FAST = Timing(
    ack_timeout_s=0.01, retry_gap_s=0.01, mode_confirm_s=0.05, landed_watch_s=0.3, poll_s=0.002
)
ACCEPTED, TEMP, DENIED = MavResult.ACCEPTED, MavResult.TEMPORARILY_REJECTED, MavResult.DENIED


class ScriptedAutopilot:
    """Answers each command from a per-command script (then ACCEPTED), applies accepted
    commands to its mode like an autopilot, and reports that mode in its heartbeat."""

    def __init__(
        self,
        stack: Stack,
        script: dict[int, list[int | None]] | None = None,
        *,
        mode: str | None = None,
        ignores_modes: bool = False,
    ) -> None:
        self.name = "fc2"
        self.stack = stack
        self.script = {k: list(v) for k, v in (script or {}).items()}
        self.mode = custom_mode(stack, mode or ("POSCTL" if stack == Stack.PX4 else "GUIDED"))
        self.armed = True
        self.landed = LandedState.IN_AIR
        self.ignores_modes = ignores_modes
        self.beat_at = 0.0
        self.sent: list[tuple[int, tuple[float, ...], int]] = []

    def command(
        self, command: int, params: tuple[float, ...], *, confirmation: int, timeout_s: float
    ) -> int | None:
        self.sent.append((command, params, confirmation))
        queue = self.script.get(command, [])
        answer = queue.pop(0) if queue else ACCEPTED
        if answer == ACCEPTED:
            self._apply(command, params)
        self.beat_at = time.monotonic()
        return answer

    def _apply(self, command: int, params: tuple[float, ...]) -> None:
        if self.ignores_modes:
            return
        if command == MAV_CMD_DO_SET_MODE:
            self.mode = custom_mode_from_set_mode(self.stack, *params[:3])
        elif command == MAV_CMD_NAV_LAND:
            self.mode = custom_mode(self.stack, "AUTO.LAND" if self.stack == Stack.PX4 else "LAND")
            self.landed = LandedState.ON_GROUND  # touches down at once
        elif command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self.mode = custom_mode(self.stack, "AUTO.RTL" if self.stack == Stack.PX4 else "RTL")
        elif command == MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = False

    def heartbeat(self) -> tuple[int, int, float] | None:
        return self.mode, 1 | (128 if self.armed else 0), self.beat_at

    def landed_state(self) -> int | None:
        return self.landed

    def commands(self) -> list[int]:
        return [c for c, _, _ in self.sent]

    def modes_requested(self) -> list[int]:
        return [
            custom_mode_from_set_mode(self.stack, *p[:3])
            for c, p, _ in self.sent
            if c == MAV_CMD_DO_SET_MODE
        ]


def run(
    autopilot: ScriptedAutopilot,
    routine: SafetyRoutine | None = None,
    cancel: threading.Event | None = None,
) -> tuple[Phase, list[Phase]]:
    phases: list[Phase] = []
    runner = SafetyRunner(
        autopilot, cancel or threading.Event(), lambda p, _: phases.append(p), FAST
    )
    return runner.run(routine or SafetyRoutine(hold_seconds=0.05)), phases


@pytest.mark.parametrize(
    ("stack", "hold", "land"),
    [(Stack.PX4, "AUTO.LOITER", "AUTO.LAND"), (Stack.ARDUPILOT, "LOITER", "LAND")],
)
def test_hold_then_land_confirmed_by_ack_and_heartbeat(stack: Stack, hold: str, land: str) -> None:
    autopilot = ScriptedAutopilot(stack)
    started = time.monotonic()
    final, phases = run(autopilot, SafetyRoutine(hold_seconds=0.1))
    assert final == Phase.LANDED
    assert phases == [Phase.HOLDING, Phase.LANDING, Phase.LANDED]
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND]
    assert autopilot.modes_requested() == [custom_mode(stack, hold)]
    assert autopilot.mode == custom_mode(stack, land)
    assert time.monotonic() - started >= 0.1


def test_px4_hold_uses_main_and_sub_mode_params() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4)
    run(autopilot)
    _, params, _ = autopilot.sent[0]
    assert params[:3] == (1.0, 4.0, 3.0)  # custom-mode flag, AUTO, LOITER


def test_temporarily_rejected_is_retried_with_incrementing_confirmation() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [TEMP, TEMP]})
    final, phases = run(autopilot)
    assert final == Phase.LANDED and phases[0] == Phase.HOLDING
    assert [conf for c, _, conf in autopilot.sent if c == MAV_CMD_DO_SET_MODE] == [0, 1, 2]


def test_lost_ack_but_mode_taken_counts_as_confirmed() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [None]})
    autopilot.mode = custom_mode(Stack.PX4, "AUTO.LOITER")  # it took the mode; ack lost
    _, phases = run(autopilot)
    assert phases[0] == Phase.HOLDING
    assert autopilot.commands().count(MAV_CMD_DO_SET_MODE) == 1


def test_no_answer_at_all_exhausts_retries_then_lands() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [None, None, None]})
    final, phases = run(autopilot)
    assert phases[0] == Phase.HOLD_REFUSED and final == Phase.LANDED
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE] * 3 + [MAV_CMD_NAV_LAND]


def test_refused_hold_falls_back_to_land_without_retrying() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [DENIED]})
    _, phases = run(autopilot)
    assert phases == [Phase.HOLD_REFUSED, Phase.LANDING, Phase.LANDED]
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND]


def test_ardupilot_tries_brake_when_loiter_is_refused() -> None:
    autopilot = ScriptedAutopilot(Stack.ARDUPILOT, {MAV_CMD_DO_SET_MODE: [MavResult.FAILED]})
    _, phases = run(autopilot)
    assert phases[0] == Phase.HOLDING
    assert autopilot.modes_requested()[:2] == [
        custom_mode(Stack.ARDUPILOT, "LOITER"),
        custom_mode(Stack.ARDUPILOT, "BRAKE"),
    ]


def test_accepted_but_never_shown_in_the_heartbeat_is_not_confirmed() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, ignores_modes=True)
    final, phases = run(autopilot)
    assert phases[0] == Phase.HOLD_REFUSED
    assert autopilot.commands().count(MAV_CMD_DO_SET_MODE) >= 3  # hold tried 3 times
    assert final == Phase.FAILED  # land never showed in the heartbeat either


def test_refused_nav_land_falls_back_to_set_mode_land() -> None:
    autopilot = ScriptedAutopilot(Stack.ARDUPILOT, {MAV_CMD_NAV_LAND: [MavResult.UNSUPPORTED]})
    final, _ = run(autopilot)
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND, MAV_CMD_DO_SET_MODE]
    assert autopilot.modes_requested()[-1] == custom_mode(Stack.ARDUPILOT, "LAND")
    assert autopilot.mode == custom_mode(Stack.ARDUPILOT, "LAND")
    assert final == Phase.LANDING  # mode confirmed; this script does not touch down then


def test_land_refused_everywhere_fails() -> None:
    autopilot = ScriptedAutopilot(
        Stack.PX4, {MAV_CMD_NAV_LAND: [DENIED], MAV_CMD_DO_SET_MODE: [ACCEPTED, DENIED]}
    )
    final, phases = run(autopilot)
    assert final == Phase.FAILED and phases[-1] == Phase.FAILED


def test_return_to_launch_and_its_fallback() -> None:
    rtl = SafetyRoutine(hold_seconds=0.01, final_action=FinalAction.RETURN_TO_LAUNCH)
    autopilot = ScriptedAutopilot(Stack.PX4)
    final, _ = run(autopilot, rtl)
    assert final == Phase.RETURNING and autopilot.commands()[-1] == MAV_CMD_NAV_RETURN_TO_LAUNCH
    refused = ScriptedAutopilot(Stack.PX4, {MAV_CMD_NAV_RETURN_TO_LAUNCH: [DENIED]})
    final, _ = run(refused, rtl)
    assert final == Phase.LANDED and refused.commands()[-1] == MAV_CMD_NAV_LAND


def test_final_hold_sends_no_landing() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4)
    final, _ = run(autopilot, SafetyRoutine(hold_seconds=0.01, final_action=FinalAction.HOLD))
    assert final == Phase.HELD and autopilot.commands() == [MAV_CMD_DO_SET_MODE]


def test_cancelled_while_holding_sends_nothing_more() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4)
    cancel = threading.Event()
    threading.Timer(0.05, cancel.set).start()
    final, _ = run(autopilot, SafetyRoutine(hold_seconds=5.0), cancel)
    assert final == Phase.CANCELLED and autopilot.commands() == [MAV_CMD_DO_SET_MODE]


def test_force_disarm_uses_the_magic_and_waits_for_a_disarmed_heartbeat() -> None:
    autopilot = ScriptedAutopilot(Stack.ARDUPILOT, {MAV_CMD_COMPONENT_ARM_DISARM: [TEMP]})
    phases: list[Phase] = []
    runner = SafetyRunner(autopilot, threading.Event(), lambda p, _: phases.append(p), FAST)
    assert runner.force_disarm() == Phase.DISARMED
    (first, second) = [s for s in autopilot.sent if s[0] == MAV_CMD_COMPONENT_ARM_DISARM]
    assert first[1][:2] == (0.0, float(FORCE_DISARM_MAGIC)) and (first[2], second[2]) == (0, 1)
    assert not autopilot.armed
