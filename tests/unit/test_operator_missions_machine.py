"""The Mission state machine (roost_operator.missions.machine): claims and Pending,
preflight, start and workloads, completion and failure, abort commands, failover policy
and the fleet guards, deletion, events.

Every input is an API model built as the API server would return it
(:mod:`tests.support.missions`); the functions under test are pure: no mocks.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime, timedelta

import pytest

from roost_api.autopilot import (
    CommandAction,
    CommandResult,
)
from roost_api.meta import condition_is_true, find_condition
from roost_api.mission import (
    MissionPhase,
    MissionSpec,
    MissionVehiclePhase,
)
from roost_api.vehicle import VehicleFailover
from roost_api.wellknown import (
    ANNOTATION_CLEAR_FAILOVER_LATCH,
    ANNOTATION_PAUSE_FAILOVER_ACTIONS,
)
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.missions.machine import (
    ABORT_COMMAND_DEADLINE_SECONDS,
    Observation,
    abort_command_id,
    plan_deletion,
    plan_mission,
    stopped,
    transition_events,
)
from roost_operator.missions.observed import (
    JobPhase,
)
from roost_operator.missions.workloads import (
    onboard_job_name,
)
from tests.support.missions import (
    ME,
    OTHER,
    T0,
    autopilots,
    claim_on,
    claimed,
    cond,
    config,
    job,
    mission_spec,
    observe,
    started,
    vehicle,
    vehicle_status,
)

# -- selection -----------------------------------------------------------------------------


# -- claims and Pending --------------------------------------------------------------------


def test_a_mission_claims_exactly_the_count_in_preference_order() -> None:
    plan = plan_mission(observe([vehicle("c"), vehicle("a"), vehicle("b")]))
    assert plan.claims == ["a", "b"]
    assert plan.jobs_to_create == []


def test_too_few_free_vehicles_keeps_the_mission_pending_and_gives_back_partial_claims() -> None:
    vehicles = [*claimed("a"), vehicle("b", claimed_by=OTHER), vehicle("c", ready=False)]
    plan = plan_mission(observe(vehicles, spec=mission_spec(vehicles={"selector": {}, "count": 3})))
    assert plan.status.phase == MissionPhase.PENDING
    assert plan.status.reason == "InsufficientVehicles"
    assert "2 missing" in (plan.status.message or "")
    assert plan.claims == []
    assert plan.releases == ["a"], "holding a partial set could deadlock two missions"
    assigned = find_condition(plan.status.conditions, "VehiclesAssigned")
    assert assigned is not None and assigned.status == "False"
    assert [e.reason for e in plan.events] == ["InsufficientVehicles"]
    assert plan.events[0].type == "Warning"


def test_once_vehicles_are_held_the_mission_stops_claiming() -> None:
    plan = plan_mission(observe([*claimed("a", "b"), vehicle("c")]))
    assert plan.claims == []
    assert plan.status.phase == MissionPhase.RUNNING


def test_a_vehicle_without_redundancy_may_fly_a_mission_that_does_not_require_it() -> None:
    single = vehicle("a")
    single.status.conditions = [
        *(c for c in single.status.conditions if c.type != "Ready"),
        cond("AutopilotsHealthy", "False", "NotRedundant"),
        cond("Ready", "False", "NotRedundant"),
    ]
    relaxed = mission_spec(
        vehicles={"names": ["a"], "count": 1}, preflight={"requireRedundancy": False}
    )
    obs = observe([single], spec=relaxed, aps=[autopilots("a", redundant=False)])
    assert plan_mission(obs).claims == ["a"]
    strict = replace(obs, spec=mission_spec(vehicles={"names": ["a"], "count": 1}))
    held = replace(
        strict,
        vehicles={"a": replace(single, claim=claim_on("a", ME.reference))},
    )
    plan = plan_mission(held)
    assert plan.status.phase == MissionPhase.PREFLIGHT
    assert vehicle_status(plan, "a").reason == "NotRedundant"


def test_vehicles_that_pass_this_missions_preflight_are_claimed_first() -> None:
    aps = [autopilots("a", redundant=False), autopilots("b"), autopilots("c")]
    plan = plan_mission(observe([vehicle("a"), vehicle("b"), vehicle("c")], aps=aps))
    assert plan.claims == ["b", "c"]


# -- preflight -----------------------------------------------------------------------------


def test_a_failing_check_keeps_the_mission_in_preflight_with_per_vehicle_reasons() -> None:
    obs = observe(claimed("a", "b"), aps=[autopilots("a"), autopilots("b", healthy=False)])
    plan = plan_mission(obs)
    assert plan.status.phase == MissionPhase.PREFLIGHT
    assert plan.jobs_to_create == [] and plan.status.start_time is None
    b = vehicle_status(plan, "b")
    assert b.phase == MissionVehiclePhase.PREFLIGHT
    assert b.reason == "ActiveAutopilotUnhealthy"
    assert vehicle_status(plan, "a").phase == MissionVehiclePhase.CLAIMED
    assert "1 of 2 vehicles fail preflight — b: active autopilot not healthy" in (
        plan.status.message or ""
    )
    passed = find_condition(plan.status.conditions, "PreflightPassed")
    assert passed is not None and passed.status == "False"


def test_a_vehicle_without_its_config_yet_fails_preflight() -> None:
    obs = replace(observe(claimed("a", "b")), config_values={"a": config("a")})
    plan = plan_mission(obs)
    assert vehicle_status(plan, "b").reason == "VehicleConfigMissing"
    assert plan.status.phase == MissionPhase.PREFLIGHT


# -- start and workloads -------------------------------------------------------------------


def test_passing_preflight_records_the_start_then_creates_one_job_per_vehicle() -> None:
    spec = mission_spec(offboard={"spec": {"containers": [{"name": "m", "image": "monitor"}]}})
    plan = plan_mission(observe(claimed("a", "b"), spec=spec))
    assert plan.status.phase == MissionPhase.RUNNING
    assert plan.status.start_time == T0
    names = [j["metadata"]["name"] for j in plan.jobs_to_create]
    assert names == [
        onboard_job_name("survey", "a"),
        onboard_job_name("survey", "b"),
        "survey-offboard",
    ]
    assert [cm["metadata"]["namespace"] for cm in plan.config_maps] == ["default", "default"]
    assert condition_is_true(plan.status.conditions, "PreflightPassed")
    assert [v.phase for v in plan.status.vehicles] == ["Running", "Running"]


# -- running, completion, failure ----------------------------------------------------------


def test_a_restart_after_start_recreates_only_missing_jobs() -> None:
    status, vehicles = started(["a", "b"])
    plan = plan_mission(observe(vehicles, status=status, jobs=[job("a")]))
    assert [j["metadata"]["name"] for j in plan.jobs_to_create] == [onboard_job_name("survey", "b")]
    assert plan.status.phase == MissionPhase.RUNNING


def test_jobs_existing_without_a_recorded_start_count_as_started() -> None:
    plan = plan_mission(observe(claimed("a", "b"), jobs=[job("a"), job("b")]))
    assert plan.claims == [] and plan.jobs_to_create == []
    assert plan.status.phase != MissionPhase.PREFLIGHT


def test_all_onboard_jobs_complete_means_succeeded_and_vehicles_released() -> None:
    status, vehicles = started(["a", "b"])
    plan = plan_mission(
        observe(
            vehicles,
            status=status,
            jobs=[job("a", JobPhase.SUCCEEDED), job("b", JobPhase.SUCCEEDED)],
        )
    )
    assert plan.status.phase == MissionPhase.SUCCEEDED
    assert plan.status.completion_time == T0
    assert sorted(plan.releases) == ["a", "b"]
    assert condition_is_true(plan.status.conditions, "Complete")


def test_progress_is_status_not_events() -> None:
    status, vehicles = started(["a", "b"])
    plan = plan_mission(
        observe(vehicles, status=status, jobs=[job("a", ready=1, active=1), job("b", active=1)])
    )
    assert plan.status.phase == MissionPhase.RUNNING
    assert vehicle_status(plan, "a").reason == "PodRunning"
    assert plan.events == []
    assert "0/2 onboard workloads completed, 2 running" in (plan.status.message or "")


def test_one_job_failing_beyond_retries_fails_the_mission_and_stops_the_rest() -> None:
    status, vehicles = started(["a", "b"])
    failed = job(
        "b", JobPhase.FAILED, failed=3, message="Job has reached the specified backoff limit"
    )
    plan = plan_mission(observe(vehicles, status=status, jobs=[job("a", active=1), failed]))
    assert plan.status.phase == MissionPhase.FAILED
    assert plan.status.reason == "VehicleWorkloadFailed"
    assert "backoff limit" in (plan.status.message or "")
    assert plan.jobs_to_delete == [onboard_job_name("survey", "a")]
    assert sorted(plan.releases) == ["a", "b"]


def test_a_finished_mission_only_winds_down() -> None:
    status, vehicles = started(["a", "b"])
    done = plan_mission(
        observe(
            vehicles,
            status=status,
            jobs=[job("a", JobPhase.SUCCEEDED), job("b", JobPhase.SUCCEEDED)],
        )
    ).status
    again = plan_mission(observe([*claimed("a"), vehicle("b")], status=done))
    assert again.status == done.model_copy(update={"observed_generation": 1})
    assert again.releases == ["a"] and again.events == [] and again.jobs_to_create == []


# -- abort ---------------------------------------------------------------------------------


def test_abort_before_start_ends_at_once_without_commanding_anything() -> None:
    obs = observe(claimed("a"), spec=mission_spec(abort=True))
    plan = plan_mission(obs)
    assert plan.status.phase == MissionPhase.ABORTED
    assert plan.commands == {} and plan.jobs_to_create == []
    assert plan.releases == ["a"]


def test_abort_stops_jobs_and_asks_every_vehicle_for_the_safety_routine() -> None:
    status, vehicles = started(["a", "b"])
    spec = mission_spec(vehicles={"names": ["a", "b"], "count": 2}, abort=True)
    plan = plan_mission(observe(vehicles, spec=spec, status=status, jobs=[job("a"), job("b")]))
    assert plan.status.phase == MissionPhase.ABORTING
    assert sorted(plan.jobs_to_delete) == sorted(onboard_job_name("survey", n) for n in "ab")
    assert plan.jobs_to_create == []
    assert {n: c.action for n, c in plan.commands.items()} == {
        "a": CommandAction.SAFETY_ROUTINE,
        "b": CommandAction.SAFETY_ROUTINE,
    }
    command = plan.commands["a"]
    assert command.id == abort_command_id(ME, "a", CommandAction.SAFETY_ROUTINE, 1)
    assert command.deadline_seconds == ABORT_COMMAND_DEADLINE_SECONDS
    assert plan.releases == [], "vehicles stay claimed until they have landed"
    assert plan.requeue_after is not None


def test_a_written_command_is_not_written_again_and_nothing_restarts() -> None:
    status, vehicles = started(["a"])
    spec = mission_spec(vehicles={"names": ["a"], "count": 1}, abort=True)
    first = plan_mission(observe(vehicles, spec=spec, status=status))
    command = first.commands["a"]
    later = T0 + timedelta(seconds=3)
    aps = [autopilots("a", command=command)]
    second = plan_mission(observe(vehicles, spec=spec, status=first.status, aps=aps, now=later))
    assert second.commands == {} and second.jobs_to_create == []
    assert vehicle_status(second, "a").reason == "SafetyRoutinePending"


def test_a_restarted_operator_adopts_its_command_instead_of_issuing_another() -> None:
    status, vehicles = started(["a"])
    spec = mission_spec(vehicles={"names": ["a"], "count": 1}, abort=True)
    written = plan_mission(observe(vehicles, spec=spec, status=status)).commands["a"]
    aps = [autopilots("a", command=written)]
    plan = plan_mission(observe(vehicles, spec=spec, status=status, aps=aps))
    assert plan.commands == {}
    assert vehicle_status(plan, "a").command == written


def test_only_a_report_after_the_command_can_end_the_abort() -> None:
    status, vehicles = started(["a"])
    spec = mission_spec(vehicles={"names": ["a"], "count": 1}, abort=True)
    first = plan_mission(observe(vehicles, spec=spec, status=status))
    command = first.commands["a"]
    stale = autopilots(
        "a", landed="OnGround", armed=False, command=command, reported_at=T0 - timedelta(seconds=5)
    )
    waiting = plan_mission(observe(vehicles, spec=spec, status=first.status, aps=[stale]))
    assert waiting.status.phase == MissionPhase.ABORTING, (
        "a report from before the abort proves nothing"
    )
    landed = autopilots(
        "a", landed="OnGround", armed=True, command=command, reported_at=T0 + timedelta(seconds=4)
    )
    done = plan_mission(observe(vehicles, spec=spec, status=first.status, aps=[landed]))
    assert done.status.phase == MissionPhase.ABORTED
    assert vehicle_status(done, "a").reason == "Landed"
    assert done.releases == ["a"]
    assert not condition_is_true(done.status.conditions, "Complete")


def test_emergency_stop_force_disarms_and_ends_only_when_disarmed() -> None:
    status, vehicles = started(["a"])
    spec = mission_spec(
        vehicles={"names": ["a"], "count": 1}, abort=True, abortAction="EmergencyStop"
    )
    first = plan_mission(observe(vehicles, spec=spec, status=status))
    command = first.commands["a"]
    assert command.action == CommandAction.EMERGENCY_STOP
    on_ground_armed = autopilots(
        "a", landed="OnGround", armed=True, command=command, reported_at=T0 + timedelta(seconds=1)
    )
    assert plan_mission(
        observe(vehicles, spec=spec, status=first.status, aps=[on_ground_armed])
    ).status.phase == (MissionPhase.ABORTING)
    executed = CommandResult(id=command.id, result="Executed", time=T0)
    disarmed = autopilots("a", landed="InAir", armed=False, command=command, last_command=executed)
    done = plan_mission(observe(vehicles, spec=spec, status=first.status, aps=[disarmed]))
    assert done.status.phase == MissionPhase.ABORTED
    assert vehicle_status(done, "a").reason == "Disarmed"


def test_an_expired_command_is_issued_again_with_the_next_id() -> None:
    status, vehicles = started(["a"])
    spec = mission_spec(vehicles={"names": ["a"], "count": 1}, abort=True)
    first = plan_mission(observe(vehicles, spec=spec, status=status))
    command = first.commands["a"]
    expired = CommandResult(id=command.id, result="Expired", time=T0)
    aps = [autopilots("a", command=command, last_command=expired)]
    retry = plan_mission(
        observe(vehicles, spec=spec, status=first.status, aps=aps, now=T0 + timedelta(minutes=5))
    )
    assert retry.commands["a"].id == abort_command_id(ME, "a", CommandAction.SAFETY_ROUTINE, 2)


def test_a_rejected_command_is_reported_and_the_abort_waits() -> None:
    status, vehicles = started(["a"])
    spec = mission_spec(vehicles={"names": ["a"], "count": 1}, abort=True)
    first = plan_mission(observe(vehicles, spec=spec, status=status))
    command = first.commands["a"]
    rejected = CommandResult(
        id=command.id, result="Rejected", message="no healthy autopilot", time=T0
    )
    aps = [autopilots("a", command=command, last_command=rejected)]
    plan = plan_mission(observe(vehicles, spec=spec, status=first.status, aps=aps))
    assert plan.commands == {}
    a = vehicle_status(plan, "a")
    assert a.reason == "SafetyRoutineRejected" and "no healthy autopilot" in a.message


def test_a_vehicle_without_redundant_autopilots_cannot_be_commanded_and_is_reported() -> None:
    spec = mission_spec(
        vehicles={"names": ["a"], "count": 1},
        preflight={"requireActiveHealthy": False, "requireRedundancy": False},
    )
    status, vehicles = started(["a"], spec=spec)
    plan = plan_mission(
        observe(vehicles, spec=spec.model_copy(update={"abort": True}), status=status, aps=[])
    )
    assert plan.status.phase == MissionPhase.ABORTED
    assert vehicle_status(plan, "a").reason == "NoRedundantAutopilot"


@pytest.mark.parametrize(
    ("action", "landed", "armed", "done"),
    [
        (CommandAction.SAFETY_ROUTINE, "OnGround", True, True),
        (CommandAction.SAFETY_ROUTINE, "InAir", False, True),
        (CommandAction.SAFETY_ROUTINE, "Landing", True, False),
        (CommandAction.EMERGENCY_STOP, "OnGround", True, False),
        (CommandAction.EMERGENCY_STOP, "InAir", False, True),
    ],
)
def test_stopped_means_on_the_ground_or_disarmed_and_disarmed_for_an_estop(
    action: CommandAction, landed: str, armed: bool, done: bool
) -> None:
    assert stopped(action, autopilots("a", landed=landed, armed=armed).status) is done


# -- failover policy -----------------------------------------------------------------------


def _failover_obs(policy: str, failover_at: datetime) -> tuple[Observation, MissionSpec]:
    spec = mission_spec(vehicles={"names": ["a", "b"], "count": 2}, onFailover=policy)
    status, vehicles = started(["a", "b"], spec=spec)
    aps = [autopilots("a", failover_at=failover_at), autopilots("b")]
    obs = observe(
        vehicles,
        spec=spec,
        status=status,
        aps=aps,
        jobs=[job("a"), job("b")],
        now=T0 + timedelta(seconds=30),
    )
    return obs, spec


def test_failover_with_continue_marks_the_mission_degraded_and_goes_on() -> None:
    obs, _ = _failover_obs("Continue", T0 + timedelta(seconds=10))
    plan = plan_mission(obs)
    assert plan.status.phase == MissionPhase.RUNNING
    assert condition_is_true(plan.status.conditions, "Degraded")
    assert plan.commands == {} and plan.jobs_to_delete == []
    assert vehicle_status(plan, "a").failed_over_at == T0 + timedelta(seconds=10)
    assert [e.reason for e in plan.events] == ["VehicleFailedOver"]
    again = plan_mission(replace(obs, status=plan.status))
    assert again.events == [], "one failover, one Event"


def test_failover_with_abort_vehicle_lands_that_vehicle_and_the_mission_carries_on() -> None:
    obs, _ = _failover_obs("AbortVehicle", T0 + timedelta(seconds=10))
    plan = plan_mission(obs)
    assert plan.status.phase == MissionPhase.RUNNING
    assert condition_is_true(plan.status.conditions, "Degraded")
    assert list(plan.commands) == ["a"]
    assert plan.commands["a"].action == CommandAction.SAFETY_ROUTINE
    assert plan.jobs_to_delete == [onboard_job_name("survey", "a")]
    assert vehicle_status(plan, "a").phase == MissionVehiclePhase.ABORTING
    assert vehicle_status(plan, "b").phase == MissionVehiclePhase.RUNNING
    command = plan.commands["a"]
    landed = autopilots(
        "a",
        failover_at=T0 + timedelta(seconds=10),
        landed="OnGround",
        command=command,
        reported_at=T0 + timedelta(seconds=40),
    )
    later = replace(
        obs,
        status=plan.status,
        autopilots={"a": landed, "b": autopilots("b")},
        jobs={onboard_job_name("survey", "b"): job("b", JobPhase.SUCCEEDED)},
    )
    done = plan_mission(later)
    assert vehicle_status(done, "a").phase == MissionVehiclePhase.ABORTED
    assert done.status.phase == MissionPhase.SUCCEEDED
    assert "1 aborted after a failover" in (done.status.message or "")
    assert condition_is_true(done.status.conditions, "Degraded")


def test_failover_with_abort_mission_aborts_every_vehicle() -> None:
    obs, _ = _failover_obs("AbortMission", T0 + timedelta(seconds=10))
    plan = plan_mission(obs)
    assert plan.status.phase == MissionPhase.ABORTING
    assert plan.status.reason == "VehicleFailedOver"
    assert sorted(plan.commands) == ["a", "b"]
    assert all(c.action == CommandAction.SAFETY_ROUTINE for c in plan.commands.values())
    assert "autopilot failover on a" in (plan.status.message or "")


def test_a_failover_before_the_mission_started_is_not_acted_on() -> None:
    obs, _ = _failover_obs("AbortMission", T0 - timedelta(seconds=1))
    plan = plan_mission(obs)
    assert plan.status.phase == MissionPhase.RUNNING
    assert plan.commands == {}


def test_every_vehicle_aborted_after_failovers_is_a_failed_mission() -> None:
    spec = mission_spec(vehicles={"names": ["a"], "count": 1}, onFailover="AbortVehicle")
    status, vehicles = started(["a"], spec=spec)
    at = T0 + timedelta(seconds=1)
    first = plan_mission(
        observe(vehicles, spec=spec, status=status, aps=[autopilots("a", failover_at=at)], now=at)
    )
    command = first.commands["a"]
    landed = autopilots(
        "a", failover_at=at, armed=False, command=command, reported_at=at + timedelta(seconds=9)
    )
    done = plan_mission(observe(vehicles, spec=spec, status=first.status, aps=[landed], now=at))
    assert done.status.phase == MissionPhase.FAILED
    assert done.status.reason == "AllVehiclesAborted"


# -- failover consequences and the fleet guards ------------------------------------------

PAUSED = {ANNOTATION_PAUSE_FAILOVER_ACTIONS: "true"}
FAILED_OVER_AT = T0 + timedelta(seconds=10)
LATCH = VehicleFailover(
    latched=True,
    latched_at=FAILED_OVER_AT,
    observed_failover_count=0,
    observed_failover_time=FAILED_OVER_AT,
)


def _guarded(
    obs: Observation, *, annotations: dict[str, str], book: VehicleFailover | None = None
) -> Observation:
    """``obs`` with vehicle a's Vehicle carrying ``annotations`` and failover bookkeeping."""
    a = vehicle("a", claimed_by=ME.reference, annotations=annotations, failover=book)
    return replace(obs, vehicles={**obs.vehicles, "a": a})


