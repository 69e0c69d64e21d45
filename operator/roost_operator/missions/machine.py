"""The Mission state machine: everything observed in, everything to do out. Pure.

:func:`plan_mission` reads an :class:`Observation` (the Mission, all Vehicles, the
RedundantAutopilots, the mission's Jobs, the vehicles' config, the clock) and returns a
:class:`Plan`. It is level-based: the same observation always gives the same plan, and
a plan applied twice does no harm (Jobs and commands have deterministic names and ids),
so the handler may run it on every event, on a timer and after a restart.

Phases::

    Pending ──claims──▶ Preflight ──all checks pass──▶ Running ──▶ Succeeded | Failed
       │                   │                              │
       └──── abort ────────┴─▶ Aborted                    └─ abort / AbortMission ─▶
                                                             Aborting ──landed──▶ Aborted

* **Pending**: not enough free vehicles. Claims are all-or-nothing (see
  :mod:`.selection`), vehicles that pass this mission's preflight first; the message
  counts what is missing and why.
* **Preflight**: vehicles held, some check failing; per-vehicle reasons in status.
* **Running**: ``status.startTime`` is written *before* any Job is created, so a restart
  in between finds "started" and creates only what is missing. A mission also counts as
  started when any of its Jobs exists.
* Per vehicle, a new autopilot failover (``RedundantAutopilot`` ``lastFailover`` or the
  ``FailedOver`` transition, at or after the start, newer than the last one handled)
  applies ``spec.onFailover``: ``Continue`` (mission Degraded), ``AbortVehicle`` (that
  vehicle's Job stops, its agent runs the safety routine, mission Degraded and goes on)
  or ``AbortMission``.
* Those consequences are cluster-side remediation and honour the fleet guards' pause
  switch and latch (:func:`~roost_operator.autopilots.guards.consequence_verdict`; not
  the concurrency cap — they only stop and land). The vehicle is safe meanwhile: its
  agent runs its own safety routine right after every failover. While a guard holds
  the consequence back, the vehicle keeps its workload, its status says
  ``FailoverActionPaused`` / ``FailoverActionLatched`` (``failoverActionHeld``), as do
  an Event and the Degraded condition; once the guard lifts the consequence is applied.
  A consequence still held when the vehicle's workload ends is not applied.
  A requested abort (``spec.abort``) is the user's own decision: no guard applies.
* **Succeeded** when every onboard Job completed (vehicles aborted after a failover
  excepted, as long as one completed); **Failed** when one fails beyond its
  ``backoffLimit`` or the offboard Job fails — then, as in a JobSet, the remaining Jobs
  are stopped.
* **Aborting**: every assigned vehicle not yet stopped gets a command on its
  RedundantAutopilot — the safety routine, or an emergency stop (force disarm) when
  ``spec.abort`` asks for ``abortAction: EmergencyStop``; aborts caused by a failover
  policy always use the safety routine. All Jobs are stopped and none is created again.
  A vehicle counts as stopped when its agent reports, *after* the command was issued,
  that the active autopilot is on the ground or disarmed (disarmed for an e-stop), so a
  report from before take-off can never end an abort. **Aborted** once all are stopped.
  An abort before anything started ends at once: nothing flew for this mission.
* Commands are re-issued (next attempt, new id) only when the agent reports one Expired
  or another request replaced it unprocessed; otherwise a command is written once.
* Finished missions release every vehicle they still hold, except one still landing
  after an AbortVehicle: it stays claimed and followed until it is down.
* A Mission deleted while it runs (:func:`plan_deletion`) sends the abort command to its
  vehicles and releases them without waiting for the landing.
* A vehicle whose **node cannot be reached** (its link is lost; its Vehicle's NodeBound
  says NodeUnreachable) stays in the mission: its pod is kept and it flies on; its
  entry shows since when (``unreachableSince``, reason VehicleUnreachable) and the
  mission goes Degraded until it is back — or aborts, when ``spec.onUnreachable`` is
  AbortMission.
* A **Vehicle deleted** while the mission runs leaves it at once: its Job is stopped,
  its config copy removed, its agent (if its RedundantAutopilot is still there) asked
  for the safety routine, and the mission goes on Degraded (``VehicleDeleted``) — or
  aborts, when ``spec.onFailover`` is AbortMission. No fleet guard applies: the
  deletion was a human's decision.
* Once the mission has finished, its config copies are removed (a copy another Mission
  has taken over since is left alone).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Literal

from roost_api.autopilot import (
    AssignedFence,
    AutopilotCommand,
    AutopilotConditionType,
    AutopilotHealth,
    CommandAction,
    RedundantAutopilotStatus,
)
from roost_api.autopilot_enums import LandedState
from roost_api.commands import CommandOutcome, command_outcome, new_command
from roost_api.meta import ConditionStatus, find_condition, set_condition
from roost_api.mission import (
    AbortAction,
    MissionConditionType,
    MissionOffboardStatus,
    MissionPhase,
    MissionReason,
    MissionSpec,
    MissionStatus,
    MissionVehiclePhase,
    MissionVehicleReason,
    MissionVehicleStatus,
    OnFailover,
    OnUnreachable,
    WorkloadPhase,
    abort_command_reason,
    failover_action_held_reason,
)
from roost_api.wellknown import ANNOTATION_CLEAR_FAILOVER_LATCH, ANNOTATION_PAUSE_FAILOVER_ACTIONS
from roost_kube.patches import Obj
from roost_operator.autopilots.guards import FleetGuards, Verdict, consequence_verdict
from roost_operator.missions.fence import assigned as assigned_fence
from roost_operator.missions.fence import fence_failures, invalid_fence
from roost_operator.missions.fence import needs_write as fence_needs_write
from roost_operator.missions.observed import (
    AutopilotView,
    JobPhase,
    JobView,
    MissionRef,
    VehicleView,
)
from roost_operator.missions.preflight import PreflightFailure, preflight_failures
from roost_operator.missions.selection import availability, held_by, shortage_message
from roost_operator.missions.workloads import (
    config_map_copy,
    offboard_job,
    offboard_job_name,
    onboard_job,
    onboard_job_name,
)
from roost_operator.records.planning import bundle_name, gathering

ABORT_COMMAND_DEADLINE_SECONDS = 30
"""How long an agent may take to see an abort command before it counts as stale."""

ABORT_POLL_SECONDS = 2.0
"""Re-check period while vehicles land (agent reports wake the mission sooner)."""

VEHICLE_EVENTS_MAX = 5
"""More vehicles than this making one transition together get one Event, not one each."""

Severity = Literal["Normal", "Warning"]

_VEHICLE_DONE = (MissionVehiclePhase.SUCCEEDED, MissionVehiclePhase.ABORTED)
_VEHICLE_FINAL = (*_VEHICLE_DONE, MissionVehiclePhase.FAILED)
_WARNING_VEHICLE_PHASES = (
    MissionVehiclePhase.PREFLIGHT,
    MissionVehiclePhase.FAILED,
    MissionVehiclePhase.ABORTING,
    MissionVehiclePhase.ABORTED,
)
_WARNING_PHASES = (MissionPhase.FAILED, MissionPhase.ABORTING, MissionPhase.ABORTED)
_WARNING_REASONS = (MissionReason.INSUFFICIENT_VEHICLES, MissionReason.PREFLIGHT_FAILED)


@dataclass(frozen=True)
class Observation:
    """Everything one mission decision reads."""

    mission: MissionRef
    generation: int
    spec: MissionSpec
    status: MissionStatus
    vehicles: Mapping[str, VehicleView]
    autopilots: Mapping[str, AutopilotView]
    """RedundantAutopilots by the vehicle they fly (``spec.vehicleName``)."""
    jobs: Mapping[str, JobView]
    """This mission's Jobs by name."""
    config_values: Mapping[str, Mapping[str, str]]
    """Each vehicle's authoritative config entries, by vehicle name."""
    live_missions: frozenset[str]
    """``namespace/name`` of the Missions whose claims count (listed after the Vehicles;
    see :func:`~roost_operator.missions.selection.holding_missions`)."""
    now: datetime
    guards: FleetGuards
    """The fleet guards a failover consequence must pass (pause and latch)."""
    records: bool = False
    """The operator gathers flight records (:mod:`roost_operator.records`): a mission that
    flew gets ``status.records`` when it ends."""
    deleting: bool = False
    """The Mission is marked for deletion: its deletion handler, not its reconcile, acts
    on it now (:func:`plan_deletion`)."""


