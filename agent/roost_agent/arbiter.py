"""The failover decision: a pure state machine from health snapshots to explicit actions.

Why pure: this is the code that decides to take the motors away from one autopilot and
give them to another. It reads nothing, writes nothing and never looks at a clock; it
gets the time, the health of every autopilot and the policy, and returns a new state and
a list of actions. The agent executes the actions (bridge write first). That makes the
whole decision table and its safety properties (never to a worse autopilot, never on the
ground, no flapping, the latch holds) testable exhaustively and by property tests.

Rules (``docs/failover.md`` has the decision table and its sources):

- The active autopilot counts as failing only on findings that trigger failover (never a
  warning), and only after it failed continuously for ``confirm`` seconds (T_on).
- A standby is a target only when it is strictly healthier: OK now, free of failures for
  ``clear`` seconds (T_off), armed and in the air. Priority: primary first, then spec order.
- Only in flight: the vehicle's flight state is the active autopilot's landed state as
  last reported while it was healthy; a standby must itself report in-air and armed.
- After an automatic failover the agent is latched: the autopilot it left is never an
  automatic target again (no switching back, no flapping) until a ClearLatch command or
  an explicit Switch command. With three or more autopilots a further failover to a
  not-yet-failed standby is still allowed, so at most N-1 automatic switches per latch.
- If no standby qualifies, keep the active one and order it to land, once per failure
  episode (both bad -> land), unless a pilot flies it in a manual mode.
- A pilot flying a manual mode keeps control: the switch happens, the safety routine is
  skipped (the thesis did exactly this), and no landing is ordered on their behalf.
- Failover mode Manual: the arbiter only reports; switches come from Switch commands.
- Failback ``OnGround``: after an automatic failover, once everything is disarmed on the
  ground and the primary has been OK for ``clear`` seconds, switch back to it and clear
  the latch. Never in the air, and never undoing a deliberate Switch command.
- Commands (Switch, SafetyRoutine, EmergencyStop, ClearLatch) are checked for expiry
  against their deadline and obey the same health rules for their target.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
from enum import StrEnum

from roost_api.autopilot_enums import (
    CommandAction,
    CommandResultKind,
    Failback,
    FailoverMode,
    FailoverTrigger,
    SafetyRoutinePhase,
)
from roost_api.core import HealthLevel
from roost_api.plain import AutopilotCommand, RedundantAutopilotSpec


@dataclass(frozen=True)
class AutopilotView:
    """What the arbiter knows about one autopilot at one instant."""

    name: str
    level: HealthLevel
    failing: bool  # at least one failover-triggering finding
    reason: str  # why it is failing (or not OK); goes into the failover record
    armed: bool | None
    in_air: bool | None
    pilot_in_control: bool = False  # flying a pilot-steered (manual) mode
    onset: float | None = None  # when its failure began, when known
    in_step: bool | None = None  # a standby following the active (None: not known, no hub)

    @property
    def flying(self) -> bool:
        """Armed and reporting in-air: the only state a standby may take over in."""
        return self.armed is True and self.in_air is True


@dataclass(frozen=True)
class Policy:
    """The parts of the spec the arbiter decides with."""

    priority: tuple[str, ...]  # primary first, then the others in spec order
    automatic: bool
    confirm_s: float
    clear_s: float
    failback: Failback
    skip_safety_in_manual_mode: bool

    @property
    def primary(self) -> str:
        """The autopilot that flies when all are healthy."""
        return self.priority[0]

    @classmethod
    def from_spec(cls, spec: RedundantAutopilotSpec) -> Policy:
        """Build the policy from a RedundantAutopilot spec."""
        names = [a.name for a in spec.autopilots]
        policy = spec.failover_policy
        return cls(
            priority=(spec.primary, *[n for n in names if n != spec.primary]),
            automatic=policy.mode == FailoverMode.AUTOMATIC,
            confirm_s=policy.thresholds.confirm_ms / 1000,
            clear_s=policy.thresholds.clear_ms / 1000,
            failback=Failback(policy.failback),
            skip_safety_in_manual_mode=policy.safety_routine.skip_in_manual_mode,
        )


@dataclass(frozen=True)
class ArbiterState:
    """Everything the arbiter remembers between steps.

    ``active``, ``latched``, ``failed_from`` and ``failover_count`` survive restarts (the
    agent persists them); the timers and flight state are rebuilt from live data.
    """

    active: str
    latched: bool = False
    failed_from: frozenset[str] = frozenset()
    failover_count: int = 0
    failing_since: float | None = None
    ok_since: Mapping[str, float] = field(default_factory=dict)  # free of failures since
    in_flight: bool | None = None
    landing_ordered: bool = False


Trigger = FailoverTrigger
"""Why the bridge switched (FailoverRecord.trigger); the value set is the API's."""


