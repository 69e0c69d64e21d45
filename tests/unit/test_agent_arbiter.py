"""The failover arbiter: decision table, command handling and safety properties.

The arbiter is pure, so these tests drive it with hand-made health views and explicit
times. The properties (never to a worse autopilot, never on the ground, no flapping, the
latch holds, hysteresis) are checked by hypothesis over random health sequences.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roost_agent.arbiter import (
    ArbiterState,
    AutopilotView,
    CommandDone,
    CommandResultKind,
    Decision,
    ForceDisarm,
    LandInPlace,
    NoHealthyStandby,
    Policy,
    RunSafetyRoutine,
    SafetyPlan,
    SwitchBridge,
    Trigger,
    deadline,
    handle_command,
    next_due,
    step,
)
from roost_agent.arbiter import settled as step_settled
from roost_api.autopilot import AutopilotCommand, Failback
from roost_api.meta import HealthLevel

OK, WARN, ERROR, STALE = HealthLevel.OK, HealthLevel.WARN, HealthLevel.ERROR, HealthLevel.STALE
CONFIRM, CLEAR = 0.1, 1.0
WALL = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)


def policy(
    names: Sequence[str] = ("fc1", "fc2"),
    *,
    automatic: bool = True,
    failback: Failback = Failback.MANUAL,
    skip_in_manual: bool = True,
) -> Policy:
    return Policy(
        priority=tuple(names),
        automatic=automatic,
        confirm_s=CONFIRM,
        clear_s=CLEAR,
        failback=failback,
        skip_safety_in_manual_mode=skip_in_manual,
    )


def view(
    name: str,
    level: HealthLevel = OK,
    *,
    armed: bool | None = True,
    in_air: bool | None = True,
    pilot: bool = False,
) -> AutopilotView:
    failing = level.rank >= ERROR.rank
    return AutopilotView(
        name=name,
        level=level,
        failing=failing,
        reason="silent for 600 ms" if failing else "",
        armed=armed,
        in_air=in_air,
        pilot_in_control=pilot,
        onset=0.0 if failing else None,
    )


def views(*vs: AutopilotView) -> dict[str, AutopilotView]:
    return {v.name: v for v in vs}


def settled(active: str = "fc1", *healthy: str, in_flight: bool | None = True) -> ArbiterState:
    """A state where ``healthy`` autopilots have been OK since t=0."""
    return ArbiterState(active=active, ok_since=dict.fromkeys(healthy, 0.0), in_flight=in_flight)


def run(
    state: ArbiterState, pol: Policy, timeline: Sequence[tuple[float, dict[str, AutopilotView]]]
) -> tuple[ArbiterState, list[object]]:
    actions: list[object] = []
    for now, vs in timeline:
        decision = step(state, vs, pol, now)
        state = decision.state
        actions.extend(decision.actions)
    return state, actions


# -- decision table ----------------------------------------------------------------------


def test_healthy_flight_does_nothing() -> None:
    state, actions = run(
        settled("fc1", "fc1", "fc2"),
        policy(),
        [(t, views(view("fc1"), view("fc2"))) for t in (5, 6)],
    )
    assert actions == [] and state.active == "fc1" and not state.latched


def test_confirmed_failure_in_flight_switches_to_the_healthy_standby() -> None:
    pol = policy()
    state = settled("fc1", "fc1", "fc2")
    bad = views(view("fc1", ERROR), view("fc2"))
    first = step(state, bad, pol, 5.0)
    assert first.actions == ()  # T_on not yet elapsed
    assert step(first.state, bad, pol, 5.05).actions == ()
    second = step(first.state, bad, pol, 5.125)
    (switch,) = second.actions
    assert isinstance(switch, SwitchBridge)
    assert (switch.from_autopilot, switch.to_autopilot) == ("fc1", "fc2")
    assert switch.trigger == Trigger.AUTOMATIC and switch.safety == SafetyPlan.RUN
    assert switch.detected_at == 5.125 and switch.reason.startswith("fc1: silent")
    assert second.state.active == "fc2" and second.state.latched
    assert second.state.failed_from == {"fc1"} and second.state.failover_count == 1


def test_a_failure_shorter_than_the_confirm_time_is_ignored() -> None:
    pol = policy()
    timeline = [
        (5.0, views(view("fc1", ERROR), view("fc2"))),
        (5.05, views(view("fc1", ERROR), view("fc2"))),
        (5.08, views(view("fc1"), view("fc2"))),
        (5.12, views(view("fc1", ERROR), view("fc2"))),
        (5.2, views(view("fc1", ERROR), view("fc2"))),
    ]
    state, actions = run(settled("fc1", "fc1", "fc2"), pol, timeline)
    assert actions == [] and state.active == "fc1"


def test_the_deadline_is_the_end_of_the_confirm_window_and_switching_at_it_switches() -> None:
    pol = policy()
    state = settled("fc1", "fc1", "fc2")
    assert deadline(state, pol) is None  # healthy: nothing to wake for
    failing = step(state, views(view("fc1", ERROR), view("fc2")), pol, 5.0).state
    due = deadline(failing, pol)
    assert due is not None and due == pytest.approx(5.0 + CONFIRM)
    early = step(failing, views(view("fc1", ERROR), view("fc2")), pol, due - 1e-6)
    assert early.actions == ()
    on_time = step(failing, views(view("fc1", ERROR), view("fc2")), pol, due)
    assert any(isinstance(a, SwitchBridge) for a in on_time.actions)
    assert on_time.state.active == "fc2" and deadline(on_time.state, pol) is None
    assert deadline(failing, policy(automatic=False)) is None  # manual: never acts alone


# When the arbiter may act next with the views unchanged (the decision loop ticks then):
# (case, state, now, due). fc1 active and failing since 5.0 unless said otherwise; a
# standby's time free of failures (T_off, CLEAR = 1 s) ends at its ok_since + CLEAR.
_FAILING = settled("fc1", "fc2")
NEXT_DUE = [
    ("healthy: nothing to wake for", settled("fc1", "fc1", "fc2"), 5.0, None),
    (
        "failing, confirm window running: its end",
        replace(_FAILING, failing_since=5.0, ok_since={"fc2": 0.0}),
        5.05,
        5.0 + CONFIRM,
    ),
    (
        "confirmed, the standby's T_off still running: its end",
        replace(_FAILING, failing_since=5.0, ok_since={"fc2": 4.8}),
        5.2,
        4.8 + CLEAR,
    ),
    (
        "confirmed, two standbys in T_off: the earlier end",
        replace(_FAILING, failing_since=5.0, ok_since={"fc2": 4.9, "fc3": 4.7}),
        5.2,
        4.7 + CLEAR,
    ),
    (
        "confirmed, no standby free of failures: not before the views change",
        replace(_FAILING, failing_since=5.0, ok_since={}),
        5.2,
        None,
    ),
    (
        "confirmed, T_off already over (the standby is no target for another reason)",
        replace(_FAILING, failing_since=5.0, ok_since={"fc2": 1.0}),
        5.2,
        None,
    ),
    (
        "confirmed, only a standby left this flight is in T_off: nothing",
        replace(_FAILING, failing_since=5.0, ok_since={"fc2": 4.8}, failed_from=frozenset({"fc2"})),
        5.2,
        None,
    ),
    (
        "the active's own T_off is no reason to wake",
        replace(_FAILING, failing_since=5.0, ok_since={"fc1": 4.9}),
        5.2,
        None,
    ),
]


@pytest.mark.parametrize(("case", "state", "now", "due"), NEXT_DUE, ids=[c[0] for c in NEXT_DUE])
def test_next_due_is_when_the_arbiter_may_act_with_the_views_unchanged(
    case: str, state: ArbiterState, now: float, due: float | None
) -> None:
    assert next_due(state, policy(("fc1", "fc2", "fc3")), now) == due, case
    assert next_due(state, policy(("fc1", "fc2", "fc3"), automatic=False), now) is None


def test_a_confirmed_failure_switches_at_the_end_of_the_standbys_t_off() -> None:
    """The active fails while the standby's T_off runs: ticking only at next_due (no
    message read in between), the switch comes at the very end of T_off, not a read
    interval later (the landing ordered meanwhile is the active's, which it leaves)."""
    pol = policy()
    failing_views = views(view("fc1", ERROR), view("fc2"))
    state = step(settled("fc1", "fc1"), views(view("fc1"), view("fc2")), pol, 4.5).state
    state = step(state, failing_views, pol, 5.0).state  # fc1 fails; fc2 free since 4.5
    now = next_due(state, pol, 5.0)
    assert now == 5.0 + CONFIRM
    confirmed = step(state, failing_views, pol, now)
    # fc2 is not a target yet (its T_off runs until 5.5): the failing active lands
    assert [type(a) for a in confirmed.actions] == [LandInPlace]
    now = next_due(confirmed.state, pol, now)
    assert now == 4.5 + CLEAR
    assert step(confirmed.state, failing_views, pol, now - 1e-6).actions == ()
    (switch,) = step(confirmed.state, failing_views, pol, now).actions
    assert isinstance(switch, SwitchBridge) and switch.to_autopilot == "fc2"


@pytest.mark.parametrize("level", [OK, WARN])
def test_warnings_never_trigger_a_failover(level: HealthLevel) -> None:
    pol = policy()
    _, actions = run(
        settled("fc1", "fc2"),
        pol,
        [(t, views(view("fc1", level), view("fc2"))) for t in (1, 2, 3)],
    )
    assert actions == []


@pytest.mark.parametrize(
    ("standby", "why"),
    [
        (view("fc2", WARN), "standby only WARN"),
        (view("fc2", ERROR), "standby failing too"),
        (view("fc2", STALE), "standby silent"),
        (view("fc2", armed=False), "standby disarmed"),
        (view("fc2", in_air=False), "standby on the ground"),
        (view("fc2", in_air=None), "standby landed state unknown"),
    ],
)
def test_no_qualifying_standby_keeps_the_active_and_lands_it_once(
    standby: AutopilotView, why: str
) -> None:
    pol = policy()
    timeline = [(t, views(view("fc1", ERROR), standby)) for t in (5.0, 5.2, 5.4, 6.0)]
    state, actions = run(settled("fc1", "fc2"), pol, timeline)
    assert state.active == "fc1", why
    assert len(actions) == 1 and isinstance(actions[0], LandInPlace), why
    assert actions[0].autopilot == "fc1"


def test_standby_must_be_free_of_failures_for_the_clear_time_before_it_is_a_target() -> None:
    pol = policy()
    state = ArbiterState(active="fc1", in_flight=True)
    timeline = [(0.0, views(view("fc1"), view("fc2", ERROR)))]
    timeline += [(t, views(view("fc1", ERROR), view("fc2"))) for t in (0.5, 0.7)]
    state, actions = run(state, pol, timeline)
    assert [type(a) for a in actions] == [LandInPlace]  # fc2 without failure only since 0.5
    state, actions = run(state, pol, [(1.6, views(view("fc1", ERROR), view("fc2")))])
    assert [type(a) for a in actions] == [SwitchBridge] and state.active == "fc2"


def test_a_passing_warning_does_not_restart_the_clear_time_but_blocks_the_moment() -> None:
    pol = policy()
    timeline = [
        (0.0, views(view("fc1"), view("fc2"))),
        (0.9, views(view("fc1"), view("fc2", WARN))),  # e.g. one late message
        (1.2, views(view("fc1", ERROR), view("fc2", WARN))),
        (1.3, views(view("fc1", ERROR), view("fc2", WARN))),
    ]
    state, actions = run(ArbiterState(active="fc1", in_flight=True), pol, timeline)
    assert [type(a) for a in actions] == [LandInPlace]  # WARN now: not a target yet
    state, actions = run(state, pol, [(1.35, views(view("fc1", ERROR), view("fc2")))])
    assert [type(a) for a in actions] == [SwitchBridge]  # OK again, failure-free since 0


def test_never_acts_when_the_active_last_reported_the_ground() -> None:
    pol = policy()
    timeline = [(1.0, views(view("fc1", in_air=False, armed=False), view("fc2")))]
    timeline += [(t, views(view("fc1", ERROR), view("fc2"))) for t in (2.0, 3.0, 4.0)]
    state, actions = run(settled("fc1", "fc2", in_flight=None), pol, timeline)
    assert actions == [] and state.active == "fc1"


def test_unknown_flight_state_relies_on_a_flying_standby() -> None:
    """After a restart the flight state is unknown until the active reports; a standby
    that is itself armed and in the air is the evidence of flight."""
    pol = policy()
    timeline = [(t, views(view("fc1", STALE), view("fc2"))) for t in (2.0, 3.0)]
    _, actions = run(settled("fc1", "fc2", in_flight=None), pol, timeline)
    assert [type(a) for a in actions] == [SwitchBridge]


def test_pilot_in_manual_mode_gets_the_switch_without_the_safety_routine() -> None:
    pol = policy()
    timeline = [(t, views(view("fc1", ERROR), view("fc2", pilot=True))) for t in (5.0, 5.2)]
    _, actions = run(settled("fc1", "fc2"), pol, timeline)
    (switch,) = actions
    assert isinstance(switch, SwitchBridge) and switch.safety == SafetyPlan.SKIPPED_PILOT


def test_pilot_mode_skip_can_be_disabled() -> None:
    pol = policy(skip_in_manual=False)
    timeline = [(t, views(view("fc1", ERROR), view("fc2", pilot=True))) for t in (5.0, 5.2)]
    _, actions = run(settled("fc1", "fc2"), pol, timeline)
    assert isinstance(actions[0], SwitchBridge) and actions[0].safety == SafetyPlan.RUN


def test_no_standby_and_a_pilot_flying_manually_only_reports() -> None:
    pol = policy()
    timeline = [
        (t, views(view("fc1", ERROR, pilot=True), view("fc2", ERROR))) for t in (5.0, 5.2, 5.4)
    ]
    _, actions = run(settled("fc1"), pol, timeline)
    assert [type(a) for a in actions] == [NoHealthyStandby]


def test_manual_failover_mode_never_acts_on_its_own() -> None:
    pol = policy(automatic=False)
    timeline = [(t, views(view("fc1", ERROR), view("fc2"))) for t in (5.0, 5.5, 9.0)]
    state, actions = run(settled("fc1", "fc2"), pol, timeline)
    assert actions == [] and state.active == "fc1"


def test_latch_never_switches_back_and_lands_the_second_failure() -> None:
    pol = policy()
    state, actions = run(
        settled("fc1", "fc1", "fc2"),
        pol,
        [(t, views(view("fc1", ERROR), view("fc2"))) for t in (5.0, 5.2)],
    )
    assert state.active == "fc2"
    # fc1 recovers completely, then fc2 fails: no way back to fc1 while latched.
    timeline = [(t, views(view("fc1"), view("fc2"))) for t in (6.0, 8.0)]
    timeline += [(t, views(view("fc1"), view("fc2", ERROR))) for t in (9.0, 9.2, 9.4)]
    state, actions = run(state, pol, timeline)
    assert state.active == "fc2" and state.latched
    assert [type(a) for a in actions] == [LandInPlace]


def test_three_autopilots_fail_over_in_priority_order_never_back() -> None:
    pol = policy(("fc1", "fc2", "fc3"))
    state = settled("fc1", "fc1", "fc2", "fc3")
    state, actions = run(
        state, pol, [(t, views(view("fc1", ERROR), view("fc2"), view("fc3"))) for t in (5.0, 5.2)]
    )
    assert state.active == "fc2"
    state, more = run(
        state, pol, [(t, views(view("fc1"), view("fc2", ERROR), view("fc3"))) for t in (6.0, 6.2)]
    )
    assert state.active == "fc3" and state.failed_from == {"fc1", "fc2"}
    state, last = run(
        state, pol, [(t, views(view("fc1"), view("fc2"), view("fc3", ERROR))) for t in (7.0, 7.2)]
    )
    switches = [a for a in actions + more + last if isinstance(a, SwitchBridge)]
    assert [(s.from_autopilot, s.to_autopilot) for s in switches] == [
        ("fc1", "fc2"),
        ("fc2", "fc3"),
    ]
    assert [type(a) for a in last] == [LandInPlace] and state.active == "fc3"


def test_primary_is_preferred_over_spec_order_when_it_is_a_standby() -> None:
    pol = policy(("fc2", "fc1", "fc3"))  # fc2 is primary
    state = settled("fc1", "fc1", "fc2", "fc3")
    _, actions = run(
        state, pol, [(t, views(view("fc1", ERROR), view("fc2"), view("fc3"))) for t in (5.0, 5.2)]
    )
    assert isinstance(actions[0], SwitchBridge) and actions[0].to_autopilot == "fc2"


def test_failback_on_ground_returns_to_the_primary_after_landing() -> None:
    pol = policy(failback=Failback.ON_GROUND)
    state, _ = run(
        settled("fc1", "fc1", "fc2"),
        pol,
        [(t, views(view("fc1", ERROR), view("fc2"))) for t in (5.0, 5.2)],
    )
    assert state.active == "fc2"
    # Still in the air: fc1 healthy again, no failback.
    state, actions = run(state, pol, [(t, views(view("fc1"), view("fc2"))) for t in (6, 8, 9)])
    assert actions == []
    # Landed but still armed: no failback.
    landed_armed = views(view("fc1", in_air=False), view("fc2", in_air=False))
    state, actions = run(state, pol, [(10.0, landed_armed)])
    assert actions == []
    down = views(view("fc1", armed=False, in_air=False), view("fc2", armed=False, in_air=False))
    state, actions = run(state, pol, [(11.0, down)])
    (back,) = actions
    assert isinstance(back, SwitchBridge) and back.trigger == Trigger.FAILBACK
    assert back.safety == SafetyPlan.NONE
    assert state.active == "fc1" and not state.latched and not state.failed_from


@pytest.mark.parametrize("failback", [Failback.NEVER, Failback.MANUAL])
def test_no_automatic_failback_unless_on_ground_policy(failback: Failback) -> None:
    pol = policy(failback=failback)
    state, _ = run(
        settled("fc1", "fc1", "fc2"),
        pol,
        [(t, views(view("fc1", ERROR), view("fc2"))) for t in (5.0, 5.2)],
    )
    down = views(view("fc1", armed=False, in_air=False), view("fc2", armed=False, in_air=False))
    state, actions = run(state, pol, [(t, down) for t in (10.0, 20.0)])
    assert actions == [] and state.active == "fc2"


# -- commands ----------------------------------------------------------------------------


def command(action: str, target: str | None = None, *, age_s: float = 1.0) -> AutopilotCommand:
    return AutopilotCommand.model_validate(
        {
            "id": f"cmd-{action}-{target}",
            "action": action,
            "target": target,
            "issuedAt": WALL - timedelta(seconds=age_s),
            "deadlineSeconds": 10,
        }
    )


def decide(
    state: ArbiterState,
    vs: dict[str, AutopilotView],
    cmd: AutopilotCommand,
    pol: Policy | None = None,
) -> Decision:
    return handle_command(state, vs, pol or policy(), cmd, now=10.0, wall_now=WALL)


def result_of(decision: Decision) -> CommandDone:
    done = [a for a in decision.actions if isinstance(a, CommandDone)]
    assert len(done) == 1
    return done[0]


def test_switch_command_to_a_flying_healthy_standby() -> None:
    decision = decide(
        settled("fc1", "fc2"), views(view("fc1"), view("fc2")), command("Switch", "fc2")
    )
    switch, done = decision.actions
    assert isinstance(switch, SwitchBridge) and switch.trigger == Trigger.COMMAND
    assert switch.safety == SafetyPlan.NONE
    assert isinstance(done, CommandDone) and done.result == CommandResultKind.EXECUTED
    assert decision.state.active == "fc2" and not decision.state.latched


@pytest.mark.parametrize(
    ("target_view", "why"),
    [
        (view("fc2", WARN), "WARN in flight"),
        (view("fc2", ERROR), "failing"),
        (view("fc2", STALE), "silent"),
        (view("fc2", armed=False), "disarmed in flight"),
    ],
)
def test_switch_command_in_flight_is_rejected_to_a_worse_autopilot(
    target_view: AutopilotView, why: str
) -> None:
    decision = decide(settled("fc1"), views(view("fc1"), target_view), command("Switch", "fc2"))
    assert result_of(decision).result == CommandResultKind.REJECTED, why
    assert decision.state.active == "fc1"


def test_switch_command_on_the_ground_accepts_a_warning_target() -> None:
    ground = views(
        view("fc1", armed=False, in_air=False), view("fc2", WARN, armed=False, in_air=False)
    )
    decision = decide(settled("fc1", in_flight=False), ground, command("Switch", "fc2"))
    assert result_of(decision).result == CommandResultKind.EXECUTED


def test_switch_command_edge_cases() -> None:
    vs = views(view("fc1"), view("fc2"))
    assert result_of(decide(settled("fc1"), vs, command("Switch", "fc1"))).result == (
        CommandResultKind.EXECUTED
    )
    assert result_of(decide(settled("fc1"), vs, command("Switch", "fc9"))).result == (
        CommandResultKind.REJECTED
    )
    expired = decide(settled("fc1", "fc2"), vs, command("Switch", "fc2", age_s=30))
    assert result_of(expired).result == CommandResultKind.EXPIRED
    assert expired.state.active == "fc1"


def test_manual_failback_follows_the_failback_policy() -> None:
    latched = replace(settled("fc2", "fc1", "fc2"), latched=True, failed_from=frozenset({"fc1"}))
    vs = views(view("fc1"), view("fc2"))
    never = decide(latched, vs, command("Switch", "fc1"), policy(failback=Failback.NEVER))
    assert result_of(never).result == CommandResultKind.REJECTED
    manual = decide(latched, vs, command("Switch", "fc1"), policy(failback=Failback.MANUAL))
    assert result_of(manual).result == CommandResultKind.EXECUTED
    assert manual.state.active == "fc1" and "fc1" not in manual.state.failed_from


def test_emergency_stop_disarms_every_autopilot() -> None:
    decision = decide(settled("fc2"), views(view("fc1"), view("fc2")), command("EmergencyStop"))
    stop, done = decision.actions
    assert isinstance(stop, ForceDisarm) and set(stop.autopilots) == {"fc1", "fc2"}
    assert isinstance(done, CommandDone) and done.result == CommandResultKind.EXECUTED


def test_clear_latch_and_safety_routine_commands() -> None:
    latched = replace(settled("fc2"), latched=True, failed_from=frozenset({"fc1"}))
    cleared = decide(latched, views(view("fc1"), view("fc2")), command("ClearLatch"))
    assert not cleared.state.latched and not cleared.state.failed_from
    routine = decide(latched, views(view("fc1"), view("fc2")), command("SafetyRoutine"))
    assert isinstance(routine.actions[0], RunSafetyRoutine)
    assert routine.actions[0].autopilot == "fc2"
    ground = views(view("fc1", armed=False, in_air=False), view("fc2", armed=False, in_air=False))
    on_ground = decide(settled("fc2", in_flight=False), ground, command("SafetyRoutine"))
    assert result_of(on_ground).result == CommandResultKind.REJECTED


# -- properties --------------------------------------------------------------------------

LEVELS = st.sampled_from([OK, OK, OK, WARN, ERROR, STALE])


@st.composite
def autopilot_view(draw: st.DrawFn, name: str, *, grounded: bool = False) -> AutopilotView:
    level = draw(LEVELS)
    return view(
        name,
        level,
        armed=draw(st.sampled_from([True, True, True, True, False, None])),
        in_air=draw(st.sampled_from([False, None]))
        if grounded
        else draw(st.sampled_from([True, True, True, True, False, None])),
        pilot=draw(st.booleans()),
    )


@dataclass(frozen=True)
class Scenario:
    names: tuple[str, ...]
    timeline: tuple[tuple[float, dict[str, AutopilotView]], ...]
    failback: Failback


@st.composite
def scenarios(draw: st.DrawFn, *, grounded: bool = False) -> Scenario:
    n = draw(st.integers(min_value=2, max_value=4))
    names = tuple(f"fc{i}" for i in range(1, n + 1))
    steps = draw(st.integers(min_value=1, max_value=60))
    now = 0.0
    timeline: list[tuple[float, dict[str, AutopilotView]]] = []
    current = {m: draw(autopilot_view(m, grounded=grounded)) for m in names}
    for _ in range(steps):
        now += draw(st.floats(min_value=0.0, max_value=0.6))
        # Health tends to persist (so latches, clear times and failbacks get exercised).
        current = {
            m: draw(autopilot_view(m, grounded=grounded)) if draw(st.integers(0, 3)) == 0 else v
            for m, v in current.items()
        }
        timeline.append((now, current))
    failback = (
        draw(st.sampled_from([Failback.NEVER, Failback.MANUAL]))
        if grounded
        else draw(st.sampled_from(list(Failback)))
    )
    return Scenario(names, tuple(timeline), failback)


def _drive(
    scenario: Scenario,
) -> list[tuple[float, dict[str, AutopilotView], Decision, ArbiterState]]:
    pol = policy(scenario.names, failback=scenario.failback)
    state = ArbiterState(active=scenario.names[0])
    trace = []
    for now, vs in scenario.timeline:
        before = state
        decision = step(state, vs, pol, now)
        trace.append((now, vs, decision, before))
        state = decision.state
    return trace


@settings(max_examples=150, deadline=None)
@given(scenarios())
def test_property_never_switches_to_a_worse_autopilot(scenario: Scenario) -> None:
    for _, vs, decision, _ in _drive(scenario):
        for action in decision.actions:
            if isinstance(action, SwitchBridge) and action.trigger == Trigger.AUTOMATIC:
                target, source = vs[action.to_autopilot], vs[action.from_autopilot]
                assert target.level == OK and not target.failing
                assert target.armed is True and target.in_air is True
                assert source.failing and source.level.rank > target.level.rank


@settings(max_examples=150, deadline=None)
@given(scenarios())
def test_property_latch_holds_and_no_flapping(scenario: Scenario) -> None:
    left: set[str] = set()
    automatic = 0
    for _, _, decision, _ in _drive(scenario):
        for action in decision.actions:
            if not isinstance(action, SwitchBridge):
                continue
            if action.trigger == Trigger.AUTOMATIC:
                assert action.to_autopilot not in left, "switched back to an autopilot it left"
                left.add(action.from_autopilot)
                automatic += 1
            else:  # only OnGround failback can return, and it resets the latch
                assert action.trigger == Trigger.FAILBACK
                left.clear()
                automatic = 0
    assert automatic <= len(scenario.names) - 1


@settings(max_examples=150, deadline=None)
@given(scenarios(grounded=True))
def test_property_never_acts_on_the_ground(scenario: Scenario) -> None:
    for _, _, decision, _ in _drive(scenario):
        assert decision.actions == ()


@settings(max_examples=150, deadline=None)
@given(scenarios())
def test_property_switch_only_after_the_confirm_time(scenario: Scenario) -> None:
    failing_since: float | None = None
    for now, vs, decision, before in _drive(scenario):
        active = vs.get(before.active)
        failing = active is None or active.failing
        failing_since = (failing_since if failing_since is not None else now) if failing else None
        if any(
            isinstance(a, SwitchBridge) and a.trigger == Trigger.AUTOMATIC for a in decision.actions
        ):
            # The arbiter's own comparison: the time against the sum (4.1 - 4.0 < 0.1 in
            # floats, while 4.1 >= 4.0 + 0.1).
            assert failing_since is not None and now >= failing_since + CONFIRM
            failing_since = None
        elif decision.state.active != before.active:
            failing_since = None


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(min_value=0.001, max_value=CONFIRM * 0.99), min_size=2, max_size=200),
    st.sampled_from([ERROR, STALE]),
)
def test_property_oscillating_health_never_switches(gaps: list[float], bad: HealthLevel) -> None:
    """Health flipping between failing and OK faster than the confirm time never switches."""
    pol = policy()
    state = settled("fc1", "fc1", "fc2")
    now = 10.0
    for i, gap in enumerate(gaps):
        now += gap
        decision = step(state, views(view("fc1", bad if i % 2 else OK), view("fc2")), pol, now)
        assert decision.actions == ()
        state = decision.state