@dataclass(frozen=True)
class MissionEvent:
    """An Event to record on the Mission (and on the vehicle it names, if any)."""

    type: Severity
    reason: str
    message: str
    vehicle: str | None = None


@dataclass
class Plan:
    """What to do now; the handler carries it out in the order of the fields."""

    status: MissionStatus
    claims: list[str] = field(default_factory=list)
    """Vehicles to claim, all or none; the plan is recomputed after claiming."""
    config_maps: list[Obj] = field(default_factory=list)
    jobs_to_create: list[Obj] = field(default_factory=list)
    commands: dict[str, AutopilotCommand] = field(default_factory=dict)
    """New commands to write, by vehicle name."""
    fences: dict[str, AssignedFence] = field(default_factory=dict)
    """The Mission's fence to write into these vehicles' RedundantAutopilots
    (roost_operator.missions.fence); it is removed when the Mission releases them."""
    jobs_to_delete: list[str] = field(default_factory=list)
    config_maps_to_delete: list[str] = field(default_factory=list)
    """Vehicles whose config copy in the Mission's namespace goes (if this Mission owns it)."""
    releases: list[str] = field(default_factory=list)
    events: list[MissionEvent] = field(default_factory=list)
    requeue_after: float | None = None
    """Reconcile again after this many seconds even without an event."""


# -- entry point -----------------------------------------------------------------------


def plan_mission(obs: Observation) -> Plan:
    """Decide what the mission should do now; see the module docstring."""
    plan = Plan(status=obs.status.model_copy(deep=True))
    phase = MissionPhase(obs.status.phase)
    if phase.finished:
        _wind_down(obs, plan)
    elif not _started(obs):
        invalid = invalid_fence(obs.spec)
        if obs.spec.abort:
            _abort_before_start(obs, plan)
        elif invalid is not None:
            _finish(obs, plan, MissionPhase.FAILED, MissionReason.INVALID_FENCE, invalid)
        else:
            _assign(obs, plan)
    elif obs.spec.abort or phase is MissionPhase.ABORTING:
        _abort(obs, plan)
    else:
        _run(obs, plan)
    plan.status.observed_generation = obs.generation
    plan.events = [*transition_events(obs.status, plan.status), *plan.events]
    _start_records(obs, plan)
    if MissionPhase(plan.status.phase).finished:
        # Nothing of a finished mission keeps running, so nothing needs its config copies.
        plan.config_maps_to_delete = [v.name for v in plan.status.vehicles]
    return plan


def _start_records(obs: Observation, plan: Plan) -> None:
    """A mission that flew and ends now: its record starts Gathering in the same status
    write as its final phase (the next reconcile gathers; see
    :mod:`roost_operator.records.gather`). One that never started has nothing to record
    and gets no ``status.records``; nor does one that had ended before records were on
    (an upgraded operator does not go back over every old Mission)."""
    status = plan.status
    ends_now = MissionPhase(status.phase).finished and not MissionPhase(obs.status.phase).finished
    if not (obs.records and ends_now and status.records is None):
        return
    if status.start_time is None:
        return
    bundle = bundle_name(obs.mission.namespace, obs.mission.name, obs.mission.uid)
    status.records = gathering(bundle, [v.name for v in status.vehicles])
    plan.requeue_after = 0.0


def fail_mission(obs: Observation, reason: str, message: str) -> Plan:
    """The plan that ends the mission as Failed (e.g. the API server rejected a Job)."""
    plan = Plan(status=obs.status.model_copy(deep=True))
    _finish(obs, plan, MissionPhase.FAILED, reason, message)
    plan.status.observed_generation = obs.generation
    plan.events = transition_events(obs.status, plan.status)
    return plan


def plan_deletion(obs: Observation) -> Plan:
    """The Mission is being deleted: abort what still flies for it, release its vehicles.

    Its Jobs go with it (owner references). A mission deleted while it runs would
    otherwise leave its vehicles in the air without their controllers, so each vehicle
    not yet stopped gets the abort command (the safety routine, or the e-stop a
    requested abort asked for); the deletion does not wait for the landing — it
    cannot be held up by a vehicle that never reports again.
    """
    plan = Plan(status=obs.status.model_copy(deep=True))
    if _started(obs) and not MissionPhase(obs.status.phase).finished:
        action = abort_action(obs.spec)
        for vehicle in plan.status.vehicles:
            if vehicle.phase != MissionVehiclePhase.ABORTED:
                _abort_vehicle(obs, plan, vehicle, action)
        if plan.commands:
            plan.events.append(
                MissionEvent(
                    "Warning",
                    "DeletedWhileRunning",
                    f"deleted while running: {action} requested on "
                    f"{', '.join(sorted(plan.commands))}",
                )
            )
    plan.releases.extend(held_by(obs.mission, obs.vehicles))
    return plan


