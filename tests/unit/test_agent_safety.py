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

from roost_agent.health import Motion
from roost_agent.safety import HoldVerdict, Phase, Progress, SafetyRunner, judge_hold
from roost_api.autopilot import FinalAction, SafetyRoutine
from roost_api.meta import Stack
from roost_mavlink import (
    FORCE_DISARM_MAGIC,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MavLandedState,
    MavResult,
    MavState,
    custom_mode,
)
from tests.support.scriptedautopilot import FAST, HOLD_PHASES, ScriptedAutopilot, run

ACCEPTED, TEMP, DENIED = MavResult.ACCEPTED, MavResult.TEMPORARILY_REJECTED, MavResult.DENIED


@pytest.mark.parametrize(
    ("stack", "hold", "land"),
    [(Stack.PX4, "AUTO.LOITER", "AUTO.LAND"), (Stack.ARDUPILOT, "BRAKE", "LAND")],
)
def test_hold_then_land_confirmed_by_ack_heartbeat_and_telemetry(
    stack: Stack, hold: str, land: str
) -> None:
    autopilot = ScriptedAutopilot(stack)
    started = time.monotonic()
    final, phases = run(autopilot, SafetyRoutine(hold_seconds=0.1))
    assert final == Phase.LANDED
    assert phases == [*HOLD_PHASES, Phase.LANDING, Phase.LANDED]
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
    assert final == Phase.LANDED and phases[:3] == HOLD_PHASES
    assert [conf for c, _, conf in autopilot.sent if c == MAV_CMD_DO_SET_MODE] == [0, 1, 2]


def test_lost_ack_but_mode_taken_counts_as_confirmed() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [None]})
    autopilot.mode = custom_mode(Stack.PX4, "AUTO.LOITER")  # it took the mode; ack lost
    _, phases = run(autopilot)
    assert phases[:3] == HOLD_PHASES
    assert autopilot.commands().count(MAV_CMD_DO_SET_MODE) == 1


def test_no_answer_at_all_exhausts_retries_then_lands() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [None, None, None]})
    final, phases = run(autopilot)
    assert phases[1] == Phase.HOLD_REFUSED and final == Phase.LANDED
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE] * 3 + [MAV_CMD_NAV_LAND]


def test_refused_hold_falls_back_to_land_without_retrying() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, {MAV_CMD_DO_SET_MODE: [DENIED]})
    _, phases = run(autopilot)
    assert phases == [Phase.STARTED, Phase.HOLD_REFUSED, Phase.LANDING, Phase.LANDED]
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND]


def test_ardupilot_holds_in_brake_then_guided_and_never_loiter() -> None:
    autopilot = ScriptedAutopilot(Stack.ARDUPILOT, {MAV_CMD_DO_SET_MODE: [MavResult.FAILED]})
    _, phases = run(autopilot)
    assert phases[:3] == HOLD_PHASES
    assert autopilot.modes_requested()[:2] == [
        custom_mode(Stack.ARDUPILOT, "BRAKE"),
        custom_mode(Stack.ARDUPILOT, "GUIDED"),
    ]
    assert custom_mode(Stack.ARDUPILOT, "LOITER") not in autopilot.modes_requested()


def test_accepted_but_never_shown_in_the_heartbeat_is_not_confirmed() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, ignores_modes=True)
    final, phases = run(autopilot)
    assert phases[1] == Phase.HOLD_REFUSED
    assert autopilot.commands().count(MAV_CMD_DO_SET_MODE) >= 3  # hold tried 3 times
    assert final == Phase.FAILED  # land never showed in the heartbeat either


# -- a hold that holds: the telemetry decision table -----------------------------------

LOITER_NO_RC = {"LOITER": -2.45}  # ArduCopter LOITER, throttle stick low (measured)


