"""Builders for the mission controller's unit tests: API models as the API server returns
them, and the controller's observation of a Mission built from them.

The mission controller's functions are pure; these builders are its inputs, shared by the
unit test file of each of its modules.
"""

from __future__ import annotations

from datetime import UTC, datetime
from functools import partial
from typing import Any

from roost_api.autopilot import (
    AutopilotCommand,
    CommandResult,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.meta import Condition, ObjectReference
from roost_api.mission import (
    MissionPhase,
    MissionSpec,
    MissionStatus,
)
from roost_api.vehicle import VehicleFailover, VehicleSpec, VehicleStatus
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.claims import Claim
from roost_operator.missions.machine import (
    Observation,
    Plan,
    plan_mission,
)
from roost_operator.missions.observed import (
    AutopilotView,
    JobPhase,
    JobView,
    MissionRef,
    VehicleView,
)
from roost_operator.missions.workloads import (
    onboard_job_name,
)
from tests.support.conditions import cond as support_cond
from tests.support.fakeagents import redundant_autopilot

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
ME = MissionRef(namespace="default", name="survey", uid="uid-survey")
OTHER = ObjectReference(namespace="default", name="rival")


cond = partial(support_cond, at=T0)


def vehicle(
    name: str,
    *,
    ready: bool = True,
    agent: bool | None = True,
    claimed_by: ObjectReference | None = None,
    labels: dict[str, str] | None = None,
    deleting: bool = False,
    annotations: dict[str, str] | None = None,
    failover: VehicleFailover | None = None,
    unreachable_since: datetime | None = None,
) -> VehicleView:
    """A Vehicle as the operator reports it; ``ready`` is the node/components side,
    ``unreachable_since`` its node's lost link (NodeBound False, NodeUnreachable)."""
    flag = "True" if ready and unreachable_since is None else "False"
    node_reason = "NodeLabeled" if ready else "NodeNotReady"
    if unreachable_since is not None:
        node_reason = "NodeUnreachable"
    conditions = [
        cond("NodeBound", flag, node_reason, at=unreachable_since or T0),
        cond("ComponentsReady", "True", "NoComponents"),
        cond("Ready", flag, "VehicleReady" if flag == "True" else node_reason),
    ]
    if agent is not None:
        conditions.append(cond("AgentConnected", "True" if agent else "False", "Reporting"))
    return VehicleView(
        name=name,
        labels=labels if labels is not None else {"fleet": "a"},
        spec=VehicleSpec.model_validate({"nodeName": f"node-{name}", "sysid": 10}),
        status=VehicleStatus(conditions=conditions, failover=failover),
        resource_version="1",
        uid=f"uid-{name}",
        deleting=deleting,
        annotations=annotations or {},
        claim=claim_on(name, claimed_by) if claimed_by is not None else None,
    )


def claim_on(name: str, holder: ObjectReference) -> Claim:
    """The claim Lease on vehicle ``name`` held by ``holder``, as the observer parses it."""
    return Claim(
        vehicle=name, holder=holder, mission_uid="", resource_version="7", uid=f"lease-{name}"
    )


def autopilots(
    vehicle_name: str,
    *,
    healthy: bool = True,
    redundant: bool = True,
    failover_at: datetime | None = None,
    landed: str = "InAir",
    armed: bool = True,
    reported_at: datetime | None = None,
    command: AutopilotCommand | None = None,
    last_command: CommandResult | None = None,
    firmware: tuple[dict[str, Any], Condition | None] | None = None,
) -> AutopilotView:
    status: dict[str, Any] = {
        "conditions": [
            cond("ActiveHealthy", "True" if healthy else "False", "HeartbeatLost").to_api(),
            cond("Redundant", "True" if redundant else "False", "StandbyStale").to_api(),
        ],
        "activeAutopilot": "fc2" if failover_at else "fc1",
        "autopilots": [
            {"name": "fc1", "level": "OK", "landedState": landed, "armed": armed},
            {"name": "fc2", "level": "OK", "landedState": landed, "armed": armed},
        ],
        "reportedAt": reported_at,
    }
    if failover_at is not None:
        status["lastFailover"] = {
            "time": failover_at,
            "from": "fc1",
            "to": "fc2",
            "reason": "heartbeat lost on fc1",
            "latencyMs": 20.0,
            "trigger": "Automatic",
        }
        status["conditions"].append(cond("FailedOver", "True", "Switched", at=failover_at).to_api())
    if last_command is not None:
        status["lastCommand"] = last_command.to_api()
    spec = redundant_autopilot(vehicle_name)["spec"]
    if command is not None:
        spec["command"] = command.to_api()
    if firmware is not None:  # (spec.firmware, the agent's FirmwareAcceptable condition)
        spec["firmware"], judged = firmware
        if judged is not None:
            status["conditions"].append(judged.to_api())
    return AutopilotView(
        name=vehicle_name,
        spec=RedundantAutopilotSpec.model_validate(spec),
        status=RedundantAutopilotStatus.model_validate(status),
    )


POD_TEMPLATE = {
    "metadata": {"labels": {"app": "controller"}},
    "spec": {
        "containers": [
            {"name": "c", "image": "controller:1", "env": [{"name": "MINE", "value": "1"}]}
        ]
    },
}


def mission_spec(**overrides: Any) -> MissionSpec:
    body: dict[str, Any] = {
        "vehicles": {"selector": {"matchLabels": {"fleet": "a"}}, "count": 2},
        "onboard": POD_TEMPLATE,
    }
    body.update(overrides)
    return MissionSpec.model_validate(body)


def config(name: str) -> dict[str, str]:
    return {"VEHICLE_NAME": name, "VEHICLE_MAVLINK_SYSID": "10"}


NO_GUARD_ENGAGED = FleetGuards()


def observe(
    vehicles: list[VehicleView],
    *,
    spec: MissionSpec | None = None,
    status: MissionStatus | None = None,
    aps: list[AutopilotView] | None = None,
    jobs: list[JobView] | None = None,
    live: set[str] | None = None,
    now: datetime = T0,
    guards: FleetGuards = NO_GUARD_ENGAGED,
) -> Observation:
    by_name = {v.name: v for v in vehicles}
    return Observation(
        mission=ME,
        generation=1,
        spec=spec or mission_spec(),
        status=status or MissionStatus(),
        vehicles=by_name,
        autopilots={
            a.vehicle_name: a
            for a in (aps if aps is not None else [autopilots(v.name) for v in vehicles])
        },
        jobs={j.name: j for j in jobs or []},
        config_values={name: config(name) for name in by_name},
        live_missions=frozenset(live if live is not None else {ME.key, "default/rival"}),
        now=now,
        guards=guards,
    )


def claimed(*names: str, **kwargs: Any) -> list[VehicleView]:
    return [vehicle(n, claimed_by=ME.reference, **kwargs) for n in names]


def job(vehicle_name: str, phase: JobPhase = JobPhase.ACTIVE, **kwargs: Any) -> JobView:
    return JobView(name=onboard_job_name(ME.name, vehicle_name), phase=phase, created=T0, **kwargs)


def started(
    names: list[str], *, spec: MissionSpec | None = None
) -> tuple[MissionStatus, list[VehicleView]]:
    """The status after the mission started on ``names`` (all preflight checks passed)."""
    plan = plan_mission(
        observe(
            claimed(*names),
            spec=spec or mission_spec(vehicles={"names": names, "count": len(names)}),
        )
    )
    assert plan.status.phase == MissionPhase.RUNNING
    return plan.status, claimed(*names)


def vehicle_status(plan: Plan, name: str) -> Any:
    return next(v for v in plan.status.vehicles if v.name == name)
