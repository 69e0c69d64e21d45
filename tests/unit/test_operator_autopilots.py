"""Decision tables of the operator's side of failover (roost_operator.autopilots).

Pure functions only: AgentConnected/AutopilotsHealthy from the agent's report, the fleet
guards (pause, latch, concurrency cap), failover accounting across partitions and
restarts, and the whole per-vehicle plan (re-point mavros, Events).
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from functools import partial
from typing import Any

import pytest

from roost_api.autopilot import (
    AutopilotHealth,
    FailoverRecord,
    HubSpec,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.vehicle import FailoverAction, VehicleFailover, VehicleSpec, VehicleStatus
from roost_api.wellknown import ANNOTATION_CLEAR_FAILOVER_LATCH, ANNOTATION_PAUSE_FAILOVER_ACTIONS
from roost_operator.autopilots.conditions import (
    agent_connected,
    autopilots_healthy,
)
from roost_operator.autopilots.guards import (
    FleetGuards,
    Verdict,
    check,
    clear_latch,
    consequence_verdict,
    new_failovers,
    observe_failovers,
    vehicle_paused,
)
from roost_operator.autopilots.plan import FailoverPlan, plan
from roost_operator.vehicles.conditions import ready_condition
from roost_operator.vehicles.config import config_hash
from roost_operator.vehicles.controller import ActionLedger
from roost_operator.vehicles.manifests import autopilots_of
from roost_operator.vehicles.pods import mavros_follows
from tests.support.conditions import cond as support_cond

NOW = datetime(2026, 5, 1, 12, 0, 0, tzinfo=UTC)
NODE = "drone-1"
URL1 = "udp://127.0.0.1:14541"
URL2 = "udp://127.0.0.1:14542"


cond = partial(support_cond, at=NOW)


def ra_spec(**policy: Any) -> RedundantAutopilotSpec:
    return RedundantAutopilotSpec.model_validate(
        {
            "vehicleName": "v1",
            "primary": "fc1",
            "autopilots": [
                {"name": "fc1", "stack": "px4", "connection": URL1, "sysid": 1, "bridgeChannel": 0},
                {"name": "fc2", "stack": "px4", "connection": URL2, "sysid": 2, "bridgeChannel": 1},
            ],
            "failoverPolicy": policy,
        }
    )


def failover(at: datetime, frm: str = "fc1", to: str = "fc2") -> FailoverRecord:
    return FailoverRecord.model_validate(
        {
            "time": at,
            "from": frm,
            "to": to,
            "reason": f"heartbeat lost on {frm}",
            "latencyMs": 3.2,
            "trigger": "Automatic",
        }
    )


def ra_status(
    *,
    active: str = "fc1",
    reported: datetime | None = NOW,
    ready: str = "True",
    active_healthy: str = "True",
    redundant: str = "True",
    failed_over: str = "False",
    count: int = 0,
    last: FailoverRecord | None = None,
    healths: list[AutopilotHealth] | None = None,
) -> RedundantAutopilotStatus:
    return RedundantAutopilotStatus(
        active_autopilot=active,
        reported_at=reported,
        node_name=NODE,
        failover_count=count,
        last_failover=last,
        autopilots=healths or [],
        conditions=[
            cond("Ready", ready, "Ready" if ready == "True" else "NotRedundant", "ready msg"),
            cond("ActiveHealthy", active_healthy, message="active msg"),
            cond("Redundant", redundant, message="redundant msg"),
            cond("FailedOver", failed_over, message="failed over msg"),
        ],
    )


# -- AgentConnected -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("reported", "node", "status", "reason"),
    [
        (None, NODE, "Unknown", "NeverReported"),
        (NOW - timedelta(seconds=5), NODE, "True", "Reporting"),
        (NOW - timedelta(seconds=30), NODE, "True", "Reporting"),
        (NOW - timedelta(seconds=31), NODE, "Unknown", "ReportsStale"),
        (NOW + timedelta(seconds=20), NODE, "True", "Reporting"),  # drone clock ahead
        (NOW, "drone-old", "Unknown", "ReportFromOtherNode"),
    ],
)
def test_agent_connected_is_true_while_reports_are_fresh_and_unknown_never_false(
    reported: datetime | None, node: str, status: str, reason: str
) -> None:
    report = ra_status(reported=reported).model_copy(update={"node_name": node})
    got = agent_connected(report, vehicle_node=NODE, now=NOW, stale_after=timedelta(seconds=30))
    assert (got.type, got.status, got.reason) == ("AgentConnected", status, reason)


# -- AutopilotsHealthy ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("ready", "active", "redundant", "failed_over", "expected"),
    [
        ("True", "True", "True", "False", ("True", "Redundant")),
        ("True", "True", "True", "True", ("True", "Redundant")),  # manual switch, both healthy
        ("False", "False", "True", "False", ("False", "ActiveUnhealthy")),
        ("False", "False", "False", "True", ("False", "ActiveUnhealthy")),  # worst first
        ("False", "True", "False", "True", ("False", "FailedOver")),
        ("False", "True", "False", "False", ("False", "NotRedundant")),
        ("Unknown", "Unknown", "True", "False", ("Unknown", "ActiveHealthUnknown")),
        ("Unknown", "True", "Unknown", "False", ("Unknown", "RedundancyUnknown")),
    ],
)
def test_autopilots_healthy_follows_the_agents_conditions_naming_the_first_problem(
    ready: str, active: str, redundant: str, failed_over: str, expected: tuple[str, str]
) -> None:
    report = ra_status(
        ready=ready, active_healthy=active, redundant=redundant, failed_over=failed_over
    )
    connected = agent_connected(report, vehicle_node=NODE, now=NOW)
    got = autopilots_healthy(report, connected)
    assert (got.type, got.status, got.reason) == ("AutopilotsHealthy", *expected)


def test_autopilots_healthy_is_unknown_when_the_agent_is_not_connected() -> None:
    report = ra_status(reported=NOW - timedelta(minutes=5), ready="True")
    connected = agent_connected(report, vehicle_node=NODE, now=NOW)
    got = autopilots_healthy(report, connected)
    assert (got.status, got.reason) == ("Unknown", "AgentNotConnected")
    assert "last reported 300 s ago" in got.message


def test_failed_over_message_says_what_happened_and_what_is_missing() -> None:
    report = ra_status(ready="False", redundant="False", failed_over="True")
    got = autopilots_healthy(report, agent_connected(report, vehicle_node=NODE, now=NOW))
    assert got.message == "failed over msg; redundant msg"


def test_autopilots_healthy_without_any_agent_conditions_is_unknown() -> None:
    report = RedundantAutopilotStatus(reported_at=NOW, node_name=NODE)
    got = autopilots_healthy(report, agent_connected(report, vehicle_node=NODE, now=NOW))
    assert (got.status, got.reason) == ("Unknown", "ActiveHealthUnknown")


# -- guards ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("fleet_paused", "paused_here", "latched", "elsewhere", "verdict"),
    [
        (False, False, False, 0, Verdict.ALLOWED),
        (False, False, False, 4, Verdict.ALLOWED),
        (False, False, False, 5, Verdict.CONCURRENCY_LIMIT),
        (False, False, True, 0, Verdict.LATCHED),
        (False, True, False, 0, Verdict.PAUSED),
        (True, False, False, 0, Verdict.PAUSED),
        (True, False, True, 9, Verdict.PAUSED),  # pause reported first
        (False, False, True, 9, Verdict.LATCHED),  # then the latch, then the cap
    ],
)
def test_guard_decision_table(
    fleet_paused: bool, paused_here: bool, latched: bool, elsewhere: int, verdict: Verdict
) -> None:
    guards = FleetGuards(max_concurrent_actions=5, paused=fleet_paused)
    got = check(guards, paused_here=paused_here, latched=latched, actions_elsewhere=elsewhere)
    assert got is verdict


@pytest.mark.parametrize(
    ("value", "paused"),
    [("true", True), ("True", True), ("1", True), ("false", False), ("", False)],
)
def test_pause_annotation(value: str, paused: bool) -> None:
    assert vehicle_paused({ANNOTATION_PAUSE_FAILOVER_ACTIONS: value}) is paused
    assert vehicle_paused({}) is False


# -- failover accounting --------------------------------------------------------------


T1 = NOW - timedelta(minutes=3)
T2 = NOW - timedelta(minutes=2)


@pytest.mark.parametrize(
    ("book", "count", "last", "new"),
    [
        (VehicleFailover(), 0, None, 0),
        (VehicleFailover(), 1, failover(T1), 1),
        (VehicleFailover(observed_failover_count=1, observed_failover_time=T1), 1, failover(T1), 0),
        (VehicleFailover(observed_failover_count=1, observed_failover_time=T1), 4, failover(T2), 3),
        # the agent restarted and counts from zero again: the latest is new if its time is
        (VehicleFailover(observed_failover_count=5, observed_failover_time=T1), 1, failover(T2), 1),
        (VehicleFailover(observed_failover_count=5, observed_failover_time=T1), 0, failover(T1), 0),
    ],
)
def test_new_failovers_are_counted_once_even_across_partitions_and_restarts(
    book: VehicleFailover, count: int, last: FailoverRecord | None, new: int
) -> None:
    assert new_failovers(book, ra_status(count=count, last=last)) == new


def test_the_nth_failover_within_the_window_latches_and_old_ones_age_out() -> None:
    guards = FleetGuards(latch_after=3, latch_window=timedelta(minutes=10))
    book = VehicleFailover(
        observed_failover_count=2,
        observed_failover_time=T1,
        recent=[NOW - timedelta(minutes=11), T1],
    )
    # one aged out: two within the window after this failover -> no latch yet
    book, new = observe_failovers(
        book, ra_status(count=3, last=failover(T2)), guards=guards, now=NOW
    )
    assert new == 1 and not book.latched and book.recent == [T1, T2]
    book, new = observe_failovers(
        book, ra_status(count=4, last=failover(NOW)), guards=guards, now=NOW
    )
    assert new == 1 and book.latched and book.latched_at == NOW
    # seeing the same report again changes nothing
    again, new = observe_failovers(
        book, ra_status(count=4, last=failover(NOW)), guards=guards, now=NOW
    )
    assert new == 0 and again == book


def test_switches_piled_up_during_a_partition_can_trip_the_latch_at_once() -> None:
    guards = FleetGuards(latch_after=3)
    book, new = observe_failovers(
        VehicleFailover(), ra_status(count=3, last=failover(T2)), guards=guards, now=NOW
    )
    assert new == 3 and book.latched and book.recent == [T2, T2, T2]


@pytest.mark.parametrize(
    ("latched", "token", "recorded", "cleared", "still_latched"),
    [
        (True, "t1", None, True, False),
        (True, "t1", "t1", False, True),  # a token clears one latch only
        (True, None, None, False, True),
        (False, "t2", "t1", False, False),  # recorded, so it cannot clear a later latch
    ],
)
def test_a_human_clears_the_latch_with_a_new_token(
    latched: bool, token: str | None, recorded: str | None, cleared: bool, still_latched: bool
) -> None:
    book = VehicleFailover(
        latched=latched, latched_at=T1 if latched else None, recent=[T1, T2], cleared_token=recorded
    )
    annotations = {ANNOTATION_CLEAR_FAILOVER_LATCH: token} if token else {}
    after, did = clear_latch(book, annotations)
    assert did is cleared and after.latched is still_latched
    assert after.cleared_token == (token or recorded)
    if cleared:
        assert after.recent == [] and after.latched_at is None


# -- mission consequences: pause and latch, never the cap ------------------------------

PAUSE = {ANNOTATION_PAUSE_FAILOVER_ACTIONS: "true"}
LATCHED = VehicleFailover(
    latched=True, latched_at=T1, observed_failover_count=3, observed_failover_time=T1
)
TWO_RECENT = VehicleFailover(observed_failover_count=2, observed_failover_time=T1, recent=[T1, T1])


@pytest.mark.parametrize(
    ("fleet_paused", "annotations", "book", "status", "verdict"),
    [
        (False, {}, None, ra_status(), Verdict.ALLOWED),
        (False, PAUSE, None, ra_status(), Verdict.PAUSED),
        (True, {}, None, ra_status(), Verdict.PAUSED),
        (False, {}, LATCHED, ra_status(count=3, last=failover(T1)), Verdict.LATCHED),
        (False, PAUSE, LATCHED, ra_status(count=3, last=failover(T1)), Verdict.PAUSED),
        # a new clear token lifts the latch before the vehicle's reconcile has honoured it
        (
            False,
            {ANNOTATION_CLEAR_FAILOVER_LATCH: "t1"},
            LATCHED,
            ra_status(count=3, last=failover(T1)),
            Verdict.ALLOWED,
        ),
        # the failover that trips the latch is held even before the latch is written
        (False, {}, TWO_RECENT, ra_status(count=3, last=failover(T2)), Verdict.LATCHED),
        (False, {}, TWO_RECENT, ra_status(count=2, last=failover(T1)), Verdict.ALLOWED),
    ],
)
def test_mission_consequence_guard_decision_table(
    fleet_paused: bool,
    annotations: dict[str, str],
    book: VehicleFailover | None,
    status: RedundantAutopilotStatus,
    verdict: Verdict,
) -> None:
    guards = FleetGuards(latch_after=3, paused=fleet_paused)
    got = consequence_verdict(guards, annotations=annotations, book=book, status=status, now=NOW)
    assert got is verdict


def test_mission_consequences_never_wait_for_the_concurrency_cap() -> None:
    full = FleetGuards(max_concurrent_actions=0)
    assert check(full, paused_here=False, latched=False, actions_elsewhere=0) is (
        Verdict.CONCURRENCY_LIMIT
    )
    got = consequence_verdict(full, annotations={}, book=None, status=ra_status(), now=NOW)
    assert got is Verdict.ALLOWED


# -- the whole plan -------------------------------------------------------------------


def vehicle_spec(mavros: bool = True) -> VehicleSpec:
    return VehicleSpec.model_validate(
        {"nodeName": NODE, "sysid": 10, "components": {"mavros": {"enabled": mavros}}}
    )


def run(
    *,
    status: VehicleStatus,
    report: RedundantAutopilotStatus,
    spec: RedundantAutopilotSpec | None = None,
    guards: FleetGuards | None = None,
    annotations: dict[str, str] | None = None,
    elsewhere: int = 0,
    rollout_done: bool = False,
    now: datetime = NOW,
) -> FailoverPlan:
    autopilots = spec or ra_spec()
    return plan(
        vehicle_name="v1",
        vehicle_spec=vehicle_spec(),
        vehicle_status=status,
        annotations=annotations or {},
        autopilot_spec=autopilots,
        autopilot_status=report,
        fcu_urls={a.name: a.fcu_url for a in autopilots_of(vehicle_spec(), autopilots)},
        guards=guards or FleetGuards(),
        paused_here=vehicle_paused(annotations or {}),
        actions_elsewhere=elsewhere,
        rollout_done=rollout_done,
        now=now,
    )


def pointed_at(name: str, url: str, **book: Any) -> VehicleStatus:
    return VehicleStatus(
        active_autopilot=name,
        fcu_url=url,
        failover=VehicleFailover(followed_autopilot=name, **book),
    )


def reasons(result: FailoverPlan) -> list[str]:
    return [e.reason for e in result.events]


def test_first_pointing_is_set_up_not_a_guarded_action() -> None:
    result = run(status=VehicleStatus(), report=ra_status(), guards=FleetGuards(paused=True))
    assert (result.fcu_url, result.failover.followed_autopilot) == (URL1, "fc1")
    assert result.failover.action is None and result.failover.blocked is None
    assert reasons(result) == []


def test_an_existing_fcu_url_tells_which_autopilot_is_followed() -> None:
    result = run(status=VehicleStatus(fcu_url=URL1), report=ra_status(active="fc2"))
    assert result.failover.followed_autopilot == "fc2"
    assert result.failover.action is not None and result.failover.action.autopilot == "fc2"


def test_a_failover_repoints_mavros_records_the_action_and_degrades_the_vehicle() -> None:
    report = ra_status(
        active="fc2",
        ready="False",
        redundant="False",
        failed_over="True",
        count=1,
        last=failover(T2),
    )
    result = run(status=pointed_at("fc1", URL1), report=report)
    assert (result.active_autopilot, result.fcu_url) == ("fc2", URL2)
    assert result.failover.followed_autopilot == "fc2"
    assert result.failover.action == FailoverAction(
        kind="RepointMavros", autopilot="fc2", started_at=NOW
    )
    assert result.acting
    assert reasons(result) == ["FailedOver", "RepointingMavros"]
    assert result.events[0].at == T2  # named after the failover: a re-post is a duplicate
    assert [(c.type, c.status, c.reason) for c in result.conditions] == [
        ("AgentConnected", "True", "Reporting"),
        ("AutopilotsHealthy", "False", "FailedOver"),
    ]


def test_the_plan_is_stable_once_written_so_a_restarted_operator_repeats_nothing() -> None:
    report = ra_status(active="fc2", count=1, last=failover(T2))
    first = run(status=pointed_at("fc1", URL1), report=report)
    written = VehicleStatus(
        active_autopilot=first.active_autopilot, fcu_url=first.fcu_url, failover=first.failover
    )
    later = NOW + timedelta(seconds=1)
    second = run(status=written, report=report, now=later)
    assert second.failover == first.failover and second.events == ()
    done = run(status=written, report=report, now=later, rollout_done=True)
    assert done.failover.action is None and reasons(done) == ["MavrosRepointed"]
    assert not done.acting


def test_an_action_that_never_finishes_stops_counting_after_the_timeout() -> None:
    action = FailoverAction(kind="RepointMavros", autopilot="fc2", started_at=NOW)
    status = pointed_at("fc2", URL2, action=action)
    guards = FleetGuards(action_timeout=timedelta(seconds=60))
    waiting = run(status=status, report=ra_status(active="fc2"), guards=guards, now=NOW)
    assert waiting.failover.action == action and waiting.events == ()
    late = NOW + timedelta(seconds=61)
    timed_out = run(status=status, report=ra_status(active="fc2"), guards=guards, now=late)
    assert timed_out.failover.action is None and reasons(timed_out) == ["MavrosRepointTimedOut"]


@pytest.mark.parametrize(
    ("guards", "annotations", "elsewhere", "blocked"),
    [
        (FleetGuards(paused=True), {}, 0, "Paused"),
        (FleetGuards(), {ANNOTATION_PAUSE_FAILOVER_ACTIONS: "true"}, 0, "Paused"),
        (FleetGuards(max_concurrent_actions=2), {}, 2, "ConcurrencyLimit"),
    ],
)
def test_a_guard_holds_the_repoint_back_but_the_vehicle_still_shows_the_true_active(
    guards: FleetGuards, annotations: dict[str, str], elsewhere: int, blocked: str
) -> None:
    report = ra_status(active="fc2", count=1, last=failover(T2))
    result = run(
        status=pointed_at("fc1", URL1),
        report=report,
        guards=guards,
        annotations=annotations,
        elsewhere=elsewhere,
    )
    assert result.active_autopilot == "fc2"  # what drives the motors, from the agent
    assert (result.fcu_url, result.failover.followed_autopilot) == (URL1, "fc1")
    assert result.failover.blocked == blocked and result.failover.action is None
    assert reasons(result) == ["FailedOver", "FailoverActionBlocked"]
    # the next reconcile does not repeat the Event; lifting the guard re-points
    held = VehicleStatus(active_autopilot="fc2", fcu_url=URL1, failover=result.failover)
    again = run(
        status=held, report=report, guards=guards, annotations=annotations, elsewhere=elsewhere
    )
    assert again.events == ()
    lifted = run(status=held, report=report)
    assert lifted.fcu_url == URL2 and lifted.failover.blocked is None
    assert reasons(lifted) == ["RepointingMavros"]


def test_the_failover_that_trips_the_latch_is_not_acted_on_until_a_human_clears_it() -> None:
    guards = FleetGuards(latch_after=3)
    book = {"observed_failover_count": 2, "observed_failover_time": T1, "recent": [T1, T1]}
    report = ra_status(active="fc2", count=3, last=failover(T2, frm="fc1", to="fc2"))
    result = run(status=pointed_at("fc1", URL1, **book), report=report, guards=guards)
    assert result.failover.latched and result.failover.blocked == "Latched"
    assert result.fcu_url == URL1
    assert reasons(result) == ["FailedOver", "FailoverLatched", "FailoverActionBlocked"]
    latched = VehicleStatus(active_autopilot="fc2", fcu_url=URL1, failover=result.failover)
    cleared = run(
        status=latched,
        report=report,
        guards=guards,
        annotations={ANNOTATION_CLEAR_FAILOVER_LATCH: "ok-by-alice"},
    )
    assert not cleared.failover.latched and cleared.fcu_url == URL2
    assert reasons(cleared) == ["FailoverLatchCleared", "RepointingMavros"]


def test_a_stale_agent_changes_conditions_but_not_the_followed_autopilot() -> None:
    report = ra_status(reported=NOW - timedelta(minutes=2))
    result = run(status=pointed_at("fc1", URL1), report=report)
    assert [c.status for c in result.conditions] == ["Unknown", "Unknown"]
    assert result.fcu_url == URL1 and result.events == ()


# -- end of a re-point, the cap's ledger, settings -----------------------------------


def config_map(url: str) -> dict[str, Any]:
    return {"data": {"vehicle.config": f"VEHICLE_FCU_URL={url}\n", "VEHICLE_FCU_URL": url}}


def mavros(
    config_hash_value: str, *, ready: str = "True", deleting: bool = False
) -> dict[str, Any]:
    meta: dict[str, Any] = {"annotations": {"roost.dev/config-hash": config_hash_value}}
    if deleting:
        meta["deletionTimestamp"] = "2024-01-01T00:00:00Z"
    return {
        "metadata": meta,
        "status": {"phase": "Running", "conditions": [{"type": "Ready", "status": ready}]},
    }


def test_mavros_follows_only_once_its_pod_comes_from_the_new_config_and_is_ready() -> None:
    new_hash = config_hash({"VEHICLE_FCU_URL": URL2})
    assert mavros_follows(URL2, config_map(URL2), mavros(new_hash))
    assert not mavros_follows(URL2, config_map(URL1), mavros(new_hash))  # config not yet
    old_hash = config_hash({"VEHICLE_FCU_URL": URL1})
    assert not mavros_follows(URL2, config_map(URL2), mavros(old_hash))  # old pod
    assert not mavros_follows(URL2, config_map(URL2), mavros(new_hash, ready="False"))  # starting
    assert not mavros_follows(URL2, config_map(URL2), mavros(new_hash, deleting=True))  # leaving
    assert not mavros_follows(URL2, None, mavros(new_hash))
    assert not mavros_follows(URL2, config_map(URL2), None)


def test_the_ledger_counts_actions_elsewhere_preferring_this_processs_own_writes() -> None:
    ledger = ActionLedger()
    with ledger.lock:
        assert ledger.others("v1", ["v1", "v2", "v3"]) == 2
        ledger.record("v2", False)  # finished here; the index has not caught up yet
        ledger.record("v4", True)  # started here; not in the index yet
        assert ledger.others("v1", ["v1", "v2", "v3"]) == 2  # v3 and v4
        assert ledger.others("v4", ["v3"]) == 1


def test_the_same_decision_made_later_names_the_same_events() -> None:
    """A crash between posting and writing must not record an Event twice."""
    report = ra_status(active="fc2", count=3, last=failover(T2))
    book = {"observed_failover_count": 2, "observed_failover_time": T1, "recent": [T1, T1]}
    for guards in (FleetGuards(), FleetGuards(latch_after=3), FleetGuards(paused=True)):
        first = run(status=pointed_at("fc1", URL1, **book), report=report, guards=guards)
        later = run(
            status=pointed_at("fc1", URL1, **book),
            report=report,
            guards=guards,
            now=NOW + timedelta(seconds=7),
        )
        assert first.events and first.events == later.events


def test_a_vehicle_with_redundant_autopilots_is_not_ready_before_its_agent_is_heard() -> None:
    bound = [cond("NodeBound", "True"), cond("ComponentsReady", "True")]
    assert ready_condition(bound) == ("True", "VehicleReady", "node bound, components ready")
    status, reason, _ = ready_condition(bound, agent_expected=True)
    assert (status, reason) == ("Unknown", "AgentNotHeardYet")
    heard = [*bound, cond("AgentConnected", "True"), cond("AutopilotsHealthy", "True")]
    assert ready_condition(heard, agent_expected=True)[0] == "True"


def test_with_the_hub_a_failover_never_repoints_or_rolls_mavros() -> None:
    spec = ra_spec().model_copy(update={"hub": HubSpec(udp="0.0.0.0:14550")})
    hub_url = "udp://:14555@127.0.0.1:14550"
    first = run(status=VehicleStatus(), report=ra_status(), spec=spec)
    assert (first.fcu_url, first.failover.followed_autopilot) == (hub_url, "fc1")
    report = ra_status(active="fc2", failed_over="True", count=1, last=failover(T2))
    result = run(status=pointed_at("fc1", hub_url), report=report, spec=spec)
    assert result.active_autopilot == "fc2"  # the vehicle shows the true active
    assert (result.fcu_url, result.failover.followed_autopilot) == (hub_url, "fc1")
    assert result.failover.action is None and not result.acting
    assert reasons(result) == ["FailedOver"]  # no RepointingMavros