@pytest.mark.parametrize(
    ("policy", "annotations", "book", "fleet_paused", "held"),
    [
        ("AbortVehicle", PAUSED, None, False, "Paused"),
        ("AbortVehicle", {}, None, True, "Paused"),
        ("AbortVehicle", {}, LATCH, False, "Latched"),
        ("AbortMission", PAUSED, None, False, "Paused"),
        ("AbortMission", {}, LATCH, False, "Latched"),
        ("AbortVehicle", {}, None, False, None),
        ("AbortMission", {}, None, False, None),
        ("Continue", PAUSED, LATCH, False, None),  # nothing to hold back
    ],
)
def test_failover_consequences_honour_the_pause_and_the_latch(
    policy: str,
    annotations: dict[str, str],
    book: VehicleFailover | None,
    fleet_paused: bool,
    held: str | None,
) -> None:
    obs, _ = _failover_obs(policy, FAILED_OVER_AT)
    obs = replace(
        _guarded(obs, annotations=annotations, book=book),
        guards=FleetGuards(paused=fleet_paused),
    )
    plan = plan_mission(obs)
    a = vehicle_status(plan, "a")
    assert a.failed_over_at == FAILED_OVER_AT
    assert a.failover_action_held == held
    degraded = find_condition(plan.status.conditions, "Degraded")
    assert degraded is not None and degraded.status == "True"
    if held is None:
        assert degraded.reason == "VehicleFailedOver"
        if policy != "Continue":
            assert plan.commands, "an unguarded consequence is applied at once"
        return
    assert plan.commands == {} and plan.jobs_to_delete == []
    assert plan.status.phase == MissionPhase.RUNNING
    assert a.phase == MissionVehiclePhase.RUNNING
    assert a.reason == degraded.reason == f"FailoverAction{held}"
    assert f"onFailover={policy} held back" in (a.message or "")
    assert [e.reason for e in plan.events] == ["VehicleFailedOver", f"FailoverAction{held}"]
    again = plan_mission(replace(obs, status=plan.status))
    assert again.events == [] and again.commands == {}, "a hold is announced once"
    assert vehicle_status(again, "a").failover_action_held == held