class SafetyPlan(StrEnum):
    """What happens on the new active autopilot after a switch."""

    RUN = SafetyRoutinePhase.RUN.value
    SKIPPED_PILOT = SafetyRoutinePhase.SKIPPED_PILOT.value
    NONE = "None"
    """No routine: nothing is written to ``lastFailover.safetyRoutine``."""


@dataclass(frozen=True)
class SwitchBridge:
    """Connect ``to_autopilot`` to the motors; the agent does this before anything else."""

    from_autopilot: str
    to_autopilot: str
    reason: str
    trigger: Trigger
    detected_at: float
    safety: SafetyPlan
    onset: float | None = None
    in_step: bool | None = None  # whether the target was in step with the failed active


@dataclass(frozen=True)
class RunSafetyRoutine:
    """Hold, then the final action, on ``autopilot`` (a SafetyRoutine command)."""

    autopilot: str
    reason: str


@dataclass(frozen=True)
class LandInPlace:
    """No healthy standby: keep ``autopilot`` on the motors and order it to land."""

    autopilot: str
    reason: str


@dataclass(frozen=True)
class NoHealthyStandby:
    """No healthy standby and a pilot flies manually: only report, do not intervene."""

    autopilot: str
    reason: str


@dataclass(frozen=True)
class ForceDisarm:
    """Emergency stop: force-disarm every listed autopilot, in flight too."""

    autopilots: tuple[str, ...]
    reason: str


@dataclass(frozen=True)
class CommandDone:
    """The outcome of one command; the agent records it under the command's id."""

    command_id: str
    result: CommandResultKind
    message: str


Action = (
    SwitchBridge | RunSafetyRoutine | LandInPlace | NoHealthyStandby | ForceDisarm | CommandDone
)


@dataclass(frozen=True)
class Decision:
    """The arbiter's answer: the next state and what to do, in order."""

    state: ArbiterState
    actions: tuple[Action, ...] = ()


def _is_target(view: AutopilotView | None, state: ArbiterState, policy: Policy, now: float) -> bool:
    """A standby that is strictly healthier: OK now, no failure for T_off, armed, in the
    air, and not one the agent left this flight."""
    if view is None or view.name in state.failed_from:
        return False
    since = state.ok_since.get(view.name)
    return (
        view.level == HealthLevel.OK
        and not view.failing
        and view.flying
        and since is not None
        and now >= since + policy.clear_s  # the sum next_due wakes at: no rounding between
    )


def _preferred(priority: tuple[str, ...], views: Mapping[str, AutopilotView]) -> list[str]:
    """Standbys in step with the active first, then the rest, each in priority order.

    A standby out of step (or not known to be in step) still takes over when no in-step
    one can: a dead active autopilot always gets the best standby available.
    """
    known = [n for n in priority if (v := views.get(n)) is not None and v.in_step is True]
    return known + [n for n in priority if n not in known]


def _ok_since(
    state: ArbiterState, views: Mapping[str, AutopilotView], now: float
) -> dict[str, float]:
    """Since when each autopilot has been free of failures (OK or a passing warning).

    A warning (a late message, a GPS glitch) does not restart T_off: it is not a failure,
    and on a busy link it comes and goes. A target must still be OK at the moment of the
    switch (:func:`_is_target`).
    """
    return {
        name: state.ok_since.get(name, now)
        for name, view in views.items()
        if view.level.rank <= HealthLevel.WARN.rank and not view.failing
    }


def settled(state: ArbiterState, views: Mapping[str, AutopilotView], policy: Policy) -> bool:
    """Whether :func:`step` with these views would return ``state`` as it is and act on
    nothing, at any time: the active autopilot is not failing, no timer runs, and no
    failback is pending. The decision loop skips the step then (most ticks of a healthy
    flight); it is a shortcut, never a different answer.
    """
    active = views.get(state.active)
    if active is None or active.failing:
        return False
    if state.failing_since is not None or state.landing_ordered:
        return False
    if active.in_air is not None and active.in_air != state.in_flight:
        return False
    healthy = 0
    for name, view in views.items():
        if view.level.rank <= HealthLevel.WARN.rank and not view.failing:
            if name not in state.ok_since:
                return False
            healthy += 1
    if healthy != len(state.ok_since):
        return False
    return (
        not policy.automatic
        or policy.failback != Failback.ON_GROUND
        or not state.latched
        or state.active == policy.primary
    )