LEVELS = st.sampled_from([OK, WARN, ERROR, STALE])
MAYBE = st.sampled_from([True, False, None])


@st.composite
def situations(
    draw: st.DrawFn,
) -> tuple[ArbiterState, dict[str, AutopilotView], Policy, float]:
    """Any state, the views of two autopilots, a policy and a time."""
    views = {name: view(name, draw(LEVELS), in_air=draw(MAYBE)) for name in ("fc1", "fc2")}
    state = ArbiterState(
        active=draw(st.sampled_from(["fc1", "fc2"])),
        latched=draw(st.booleans()),
        failing_since=draw(st.sampled_from([None, 3.0])),
        ok_since=draw(st.sampled_from([{}, {"fc1": 1.0}, {"fc2": 2.0}, {"fc1": 1.0, "fc2": 2.0}])),
        in_flight=draw(MAYBE),
        landing_ordered=draw(st.booleans()),
    )
    rules = policy(automatic=draw(st.booleans()), failback=draw(st.sampled_from(list(Failback))))
    return state, views, rules, draw(st.sampled_from([3.0, 5.0, 50.0]))


@settings(max_examples=500, deadline=None)
@given(situations())
def test_a_settled_state_is_what_step_returns_unchanged_and_without_actions(
    situation: tuple[ArbiterState, dict[str, AutopilotView], Policy, float],
) -> None:
    state, views, rules, now = situation
    if step_settled(state, views, rules):
        assert step(state, views, rules, now) == Decision(state)
    # and a healthy steady flight settles after one step (the shortcut is taken)
    after = step(state, views, rules, now)
    steady = all(v.level == OK and v.in_air is True for v in views.values())
    pending_failback = rules.failback == Failback.ON_GROUND and after.state.latched
    if steady and not after.actions and not (rules.automatic and pending_failback):
        assert step_settled(after.state, views, rules)