def test_a_paused_abort_vehicle_is_applied_once_the_pause_is_lifted() -> None:
    obs, _ = _failover_obs("AbortVehicle", FAILED_OVER_AT)
    held = plan_mission(_guarded(obs, annotations=PAUSED))
    lifted = plan_mission(replace(_guarded(obs, annotations={}), status=held.status))
    a = vehicle_status(lifted, "a")
    assert a.phase == MissionVehiclePhase.ABORTING and a.failover_action_held is None
    assert list(lifted.commands) == ["a"]
    assert lifted.commands["a"].action == CommandAction.SAFETY_ROUTINE
    assert lifted.jobs_to_delete == [onboard_job_name("survey", "a")]
    assert "VehicleFailedOver" not in [e.reason for e in lifted.events], "not a new failover"
    degraded = find_condition(lifted.status.conditions, "Degraded")
    assert degraded is not None and degraded.reason == "VehicleFailedOver"


def test_a_consequence_held_until_the_workload_ends_is_not_applied() -> None:
    obs, _ = _failover_obs("AbortVehicle", FAILED_OVER_AT)
    held = plan_mission(_guarded(obs, annotations=PAUSED))
    done = plan_mission(
        replace(
            _guarded(obs, annotations=PAUSED),
            status=held.status,
            jobs={onboard_job_name("survey", "a"): job("a", JobPhase.SUCCEEDED)},
        )
    )
    a = vehicle_status(done, "a")
    assert a.phase == MissionVehiclePhase.SUCCEEDED and a.failover_action_held is None
    assert done.commands == {}