def deadline(state: ArbiterState, policy: Policy) -> float | None:
    """The end of the confirm window of a failing active autopilot (None: no such timer
    runs): from then on :func:`step` switches to a target if there is one."""
    if not policy.automatic or state.failing_since is None:
        return None
    return state.failing_since + policy.confirm_s


def next_due(state: ArbiterState, policy: Policy, now: float) -> float | None:
    """When, after ``now``, :func:`step` may act with the views unchanged (None: not
    before they change). The decision loop ticks then, not at its next read.

    While a failing active autopilot's confirm window runs, its end. Once confirmed with
    no standby a target yet, the earliest end of a standby's time free of failures
    (T_off) still running: the standby becomes a target then, and a loop that waited for
    its next read would switch up to a read interval late. A standby not free of
    failures has no such time; hearing it again changes the views, which wakes the loop.
    """
    confirmed_at = deadline(state, policy)
    if confirmed_at is None:
        return None
    if now < confirmed_at:
        return confirmed_at
    ends = (
        since + policy.clear_s
        for name, since in state.ok_since.items()
        if name != state.active and name not in state.failed_from
    )
    return min((end for end in ends if end > now), default=None)


def step(
    state: ArbiterState,
    views: Mapping[str, AutopilotView],
    policy: Policy,
    now: float,
) -> Decision:
    """Advance the state machine by one observation of every autopilot at time ``now``."""
    active = views.get(state.active)
    failing = active is None or active.failing
    state = replace(
        state,
        ok_since=_ok_since(state, views, now),
        failing_since=(state.failing_since if state.failing_since is not None else now)
        if failing
        else None,
        in_flight=state.in_flight
        if failing or active is None or active.in_air is None
        else active.in_air,
        landing_ordered=state.landing_ordered and failing,
    )
    if not policy.automatic:
        return Decision(state)
    if not failing:
        return _failback(state, views, policy, now)
    confirmed_at = deadline(state, policy)
    assert confirmed_at is not None
    if now < confirmed_at:  # the same sum the decision loop wakes at: no rounding between
        return Decision(state)
    reason = f"{state.active}: {active.reason}" if active else f"{state.active}: no data"
    onset = active.onset if active else None
    for name in _preferred(policy.priority, views):
        if name == state.active:
            continue
        candidate = views.get(name)
        if not _is_target(candidate, state, policy, now):
            continue
        assert candidate is not None
        if state.in_flight is False:
            return Decision(state)  # the active said it was on the ground: never act there
        plan = (
            SafetyPlan.SKIPPED_PILOT
            if candidate.pilot_in_control and policy.skip_safety_in_manual_mode
            else SafetyPlan.RUN
        )
        switched = replace(
            state,
            active=name,
            latched=True,
            failed_from=state.failed_from | {state.active},
            failover_count=state.failover_count + 1,
            failing_since=None,
            in_flight=True,
            landing_ordered=False,
        )
        return Decision(
            switched,
            (
                SwitchBridge(
                    state.active,
                    name,
                    reason,
                    Trigger.AUTOMATIC,
                    now,
                    plan,
                    onset,
                    candidate.in_step,
                ),
            ),
        )
    if state.in_flight is not True or state.landing_ordered:
        return Decision(state)
    state = replace(state, landing_ordered=True)
    if active is not None and active.pilot_in_control and policy.skip_safety_in_manual_mode:
        return Decision(state, (NoHealthyStandby(state.active, reason),))
    return Decision(state, (LandInPlace(state.active, f"no healthy standby; {reason}"),))


