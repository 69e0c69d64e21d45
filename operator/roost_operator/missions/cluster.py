"""A mission's reads and writes: build an Observation, carry out a Plan. No decisions.

Everything goes through :class:`~roost_kube.client.Kube`. The parts that need care:

* **Claims** are Leases in the operator's namespace (:mod:`roost_operator.claims`),
  written by this module only: created to claim, taken over from an orphan with the
  ``resourceVersion`` it was judged at, deleted with preconditions to release. Of two
  missions claiming one vehicle, the API server accepts exactly one write; the other
  gets 409 and has lost (nobody else writes claims). Claims are all-or-nothing: when
  one fails, the vehicles claimed in the same round are given back and the mission
  plans again from a fresh read.
* **Order**: Vehicles and claims are listed before Missions, so an orphaned claim is never
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
from functools import partial
from typing import Any, Final, TypeVar

from pydantic import ValidationError

from roost_api.autopilot import AssignedFence, AutopilotCommand
from roost_api.commands import command_patch
from roost_api.meta import API_VERSION
from roost_api.mission import (
    MissionPhase,
    MissionReason,
    MissionRecordsStatus,
    MissionSpec,
    MissionStatus,
    RecordsState,
    RecordsUploadStatus,
    UploadState,
)
from roost_api.resources import MISSION, VEHICLE
from roost_api.wellknown import (
    LABEL_COMPONENT,
    LABEL_MANAGED_BY,
    LABEL_MISSION,
    LABEL_VEHICLE,
    MANAGED_BY,
)
from roost_kube.client import Kube
from roost_kube.errors import ApiError, ConflictError, TemporaryApiError
from roost_kube.patches import Obj, needs_apply, with_applied_hash
from roost_kube.resources import CONFIGMAPS, JOBS, LEASES, MISSIONS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_operator import claims
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.claims import Claim
from roost_operator.missions.fence import fence_patch
from roost_operator.missions.fence import held_by as fence_held_by
from roost_operator.missions.machine import (
    MissionEvent,
    Observation,
    Plan,
    fail_mission,
    plan_deletion,
    plan_mission,
)
from roost_operator.missions.observed import AutopilotView, JobView, MissionRef, VehicleView
from roost_operator.missions.selection import holding_missions
from roost_operator.missions.workloads import bounded_name, template_probes
from roost_operator.records.gather import VehicleTarget, gather_round
from roost_operator.records.settings import RecordsSettings
from roost_operator.records.upload import upload_round
from roost_operator.vehicles.config import CONFIG_COMPONENT, config_map_name, config_values_of

log = logging.getLogger(__name__)

RELEASE_RETRIES: Final = 5
CLAIM_ROUNDS: Final = 3
"""Claim rounds per reconcile; after that the mission waits a jittered moment."""
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


def _parse_all(items: Iterable[Obj], parse: Callable[[Obj], T], what: str) -> list[T]:
    """Parse each object; one malformed object is logged and skipped, not fatal."""
    parsed = []
    for item in items:
        try:
            parsed.append(parse(item))
        except (ValidationError, KeyError) as error:
            name = item.get("metadata", {}).get("name")
            log.warning("%s %s: malformed, skipped: %s", what, name, error)
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
    vehicle_bodies = kube.list_objects(VEHICLES)
    held = claims.claims_by_vehicle(
        kube.list_objects(LEASES, namespace=operator_namespace, labels=claims.CLAIM_LABELS)
    )
    vehicles = _parse_all(
        vehicle_bodies,
        lambda body: VehicleView.from_body(body, held.get(body["metadata"]["name"])),
        "Vehicle",
    )
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
        deleting=bool(meta.get("deletionTimestamp")),
    )


# -- claims ---------------------------------------------------------------------------


def _claim_view(kube: Kube, namespace: str, vehicle: str) -> Claim | None:
    return claims.claim_of(kube.get(LEASES, claims.lease_name(vehicle), namespace) or {})


def claim_vehicle(
    kube: Kube, namespace: str, vehicle: VehicleView, mission: MissionRef, *, at: datetime
) -> VehicleView | None:
    """Claim ``vehicle`` for ``mission`` in the operator's ``namespace``; the claimed view.

    ``vehicle.claim`` is the claim as the caller read it: None means "create the claim",
    an orphan's claim means "take it over at the version read". A 409 means another
    mission was faster, unless the fresh claim turns out to be this mission's own.
    """
    try:
        if vehicle.claim is None:
            manifest = claims.claim_lease(
                vehicle=vehicle.name,
                vehicle_uid=vehicle.uid,
                holder=mission.reference,
                mission_uid=mission.uid,
                namespace=namespace,
                at=at,
            )
            lease = kube.create(manifest)
        else:
            lease = kube.merge_patch(
                LEASES,
                claims.lease_name(vehicle.name),
                claims.takeover_patch(vehicle.claim, mission.reference, mission.uid, at),
                namespace=namespace,
            )
    except ConflictError:
        fresh = _claim_view(kube, namespace, vehicle.name)
        if fresh is not None and mission.owns(fresh.holder):
            return replace(vehicle, claim=fresh)
        return None
    return replace(vehicle, claim=claims.claim_of(lease))


def release_vehicle(kube: Kube, namespace: str, name: str, mission: MissionRef) -> bool:
    """Delete the claim on vehicle ``name`` if ``mission`` holds it; True when released."""
    for _ in range(RELEASE_RETRIES):
        claim = _claim_view(kube, namespace, name)
        if claim is None or not mission.owns(claim.holder):
            return False
        path = LEASES.object_path(claims.lease_name(name), namespace)
        try:
            kube.request("DELETE", path, body=claims.release_options(claim))
        except ConflictError:
            continue
        vehicle = kube.get(VEHICLES, name)
        if vehicle is not None:
            kube.post_event(
                vehicle,
                reason="Released",
                message=f"released by mission {mission.key}",
                at=datetime.now(UTC),
            )
        return True
    raise ConflictError(409, "DELETE", f"leases/{name}", "release kept conflicting")


def _claim_all(
    kube: Kube, namespace: str, obs: Observation, names: list[str]
) -> Observation | None:
    """Claim every vehicle in ``names`` or none; the observation with the claims."""
    claimed: dict[str, VehicleView] = {}
    for name in names:
        view = claim_vehicle(kube, namespace, obs.vehicles[name], obs.mission, at=obs.now)
        if view is None:
            log.info("Mission %s: lost the race for Vehicle %s", obs.mission.key, name)
            for taken in claimed:
                release_vehicle(kube, namespace, taken, obs.mission)
            return None
        claimed[name] = view
    _each(
        lambda view: kube.post_event(
            vehicle_body(view),
            reason="Claimed",
            message=f"claimed by mission {obs.mission.key}",
            at=obs.now,
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


def _delete_config_copies(
    kube: Kube, obs: Observation, vehicles: Sequence[str], operator_namespace: str
) -> None:
    """Delete this mission's config copies of ``vehicles`` (one list request first).

    Only copies whose sole owner is this Mission: a copy another Mission in the same
    namespace has applied since (it owns it now) stays for that Mission's pods.
    """
    if not vehicles or obs.mission.namespace == operator_namespace:
        return
    wanted = {config_map_name(name) for name in vehicles}
    copies = kube.list_objects(
        CONFIGMAPS,
        namespace=obs.mission.namespace,
        labels={LABEL_MANAGED_BY: MANAGED_BY, LABEL_COMPONENT: CONFIG_COMPONENT},
    )
    ours = [
        cm
        for cm in copies
        if cm["metadata"]["name"] in wanted
        and [ref.get("uid") for ref in cm["metadata"].get("ownerReferences") or []]
        == [obs.mission.uid]
    ]
    _each(lambda cm: kube.delete(CONFIGMAPS, cm["metadata"]["name"], obs.mission.namespace), ours)


class JobRejectedError(ApiError):
    """The API server refused a Job (400, 422, …): retrying the same Job cannot help."""


DRY_RUN: Final = {"dryRun": "All"}


def check_templates(kube: Kube, obs: Observation, vehicles: Sequence[str]) -> Plan | None:
    """Dry-run the mission's Jobs; the plan that fails the mission if one is refused.

    Runs before any claim, so a template the Job API would refuse never holds a
    vehicle. The message is the API server's own words (its Status ``message``), not
    its JSON. Temporary errors are raised (the reconcile is retried).
    """
    probes = template_probes(
        mission=obs.mission, spec=obs.spec, vehicles=vehicles, config_values=obs.config_values
    )
    for field_path, manifest in probes:
        try:
            kube.request(
                "POST",
                JOBS.collection_path(obs.mission.namespace),
                query={**DRY_RUN, "fieldManager": kube.field_manager},
                body=manifest,
            )
        except ConflictError:
            continue  # a Job of that name exists: the template was accepted before
        except ApiError as error:
            if isinstance(error, TemporaryApiError):
                raise
            log.warning(
                "Mission %s: %s refused by the Job API: %s",
                obs.mission.key,
                field_path,
                error.message,
            )
            return fail_mission(
                obs,
                MissionReason.INVALID_TEMPLATE,
                f"{field_path} is refused by the Job API: {error.message}",
            )
    return None


def _create(kube: Kube, manifest: Obj) -> None:
    """Apply a ConfigMap copy or create a Job (an existing Job is left as it is)."""
    if manifest["kind"] != "Job":
        kube.apply(manifest)
        return
    try:
        kube.create(manifest)
    except ConflictError:
        meta = manifest["metadata"]
        log.debug("Job %s/%s: already exists", meta.get("namespace"), meta["name"])
    except ApiError as error:
        if not isinstance(error, TemporaryApiError):
            raise JobRejectedError(error.status, "POST", "jobs", error.body) from error
        raise


def _post(kube: Kube, obs: Observation, events: list[MissionEvent]) -> None:
    at = obs.now

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


def _write_fences(kube: Kube, obs: Observation, plan: Plan) -> None:
    """Write the Mission's fence into its vehicles' RedundantAutopilots, and remove it
    from the ones it releases (roost_operator.missions.fence)."""
    writes: list[tuple[str, AssignedFence | None]] = list(plan.fences.items())
    writes += [
        (name, None)
        for name in plan.releases
        if name not in plan.fences and fence_held_by(obs.mission, obs.autopilots.get(name))
    ]

    def write(item: tuple[str, AssignedFence | None]) -> None:
        vehicle_name, fence = item
        kube.merge_patch(
            REDUNDANT_AUTOPILOTS, obs.autopilots[vehicle_name].name, fence_patch(fence)
        )

    _each(write, writes)


def carry_out(kube: Kube, obs: Observation, plan: Plan, operator_namespace: str) -> None:
    """Write what ``plan`` says, in the order the module docstring explains."""
    _write_status(kube, obs, plan.status)
    config_maps = _config_maps_to_apply(kube, obs, plan.config_maps, operator_namespace)
    try:
        # A pod waits for its ConfigMap to appear, so both go out together.
        _each(lambda manifest: _create(kube, manifest), [*config_maps, *plan.jobs_to_create])
    except JobRejectedError as error:
        rejected = fail_mission(
            obs, MissionReason.JOB_REJECTED, f"the API server rejected a Job: {error.message}"
        )
        carry_out(kube, obs, rejected, operator_namespace)
        return
    _write_commands(kube, obs, plan.commands)
    _write_fences(kube, obs, plan)
    _each(lambda job_name: kube.delete(JOBS, job_name, obs.mission.namespace), plan.jobs_to_delete)
    _delete_config_copies(kube, obs, plan.config_maps_to_delete, operator_namespace)
    _each(
        lambda vehicle_name: release_vehicle(kube, operator_namespace, vehicle_name, obs.mission),
        plan.releases,
    )
    _post(kube, obs, plan.events)


def reconcile_mission(
    kube: Kube,
    *,
    namespace: str,
    name: str,
    operator_namespace: str,
    guards: FleetGuards,
    records: RecordsSettings | None = None,
) -> Outcome | None:
    """Observe, plan, claim (all or nothing), carry out. None when the Mission is gone
    or being deleted (its deletion handler acts then).

    ``records``: gather the flight records of a mission that flew once it has ended
    (a round per reconcile while ``status.records`` says Gathering; its result goes
    out with the mission's one status write)."""
    obs = observe(
        kube, namespace=namespace, name=name, operator_namespace=operator_namespace, guards=guards
    )
    if obs is None or obs.deleting:
        return None
    gathering = records is not None and records.directory is not None
    obs = replace(obs, records=gathering)
    plan = plan_mission(obs)
    if records is not None and _gathering(obs):
        plan.status.records = gather_round(
            kube,
            replace(records, agent_namespace=records.agent_namespace or operator_namespace),
            namespace=namespace,
            name=name,
            uid=obs.mission.uid,
            status=obs.status,
            vehicles=[_target(obs, v.name) for v in obs.status.vehicles],
            now=obs.now,
        )
        if not RecordsState(plan.status.records.state).final:
            plan.requeue_after = min(
                plan.requeue_after or records.retry_seconds, records.retry_seconds
            )
    if records is not None and records.bucket is not None and _uploading(obs, plan.status):
        assert plan.status.records is not None
        plan.status.records = upload_round(plan.status.records, records, obs.now)
        wait = _upload_wait(plan.status.records.upload, obs.now)
        if wait is not None:
            plan.requeue_after = min(plan.requeue_after or wait, wait)
    if plan.claims:
        refused = check_templates(kube, obs, plan.claims)
        if refused is not None:
            carry_out(kube, obs, refused, operator_namespace)
            return Outcome(refused, None, True, (), False)
    rounds = 0
    while plan.claims:
        rounds += 1
        claimed = _claim_all(kube, operator_namespace, obs, plan.claims)
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
        and (status.records is None or _records_final(status.records))
        and not (plan.releases or plan.jobs_to_delete or plan.requeue_after is not None),
        assigned=tuple(v.name for v in status.vehicles),
        waiting_for_vehicles=status.start_time is None,
    )