def _started(obs: Observation) -> bool:
    return obs.status.start_time is not None or bool(obs.jobs)


# -- conditions --------------------------------------------------------------------------


def _condition(
    obs: Observation,
    status: MissionStatus,
    type_: MissionConditionType,
    value: ConditionStatus,
    *,
    reason: str,
    message: str = "",
) -> None:
    status.conditions = set_condition(
        status.conditions,
        type=type_,
        status=value,
        reason=reason,
        message=message,
        observed_generation=obs.generation,
        at=obs.now.replace(microsecond=0),
    )


def _set_phase(status: MissionStatus, phase: MissionPhase, reason: str, message: str) -> None:
    status.phase = phase
    status.reason = reason
    status.message = message


# -- Pending and Preflight ------------------------------------------------------------


def _assign(obs: Observation, plan: Plan) -> None:
    status = plan.status
    required = obs.spec.vehicles.count
    held = held_by(obs.mission, obs.vehicles)
    previous = [v.name for v in obs.status.vehicles if v.name in held]
    order = [*previous, *(n for n in held if n not in previous)]
    if len(order) > required:
        plan.releases.extend(order[required:])
        order = order[:required]
    if len(order) < required:
        available = availability(obs.spec.vehicles, obs.vehicles, obs.mission, obs.live_missions)
        need = required - len(order)
        if len(available.free) >= need:
            fit_first = sorted(available.free, key=lambda name: bool(_failures(obs, name)))
            plan.claims = fit_first[:need]
            _set_phase(
                status,
                MissionPhase.PENDING,
                MissionReason.CLAIMING,
                f"claiming {need} vehicle{'s' if need != 1 else ''}",
            )
            plan.requeue_after = 0.0
            return
        message = shortage_message(required=required, held=len(order), available=available)
        plan.releases.extend(order)
        status.vehicles = []
        status.assigned_count = 0
        _wait(
            obs,
            status,
            MissionPhase.PENDING,
            MissionConditionType.VEHICLES_ASSIGNED,
            reason=MissionReason.INSUFFICIENT_VEHICLES,
            message=message,
        )
        return
    _preflight(obs, plan, order)


def _wait(
    obs: Observation,
    status: MissionStatus,
    phase: MissionPhase,
    failing: MissionConditionType,
    *,
    reason: str,
    message: str,
) -> None:
    """Not started yet: ``phase`` with ``reason``, condition ``failing`` False."""
    _set_phase(status, phase, reason, message)
    _condition(obs, status, failing, "False", reason=reason, message=message)
    _condition(
        obs, status, MissionConditionType.COMPLETE, "False", reason=MissionReason.NOT_STARTED
    )


def _failures(obs: Observation, name: str) -> list[PreflightFailure]:
    """Every preflight check ``name`` fails for this mission (its config included)."""
    failures = preflight_failures(
        obs.vehicles.get(name), obs.autopilots.get(name), obs.spec.preflight
    )
    failures += fence_failures(assigned_fence(obs.mission, obs.spec), obs.autopilots.get(name))
    if name not in obs.config_values:
        failures.append(
            PreflightFailure(
                MissionVehicleReason.VEHICLE_CONFIG_MISSING,
                "the vehicle's config ConfigMap has not been written yet",
            )
        )
    return failures


def _preflight(obs: Observation, plan: Plan, assigned: list[str]) -> None:
    status = plan.status
    status.assigned_count = len(assigned)
    names = ", ".join(assigned)
    _condition(
        obs,
        status,
        MissionConditionType.VEHICLES_ASSIGNED,
        "True",
        reason=MissionReason.ASSIGNED,
        message=f"{len(assigned)}/{obs.spec.vehicles.count}: {names}",
    )
    results = {name: _failures(obs, name) for name in assigned}
    fence = assigned_fence(obs.mission, obs.spec)
    for name in assigned:
        if fence is not None and fence_needs_write(fence, obs.autopilots.get(name)):
            plan.fences[name] = fence
    vehicles = []
    for name in assigned:
        vehicle = obs.vehicles.get(name)
        failures = results[name]
        vehicles.append(
            MissionVehicleStatus(
                name=name,
                node_name=vehicle.node_name if vehicle else None,
                phase=MissionVehiclePhase.PREFLIGHT if failures else MissionVehiclePhase.CLAIMED,
                reason=failures[0].reason if failures else MissionVehicleReason.PREFLIGHT_PASSED,
                message="; ".join(f.message for f in failures) or "all preflight checks pass",
                job_name=onboard_job_name(obs.mission.name, name),
            )
        )
    status.vehicles = vehicles
    failing = [v for v in vehicles if v.phase == MissionVehiclePhase.PREFLIGHT]
    if failing:
        summary = "; ".join(f"{v.name}: {v.message}" for v in failing[:5])
        more = f"; and {len(failing) - 5} more" if len(failing) > 5 else ""
        message = f"{len(failing)} of {len(vehicles)} vehicles fail preflight — {summary}{more}"
        _wait(
            obs,
            status,
            MissionPhase.PREFLIGHT,
            MissionConditionType.PREFLIGHT_PASSED,
            reason=MissionReason.PREFLIGHT_FAILED,
            message=message,
        )
        return
    _start(obs, plan, assigned)


def _start(obs: Observation, plan: Plan, assigned: list[str]) -> None:
    status = plan.status
    status.start_time = obs.now
    for vehicle in status.vehicles:
        _launch(obs, plan, vehicle, assigned)
    if obs.spec.offboard is not None:
        name = offboard_job_name(obs.mission.name)
        status.offboard = MissionOffboardStatus(
            job_name=name, phase=WorkloadPhase.RUNNING, message="offboard Job created"
        )
        plan.jobs_to_create.append(
            offboard_job(mission=obs.mission, spec=obs.spec, assigned=assigned)
        )
    count = len(assigned)
    _set_phase(
        status,
        MissionPhase.RUNNING,
        MissionReason.STARTED,
        f"preflight passed; onboard workloads started on {count} "
        f"vehicle{'s' if count != 1 else ''}",
    )
    _condition(
        obs,
        status,
        MissionConditionType.PREFLIGHT_PASSED,
        "True",
        reason=MissionReason.ALL_CHECKS_PASSED,
    )
    _condition(
        obs, status, MissionConditionType.DEGRADED, "False", reason=MissionReason.NO_FAILOVER
    )
    _condition(obs, status, MissionConditionType.COMPLETE, "False", reason=MissionReason.RUNNING)