def _failback(
    state: ArbiterState, views: Mapping[str, AutopilotView], policy: Policy, now: float
) -> Decision:
    """Failback OnGround: back to a healthy primary once everything is disarmed on the ground."""
    if policy.failback != Failback.ON_GROUND or not state.latched or state.active == policy.primary:
        return Decision(state)
    primary = views.get(policy.primary)
    since = state.ok_since.get(policy.primary)
    on_ground = all(v.armed is False and v.in_air is not True for v in views.values())
    if (
        primary is None
        or primary.level != HealthLevel.OK
        or since is None
        or now < since + policy.clear_s
        or not on_ground
    ):
        return Decision(state)
    back = replace(state, active=policy.primary, latched=False, failed_from=frozenset())
    return Decision(
        back,
        (
            SwitchBridge(
                state.active,
                policy.primary,
                f"failback to {policy.primary}: landed, disarmed and healthy",
                Trigger.FAILBACK,
                now,
                SafetyPlan.NONE,
                in_step=primary.in_step,
            ),
        ),
    )


def _in_step_of(views: Mapping[str, AutopilotView], name: str) -> bool | None:
    view = views.get(name)
    return None if view is None else view.in_step


def _vehicle_in_flight(state: ArbiterState, views: Mapping[str, AutopilotView]) -> bool:
    """In flight as far as anyone can tell: the active's last state, or anyone flying."""
    return state.in_flight is True or any(v.flying for v in views.values())


def command_expired(command: AutopilotCommand, wall_now: datetime) -> bool:
    """True when the command is seen later than its deadline after it was issued."""
    issued = command.issued_at
    if issued.tzinfo is None:
        issued = issued.replace(tzinfo=UTC)
    return wall_now > issued + timedelta(seconds=command.deadline_seconds)


def handle_command(
    state: ArbiterState,
    views: Mapping[str, AutopilotView],
    policy: Policy,
    command: AutopilotCommand,
    *,
    now: float,
    wall_now: datetime,
) -> Decision:
    """Decide one command. The agent guarantees each command id reaches this only once."""

    def done(result: CommandResultKind, message: str) -> CommandDone:
        return CommandDone(command.id, result, message)

    if command_expired(command, wall_now):
        return Decision(
            state,
            (done(CommandResultKind.EXPIRED, "seen after its deadline; not executed"),),
        )
    action = CommandAction(command.action)
    if action == CommandAction.EMERGENCY_STOP:
        return Decision(
            state,
            (
                ForceDisarm(policy.priority, f"EmergencyStop command {command.id}"),
                done(CommandResultKind.EXECUTED, "force disarm sent to every autopilot"),
            ),
        )
    if action == CommandAction.CLEAR_LATCH:
        cleared = replace(state, latched=False, failed_from=frozenset())
        return Decision(cleared, (done(CommandResultKind.EXECUTED, "latch cleared"),))
    if action == CommandAction.SAFETY_ROUTINE:
        if not _vehicle_in_flight(state, views):
            return Decision(state, (done(CommandResultKind.REJECTED, "vehicle is on the ground"),))
        return Decision(
            state,
            (
                RunSafetyRoutine(state.active, f"SafetyRoutine command {command.id}"),
                done(CommandResultKind.EXECUTED, f"safety routine started on {state.active}"),
            ),
        )
    return _switch_command(state, views, policy, command, now)


def _switch_command(
    state: ArbiterState,
    views: Mapping[str, AutopilotView],
    policy: Policy,
    command: AutopilotCommand,
    now: float,
) -> Decision:
    def rejected(message: str) -> Decision:
        return Decision(state, (CommandDone(command.id, CommandResultKind.REJECTED, message),))

    target = command.target
    if target is None or target not in policy.priority:
        return rejected(f"unknown target {target!r}")
    if target == state.active:
        return Decision(
            state,
            (CommandDone(command.id, CommandResultKind.EXECUTED, f"{target} is already active"),),
        )
    if target in state.failed_from and policy.failback == Failback.NEVER:
        return rejected(f"{target} failed this flight and failback is Never")
    view = views.get(target)
    if view is None or view.failing or view.level.rank >= HealthLevel.ERROR.rank:
        return rejected(f"{target} is not healthy: {view.reason if view else 'no data'}")
    if _vehicle_in_flight(state, views) and not (view.level == HealthLevel.OK and view.flying):
        return rejected(f"in flight {target} must be OK, armed and in the air")
    switched = replace(
        state,
        active=target,
        failed_from=state.failed_from - {target},
        failing_since=None,
        landing_ordered=False,
    )
    return Decision(
        switched,
        (
            SwitchBridge(
                state.active,
                target,
                f"Switch command {command.id}",
                Trigger.COMMAND,
                now,
                SafetyPlan.NONE,
                in_step=_in_step_of(views, target),
            ),
            CommandDone(command.id, CommandResultKind.EXECUTED, f"switched to {target}"),
        ),
    )
