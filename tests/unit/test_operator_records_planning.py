"""Mission records, the pure part (roost_operator.records.planning) and its start in the
Mission state machine: which flights belong to a Mission, what is fetched, what is
missing and why, each vehicle's and the bundle's state, retention. Decision tables;
every input is built as the agent's ``GET /records`` would list it. No mocks.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest

from roost_api.mission import MissionPhase, RecordsState
from roost_operator.missions.machine import plan_mission
from roost_operator.missions.observed import JobPhase
from roost_operator.records.planning import (
    AgentFlight,
    BundleInfo,
    Listing,
    VehiclePlan,
    VehicleState,
    Window,
    bundle_name,
    bundle_state,
    expired,
    not_gathered,
    overlaps,
    plan_vehicle,
    records_status,
    safe_path,
)
from roost_operator.records.settings import AgentRecords, RecordsSettings, parse_agent_records
from tests.support.missions import claimed, job, mission_spec, observe, started

START = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)
END = START + timedelta(minutes=10)
WINDOW = Window(START, END)
SETTINGS = RecordsSettings()


def at(minutes: float) -> datetime:
    return START + timedelta(minutes=minutes)


def flight(
    armed: float,
    disarmed: float | None,
    *,
    state: str = "Complete",
    files: list[dict[str, Any]] | None = None,
    vehicle: str = "a",
) -> AgentFlight:
    armed_at = at(armed)
    return AgentFlight.parse(
        {
            "flightId": f"{vehicle}-{armed_at:%Y%m%dT%H%M%SZ}",
            "vehicle": vehicle,
            "armedAt": armed_at.isoformat().replace("+00:00", "Z"),
            "disarmedAt": at(disarmed).isoformat() if disarmed is not None else None,
            "state": state,
            "files": files
            if files is not None
            else [{"path": "hub.tlog", "kind": "tlog", "state": "Complete", "sha256": "ab" * 32}],
        }
    )


@pytest.mark.parametrize(
    ("armed", "disarmed", "belongs"),
    [
        (1, 9, True),  # inside the run
        (-5, 1, True),  # armed before the start, landed during it
        (9, 15, True),  # armed during, landed after the end
        (-5, 15, True),  # spans the whole run
        (-10, -1, False),  # a flight before the mission
        (11, 12, False),  # a flight after it
        (10, 12, True),  # armed exactly at the end
        (-3, 0, True),  # disarmed exactly at the start
        (-3, None, True),  # still armed now (now is after the start)
        (12, None, False),  # armed after the end, still in the air
    ],
)
def test_a_flight_belongs_when_its_armed_interval_overlaps_the_missions_run(
    armed: float, disarmed: float | None, belongs: bool
) -> None:
    assert overlaps(flight(armed, disarmed), WINDOW, now=at(20)) is belongs


def plan(listing: Listing, now: float = 11, **kwargs: Any) -> VehiclePlan:
    return plan_vehicle(
        listing,
        WINDOW,
        held=kwargs.pop("held", frozenset()),
        attempts=kwargs.pop("attempts", {}),
        now=at(now),
        settings=kwargs.pop("settings", SETTINGS),
    )


def test_only_the_missions_flights_are_fetched() -> None:
    before, during, after = flight(-30, -20), flight(1, 9), flight(30, 40)
    result = plan(Listing("a", (after, during, before)), now=50)
    assert [f.flight_id for f in result.flights] == [during.flight_id]
    assert [(f.flight_id, f.file.path) for f in result.fetch] == [(during.flight_id, "hub.tlog")]
    assert result.state is VehicleState.PENDING


def test_a_vehicle_with_everything_held_is_complete() -> None:
    during = flight(1, 9)
    result = plan(Listing("a", (during,)), held=frozenset({(during.flight_id, "hub.tlog")}))
    assert result.state is VehicleState.COMPLETE and result.fetch == [] and result.missing == []


def test_a_vehicle_that_did_not_fly_is_complete_and_says_so() -> None:
    result = plan(Listing("a", ()))
    assert result.state is VehicleState.COMPLETE
    assert "no flight" in (result.message or "")


@pytest.mark.parametrize(
    ("agents", "direct", "state"),
    [
        # the agents serve where the operator reaches them: gather
        (AgentRecords.REACHABLE, False, None),
        (AgentRecords.REACHABLE, True, None),
        # the chart's default, loopback only: final at once, never retried
        (AgentRecords.ON_VEHICLE, False, VehicleState.ON_VEHICLE),
        # a Vehicle naming its records server's URL is reached whatever the setting
        (AgentRecords.ON_VEHICLE, True, None),
        (AgentRecords.OFF, False, VehicleState.NOT_RECORDED),
        (AgentRecords.OFF, True, None),
    ],
)
def test_a_vehicle_is_contacted_only_when_its_records_can_be_reached(
    agents: AgentRecords, direct: bool, state: VehicleState | None
) -> None:
    result = not_gathered("a", agents, direct=direct, node="node-a", port=9468)
    if state is None:
        assert result is None
        return
    assert result is not None and result.state is state and result.fetch == []
    assert [(m.vehicle, m.reason) for m in result.missing] == [("a", result.message)]


def test_a_vehicle_kept_on_board_says_where_its_flights_are_and_how_to_gather_them() -> None:
    kept = not_gathered("a", AgentRecords.ON_VEHICLE, direct=False, node="node-a", port=9468)
    assert kept is not None and kept.message is not None
    for words in ("agent.records.bindNodeAddress: true", "node-a", "127.0.0.1:9468/records"):
        assert words in kept.message
    off = not_gathered("a", AgentRecords.OFF, direct=False, node="node-a", port=9468)
    assert off is not None and "agent.records.enabled: false" in (off.message or "")
    status = records_status(
        "b", [kept, VehiclePlan("c", VehicleState.COMPLETE)], previous=None, now=at(1)
    )
    assert status.state == RecordsState.PARTIAL and status.ready_time == at(1)
    assert status.message == "not gathered: a (each vehicle's message says where its flights are)"
    assert [(v.name, v.state, v.message) for v in status.vehicles] == [
        ("a", "OnVehicle", kept.message),
        ("c", "Complete", None),
    ]


@pytest.mark.parametrize(
    ("text", "agents"),
    [
        ("reachable", AgentRecords.REACHABLE),
        ("on-vehicle", AgentRecords.ON_VEHICLE),
        (" OFF ", AgentRecords.OFF),
        ("yes", None),
    ],
)
def test_the_agents_records_setting_is_parsed_or_refused_with_the_accepted_values(
    text: str, agents: AgentRecords | None
) -> None:
    if agents is None:
        with pytest.raises(ValueError, match="reachable, on-vehicle, off"):
            parse_agent_records(text)
    else:
        assert parse_agent_records(text) is agents


@pytest.mark.parametrize(
    ("since_end", "state", "reason"),
    [
        (timedelta(minutes=1), VehicleState.PENDING, "gathered when it is back"),
        (timedelta(hours=23), VehicleState.PENDING, "gathered when it is back"),
        (timedelta(hours=24), VehicleState.MISSING, "unreachable"),
    ],
)
def test_an_unreachable_vehicle_is_waited_for_then_given_up(
    since_end: timedelta, state: VehicleState, reason: str
) -> None:
    result = plan_vehicle(
        Listing("a", error="connection refused"),
        WINDOW,
        held=frozenset(),
        attempts={},
        now=END + since_end,
        settings=SETTINGS,
    )
    assert result.state is state
    assert reason in (result.message or "")
    assert bool(result.missing) is (state is VehicleState.MISSING)


@pytest.mark.parametrize(
    ("flight_state", "since_end", "fetches", "state"),
    [
        ("Recording", timedelta(minutes=1), False, VehicleState.PENDING),
        ("Landed", timedelta(minutes=1), False, VehicleState.PENDING),  # logs still coming
        ("Landed", timedelta(minutes=15), True, VehicleState.PENDING),  # settled: take it
        ("Complete", timedelta(0), True, VehicleState.PENDING),
        ("Failed", timedelta(0), True, VehicleState.PENDING),
    ],
)
def test_a_flight_is_fetched_once_final_or_settled(
    flight_state: str, since_end: timedelta, fetches: bool, state: VehicleState
) -> None:
    result = plan_vehicle(
        Listing("a", (flight(1, 9, state=flight_state),)),
        WINDOW,
        held=frozenset(),
        attempts={},
        now=END + since_end,
        settings=SETTINGS,
    )
    assert bool(result.fetch) is fetches
    assert result.state is state


def test_what_the_vehicle_failed_or_kept_partial_is_named_in_missing() -> None:
    files = [
        {"path": "hub.tlog", "kind": "tlog", "state": "Complete", "sha256": "ab" * 32},
        {
            "path": "autopilot-logs/ap1/3.ulg",
            "kind": "autopilot-log",
            "autopilot": "ap1",
            "state": "Failed",
            "message": "log download cut by a reboot",
        },
        {"path": "decisions.jsonl", "kind": "decisions", "state": "Partial"},
        {"path": "../../etc/passwd", "kind": "tlog", "state": "Complete", "sha256": "cd" * 32},
    ]
    during = flight(1, 9, files=files)
    first = plan(Listing("a", (during,)))
    assert [f.file.path for f in first.fetch] == ["hub.tlog", "decisions.jsonl"]
    held = frozenset({(during.flight_id, "hub.tlog"), (during.flight_id, "decisions.jsonl")})
    result = plan(Listing("a", (during,)), held=held)
    assert result.state is VehicleState.PARTIAL
    reasons = {m.path: m.reason for m in result.missing}
    assert reasons == {
        "autopilot-logs/ap1/3.ulg": "Failed on the vehicle: log download cut by a reboot",
        "decisions.jsonl": "Partial on the vehicle",
        "../../etc/passwd": "path outside the flight refused",
    }


@pytest.mark.parametrize(("attempts", "fetched"), [(0, True), (2, True), (3, False)])
def test_a_corrupt_file_is_downloaded_again_then_counted_corrupt(
    attempts: int, fetched: bool
) -> None:
    during = flight(1, 9)
    result = plan(Listing("a", (during,)), attempts={(during.flight_id, "hub.tlog"): attempts})
    assert bool(result.fetch) is fetched
    if not fetched:
        assert result.state is VehicleState.PARTIAL
        assert "sha256 did not match after 3 downloads" in result.missing[0].reason


@pytest.mark.parametrize(
    ("states", "bundle"),
    [
        ([VehicleState.COMPLETE, VehicleState.COMPLETE], RecordsState.COMPLETE),
        ([VehicleState.COMPLETE, VehicleState.PENDING], RecordsState.GATHERING),
        ([VehicleState.PARTIAL, VehicleState.PENDING], RecordsState.GATHERING),
        ([VehicleState.COMPLETE, VehicleState.PARTIAL], RecordsState.PARTIAL),
        ([VehicleState.COMPLETE, VehicleState.MISSING], RecordsState.PARTIAL),
        ([VehicleState.ON_VEHICLE, VehicleState.ON_VEHICLE], RecordsState.PARTIAL),
        ([VehicleState.NOT_RECORDED], RecordsState.PARTIAL),
        ([VehicleState.ON_VEHICLE, VehicleState.PENDING], RecordsState.GATHERING),
    ],
)
def test_the_bundle_is_gathering_while_a_vehicle_is_pending(
    states: list[VehicleState], bundle: RecordsState
) -> None:
    plans = [VehiclePlan(f"v{i}", s) for i, s in enumerate(states)]
    assert bundle_state(plans) is bundle


def test_ready_time_is_set_once_when_the_bundle_becomes_final() -> None:
    pending = records_status(
        "b", [VehiclePlan("a", VehicleState.PENDING)], previous=None, now=at(1)
    )
    assert pending.ready_time is None and pending.message == "pending: a"
    done = records_status(
        "b", [VehiclePlan("a", VehicleState.COMPLETE)], previous=pending, now=at(2)
    )
    assert done.ready_time == at(2)
    again = records_status("b", [VehiclePlan("a", VehicleState.COMPLETE)], previous=done, now=at(3))
    assert again.ready_time == at(2)


def info(name: str, days_ago: float | None, written_days_ago: float = 0) -> BundleInfo:
    ready = None if days_ago is None else at(0) - timedelta(days=days_ago)
    return BundleInfo(name, ready, at(0) - timedelta(days=written_days_ago))


@pytest.mark.parametrize(
    ("keep_count", "keep_for", "gone"),
    [
        (0, None, []),
        (2, None, ["old"]),
        (1, None, ["mid", "old"]),
        (0, timedelta(days=10), ["old"]),
        (5, timedelta(days=1), ["mid", "old"]),
    ],
)
def test_retention_removes_the_oldest_final_bundles_never_one_gathering(
    keep_count: int, keep_for: timedelta | None, gone: list[str]
) -> None:
    bundles = [info("new", 0.5), info("mid", 5), info("old", 20), info("gathering", None, 1)]
    assert expired(bundles, keep_count=keep_count, keep_for=keep_for, now=at(0)) == gone


def test_a_bundle_left_gathering_by_a_deleted_mission_ages_out_from_its_last_write() -> None:
    left = [info("left", None, written_days_ago=40), info("recent", None, written_days_ago=1)]
    gone = expired(
        left,
        keep_count=0,
        keep_for=timedelta(days=30),
        now=at(0),
        abandoned_after=timedelta(days=2),
    )
    assert gone == ["left"]


@pytest.mark.parametrize(
    ("path", "safe"),
    [
        ("hub.tlog", True),
        ("autopilot-logs/ap1/1.ulg", True),
        ("../x", False),
        ("/etc/passwd", False),
        ("a/../../x", False),
        ("", False),
    ],
)
def test_paths_outside_a_flight_are_refused(path: str, safe: bool) -> None:
    assert safe_path(path) is safe


def test_bundle_names_are_unique_per_mission_object() -> None:
    assert bundle_name("flights", "survey", "1234abcd-0000") == "flights_survey_1234abcd"


# -- the state machine starts the record ----------------------------------------------------


def test_a_mission_that_flew_starts_gathering_when_it_ends() -> None:
    status, vehicles = started(["a", "b"])
    obs = observe(
        vehicles, status=status, jobs=[job("a", JobPhase.SUCCEEDED), job("b", JobPhase.SUCCEEDED)]
    )
    plan = plan_mission(replace(obs, records=True))
    assert plan.status.phase == MissionPhase.SUCCEEDED
    records = plan.status.records
    assert records is not None and records.state == RecordsState.GATHERING
    assert [v.name for v in records.vehicles] == ["a", "b"]
    assert plan.requeue_after == 0.0
    assert plan_mission(obs).status.records is None  # records off: nothing
    ended = replace(obs, status=plan_mission(obs).status, records=True)
    assert plan_mission(ended).status.records is None  # ended before records were on


def test_a_mission_that_never_flew_gets_no_record() -> None:
    obs = observe(claimed("a"), spec=mission_spec(abort=True))
    plan = plan_mission(replace(obs, records=True))
    assert plan.status.phase == MissionPhase.ABORTED
    assert plan.status.records is None