def _launch(
    obs: Observation, plan: Plan, vehicle: MissionVehicleStatus, assigned: Sequence[str]
) -> None:
    """Create the vehicle's onboard Job (and its config copy); it is Running from now."""
    values = obs.config_values[vehicle.name]
    plan.config_maps.append(config_map_copy(obs.mission, vehicle.name, values))
    plan.jobs_to_create.append(
        onboard_job(
            mission=obs.mission,
            spec=obs.spec,
            vehicle_name=vehicle.name,
            assigned=assigned,
            config_values=values,
        )
    )
    vehicle.phase = MissionVehiclePhase.RUNNING
    vehicle.reason = MissionVehicleReason.JOB_CREATED
    vehicle.message = f"onboard Job {vehicle.job_name} created"


# -- Running -----------------------------------------------------------------------------


def failover_time(status: RedundantAutopilotStatus) -> datetime | None:
    """When the agent last switched autopilots: ``lastFailover`` or the FailedOver edge."""
    times = [status.last_failover.time] if status.last_failover else []
    failed_over = find_condition(status.conditions, AutopilotConditionType.FAILED_OVER)
    if failed_over is not None and failed_over.status == "True":
        times.append(failed_over.last_transition_time)
    return max(times, default=None)


def _failover_text(status: RedundantAutopilotStatus) -> str:
    last = status.last_failover
    if last is None:
        return "autopilot failed over"
    return (
        f"autopilot failed over from {last.from_autopilot} to {last.to_autopilot} ({last.reason})"
    )


def _assigned(obs: Observation) -> list[str]:
    return [v.name for v in obs.status.vehicles]


def _run(obs: Observation, plan: Plan) -> None:
    status = plan.status
    start = status.start_time or min(
        (j.created for j in obs.jobs.values() if j.created), default=obs.now
    )
    status.start_time = start
    assigned = _assigned(obs)
    abort_mission_because: str | None = None
    updated: list[MissionVehicleStatus] = []
    for previous in status.vehicles:
        vehicle = previous.model_copy(deep=True)
        job_name = vehicle.job_name or onboard_job_name(obs.mission.name, vehicle.name)
        vehicle.job_name = job_name
        job = obs.jobs.get(job_name)
        autopilots = obs.autopilots.get(vehicle.name)
        phase = MissionVehiclePhase(vehicle.phase)
        if phase not in _VEHICLE_FINAL and vehicle_lost(obs, vehicle.name):
            if _leave(obs, plan, vehicle, job) and OnFailover(obs.spec.on_failover) is (
                OnFailover.ABORT_MISSION
            ):
                abort_mission_because = (
                    f"{vehicle.name}: the Vehicle was deleted (onFailover=AbortMission)"
                )
            updated.append(vehicle)
            continue
        if phase in (MissionVehiclePhase.ABORTING, MissionVehiclePhase.ABORTED):
            _stop_job(plan, job)
            if phase is MissionVehiclePhase.ABORTING:
                _abort_vehicle(obs, plan, vehicle, CommandAction.SAFETY_ROUTINE)
            updated.append(vehicle)
            continue
        if phase in (MissionVehiclePhase.SUCCEEDED, MissionVehiclePhase.FAILED):
            updated.append(vehicle)
            continue
        policy = OnFailover(obs.spec.on_failover)
        failed_over = _new_failover(vehicle, autopilots, start)
        pending = vehicle.failover_action_held is not None
        if failed_over is not None and autopilots is not None:
            vehicle.failed_over_at = failed_over
            pending = True
            plan.events.append(
                MissionEvent(
                    "Warning",
                    "VehicleFailedOver",
                    f"{vehicle.name}: {_failover_text(autopilots.status)}; onFailover={policy}",
                    vehicle=vehicle.name,
                )
            )
        held = vehicle.failover_action_held
        vehicle.failover_action_held = None
        if pending and autopilots is not None and policy is not OnFailover.CONTINUE:
            verdict = _consequence_verdict(obs, vehicle.name, autopilots)
            if verdict is not Verdict.ALLOWED:
                _hold(obs, plan, vehicle, verdict, held)
                _follow_job(obs, plan, vehicle, job, assigned)
                if vehicle.phase == MissionVehiclePhase.RUNNING:
                    vehicle.reason = failover_action_held_reason(verdict.value)
                    vehicle.message = _held_text(vehicle.name, verdict, policy)
                else:  # its workload ended meanwhile: nothing is left to hold back
                    vehicle.failover_action_held = None
                updated.append(vehicle)
                continue
            what = _failover_text(autopilots.status)
            if policy is OnFailover.ABORT_VEHICLE:
                vehicle.phase = MissionVehiclePhase.ABORTING
                vehicle.reason = MissionVehicleReason.FAILED_OVER
                vehicle.message = f"{what}; landing it (onFailover=AbortVehicle)"
                _stop_job(plan, job)
                _abort_vehicle(obs, plan, vehicle, CommandAction.SAFETY_ROUTINE)
                updated.append(vehicle)
                continue
            if policy is OnFailover.ABORT_MISSION:
                abort_mission_because = f"{vehicle.name}: {what} (onFailover=AbortMission)"
        _follow_job(obs, plan, vehicle, job, assigned)
        abort_mission_because = _reachability(obs, plan, vehicle) or abort_mission_because
        updated.append(vehicle)
    status.vehicles = updated
    _follow_offboard(obs, plan, assigned)
    _degraded(obs, status)
    if abort_mission_because is not None:
        _set_phase(
            status, MissionPhase.ABORTING, MissionReason.VEHICLE_FAILED_OVER, abort_mission_because
        )
        _abort(obs, plan)
        return
    _aggregate(obs, plan)


def _stamp(at: datetime) -> str:
    return at.isoformat().replace("+00:00", "Z")