def test_a_latched_abort_mission_waits_for_a_human_to_clear_the_latch() -> None:
    obs, _ = _failover_obs("AbortMission", FAILED_OVER_AT)
    held = plan_mission(_guarded(obs, annotations={}, book=LATCH))
    assert held.status.phase == MissionPhase.RUNNING
    cleared = plan_mission(
        replace(
            _guarded(obs, annotations={ANNOTATION_CLEAR_FAILOVER_LATCH: "looked"}, book=LATCH),
            status=held.status,
        )
    )
    assert cleared.status.phase == MissionPhase.ABORTING
    assert sorted(cleared.commands) == ["a", "b"]


def test_a_requested_abort_is_never_held_back_by_a_guard() -> None:
    obs, spec = _failover_obs("AbortVehicle", FAILED_OVER_AT)
    held = plan_mission(_guarded(obs, annotations=PAUSED, book=LATCH))
    assert vehicle_status(held, "a").failover_action_held == "Paused"
    aborting = spec.model_copy(update={"abort": True})
    plan = plan_mission(
        replace(
            _guarded(obs, annotations=PAUSED, book=LATCH),
            spec=aborting,
            status=held.status,
            guards=FleetGuards(paused=True),
        )
    )
    assert plan.status.phase == MissionPhase.ABORTING
    assert sorted(plan.commands) == ["a", "b"]
    assert vehicle_status(plan, "a").failover_action_held is None