def _gathering(obs: Observation) -> bool:
    """The mission has ended (as observed) and its record is still being gathered."""
    return (
        obs.records
        and MissionPhase(obs.status.phase).finished
        and obs.status.records is not None
        and not RecordsState(obs.status.records.state).final
        and obs.status.start_time is not None
    )


def _uploading(obs: Observation, status: MissionStatus) -> bool:
    """The mission's bundle is final and its copy in the bucket is not (or not begun)."""
    records = status.records
    return (
        obs.records
        and MissionPhase(status.phase).finished
        and records is not None
        and RecordsState(records.state).final
        and (records.upload is None or not UploadState(records.upload.state).final)
    )


def _upload_wait(upload: RecordsUploadStatus | None, now: datetime) -> float | None:
    """Seconds until the next upload round (None: nothing more to do)."""
    if upload is None or UploadState(upload.state).final:
        return None
    if upload.next_attempt_time is None:
        return 0.1
    return max((upload.next_attempt_time - now).total_seconds(), 0.1)


def _records_final(records: MissionRecordsStatus) -> bool:
    """Gathering is over and so is the upload, if there is one."""
    return RecordsState(records.state).final and (
        records.upload is None or UploadState(records.upload.state).final
    )


def _target(obs: Observation, vehicle: str) -> VehicleTarget:
    view = obs.vehicles.get(vehicle)
    if view is None:
        return VehicleTarget(vehicle)
    return VehicleTarget(vehicle, view.node_name, view.annotations)