def _reachability(obs: Observation, plan: Plan, vehicle: MissionVehicleStatus) -> str | None:
    """Show a running vehicle whose node cannot be reached (its link is lost), with an
    Event when that starts and when it ends; why to abort the mission, when
    ``spec.onUnreachable`` is AbortMission.

    Nothing else changes: its onboard pod is kept (it tolerates the lost link), its Job
    is not stopped, and the vehicle flies on; a failover during the drop is seen, with
    its own time, once the agent's report gets through.
    """
    view = obs.vehicles.get(vehicle.name)
    since = view.unreachable_since if view is not None else None
    before = vehicle.unreachable_since
    if vehicle.phase != MissionVehiclePhase.RUNNING:
        since = None
    vehicle.unreachable_since = since
    if since is None:
        if before is not None:
            plan.events.append(
                MissionEvent(
                    "Normal",
                    "VehicleReachable",
                    f"{vehicle.name}: its node is reachable again "
                    f"(unreachable since {_stamp(before)})",
                    vehicle=vehicle.name,
                )
            )
        return None
    policy = OnUnreachable(obs.spec.on_unreachable)
    node = view.node_name if view is not None else "?"
    vehicle.reason = MissionVehicleReason.VEHICLE_UNREACHABLE
    vehicle.message = (
        f"node {node} unreachable since {_stamp(since)}; its onboard pod is kept and the "
        f"vehicle flies on (onUnreachable={policy}); last seen: {vehicle.message}"
    )
    if before is None:
        plan.events.append(
            MissionEvent(
                "Warning",
                "VehicleUnreachable",
                f"{vehicle.name}: node {node} unreachable since {_stamp(since)} "
                f"(onUnreachable={policy})",
                vehicle=vehicle.name,
            )
        )
    if policy is OnUnreachable.ABORT_MISSION:
        return f"{vehicle.name}: node {node} unreachable since {_stamp(since)} " + (
            "(onUnreachable=AbortMission)"
        )
    return None


def vehicle_lost(obs: Observation, name: str) -> bool:
    """Whether the Vehicle ``name`` is gone or being deleted (it left the fleet)."""
    view = obs.vehicles.get(name)
    return view is None or view.deleting


def _leave(
    obs: Observation, plan: Plan, vehicle: MissionVehicleStatus, job: JobView | None
) -> bool:
    """The Vehicle was deleted mid-mission: it leaves the mission now.

    Its Job is stopped at once (its node is released, nothing must keep running there
    for the mission) and its copy of the vehicle config is removed. Its agent, if its
    RedundantAutopilot is still there, is asked to run the safety routine — the same
    reasoning as for a deleted Mission: the vehicle must not stay in the air without its
    controllers. No fleet guard applies: deleting the Vehicle was a human's decision.
    True the first time (the mission then applies ``spec.onFailover``: AbortMission
    aborts it, otherwise it goes on Degraded).
    """
    _stop_job(plan, job)
    plan.config_maps_to_delete.append(vehicle.name)
    first = vehicle.reason != MissionVehicleReason.VEHICLE_DELETED
    vehicle.failover_action_held = None  # nothing is left to hold back
    _abort_vehicle(obs, plan, vehicle, CommandAction.SAFETY_ROUTINE)
    vehicle.reason = MissionVehicleReason.VEHICLE_DELETED
    vehicle.message = f"the Vehicle was deleted during the mission; {vehicle.message}"
    if first:
        plan.events.append(
            MissionEvent(
                "Warning",
                "VehicleDeleted",
                f"{vehicle.name}: the Vehicle was deleted; its Job is stopped and it leaves "
                f"the mission (onFailover={obs.spec.on_failover})",
                vehicle=vehicle.name,
            )
        )
    return first


def _consequence_verdict(obs: Observation, name: str, autopilots: AutopilotView) -> Verdict:
    """Whether the fleet guards let ``spec.onFailover`` act on vehicle ``name`` now."""
    view = obs.vehicles.get(name)
    return consequence_verdict(
        obs.guards,
        annotations=view.annotations if view is not None else {},
        book=view.status.failover if view is not None else None,
        status=autopilots.status,
        now=obs.now,
    )


def _held_text(name: str, verdict: Verdict, policy: OnFailover) -> str:
    why = {
        Verdict.PAUSED: f"failover actions are paused ({ANNOTATION_PAUSE_FAILOVER_ACTIONS} "
        "on the Vehicle, or fleet-wide)",
        Verdict.LATCHED: "the vehicle's failover latch is set; a human clears it with "
        f"kubectl annotate vehicle {name} {ANNOTATION_CLEAR_FAILOVER_LATCH}=<new token> "
        "--overwrite",
    }[verdict]
    return (
        f"onFailover={policy} held back: {why}; the vehicle's agent ran its own safety "
        "routine; applied once the guard lifts"
    )


def _hold(
    obs: Observation,
    plan: Plan,
    vehicle: MissionVehicleStatus,
    verdict: Verdict,
    held_before: str | None,
) -> None:
    """Record that a guard holds the vehicle's failover consequence; an Event when new."""
    vehicle.failover_action_held = verdict
    if held_before != verdict.value:
        policy = OnFailover(obs.spec.on_failover)
        plan.events.append(
            MissionEvent(
                "Warning",
                f"FailoverAction{verdict.value}",
                f"{vehicle.name}: {_held_text(vehicle.name, verdict, policy)}",
                vehicle=vehicle.name,
            )
        )


def _new_failover(
    vehicle: MissionVehicleStatus, autopilots: AutopilotView | None, start: datetime
) -> datetime | None:
    if autopilots is None:
        return None
    when = failover_time(autopilots.status)
    if when is None or when < start:
        return None
    if vehicle.failed_over_at is not None and when <= vehicle.failed_over_at:
        return None
    return when


def _stop_job(plan: Plan, job: JobView | None) -> None:
    if job is not None and job.phase is JobPhase.ACTIVE and not job.deleting:
        plan.jobs_to_delete.append(job.name)