# -- deletion, events, wake-ups ------------------------------------------------------------


def test_deleting_a_running_mission_lands_its_vehicles_and_releases_them() -> None:
    status, vehicles = started(["a", "b"])
    plan = plan_deletion(observe(vehicles, status=status, jobs=[job("a"), job("b")]))
    assert sorted(plan.commands) == ["a", "b"]
    assert sorted(plan.releases) == ["a", "b"]
    assert [e.reason for e in plan.events] == ["DeletedWhileRunning"]


def test_deleting_a_pending_mission_only_releases() -> None:
    plan = plan_deletion(observe(claimed("a")))
    assert plan.commands == {} and plan.releases == ["a"]


def test_transitions_produce_events_for_the_mission_and_each_vehicle() -> None:
    before, _ = started(["a", "b"])
    preflight = plan_mission(
        observe(
            claimed("a", "b"),
            spec=mission_spec(vehicles={"names": ["a", "b"], "count": 2}),
            aps=[autopilots("a"), autopilots("b", redundant=False)],
        )
    )
    reasons = [(e.reason, e.vehicle, e.type) for e in preflight.events]
    assert ("PreflightFailed", None, "Warning") in reasons
    assert ("NotRedundant", "b", "Warning") in reasons
    assert ("PreflightPassed", "a", "Normal") in reasons
    assert transition_events(before, before) == []