@pytest.mark.parametrize(
    ("climb_in", "telemetry", "final_action", "phases_after_hold", "commands_after_hold"),
    [
        # holds: confirmed by telemetry, then the final action
        ({}, True, FinalAction.LAND, [Phase.HOLDING, Phase.LANDING, Phase.LANDED], [21]),
        ({}, True, FinalAction.HOLD, [Phase.HOLDING, Phase.HELD], []),
        # sinks in the hold mode: escalate to the final action at once, say so
        (
            {"AUTO.LOITER": -2.45},
            True,
            FinalAction.LAND,
            [Phase.HOLD_FAILED, *[Phase.LANDING, Phase.LANDED]],
            [21],
        ),
        # a final action of Hold cannot be escalated to: land
        (
            {"AUTO.LOITER": -2.45},
            True,
            FinalAction.HOLD,
            [Phase.HOLD_FAILED, Phase.LANDING, Phase.LANDED],
            [21],
        ),
        # RTL stays the escalation when it is the final action
        (
            {"AUTO.LOITER": -1.0},
            True,
            FinalAction.RETURN_TO_LAUNCH,
            [Phase.HOLD_FAILED, Phase.RETURNING],
            [20],
        ),
        # braking a climb endangers nothing: still a hold
        (
            {"AUTO.LOITER": 0.7},
            True,
            FinalAction.LAND,
            [Phase.HOLDING, Phase.LANDING, Phase.LANDED],
            [21],
        ),
        # slow drift inside the limits is a hold
        (
            {"AUTO.LOITER": -0.2},
            True,
            FinalAction.LAND,
            [Phase.HOLDING, Phase.LANDING, Phase.LANDED],
            [21],
        ),
        # no altitude telemetry: the hold cannot be confirmed, escalate
        ({}, False, FinalAction.LAND, [Phase.HOLD_FAILED, Phase.LANDING, Phase.LANDED], [21]),
        ({}, False, FinalAction.HOLD, [Phase.HOLD_FAILED, Phase.LANDING, Phase.LANDED], [21]),
    ],
)
def test_hold_is_confirmed_by_telemetry_or_escalates_at_once(
    climb_in: dict[str, float],
    telemetry: bool,
    final_action: FinalAction,
    phases_after_hold: list[Phase],
    commands_after_hold: list[int],
) -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, climb_in=climb_in, telemetry=telemetry)
    routine = SafetyRoutine(hold_seconds=0.3, final_action=final_action)
    final, phases = run(autopilot, routine)
    assert phases[:2] == [Phase.STARTED, Phase.CONFIRMING_HOLD]
    assert phases[2:] == phases_after_hold
    assert final == phases_after_hold[-1]
    assert autopilot.commands()[1:] == commands_after_hold


def test_loiter_without_rc_escalates_within_the_band_instead_of_crashing() -> None:
    """The old routine put ArduCopter in LOITER and reported it holding while it sank
    2.45 m/s into the ground. Forced to use LOITER, the routine now sees the descent and
    lands at once, having lost little more than the band."""
    autopilot = ScriptedAutopilot(Stack.ARDUPILOT, climb_in=LOITER_NO_RC, touches_down=False)
    autopilot.altitude = 4.8
    phases: list[tuple[Phase, str]] = []
    runner = SafetyRunner(
        autopilot,
        threading.Event(),
        lambda p, m: phases.append((p, m)),
        FAST,
        hold_modes_override=("LOITER",),
    )
    runner.run(SafetyRoutine(hold_seconds=3.0))
    failed = [m for p, m in phases if p == Phase.HOLD_FAILED]
    assert failed and "descending at 2.45 m/s" in failed[0] and "land at once" in failed[0].lower()
    assert Phase.HOLDING not in [p for p, _ in phases]
    assert autopilot.commands()[-1] in (MAV_CMD_NAV_LAND, MAV_CMD_DO_SET_MODE)
    assert 4.8 - autopilot.lowest < 0.5