def _follow_job(
    obs: Observation,
    plan: Plan,
    vehicle: MissionVehicleStatus,
    job: JobView | None,
    assigned: Sequence[str],
) -> None:
    """Per-vehicle phase from its onboard Job; (re)create the Job when it is missing."""
    if job is None:
        if vehicle.name not in obs.vehicles:
            vehicle.phase = MissionVehiclePhase.FAILED
            vehicle.reason = MissionVehicleReason.VEHICLE_MISSING
            vehicle.message = "the Vehicle was deleted before its onboard Job could run"
            return
        if vehicle.name not in obs.config_values:
            vehicle.phase = MissionVehiclePhase.FAILED
            vehicle.reason = MissionVehicleReason.VEHICLE_CONFIG_MISSING
            vehicle.message = "the vehicle's config ConfigMap is gone; cannot start its Job"
            return
        _launch(obs, plan, vehicle, assigned)
        return
    if vehicle.name in obs.config_values:
        plan.config_maps.append(
            config_map_copy(obs.mission, vehicle.name, obs.config_values[vehicle.name])
        )
    attempts = obs.spec.backoff_limit + 1
    if job.phase is JobPhase.SUCCEEDED:
        vehicle.phase = MissionVehiclePhase.SUCCEEDED
        vehicle.reason = MissionVehicleReason.COMPLETED
        vehicle.message = f"onboard Job {job.name} completed"
    elif job.phase is JobPhase.FAILED:
        vehicle.phase = MissionVehiclePhase.FAILED
        vehicle.reason = MissionVehicleReason.JOB_FAILED
        vehicle.message = (
            f"onboard Job {job.name} failed after {job.failed} of {attempts} attempts: "
            f"{job.message or 'no message'}"
        )
    else:
        vehicle.phase = MissionVehiclePhase.RUNNING
        vehicle.reason = (
            MissionVehicleReason.POD_RUNNING if job.ready else MissionVehicleReason.POD_STARTING
        )
        vehicle.message = (
            f"onboard Job {job.name}: {job.active} active, {job.ready} ready, "
            f"{job.failed} failed of {attempts} attempts"
        )


def _follow_offboard(obs: Observation, plan: Plan, assigned: Sequence[str]) -> None:
    if obs.spec.offboard is None:
        return
    status = plan.status
    name = offboard_job_name(obs.mission.name)
    job = obs.jobs.get(name)
    previous = status.offboard
    if job is None:
        if previous is not None and previous.phase != WorkloadPhase.RUNNING:
            return
        plan.jobs_to_create.append(
            offboard_job(mission=obs.mission, spec=obs.spec, assigned=assigned)
        )
        status.offboard = MissionOffboardStatus(
            job_name=name, phase=WorkloadPhase.RUNNING, message="offboard Job created"
        )
        return
    phase = {
        JobPhase.ACTIVE: WorkloadPhase.RUNNING,
        JobPhase.SUCCEEDED: WorkloadPhase.SUCCEEDED,
        JobPhase.FAILED: WorkloadPhase.FAILED,
    }[job.phase]
    message = {
        JobPhase.ACTIVE: f"{job.active} active, {job.ready} ready",
        JobPhase.SUCCEEDED: "completed",
        JobPhase.FAILED: f"failed: {job.message or 'no message'}",
    }[job.phase]
    status.offboard = MissionOffboardStatus(job_name=name, phase=phase, message=message)


def _degraded(obs: Observation, status: MissionStatus) -> None:
    lost = [
        v.name
        for v in status.vehicles
        if v.phase != MissionVehiclePhase.SUCCEEDED and vehicle_lost(obs, v.name)
    ]
    failed_over = [v for v in status.vehicles if v.failed_over_at is not None]
    if lost and not failed_over:
        _condition(
            obs,
            status,
            MissionConditionType.DEGRADED,
            "True",
            reason=MissionReason.VEHICLE_DELETED,
            message=f"Vehicle deleted during the mission: {', '.join(lost)}",
        )
        return
    if not failed_over:
        _unreachable_degraded(obs, status)
        return
    names = ", ".join(v.name for v in failed_over)
    policy = OnFailover(obs.spec.on_failover)
    message = f"autopilot failover on {names} (onFailover={policy})"
    reason: str = MissionReason.VEHICLE_FAILED_OVER
    held = [v for v in failed_over if v.failover_action_held is not None]
    if held:
        reason = failover_action_held_reason(str(held[0].failover_action_held))
        message += "; held back by a fleet guard on " + ", ".join(
            f"{v.name} ({v.failover_action_held})" for v in held
        )
    _condition(
        obs,
        status,
        MissionConditionType.DEGRADED,
        "True",
        reason=reason,
        message=message,
    )


def _unreachable_degraded(obs: Observation, status: MissionStatus) -> None:
    """Degraded while a vehicle's node cannot be reached (and nothing worse happened);
    False again once every vehicle is reachable."""
    out = [v for v in status.vehicles if v.unreachable_since is not None]
    degraded = find_condition(status.conditions, MissionConditionType.DEGRADED)
    if out:
        _condition(
            obs,
            status,
            MissionConditionType.DEGRADED,
            "True",
            reason=MissionReason.VEHICLE_UNREACHABLE,
            message="node unreachable (the vehicle flies on): "
            + ", ".join(
                f"{v.name} since {_stamp(v.unreachable_since)}" for v in out if v.unreachable_since
            ),
        )
    elif degraded is not None and degraded.reason == MissionReason.VEHICLE_UNREACHABLE:
        _condition(
            obs,
            status,
            MissionConditionType.DEGRADED,
            "False",
            reason=MissionReason.VEHICLES_REACHABLE,
            message="every vehicle's node is reachable again",
        )


def _aggregate(obs: Observation, plan: Plan) -> None:
    status = plan.status
    vehicles = status.vehicles
    failed = [v for v in vehicles if v.phase == MissionVehiclePhase.FAILED]
    offboard_failed = status.offboard is not None and status.offboard.phase == WorkloadPhase.FAILED
    if failed:
        first = failed[0]
        _finish(
            obs,
            plan,
            MissionPhase.FAILED,
            MissionReason.VEHICLE_WORKLOAD_FAILED,
            f"{first.name}: {first.message}",
        )
        return
    if offboard_failed and status.offboard is not None:
        _finish(
            obs,
            plan,
            MissionPhase.FAILED,
            MissionReason.OFFBOARD_WORKLOAD_FAILED,
            f"offboard Job {status.offboard.job_name} {status.offboard.message}",
        )
        return
    succeeded = [v for v in vehicles if v.phase == MissionVehiclePhase.SUCCEEDED]
    aborted = [v for v in vehicles if v.phase == MissionVehiclePhase.ABORTED]
    if vehicles and all(MissionVehiclePhase(v.phase) in _VEHICLE_DONE for v in vehicles):
        if succeeded:
            why = (
                "a failover or the Vehicle's deletion"
                if any(v.reason == MissionVehicleReason.VEHICLE_DELETED for v in aborted)
                else "a failover"
            )
            extra = f"; {len(aborted)} aborted after {why}" if aborted else ""
            _finish(
                obs,
                plan,
                MissionPhase.SUCCEEDED,
                MissionReason.COMPLETED,
                f"{len(succeeded)} onboard workload{'s' if len(succeeded) != 1 else ''} "
                f"completed{extra}",
            )
        else:
            _finish(
                obs,
                plan,
                MissionPhase.FAILED,
                MissionReason.ALL_VEHICLES_ABORTED,
                "every vehicle was aborted after an autopilot failover",
            )
        return
    running = len(vehicles) - len(succeeded) - len(aborted)
    message = f"{len(succeeded)}/{len(vehicles)} onboard workloads completed, {running} running"
    if aborted:
        message += f", {len(aborted)} aborted"
    _set_phase(status, MissionPhase.RUNNING, MissionReason.STARTED, message)


