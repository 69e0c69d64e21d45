"""A mission's reads and writes: build an Observation, carry out a Plan. No decisions.

Everything goes through :class:`~roost_kube.client.Kube`. The parts that need care:

* **Claims** are a JSON merge patch of ``status.claimedBy`` alone, carrying the
  ``resourceVersion`` the decision was made on. Of two missions claiming one vehicle,
  the API server accepts exactly one patch; the other gets 409. A 409 is not always a
  lost race — the vehicle operator also writes Vehicle status (its own fields only) —
  so the loser re-reads the vehicle and retries only while it is still unclaimed and
  claimable. Claims are all-or-nothing: when one fails, the vehicles claimed in the same
  round are given back and the mission plans again from a fresh read.
* **Order**: Vehicles are listed before Missions, so an orphaned claim is never
  confused with a claim by a Mission created in between (see
  :mod:`~roost_operator.missions.selection`). The status is written before Jobs are
  created, so ``startTime`` precedes every workload; commands before releases, so a
  vehicle is never free while its abort is still unwritten.
* **Writes only on change**: the status is patched only when it differs, ConfigMap
  copies only when their content hash differs, Jobs are created only when missing
  (an AlreadyExists answer counts as success).
* **Independent writes in parallel** (:func:`_each`): a 100-vehicle mission's Jobs,
  ConfigMap copies, commands and Events are each one request per vehicle; sent one
  after another they would cost 100 round trips of latency each.
"""

from __future__ import annotations

import logging
import random
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any, Final, TypeVar

from pydantic import ValidationError