def test_judge_hold_table() -> None:
    t = FAST
    steady = [Motion(10.0, 0.0, 1.0), Motion(10.0, 0.05, 1.02)]
    assert judge_hold(steady, 10.0, 1.03, t) is None
    assert judge_hold([], 10.0, 1.0, t) == HoldVerdict(
        False, "no altitude telemetry (none received)"
    )
    stale = judge_hold(steady, 10.0, 2.0, t)
    assert stale is not None and stale.reason == "no altitude telemetry (last 1.0 s ago)"
    low = judge_hold([Motion(9.3, 0.0, 1.0)], 10.0, 1.0, t)
    assert low is not None and low.reason.startswith("lost 0.70 m")
    # one fast sample is noise; a fast run longer than hold_violation_s is not
    assert judge_hold([Motion(10.0, -2.0, 1.0), Motion(10.0, 0.0, 1.005)], 10.0, 1.01, t) is None
    sinking = judge_hold([Motion(10.0, -2.0, 1.0), Motion(9.9, -2.0, 1.02)], 10.0, 1.02, t)
    assert sinking is not None and sinking.reason.startswith("descending at 2.00 m/s")


# -- landing -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("stack", "landed", "armed", "status", "touched"),
    [
        (Stack.PX4, MavLandedState.ON_GROUND, True, MavState.ACTIVE, True),
        (Stack.PX4, MavLandedState.LANDING, False, MavState.STANDBY, True),  # auto-disarmed
        (Stack.PX4, MavLandedState.LANDING, True, MavState.STANDBY, False),  # PX4: no such rule
        (Stack.ARDUPILOT, None, True, MavState.STANDBY, True),  # land detector, still armed
        (Stack.ARDUPILOT, None, True, MavState.ACTIVE, False),
        (Stack.ARDUPILOT, MavLandedState.IN_AIR, True, MavState.ACTIVE, False),
    ],
)
def test_landed_is_what_the_vehicle_reports(
    stack: Stack, landed: int | None, armed: bool, status: int, touched: bool
) -> None:
    autopilot = ScriptedAutopilot(stack, mode="AUTO.LAND" if stack == Stack.PX4 else "LAND")
    autopilot.landed = landed  # type: ignore[assignment]
    autopilot.armed, autopilot.status, autopilot.beat_at = armed, status, time.monotonic()
    runner = SafetyRunner(autopilot, threading.Event(), lambda p, m: None, FAST)
    assert (runner.landed(0.0) is not None) == touched


def test_landing_that_does_not_end_times_out_is_ordered_again_then_fails() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, touches_down=False)
    phases: list[tuple[Phase, str]] = []
    runner = SafetyRunner(autopilot, threading.Event(), lambda p, m: phases.append((p, m)), FAST)
    assert runner.land_now() == Phase.FAILED
    assert [p for p, _ in phases] == [Phase.LANDING, Phase.LAND_TIMED_OUT, Phase.FAILED]
    assert autopilot.commands() == [MAV_CMD_NAV_LAND, MAV_CMD_NAV_LAND]
    assert "land ordered again" in phases[1][1]


def test_refused_nav_land_falls_back_to_set_mode_land() -> None:
    autopilot = ScriptedAutopilot(
        Stack.ARDUPILOT, {MAV_CMD_NAV_LAND: [MavResult.UNSUPPORTED]}, touches_down=False
    )
    autopilot.status = MavState.STANDBY  # ArduCopter's land detector fired
    final, _ = run(autopilot)
    assert autopilot.commands() == [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND, MAV_CMD_DO_SET_MODE]
    assert autopilot.modes_requested()[-1] == custom_mode(Stack.ARDUPILOT, "LAND")
    assert autopilot.mode == custom_mode(Stack.ARDUPILOT, "LAND")
    assert final == Phase.LANDED


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


# -- progress and resuming after a restart ---------------------------------------------


def test_every_step_is_recorded_before_it_is_reported() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4)
    log: list[tuple[str, Phase]] = []
    runner = SafetyRunner(
        autopilot,
        threading.Event(),
        lambda p, _: log.append(("report", p)),
        FAST,
        progress=lambda pr: log.append(("record", pr.phase)),
    )
    runner.run(SafetyRoutine(hold_seconds=0.05))
    recorded = [p for kind, p in log if kind == "record"]
    assert recorded == [*HOLD_PHASES, Phase.LANDING, Phase.LANDED]
    for i, (kind, phase) in enumerate(log):
        if kind == "report":
            assert log[i - 1] == ("record", phase)


WALL = 1_000_000.0