def test_a_vehicle_still_landing_when_the_mission_fails_stays_claimed_until_it_is_down() -> None:
    obs, _ = _failover_obs("AbortVehicle", T0 + timedelta(seconds=10))
    landing = plan_mission(obs)
    command = landing.commands["a"]
    failed_b = job("b", JobPhase.FAILED, failed=3, message="BackoffLimitExceeded")
    failed = plan_mission(replace(obs, status=landing.status, jobs={failed_b.name: failed_b}))
    assert failed.status.phase == MissionPhase.FAILED
    assert failed.releases == ["b"], "a is still in the air"
    assert failed.requeue_after is not None
    down = autopilots(
        "a",
        failover_at=T0 + timedelta(seconds=10),
        landed="OnGround",
        command=command,
        reported_at=T0 + timedelta(seconds=50),
    )
    later = plan_mission(
        replace(obs, status=failed.status, autopilots={"a": down, "b": autopilots("b")})
    )
    assert vehicle_status(later, "a").phase == MissionVehiclePhase.ABORTED
    assert later.releases == ["a", "b"] and later.requeue_after is None


def test_many_vehicles_making_one_transition_share_one_event() -> None:
    names = [f"v{i}" for i in range(12)]
    spec = mission_spec(vehicles={"selector": {}, "count": 12})
    plan = plan_mission(observe(claimed(*names), spec=spec))
    assert plan.status.phase == MissionPhase.RUNNING
    vehicle_events = [e for e in plan.events if e.reason == "JobCreated"]
    assert len(vehicle_events) == 1
    assert vehicle_events[0].message.startswith("12 vehicles Running: v0, v1")
    assert vehicle_events[0].vehicle is None


