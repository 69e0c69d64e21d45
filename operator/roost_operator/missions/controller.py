"""The Mission controller's side of the engine: one queued Mission key, one reconcile.

The engine's work queue (:mod:`roost_operator.engine.workqueue`, built in
:class:`~roost_operator.runtime.Runtime`) runs :meth:`MissionController.reconcile` for a
key ``namespace/name`` that kopf's handlers or the claim watch queued
(:mod:`~roost_operator.missions.handlers`): observe → pure plan → claims and writes → one
status write (:func:`~roost_operator.missions.cluster.reconcile_mission`). What it
returns is when to look again without an event (:func:`~.interest.next_look`); the queue
keeps that as the key's deadline.

Errors leave the reconcile as they are: the queue retries temporary ones with its
backoff (:class:`~roost_operator.settings.MissionTimings`) and hands a permanent one
(:func:`~roost_operator.engine.errors.is_permanent`) to :meth:`report_permanent` once,
not retrying it until an event about the Mission queues it again.

Deletion stays with kopf, behind Roost's finalizer (:func:`release_deleted_mission` via
:meth:`delete`): it takes the Mission's lock, so it waits for a reconcile that is
running, and a reconcile that starts after the deletion mark does nothing
(:attr:`~roost_operator.missions.machine.Observation.deleting`). The queue runs one
reconcile of a Mission at a time by itself; the lock is for the deletion handler only.

Only the leader runs any of this: a standby replica has not started kopf or the queue
(:mod:`roost_operator.engine.leader`). A new leader's first listing of Missions queues
each one, so it continues every Mission from what the cluster shows (deterministic Job
names, claim Leases and command ids make a repeated step a no-op).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from roost_api.meta import now
from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.resources import MISSIONS
from roost_operator.missions.cluster import Outcome, reconcile_mission, release_deleted_mission
from roost_operator.missions.interest import Interest, next_look
from roost_operator.settings import Settings

log = logging.getLogger(__name__)
T = TypeVar("T")


def mission_key(namespace: str, name: str) -> str:
    return f"{namespace}/{name}"


def split_key(key: str) -> tuple[str, str]:
    namespace, _, name = key.partition("/")
    return namespace, name


@dataclass
class MissionController:
    """Reconciles and deletes Missions for the queue and kopf (see the module docstring)."""

    kube: Kube
    settings: Settings
    interest: Interest = field(default_factory=Interest)
    _locks: dict[str, threading.Lock] = field(default_factory=dict)
    _reported: dict[str, str] = field(default_factory=dict)
    _guard: threading.Lock = field(default_factory=threading.Lock)

    def _lock(self, key: str) -> threading.Lock:
        with self._guard:
            return self._locks.setdefault(key, threading.Lock())

    def _under_lock(self, key: str, step: Callable[..., T], **more: Any) -> T:
        """Run ``step`` (reconcile or delete) on Mission ``key`` holding its lock."""
        namespace, name = split_key(key)
        with self._lock(key):
            return step(
                self.kube,
                namespace=namespace,
                name=name,
                operator_namespace=self.settings.namespace,
                guards=self.settings.guards,
                **more,
            )

    def reconcile(self, key: str) -> float | None:
        """One reconcile of Mission ``key``; seconds until the next without an event
        (None: only on an event)."""
        outcome: Outcome | None = self._under_lock(
            key, reconcile_mission, records=self.settings.records
        )
        self._reported.pop(key, None)
        if outcome is None or outcome.finished:
            self.interest.forget(key)
            return None
        self.interest.track(key, vehicles=outcome.assigned, waiting=outcome.waiting_for_vehicles)
        return next_look(
            finished=outcome.finished,
            requeue_after=outcome.requeue_after,
            resync_s=self.settings.missions.resync_seconds,
        )

    def delete(self, namespace: str, name: str) -> list[str]:
        """Abort what still flies for the Mission and release its vehicles, after any
        reconcile of it that is running; what could not be done (see
        :func:`release_deleted_mission`)."""
        key = mission_key(namespace, name)
        left: list[str] = self._under_lock(key, release_deleted_mission)
        self.interest.forget(key)
        return left

    def forget(self, key: str) -> None:
        """The Mission is gone."""
        self.interest.forget(key)
        self._reported.pop(key, None)
        with self._guard:
            self._locks.pop(key, None)

    def report_permanent(self, key: str, error: BaseException) -> None:
        """A reconcile the API server refused for good: one log line and one Warning
        Event per distinct refusal (a human may fix what it names: a quota, a policy)."""
        if self._reported.get(key) == str(error):
            return
        self._reported[key] = str(error)
        log.error("Mission %s: not reconciled until it changes: %s", key, error)
        namespace, name = split_key(key)
        try:
            body = self.kube.get(MISSIONS, name, namespace)
            if body is not None:
                message = getattr(error, "message", str(error))
                self.kube.post_event(
                    body,
                    reason="WriteRefused",
                    message=f"the API server refused a write for this mission: {message}",
                    type="Warning",
                    at=now(),
                )
        except ApiError as failed:
            log.warning("Mission %s: could not post the Event: %s", key, failed)