from roost_api.autopilot import AutopilotCommand
from roost_api.commands import command_patch
from roost_api.meta import API_VERSION, ObjectReference
from roost_api.mission import MissionPhase, MissionSpec, MissionStatus
from roost_api.resources import MISSION, VEHICLE
from roost_api.wellknown import (
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_MISSION,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_kube.client import Kube
from roost_kube.errors import ApiError, ConflictError
from roost_kube.patches import Obj, needs_apply, with_applied_hash
from roost_kube.resources import CONFIGMAPS, JOBS, MISSIONS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.missions.machine import (
    MissionEvent,
    Observation,
    Plan,
    fail_mission,
    plan_deletion,
    plan_mission,
)
from roost_operator.missions.observed import AutopilotView, JobView, MissionRef, VehicleView
from roost_operator.missions.selection import holding_missions, is_claimable
from roost_operator.missions.workloads import bounded_name
from roost_operator.vehicles.config import CONFIG_COMPONENT, config_values_of
from roost_operator.vehicles.status import write_vehicle_status

log = logging.getLogger(__name__)

CLAIM_RETRIES: Final = 3
"""Re-reads of one vehicle after a 409 before giving up on claiming it."""
RELEASE_RETRIES: Final = 5
CLAIM_ROUNDS: Final = 3
"""Claim rounds per reconcile; after that the mission waits a jittered moment."""
UNPROCESSABLE: Final = 422
WRITE_CONCURRENCY: Final = 8
"""Independent writes of one reconcile in flight at once (Jobs, ConfigMaps, Events)."""

T = TypeVar("T")


def _each(write: Callable[[T], object], items: Sequence[T]) -> None:
    """Call ``write`` on every item, up to :data:`WRITE_CONCURRENCY` at once.

    Independent writes (one Job per vehicle, one Event each) are bound by request
    latency, not by the API server's capacity, so a 100-vehicle mission would otherwise
    wait for 100 round trips in a row. The first error is raised after all have run.
    """
    if len(items) <= 1:
        for item in items:
            write(item)
        return
    with ThreadPoolExecutor(max_workers=WRITE_CONCURRENCY) as pool:
        for _ in pool.map(write, items):
            pass


def _timestamp(at: datetime) -> str:
    return at.astimezone(UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def _parse_all(items: Iterable[Obj], parse: Callable[[Obj], T], what: str) -> list[T]:
    """Parse each object; one malformed object is logged and skipped, not fatal."""
    parsed = []
    for item in items:
        try:
            parsed.append(parse(item))
        except (ValidationError, KeyError) as error:
            name = item.get("metadata", {}).get("name")
            log.warning("skipping malformed %s %s: %s", what, name, error)
    return parsed


def _owned_by(body: Mapping[str, Any], uid: str) -> bool:
    refs = body.get("metadata", {}).get("ownerReferences") or []
    return any(ref.get("uid") == uid for ref in refs)


def mission_body(mission: MissionRef) -> Obj:
    """The minimal Mission object Events and owner references need."""
    return {
        "apiVersion": API_VERSION,
        "kind": MISSION.kind,
        "metadata": {"name": mission.name, "namespace": mission.namespace, "uid": mission.uid},
    }


def vehicle_body(vehicle: VehicleView) -> Obj:
    """The minimal Vehicle object Events need."""
    return {
        "apiVersion": API_VERSION,
        "kind": VEHICLE.kind,
        "metadata": {"name": vehicle.name, "uid": vehicle.uid},
    }


def observe(
    kube: Kube, *, namespace: str, name: str, operator_namespace: str, guards: FleetGuards
) -> Observation | None:
    """Read everything a decision about Mission ``namespace/name`` needs (None if gone)."""
    body = kube.get(MISSIONS, name, namespace)
    if body is None:
        return None
    meta = body["metadata"]
    mission = MissionRef(namespace=namespace, name=name, uid=meta["uid"])
    status = MissionStatus.model_validate(body.get("status") or {})
    vehicles = _parse_all(kube.list_objects(VEHICLES), VehicleView.from_body, "Vehicle")
    autopilots = _parse_all(
        kube.list_objects(REDUNDANT_AUTOPILOTS), AutopilotView.from_body, "RedundantAutopilot"
    )
    jobs = [
        JobView.from_body(job)
        for job in kube.list_objects(
            JOBS, namespace=namespace, labels={LABEL_MISSION: bounded_name(name)}
        )
        if _owned_by(job, mission.uid)
    ]
    config_maps = kube.list_objects(
        CONFIGMAPS,
        namespace=operator_namespace,
        labels={LABEL_MANAGED_BY: MANAGED_BY, LABEL_COMPONENT: CONFIG_COMPONENT},
    )
    started = status.start_time is not None or bool(jobs)
    live = frozenset({mission.key}) if started else holding_missions(kube.list_objects(MISSIONS))
    return Observation(
        mission=mission,
        generation=int(meta.get("generation") or 0),
        spec=MissionSpec.model_validate(body["spec"]),
        status=status,
        vehicles={v.name: v for v in vehicles},
        autopilots={a.vehicle_name: a for a in autopilots},
        jobs={j.name: j for j in jobs},
        config_values={
            cm["metadata"]["labels"][LABEL_VEHICLE]: config_values_of(cm)
            for cm in config_maps
            if LABEL_VEHICLE in cm["metadata"].get("labels", {})
        },
        live_missions=live,
        now=datetime.now(UTC),
        guards=guards,
    )


# -- claims ---------------------------------------------------------------------------


CLAIM_FIELDS: Final = ("claimedBy",)
"""The only Vehicle status field the mission controller writes."""


def _patch_claim(kube: Kube, vehicle: VehicleView, claim: ObjectReference | None) -> VehicleView:
    """Write ``claimedBy`` alone, conditional on the resourceVersion ``vehicle`` was read at."""
    claimed = vehicle.status.model_copy(update={"claimed_by": claim})
    read_at = {"metadata": {"name": vehicle.name, "resourceVersion": vehicle.resource_version}}
    write_vehicle_status(
        kube, read_at, vehicle.status, claimed, fields=CLAIM_FIELDS, event_types=()
    )
    return replace(vehicle, status=claimed)


def claim_vehicle(kube: Kube, vehicle: VehicleView, mission: MissionRef) -> VehicleView | None:
    """Claim ``vehicle`` for ``mission`` unless someone else holds it; the claimed view.

    The first attempt may take over an orphaned claim (decided by the caller from the
    same read); retries after a 409 only claim a vehicle that is unclaimed and claimable.
    """
    claim = mission.reference
    current = vehicle
    for _ in range(CLAIM_RETRIES):
        try:
            return _patch_claim(kube, current, claim)
        except ConflictError:
            fresh = kube.get(VEHICLES, vehicle.name)
            if fresh is None:
                return None
            current = VehicleView.from_body(fresh)
            if mission.owns(current.status.claimed_by):
                return current
            if current.status.claimed_by is not None or not is_claimable(current):
                return None
    return None


def release_vehicle(kube: Kube, name: str, mission: MissionRef) -> bool:
    """Clear ``claimedBy`` on ``name`` if ``mission`` holds it; True when released."""
    for _ in range(RELEASE_RETRIES):
        fresh = kube.get(VEHICLES, name)
        if fresh is None:
            return False
        vehicle = VehicleView.from_body(fresh)
        if not mission.owns(vehicle.status.claimed_by):
            return False
        try:
            _patch_claim(kube, vehicle, None)
        except ConflictError:
            continue
        kube.post_event(
            vehicle_body(vehicle),
            reason="Released",
            message=f"released by mission {mission.key}",
            at=_timestamp(datetime.now(UTC)),
        )
        return True
    raise ConflictError(409, "PATCH", f"vehicles/{name}/status", "release kept conflicting")


def _claim_all(kube: Kube, obs: Observation, names: list[str]) -> Observation | None:
    """Claim every vehicle in ``names`` or none; the observation with the claims."""
    claimed: dict[str, VehicleView] = {}
    for name in names:
        view = claim_vehicle(kube, obs.vehicles[name], obs.mission)
        if view is None:
            log.info("mission %s lost the race for vehicle %s", obs.mission.key, name)
            for taken in claimed:
                release_vehicle(kube, taken, obs.mission)
            return None
        claimed[name] = view
    _each(
        lambda view: kube.post_event(
            vehicle_body(view),
            reason="Claimed",
            message=f"claimed by mission {obs.mission.key}",
            at=_timestamp(obs.now),
        ),
        list(claimed.values()),
    )
    return replace(obs, vehicles={**obs.vehicles, **claimed})


# -- carrying out a plan -------------------------------------------------------------


@dataclass(frozen=True)
class Outcome:
    """What a reconcile did and when to look again."""

    plan: Plan
    requeue_after: float | None
    finished: bool
    assigned: tuple[str, ...]
    waiting_for_vehicles: bool


def _write_status(kube: Kube, obs: Observation, status: MissionStatus) -> None:
    if status.to_api() == obs.status.to_api():
        return
    kube.merge_patch(
        MISSIONS,
        obs.mission.name,
        {"status": status.to_api()},
        namespace=obs.mission.namespace,
        subresource="status",
    )


def _config_maps_to_apply(
    kube: Kube, obs: Observation, config_maps: list[Obj], operator_namespace: str
) -> list[Obj]:
    """The ConfigMap copies that are missing or differ (one list request)."""
    if not config_maps or obs.mission.namespace == operator_namespace:
        # In the operator's namespace the authoritative ConfigMap is already there.
        return []
    existing = {
        cm["metadata"]["name"]: cm
        for cm in kube.list_objects(
            CONFIGMAPS,
            namespace=obs.mission.namespace,
            labels={LABEL_MANAGED_BY: MANAGED_BY, LABEL_COMPONENT: CONFIG_COMPONENT},
        )
    }
    return [
        manifest
        for manifest in config_maps
        if needs_apply(with_applied_hash(manifest), existing.get(manifest["metadata"]["name"]))
    ]


class JobRejectedError(ApiError):
    """The API server refused a Job as invalid (422): retrying cannot help."""


def _create(kube: Kube, manifest: Obj) -> None:
    """Apply a ConfigMap copy or create a Job (an existing Job is left as it is)."""
    if manifest["kind"] != "Job":
        kube.apply(manifest)
        return
    try:
        kube.create(manifest)
    except ConflictError:
        log.debug("job %s already exists", manifest["metadata"]["name"])
    except ApiError as error:
        if error.status == UNPROCESSABLE:
            raise JobRejectedError(error.status, "POST", "jobs", error.body) from error
        raise


def _post(kube: Kube, obs: Observation, events: list[MissionEvent]) -> None:
    at = _timestamp(obs.now)

    def post(event: MissionEvent) -> None:
        kube.post_event(
            mission_body(obs.mission),
            reason=event.reason,
            message=event.message,
            type=event.type,
            at=at,
        )
        vehicle = obs.vehicles.get(event.vehicle or "")
        if vehicle is not None:
            kube.post_event(
                vehicle_body(vehicle),
                reason=event.reason,
                message=f"mission {obs.mission.key}: {event.message}",
                type=event.type,
                at=at,
            )

    _each(post, events)


def _write_commands(kube: Kube, obs: Observation, commands: Mapping[str, AutopilotCommand]) -> None:
    def write(item: tuple[str, AutopilotCommand]) -> None:
        vehicle_name, command = item
        autopilots = obs.autopilots[vehicle_name]
        kube.merge_patch(REDUNDANT_AUTOPILOTS, autopilots.name, command_patch(command))

    _each(write, list(commands.items()))


def carry_out(kube: Kube, obs: Observation, plan: Plan, operator_namespace: str) -> None:
    """Write what ``plan`` says, in the order the module docstring explains."""
    _write_status(kube, obs, plan.status)
    config_maps = _config_maps_to_apply(kube, obs, plan.config_maps, operator_namespace)
    try:
        # A pod waits for its ConfigMap to appear, so both go out together.
        _each(lambda manifest: _create(kube, manifest), [*config_maps, *plan.jobs_to_create])
    except JobRejectedError as error:
        rejected = fail_mission(obs, "JobRejected", f"the API server rejected a Job: {error.body}")
        carry_out(kube, obs, rejected, operator_namespace)
        return
    _write_commands(kube, obs, plan.commands)
    _each(lambda job_name: kube.delete(JOBS, job_name, obs.mission.namespace), plan.jobs_to_delete)
    _each(lambda vehicle_name: release_vehicle(kube, vehicle_name, obs.mission), plan.releases)
    _post(kube, obs, plan.events)


def reconcile_mission(
    kube: Kube, *, namespace: str, name: str, operator_namespace: str, guards: FleetGuards
) -> Outcome | None:
    """Observe, plan, claim (all or nothing), carry out. None when the Mission is gone."""
    obs = observe(
        kube, namespace=namespace, name=name, operator_namespace=operator_namespace, guards=guards
    )
    if obs is None:
        return None
    plan = plan_mission(obs)
    rounds = 0
    while plan.claims:
        rounds += 1
        claimed = _claim_all(kube, obs, plan.claims)
        if claimed is not None:
            obs = claimed
        elif rounds >= CLAIM_ROUNDS:
            return Outcome(plan, random.uniform(0.5, 2.0), False, (), True)
        else:
            fresh = observe(
                kube,
                namespace=namespace,
                name=name,
                operator_namespace=operator_namespace,
                guards=guards,
            )
            if fresh is None:
                return None
            obs = fresh
        plan = plan_mission(obs)
    carry_out(kube, obs, plan, operator_namespace)
    status = plan.status
    phase_finished = MissionPhase(status.phase).finished
    return Outcome(
        plan=plan,
        requeue_after=plan.requeue_after,
        finished=phase_finished
        and not (plan.releases or plan.jobs_to_delete or plan.requeue_after is not None),
        assigned=tuple(v.name for v in status.vehicles),
        waiting_for_vehicles=status.start_time is None,
    )


def release_deleted_mission(
    kube: Kube, *, namespace: str, name: str, operator_namespace: str, guards: FleetGuards
) -> None:
    """The Mission is being deleted: abort what still flies for it, release its vehicles."""
    obs = observe(
        kube, namespace=namespace, name=name, operator_namespace=operator_namespace, guards=guards
    )
    if obs is None:
        return
    plan = plan_deletion(obs)
    _write_commands(kube, obs, plan.commands)
    _each(lambda vehicle_name: release_vehicle(kube, vehicle_name, obs.mission), plan.releases)
    _post(kube, obs, plan.events)