# -- a Vehicle deleted mid-mission ----------------------------------------------------------


def _deleted_mid_mission(
    policy: str, *, gone: bool = False, with_autopilots: bool = True
) -> Observation:
    """Mission on a and b running; Vehicle a is being deleted (or already gone)."""
    spec = mission_spec(vehicles={"names": ["a", "b"], "count": 2}, onFailover=policy)
    status, _ = started(["a", "b"], spec=spec)
    vehicles = [*([] if gone else claimed("a", deleting=True)), *claimed("b")]
    aps = [autopilots("b"), *([autopilots("a")] if with_autopilots else [])]
    return observe(
        vehicles,
        spec=spec,
        status=status,
        aps=aps,
        jobs=[job("a"), job("b")],
        now=T0 + timedelta(seconds=30),
    )


@pytest.mark.parametrize(
    ("policy", "gone", "with_autopilots", "mission_phase", "vehicle_phase", "commanded"),
    [
        # policy        Vehicle    its RA  → mission    vehicle a    safety routine to
        ("Continue", False, True, "Running", "Aborting", ["a"]),
        ("Continue", True, True, "Running", "Aborting", ["a"]),
        ("Continue", True, False, "Running", "Aborted", []),
        ("AbortVehicle", False, True, "Running", "Aborting", ["a"]),
        ("AbortMission", False, True, "Aborting", "Aborting", ["a", "b"]),
        ("AbortMission", True, False, "Aborting", "Aborted", ["b"]),
    ],
)
def test_a_vehicle_deleted_mid_mission_leaves_it_at_once(
    policy: str,
    *,
    gone: bool,
    with_autopilots: bool,
    mission_phase: str,
    vehicle_phase: str,
    commanded: list[str],
) -> None:
    plan = plan_mission(_deleted_mid_mission(policy, gone=gone, with_autopilots=with_autopilots))
    assert plan.status.phase == mission_phase
    a = vehicle_status(plan, "a")
    assert a.phase == vehicle_phase
    if mission_phase != "Aborting":  # an aborting mission words every vehicle's reason
        assert a.reason == "VehicleDeleted"
    assert onboard_job_name("survey", "a") in plan.jobs_to_delete, "its Job stops at once"
    assert "a" in plan.config_maps_to_delete, "its config copy goes with it"
    assert sorted(plan.commands) == commanded
    assert condition_is_true(plan.status.conditions, "Degraded") or mission_phase == "Aborting"
    assert "VehicleDeleted" in [e.reason for e in plan.events]