def _finish(obs: Observation, plan: Plan, phase: MissionPhase, reason: str, message: str) -> None:
    status = plan.status
    _set_phase(status, phase, reason, message)
    status.completion_time = obs.now
    for job in obs.jobs.values():
        _stop_job(plan, job)
    for vehicle in status.vehicles:
        if vehicle.phase in (MissionVehiclePhase.RUNNING, MissionVehiclePhase.CLAIMED):
            vehicle.phase = MissionVehiclePhase.FAILED
            vehicle.reason = MissionVehicleReason.MISSION_ENDED
            vehicle.message = f"workload stopped: the mission {phase.value.lower()} ({reason})"
    if status.offboard is not None and status.offboard.phase == WorkloadPhase.RUNNING:
        status.offboard.phase = WorkloadPhase.STOPPED
        status.offboard.message = f"stopped: the mission {phase.value.lower()}"
    complete: ConditionStatus = "True" if phase is MissionPhase.SUCCEEDED else "False"
    _condition(obs, status, MissionConditionType.COMPLETE, complete, reason=reason, message=message)
    _release_landed(obs, plan)


def _release_landed(obs: Observation, plan: Plan) -> None:
    """Release every held vehicle except those still landing after an abort."""
    landing = {v.name for v in plan.status.vehicles if v.phase == MissionVehiclePhase.ABORTING}
    plan.releases.extend(n for n in held_by(obs.mission, obs.vehicles) if n not in landing)
    if landing:
        plan.requeue_after = ABORT_POLL_SECONDS


def _wind_down(obs: Observation, plan: Plan) -> None:
    """A finished mission: stop anything still active and give back its vehicles.

    A vehicle still landing after an AbortVehicle when the mission ended (another
    vehicle's workload failed meanwhile) stays claimed and followed until it is down,
    so no other mission can take it in the air.
    """
    for job in obs.jobs.values():
        _stop_job(plan, job)
    for vehicle in plan.status.vehicles:
        if vehicle.phase == MissionVehiclePhase.ABORTING:
            _abort_vehicle(obs, plan, vehicle, CommandAction.SAFETY_ROUTINE)
    _release_landed(obs, plan)


# -- Abort -------------------------------------------------------------------------------


def _abort_before_start(obs: Observation, plan: Plan) -> None:
    status = plan.status
    _set_phase(
        status,
        MissionPhase.ABORTED,
        MissionReason.ABORTED_BEFORE_START,
        "aborted before any workload started; no vehicle was commanded",
    )
    status.completion_time = obs.now
    for vehicle in status.vehicles:
        vehicle.phase = MissionVehiclePhase.ABORTED
        vehicle.reason = MissionVehicleReason.ABORTED_BEFORE_START
        vehicle.message = "nothing was started on this vehicle"
    _condition(
        obs,
        status,
        MissionConditionType.COMPLETE,
        "False",
        reason=MissionReason.ABORTED_BEFORE_START,
    )
    plan.releases.extend(held_by(obs.mission, obs.vehicles))


def abort_action(spec: MissionSpec) -> CommandAction:
    """The command an abort sends: the spec's for a requested abort, else the safety routine."""
    if spec.abort and AbortAction(spec.abort_action) is AbortAction.EMERGENCY_STOP:
        return CommandAction.EMERGENCY_STOP
    return CommandAction.SAFETY_ROUTINE


def _abort(obs: Observation, plan: Plan) -> None:
    status = plan.status
    action = abort_action(obs.spec)
    if obs.spec.abort:
        status.reason = MissionReason.ABORT_REQUESTED
    for job in obs.jobs.values():
        _stop_job(plan, job)
    if status.offboard is not None and status.offboard.phase == WorkloadPhase.RUNNING:
        status.offboard.phase = WorkloadPhase.STOPPED
        status.offboard.message = "stopped by the abort"
    for vehicle in status.vehicles:
        vehicle.failover_action_held = None  # the abort supersedes a held consequence
        if vehicle.phase != MissionVehiclePhase.ABORTED:
            _abort_vehicle(obs, plan, vehicle, action)
    waiting = [v for v in status.vehicles if v.phase != MissionVehiclePhase.ABORTED]
    if waiting:
        listed = "; ".join(f"{v.name}: {v.message}" for v in waiting[:5])
        more = f"; and {len(waiting) - 5} more" if len(waiting) > 5 else ""
        _set_phase(
            status,
            MissionPhase.ABORTING,
            status.reason or MissionReason.ABORT_REQUESTED,
            f"{_abort_cause(obs, status, action)} — waiting for {len(waiting)} vehicle"
            f"{'s' if len(waiting) != 1 else ''}: {listed}{more}",
        )
        plan.requeue_after = ABORT_POLL_SECONDS
        return
    count = len(status.vehicles)
    _set_phase(
        status,
        MissionPhase.ABORTED,
        status.reason or MissionReason.ABORT_REQUESTED,
        f"{_abort_cause(obs, status, action)} — {count} vehicle{'s' if count != 1 else ''} stopped",
    )
    status.completion_time = obs.now
    _condition(
        obs,
        status,
        MissionConditionType.COMPLETE,
        "False",
        reason=MissionReason.ABORTED,
        message=status.message or "",
    )
    plan.releases.extend(held_by(obs.mission, obs.vehicles))


def _abort_cause(obs: Observation, status: MissionStatus, action: CommandAction) -> str:
    if status.reason == MissionReason.ABORT_REQUESTED:
        return f"abort requested ({action})"
    names = ", ".join(v.name for v in status.vehicles if v.failed_over_at is not None)
    return f"autopilot failover on {names or 'a vehicle'} (onFailover=AbortMission; {action})"