def release_deleted_mission(
    kube: Kube, *, namespace: str, name: str, operator_namespace: str, guards: FleetGuards
) -> list[str]:
    """The Mission is being deleted: abort what still flies for it, release its vehicles.

    Every step is tried even when another fails. Temporary errors are raised (the
    deletion is retried); permanent ones are returned as what was left, so the
    Mission's finalizer is released anyway.
    """
    obs = observe(
        kube, namespace=namespace, name=name, operator_namespace=operator_namespace, guards=guards
    )
    if obs is None:
        return []
    plan = plan_deletion(obs)
    left: list[str] = []

    def attempt(what: str, step: Callable[[], object]) -> None:
        try:
            step()
        except ApiError as error:
            if isinstance(error, TemporaryApiError):
                raise
            left.append(f"{what}: {error.message}")

    for vehicle_name, command in plan.commands.items():
        attempt(
            f"abort command to {vehicle_name}",
            partial(_write_commands, kube, obs, {vehicle_name: command}),
        )
    attempt("fences", partial(_write_fences, kube, obs, plan))
    for vehicle_name in plan.releases:
        attempt(
            f"claim on {vehicle_name}",
            partial(release_vehicle, kube, operator_namespace, vehicle_name, obs.mission),
        )
    attempt("Events", lambda: _post(kube, obs, plan.events))
    return left
