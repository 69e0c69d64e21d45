"""How the sandbox reads the cluster to narrate a failover, and what it asks the simulators.

Pure parts of :mod:`roost_cli.sandbox.director` and :mod:`roost_cli.sandbox.sims`; the e2e
sandbox test runs them against a live fleet.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest

from roost_cli.errors import CliError
from roost_cli.sandbox import director, plan, sims, state
from roost_cli.sandbox.runner import announced_telemetry
from roost_cli.tables import format_latency

FAULT_AT = datetime(2026, 5, 1, 12, 0, 0, 600000, tzinfo=UTC)


def _ra(last_failover_at: datetime | None, safety: str | None = "Holding") -> dict[str, Any]:
    status: dict[str, Any] = {"activeAutopilot": "px4-b"}
    if last_failover_at is not None:
        status["lastFailover"] = {
            "time": last_failover_at.isoformat(),
            "from": "px4-a",
            "to": "px4-b",
            "reason": "px4-a: silent for 610 ms",
            "latencyMs": 0.4,
            "trigger": "Automatic",
            "safetyRoutine": safety,
        }
    return {"metadata": {"name": "drone-1"}, "status": status}


def test_only_a_failover_after_the_fault_counts() -> None:
    assert director.failover_since(_ra(None), FAULT_AT) is None
    assert director.failover_since(_ra(FAULT_AT - timedelta(seconds=5)), FAULT_AT) is None
    # Kubernetes keeps whole seconds: a switch in the same second as the fault counts.
    same_second = FAULT_AT.replace(microsecond=0)
    record = director.failover_since(_ra(same_second), FAULT_AT)
    assert record is not None and record.to_autopilot == "px4-b"


def test_the_active_autopilot_is_unknown_until_the_agent_reports() -> None:
    assert director.active_autopilot({"status": {}}) is None
    assert director.active_autopilot({}) is None
    assert director.active_autopilot(_ra(None)) == "px4-b"
    assert director.active_autopilot({"status": {"autopilots": "garbage"}}) is None


@pytest.mark.parametrize(
    ("phase", "done"),
    [
        (None, False),
        ("Run", False),
        ("Holding", False),
        ("Landing", False),
        ("ReturningToLaunch", False),
        ("Landed", True),
        ("Held", True),
        ("Failed", True),
        ("Disarmed", True),
        ("Cancelled", False),
        ("Skipped: pilot in manual mode", True),
    ],
)
def test_the_safety_routine_is_done_only_in_a_final_phase(phase: str | None, done: bool) -> None:
    assert director.routine_done(phase) is done


def test_mission_phase_defaults_to_pending() -> None:
    assert director.mission_phase({}) == "Pending"
    assert director.mission_phase({"status": {"phase": "Running"}}) == "Running"


@pytest.mark.parametrize(
    ("ms", "text"), [(0.4, "0.40 ms"), (7.46, "7.5 ms"), (21.4, "21 ms"), (1500.0, "1500 ms")]
)
def test_latency_reads_well_at_every_scale(ms: float, text: str) -> None:
    assert format_latency(ms) == text


def test_each_sim_binds_a_port_of_its_own_choosing_at_its_vehicles_home() -> None:
    fleet = plan.plan_fleet(2)
    config = sims.sim_config(fleet)
    assert (config["fast_boot"], config["preset_streams"]) == (True, True)
    first, second = config["vehicles"]
    assert first == {
        "name": "drone-1",
        "home_lat_deg": 47.397742,
        "home_lon_deg": 8.545594,
        "autopilots": [
            {"name": "px4-a", "stack": "px4", "sysid": 1, "udp_bind": "127.0.0.1:0"},
            {"name": "px4-b", "stack": "px4", "sysid": 2, "udp_bind": "127.0.0.1:0"},
        ],
    }
    assert second["name"] == "drone-2"
    assert second["home_lon_deg"] == round(sims.home(1)[1], 9)
    assert [a["sysid"] for a in second["autopilots"]] == [a.sysid for a in fleet[1].autopilots]


@pytest.mark.parametrize(
    ("count", "sizes"), [(1, [1]), (10, [10]), (11, [5, 6]), (21, [7, 7, 7]), (25, [8, 8, 9])]
)
def test_vehicles_share_few_simulator_processes_of_similar_size(
    count: int, sizes: list[int]
) -> None:
    fleet = plan.plan_fleet(count)
    groups = sims.process_groups(fleet)
    assert [len(g) for g in groups] == sizes
    assert [v for g in groups for v in g] == list(fleet)  # each vehicle once, in order


def test_sandbox_vehicles_start_apart_on_an_east_west_line() -> None:
    first, second = sims.home(0), sims.home(1)
    assert first[0] == second[0]
    metres = (second[1] - first[1]) * 111_320.0 * math.cos(math.radians(first[0]))
    assert metres == pytest.approx(sims.SPACING_M)


def test_fault_requests_follow_the_simulators_fault_table() -> None:
    assert sims.fault_message("sensor", "gyro") == {
        "op": "fault",
        "kind": "sensor",
        "value": "gyro",
    }
    assert sims.fault_message("clear", None) == {"op": "clear", "kind": None}
    with pytest.raises(CliError, match="unknown fault 'melt': one of silence"):
        sims.fault_message("melt", None)


def test_the_sandbox_reads_the_url_each_agent_announces() -> None:
    log = '2026 INFO roost_agent: started\n{"event": "Started"}\n{"telemetry": "ws://127.0.0.1:4242/"}\n'
    assert announced_telemetry(log) == "ws://127.0.0.1:4242/"
    assert announced_telemetry('{"telemetry": ') is None


_NO_STATE = state.SandboxState(pid=1, create_time=0.0, directory="/nonexistent")
"""A sandbox with no vehicles: the retry tests touch neither simulators nor cluster."""


def test_a_poll_the_api_server_does_not_answer_is_asked_again() -> None:
    script = director.Script()
    directing = director.Director(lambda: pytest.fail("no fleet needed"), _NO_STATE, script, None)
    answers: list[bool | CliError] = [CliError("the API server did not answer"), False, True]

    def poll() -> bool:
        answer = answers.pop(0)
        if isinstance(answer, CliError):
            raise answer
        return answer

    assert directing._wait(poll, timeout_s=30.0) is True
    assert answers == []
    assert [style for _, style in script.lines()] == ["dim"]


def test_a_poll_that_never_answers_ends_at_the_timeout() -> None:
    directing = director.Director(
        lambda: pytest.fail("no fleet needed"), _NO_STATE, director.Script(), None
    )

    def poll() -> bool:
        raise CliError("the API server did not answer")

    assert directing._wait(poll, timeout_s=0.0) is False


@pytest.mark.parametrize(
    ("conditions", "ready"),
    [
        ([{"type": "Ready", "status": "True"}], True),
        ([{"type": "Ready", "status": "False"}], False),
        ([{"type": "Ready", "status": "Unknown"}], False),
        ([{"type": "NodeBound", "status": "True"}], False),
        (None, False),
    ],
)
def test_a_vehicle_is_ready_only_when_its_ready_condition_is_true(
    conditions: list[dict[str, str]] | None, ready: bool
) -> None:
    vehicle: dict[str, Any] = {"metadata": {"name": "drone-1"}}
    if conditions is not None:
        vehicle["status"] = {"conditions": conditions}
    assert director.vehicle_ready(vehicle) is ready