def abort_command_id(
    mission: MissionRef, vehicle_name: str, action: CommandAction, attempt: int
) -> str:
    """Deterministic id of a mission's abort command, unique per mission, vehicle, action."""
    digest = hashlib.sha256(f"{mission.uid}/{vehicle_name}".encode()).hexdigest()[:12]
    return f"mission-{digest}-{CommandAction(action).value.lower()}-{attempt}"


def _attempt_of(
    command: AutopilotCommand | None, mission: MissionRef, vehicle_name: str, action: CommandAction
) -> int:
    if command is None:
        return 0
    prefix = abort_command_id(mission, vehicle_name, action, 0)[:-1]
    tail = command.id.removeprefix(prefix)
    return int(tail) if tail != command.id and tail.isdigit() else 0


def _active_health(status: RedundantAutopilotStatus) -> list[AutopilotHealth]:
    active = [h for h in status.autopilots if h.name == status.active_autopilot]
    return active or list(status.autopilots)


def stopped(action: CommandAction, status: RedundantAutopilotStatus) -> bool:
    """Whether the vehicle has done what ``action`` asks, by its active autopilot's report.

    The safety routine ends on the ground (or disarmed); an emergency stop ends disarmed.
    Without an active autopilot in the report, every reported autopilot must agree.
    """
    health = _active_health(status)
    if not health:
        return False
    if CommandAction(action) is CommandAction.EMERGENCY_STOP:
        return all(h.armed is False for h in health)
    return all(h.landed_state == LandedState.ON_GROUND or h.armed is False for h in health)


def _reported_since(status: RedundantAutopilotStatus, command: AutopilotCommand) -> bool:
    if status.last_command is not None and status.last_command.id == command.id:
        return True
    return status.reported_at is not None and status.reported_at >= command.issued_at


def _flight_text(status: RedundantAutopilotStatus) -> str:
    health = _active_health(status)
    if not health:
        return "no autopilot report"
    h = health[0]
    armed = {True: "armed", False: "disarmed", None: "armed state unknown"}[h.armed]
    return f"{h.name} {h.landed_state or 'landed state unknown'}, {armed}"


def _abort_vehicle(
    obs: Observation, plan: Plan, vehicle: MissionVehicleStatus, action: CommandAction
) -> None:
    """Ask one vehicle's agent to stop it, and mark it Aborted once it reports stopped."""
    autopilots = obs.autopilots.get(vehicle.name)
    if autopilots is None:
        vehicle.phase = MissionVehiclePhase.ABORTED
        vehicle.reason = MissionVehicleReason.NO_REDUNDANT_AUTOPILOT
        vehicle.message = (
            f"no RedundantAutopilot: cannot request {action}; its workload was stopped"
        )
        return
    command = vehicle.command
    outcome = (
        command_outcome(command, autopilots.spec.command, autopilots.status.last_command)
        if command is not None and command.action == action
        else None
    )
    if outcome is None or outcome in (CommandOutcome.EXPIRED, CommandOutcome.SUPERSEDED):
        attempt = _attempt_of(command if outcome else None, obs.mission, vehicle.name, action) + 1
        command_id = abort_command_id(obs.mission, vehicle.name, action, attempt)
        existing = autopilots.spec.command
        if existing is not None and existing.id == command_id:
            command = existing
        else:
            command = new_command(
                action,
                command_id=command_id,
                issued_at=obs.now,
                deadline_seconds=ABORT_COMMAND_DEADLINE_SECONDS,
            )
            plan.commands[vehicle.name] = command
        vehicle.command = command
        outcome = command_outcome(command, command, autopilots.status.last_command)
    assert command is not None
    status = autopilots.status
    if _reported_since(status, command) and stopped(action, status):
        vehicle.phase = MissionVehiclePhase.ABORTED
        vehicle.reason = (
            MissionVehicleReason.DISARMED
            if action is CommandAction.EMERGENCY_STOP
            else MissionVehicleReason.LANDED
        )
        vehicle.message = f"{action} done: {_flight_text(status)}"
        return
    vehicle.phase = MissionVehiclePhase.ABORTING
    vehicle.reason = abort_command_reason(action, outcome)
    detail = ""
    if outcome is CommandOutcome.REJECTED and status.last_command is not None:
        detail = f" ({status.last_command.message})"
    vehicle.message = f"{action} {str(outcome).lower()}{detail}; {_flight_text(status)}"


# -- Events -----------------------------------------------------------------------------


def transition_events(old: MissionStatus, new: MissionStatus) -> list[MissionEvent]:
    """Events for what changed: the mission's phase/reason, each vehicle's phase/reason.

    Progress inside Running (a pod becoming ready) is status, not an Event. When more
    than :data:`VEHICLE_EVENTS_MAX` vehicles make the same transition at once (a large
    mission starting), one Event names them instead of one Event each.
    """
    events: list[MissionEvent] = []
    if (old.phase, old.reason) != (new.phase, new.reason) and new.reason:
        warning = MissionPhase(new.phase) in _WARNING_PHASES or new.reason in _WARNING_REASONS
        severity: Severity = "Warning" if warning else "Normal"
        events.append(MissionEvent(severity, new.reason, new.message or str(new.phase)))
    before = {v.name: (v.phase, v.reason) for v in old.vehicles}
    moved: dict[tuple[MissionVehiclePhase, str], list[MissionVehicleStatus]] = {}
    for vehicle in new.vehicles:
        phase = MissionVehiclePhase(vehicle.phase)
        prior = before.get(vehicle.name)
        quiet = phase is MissionVehiclePhase.RUNNING or (
            prior is not None and prior[1] == vehicle.reason
        )
        if prior is not None and prior[0] == phase and quiet:
            continue
        moved.setdefault((phase, vehicle.reason or phase.value), []).append(vehicle)
    for (phase, reason), vehicles in moved.items():
        severity = "Warning" if phase in _WARNING_VEHICLE_PHASES else "Normal"
        if len(vehicles) > VEHICLE_EVENTS_MAX:
            names = ", ".join(v.name for v in vehicles[:VEHICLE_EVENTS_MAX])
            events.append(
                MissionEvent(severity, reason, f"{len(vehicles)} vehicles {phase}: {names}, …")
            )
            continue
        events.extend(
            MissionEvent(severity, reason, f"{v.name}: {v.message or phase}", vehicle=v.name)
            for v in vehicles
        )
    return events