@pytest.mark.parametrize(
    ("progress", "mode", "landed", "expect_commands", "expect_final"),
    [
        # killed before the hold was confirmed: the routine starts over
        (
            Progress("fc2", Phase.STARTED, FinalAction.LAND, 0.05),
            "POSCTL",
            MavLandedState.IN_AIR,
            [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND],
            Phase.LANDED,
        ),
        # killed holding, hold time left: hold again (confirmed by telemetry), then land
        (
            Progress("fc2", Phase.HOLDING, FinalAction.LAND, 60.0, hold_started=WALL - 59.9),
            "AUTO.LOITER",
            MavLandedState.IN_AIR,
            [MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_LAND],
            Phase.LANDED,
        ),
        # killed holding, hold time passed while down: straight to the final action
        (
            Progress("fc2", Phase.HOLDING, FinalAction.LAND, 3.0, hold_started=WALL - 10),
            "AUTO.LOITER",
            MavLandedState.IN_AIR,
            [MAV_CMD_NAV_LAND],
            Phase.LANDED,
        ),
        (
            Progress("fc2", Phase.CONFIRMING_HOLD, FinalAction.HOLD, 3.0, hold_started=WALL - 10),
            "AUTO.LOITER",
            MavLandedState.IN_AIR,
            [],
            Phase.HELD,
        ),
        # killed landing, still landing: confirmed by watching, not restarted
        (
            Progress("fc2", Phase.LANDING, FinalAction.LAND, 3.0, land_started=WALL - 1),
            "AUTO.LAND",
            MavLandedState.ON_GROUND,
            [],
            Phase.LANDED,
        ),
        # killed landing, but no longer in the land mode: land again
        (
            Progress("fc2", Phase.LANDING, FinalAction.LAND, 3.0, land_started=WALL - 1),
            "AUTO.LOITER",
            MavLandedState.IN_AIR,
            [MAV_CMD_NAV_LAND],
            Phase.LANDED,
        ),
        # killed while escalating a failed hold: the escalation goes on
        (
            Progress("fc2", Phase.HOLD_FAILED, FinalAction.HOLD, 3.0, hold_started=WALL - 1),
            "AUTO.LOITER",
            MavLandedState.IN_AIR,
            [MAV_CMD_NAV_LAND],
            Phase.LANDED,
        ),
        # killed right after a landing order: land
        (
            Progress("fc2", Phase.STARTED, FinalAction.LAND, 0.0, holds=False),
            "POSCTL",
            MavLandedState.IN_AIR,
            [MAV_CMD_NAV_LAND],
            Phase.LANDED,
        ),
        # finished before the kill: nothing to do
        (
            Progress("fc2", Phase.LANDED, FinalAction.LAND, 3.0),
            "AUTO.LAND",
            MavLandedState.ON_GROUND,
            [],
            Phase.LANDED,
        ),
    ],
)
def test_resume_decision_table(
    progress: Progress, mode: str, landed: int, expect_commands: list[int], expect_final: Phase
) -> None:
    autopilot = ScriptedAutopilot(Stack.PX4, mode=mode)
    autopilot.landed = landed  # type: ignore[assignment]
    autopilot.beat_at = time.monotonic()
    runner = SafetyRunner(autopilot, threading.Event(), lambda p, m: None, FAST, wall=lambda: WALL)
    assert runner.resume(progress) == expect_final
    assert autopilot.commands() == expect_commands


def test_force_disarm_uses_the_magic_and_waits_for_a_disarmed_heartbeat() -> None:
    autopilot = ScriptedAutopilot(Stack.ARDUPILOT, {MAV_CMD_COMPONENT_ARM_DISARM: [TEMP]})
    phases: list[Phase] = []
    runner = SafetyRunner(autopilot, threading.Event(), lambda p, _: phases.append(p), FAST)
    assert runner.force_disarm() == Phase.DISARMED
    (first, second) = [s for s in autopilot.sent if s[0] == MAV_CMD_COMPONENT_ARM_DISARM]
    assert first[1][:2] == (0.0, float(FORCE_DISARM_MAGIC)) and (first[2], second[2]) == (0, 1)
    assert not autopilot.armed
