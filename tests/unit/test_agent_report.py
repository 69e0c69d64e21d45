"""The agent's report on its RedundantAutopilot: conditions and write urgency, as tables."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import replace
from datetime import UTC, datetime, timedelta

import pytest

from roost_agent.report import Change, change_class, conditions, report, write_delay
from roost_api.core import HealthLevel, find_condition
from roost_api.plain import (
    AutopilotHealth,
    CommandResult,
    Condition,
    FailoverRecord,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)

NOW = datetime(2026, 5, 1, 12, 0, 0, tzinfo=UTC)
OK, WARN, ERROR, STALE = HealthLevel.OK, HealthLevel.WARN, HealthLevel.ERROR, HealthLevel.STALE
STARTING = HealthLevel.STARTING

SPEC = RedundantAutopilotSpec.from_api(
    {
        "vehicleName": "v1",
        "primary": "fc1",
        "autopilots": [
            {
                "name": f"fc{i}",
                "stack": "px4",
                "connection": f"udp://127.0.0.1:1454{i}",
                "sysid": i,
                "bridgeChannel": i,
            }
            for i in (1, 2, 3)
        ],
    }
)


def health(
    name: str,
    level: HealthLevel,
    *reasons: str,
    armed: bool | None = False,
    landed: str | None = "OnGround",
) -> AutopilotHealth:
    return AutopilotHealth(
        name=name, level=level, reasons=list(reasons), armed=armed, landed_state=landed
    )


def switch(frm: str, to: str, trigger: str = "Automatic") -> FailoverRecord:
    return FailoverRecord.from_api(
        {
            "time": NOW,
            "from": frm,
            "to": to,
            "reason": f"{frm}: silent",
            "latencyMs": 2.0,
            "trigger": trigger,
        }
    )


def observed(
    active: str | None,
    *healths: AutopilotHealth,
    latched: bool = False,
    last: FailoverRecord | None = None,
) -> RedundantAutopilotStatus:
    return RedundantAutopilotStatus(
        active_autopilot=active,
        autopilots=list(healths),
        latched=latched,
        last_failover=last,
        failover_count=1 if last else 0,
    )


def summary(
    status: RedundantAutopilotStatus, left_behind: Collection[str] = ()
) -> dict[str, tuple[str, str]]:
    result = conditions(
        [], spec=SPEC, status=status, left_behind=left_behind, generation=3, now=NOW
    )
    return {c.type: (c.status, c.reason) for c in result}


@pytest.mark.parametrize(
    ("status", "active_healthy", "redundant"),
    [
        (
            observed("fc1", health("fc1", OK), health("fc2", OK)),
            ("True", "Healthy"),
            ("True", "StandbyAvailable"),
        ),
        (
            observed("fc1", health("fc1", WARN, "gps"), health("fc2", OK)),
            ("True", "Degraded"),
            ("True", "StandbyAvailable"),
        ),
        (
            observed("fc1", health("fc1", ERROR, "gyro"), health("fc2", OK)),
            ("False", "Unhealthy"),
            ("True", "StandbyAvailable"),
        ),
        (
            observed("fc1", health("fc1", STALE), health("fc2", WARN)),
            ("False", "NoData"),
            ("False", "NoHealthyStandby"),
        ),
        (observed("fc1", health("fc1", OK)), ("True", "Healthy"), ("False", "NoStandby")),
        (observed("fc1", health("fc2", OK)), ("Unknown", "NoHealth"), ("True", "StandbyAvailable")),
        (
            observed(None, health("fc1", OK)),
            ("Unknown", "NoActiveAutopilot"),
            ("Unknown", "NoActiveAutopilot"),
        ),
        # a standby whose armed or landed state is unknown can never be switched to
        (
            observed("fc1", health("fc1", OK), health("fc2", OK, armed=None, landed=None)),
            ("True", "Healthy"),
            ("False", "StandbyStateUnknown"),
        ),
        (
            observed("fc1", health("fc1", OK), health("fc2", OK, landed="Undefined")),
            ("True", "Healthy"),
            ("False", "StandbyStateUnknown"),
        ),
        (
            observed("fc1", health("fc1", OK), health("fc2", OK, landed=None)),
            ("True", "Healthy"),
            ("False", "StandbyStateUnknown"),
        ),
        # ... one that is known beside it still counts
        (
            observed(
                "fc1",
                health("fc1", OK),
                health("fc2", OK, armed=None, landed=None),
                health("fc3", OK, armed=True, landed="InAir"),
            ),
            ("True", "Healthy"),
            ("True", "StandbyAvailable"),
        ),
        # start-up is neither healthy nor failed
        (
            observed("fc1", health("fc1", STARTING, "booting"), health("fc2", STARTING)),
            ("False", "Starting"),
            ("False", "NoHealthyStandby"),
        ),
        # after a failover the agent never returns on its own to the autopilot it left
        (
            observed(
                "fc2", health("fc1", OK), health("fc2", OK), latched=True, last=switch("fc1", "fc2")
            ),
            ("True", "Healthy"),
            ("False", "Latched"),
        ),
        # ... but a third autopilot still makes the vehicle redundant
        (
            observed(
                "fc2",
                health("fc1", OK),
                health("fc2", OK),
                health("fc3", OK),
                latched=True,
                last=switch("fc1", "fc2"),
            ),
            ("True", "Healthy"),
            ("True", "StandbyAvailable"),
        ),
    ],
)
def test_active_healthy_and_redundant_decision_table(
    status: RedundantAutopilotStatus, active_healthy: tuple[str, str], redundant: tuple[str, str]
) -> None:
    got = summary(status)
    assert got["ActiveHealthy"] == active_healthy
    assert got["Redundant"] == redundant
    ready = active_healthy if active_healthy[0] != "True" else redundant
    assert got["Ready"] == (ready if ready[0] != "True" else ("True", "Ready"))


def test_left_behind_given_by_the_agent_overrides_the_guess_from_the_last_failover() -> None:
    status = observed(
        "fc3",
        health("fc1", OK),
        health("fc2", OK),
        health("fc3", OK),
        latched=True,
        last=switch("fc2", "fc3"),
    )
    assert summary(status)["Redundant"] == ("True", "StandbyAvailable")
    assert summary(status, left_behind={"fc1", "fc2"})["Redundant"] == ("False", "Latched")


@pytest.mark.parametrize(
    ("status", "failed_over"),
    [
        (observed("fc1", health("fc1", OK)), ("False", "OnPrimary")),
        (
            observed("fc2", health("fc2", OK), last=switch("fc1", "fc2")),
            ("True", "AutomaticFailover"),
        ),
        (
            observed("fc2", health("fc2", OK), last=switch("fc1", "fc2", "Command")),
            ("True", "SwitchedByCommand"),
        ),
        (observed("fc2", health("fc2", OK)), ("True", "NotOnPrimary")),  # restarted on fc2
        (observed(None), ("Unknown", "NoActiveAutopilot")),
    ],
)
def test_failed_over_decision_table(
    status: RedundantAutopilotStatus, failed_over: tuple[str, str]
) -> None:
    assert summary(status)["FailedOver"] == failed_over


def test_transition_time_moves_only_when_a_status_changes() -> None:
    healthy = observed("fc1", health("fc1", OK), health("fc2", OK))
    first = report(None, healthy, spec=SPEC, generation=1, node_name="n", now=NOW)
    later = NOW + timedelta(seconds=30)
    warned = observed("fc1", health("fc1", WARN, "gps 3 sats"), health("fc2", OK))
    second = report(first, warned, spec=SPEC, generation=2, node_name="n", now=later)
    active = find_condition(second.conditions, "ActiveHealthy")
    assert active is not None and active.reason == "Degraded"
    assert active.last_transition_time == NOW  # still True
    assert active.observed_generation == 2
    failed = observed("fc1", health("fc1", ERROR, "gyro"), health("fc2", OK))
    third = report(second, failed, spec=SPEC, generation=2, node_name="n", now=later)
    active = find_condition(third.conditions, "ActiveHealthy")
    assert active is not None and active.last_transition_time == later
    assert (third.reported_at, third.node_name, third.observed_generation) == (later, "n", 2)


def command(result: str) -> CommandResult:
    return CommandResult(id="c1", result=result, time=NOW)


BASE = report(
    None,
    observed("fc1", health("fc1", OK), health("fc2", ERROR, "no heartbeat for 3.1 s")),
    spec=SPEC,
    generation=1,
    node_name="n",
    now=NOW,
)


@pytest.mark.parametrize(
    ("update", "change"),
    [
        ({"reported_at": NOW + timedelta(seconds=9)}, Change.NONE),
        (
            {"autopilots": [health("fc1", OK), health("fc2", ERROR, "no heartbeat for 7.9 s")]},
            Change.NONE,
        ),
        (
            {
                "autopilots": [
                    health("fc1", WARN, "gps"),
                    health("fc2", ERROR, "no heartbeat for 7 s"),
                ]
            },
            Change.ROUTINE,
        ),
        ({"observed_generation": 2}, Change.ROUTINE),
        ({"active_autopilot": "fc2"}, Change.URGENT),
        ({"failover_count": 1}, Change.URGENT),
        ({"last_failover": switch("fc1", "fc2")}, Change.URGENT),
        ({"latched": True}, Change.URGENT),
        ({"last_command": command("Executed")}, Change.URGENT),
    ],
)
def test_only_meaningful_changes_are_written_and_the_switch_goes_first(
    update: dict[str, object], change: Change
) -> None:
    assert change_class(BASE, replace(BASE, **update)) is change


def test_a_standby_falling_out_of_step_is_written_its_message_alone_is_not() -> None:
    def with_in_step(status: str, reason: str, message: str) -> RedundantAutopilotStatus:
        cond = Condition(
            type="StandbyInStep",
            status=status,
            reason=reason,
            message=message,
            last_transition_time=NOW,
        )
        fc2 = replace(health("fc2", ERROR, "no heartbeat for 3.1 s"), conditions=[cond])
        return replace(BASE, autopilots=[health("fc1", OK), fc2])

    in_step = with_in_step("True", "InStep", "agree")
    assert change_class(in_step, with_in_step("True", "InStep", "agree again")) is Change.NONE
    out = with_in_step("False", "ModeDiffers", "mode AUTO.RTL")
    assert change_class(in_step, out) is Change.ROUTINE


def test_the_first_report_is_urgent() -> None:
    assert change_class(None, BASE) is Change.URGENT


@pytest.mark.parametrize(
    ("change", "since", "delay"),
    [
        (Change.URGENT, 0.0, 0.0),  # a switch never waits for the coalescing interval
        (Change.ROUTINE, 0.2, 0.8),  # a burst waits: one write carries its latest state
        (Change.ROUTINE, 1.5, 0.0),
        (Change.NONE, 0.2, 9.8),  # nothing new: only the periodic refresh
        (Change.NONE, 12.0, 0.0),
    ],
)
def test_write_delay_decision_table(change: Change, since: float, delay: float) -> None:
    got = write_delay(change, since, min_interval_s=1.0, refresh_s=10.0)
    assert got == pytest.approx(delay)


def test_a_flapping_health_level_costs_one_write_per_interval() -> None:
    """Ten health flips within a second: one write now, the next one a second later."""
    writes, last_write, now = [], float("-inf"), 0.0
    for flip in range(10):
        now = flip * 0.1
        if write_delay(Change.ROUTINE, now - last_write, min_interval_s=1.0, refresh_s=10.0) == 0:
            writes.append(now)
            last_write = now
    assert writes == [0.0]