def test_a_deleted_vehicle_is_reported_once_and_the_mission_goes_on_without_it() -> None:
    obs = _deleted_mid_mission("Continue", gone=True, with_autopilots=False)
    first = plan_mission(obs)
    degraded = find_condition(first.status.conditions, "Degraded")
    assert degraded is not None and degraded.reason == "VehicleDeleted"
    again = plan_mission(replace(obs, status=first.status))
    assert "VehicleDeleted" not in [e.reason for e in again.events], "one Event per deletion"
    assert onboard_job_name("survey", "b") not in again.jobs_to_delete
    done = plan_mission(
        replace(
            obs,
            status=again.status,
            jobs={onboard_job_name("survey", "b"): job("b", JobPhase.SUCCEEDED)},
        )
    )
    assert done.status.phase == MissionPhase.SUCCEEDED
    assert "1 aborted after a failover or the Vehicle's deletion" in (done.status.message or "")
    assert sorted(done.config_maps_to_delete) == ["a", "b"], "a finished mission keeps no copy"


def test_a_deleted_vehicle_still_landing_is_followed_until_it_is_down() -> None:
    obs = _deleted_mid_mission("AbortVehicle", gone=True)
    first = plan_mission(obs)
    command = first.commands["a"]
    landed = autopilots(
        "a", landed="OnGround", command=command, reported_at=T0 + timedelta(seconds=40)
    )
    later = plan_mission(
        replace(obs, status=first.status, autopilots={**obs.autopilots, "a": landed})
    )
    a = vehicle_status(later, "a")
    assert (a.phase, a.reason) == (MissionVehiclePhase.ABORTED, "VehicleDeleted")
    assert later.commands == {}, "the command is written once"


# -- a vehicle whose node cannot be reached ------------------------------------------------


def _unreachable_mid_mission(policy: str | None, since: datetime | None) -> Observation:
    """Mission on a and b running; a's node unreachable since ``since`` (None: reachable)."""
    extra = {} if policy is None else {"onUnreachable": policy}
    spec = mission_spec(vehicles={"names": ["a", "b"], "count": 2}, **extra)
    status, _ = started(["a", "b"], spec=spec)
    vehicles = [*claimed("a", unreachable_since=since), *claimed("b")]
    return observe(
        vehicles,
        spec=spec,
        status=status,
        jobs=[job("a", ready=1, active=1), job("b", ready=1, active=1)],
        now=T0 + timedelta(seconds=90),
    )


@pytest.mark.parametrize(
    ("policy", "mission_phase", "commanded"),
    [
        # spec.onUnreachable → mission     safety routine to
        (None, "Running", []),  # the default keeps flying
        ("Continue", "Running", []),
        ("AbortMission", "Aborting", ["a", "b"]),
    ],
)
def test_an_unreachable_vehicle_is_shown_and_flies_on_unless_the_policy_aborts(
    policy: str | None, mission_phase: str, commanded: list[str]
) -> None:
    since = T0 + timedelta(seconds=40)
    plan = plan_mission(_unreachable_mid_mission(policy, since))
    assert plan.status.phase == mission_phase
    assert sorted(plan.commands) == commanded
    a = vehicle_status(plan, "a")
    assert a.unreachable_since == since
    if mission_phase == "Running":
        assert plan.jobs_to_delete == [], "nothing is stopped for a lost link"
        assert (a.phase, a.reason) == ("Running", "VehicleUnreachable")
        assert "2026-03-01T12:00:40Z" in a.message
        degraded = find_condition(plan.status.conditions, "Degraded")
        assert degraded is not None and (degraded.status, degraded.reason) == (
            "True",
            "VehicleUnreachable",
        )
    assert vehicle_status(plan, "b").unreachable_since is None
    assert "VehicleUnreachable" in [e.reason for e in plan.events]


def test_an_unreachable_vehicle_is_reported_once_and_its_return_clears_degraded() -> None:
    obs = _unreachable_mid_mission(None, T0 + timedelta(seconds=40))
    first = plan_mission(obs)
    again = plan_mission(replace(obs, status=first.status))
    assert again.events == [], "one lost link, one Event"
    back = _unreachable_mid_mission(None, None)
    returned = plan_mission(replace(back, status=again.status))
    a = vehicle_status(returned, "a")
    assert a.unreachable_since is None and a.reason == "PodRunning"
    assert [e.reason for e in returned.events] == ["VehicleReachable"]
    degraded = find_condition(returned.status.conditions, "Degraded")
    assert degraded is not None and (degraded.status, degraded.reason) == (
        "False",
        "VehiclesReachable",
    )
