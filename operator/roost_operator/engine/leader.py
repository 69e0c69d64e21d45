"""Leader election on a ``coordination.k8s.io`` Lease: one operator replica acts, the
others stand by and take over when it dies.

Why a Lease and not kopf's peering: peering makes a lower-priority operator *pause* while
a higher-priority one is alive, and lets two of the same priority run together with a
warning; it has no notion of "exactly one acts" and no takeover deadline. A Lease is
what Kubernetes' own controllers use: the holder renews it every :attr:`Timings.renew_s`;
another replica takes it once it has seen no renewal for :attr:`Timings.lease_s` on its
*own* clock (it never compares its clock with the holder's), and every write carries the
``resourceVersion`` it read, so two replicas racing for an expired Lease cannot both win.

Standing by happens before kopf starts (:func:`~roost_operator.main.main`): a standby
watches nothing, runs no handler and writes only to its Lease attempt, so a takeover
cannot repeat what the old leader did beyond what any restart repeats (deterministic
names make that a no-op). A leader that cannot renew for :attr:`Timings.renew_deadline_s`
(shorter than the lease) stops the process before anyone else may take over: it never
acts without holding the Lease.

:func:`decide` is the whole decision, pure; :class:`LeaderElector` reads, writes and keeps
the time.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any, Final

from roost_kube.client import Kube
from roost_kube.errors import ApiError, ConflictError
from roost_kube.patches import Obj
from roost_kube.resources import LEASES
from roost_operator.claims import micro_time

log = logging.getLogger(__name__)

LEASE_NAME: Final = "roost-operator-leader"


@dataclass(frozen=True)
class Timings:
    """Lease timings; takeover after a leader's death takes at most
    ``lease_s + retry_s`` (plus one request)."""

    lease_s: float = 8.0
    renew_s: float = 2.0
    renew_deadline_s: float = 6.0
    """A leader that could not renew for this long stops (before ``lease_s`` runs out)."""
    retry_s: float = 1.0
    """How often a standby looks at the Lease."""


class Step(StrEnum):
    """What a replica does about the Lease now."""

    CREATE = "create"
    """No Lease: create it, holding it."""
    TAKE = "take"
    """Free, expired or already ours: write ourselves in (with its resourceVersion)."""
    WAIT = "wait"
    """Another replica holds it and renewed within the lease: stand by."""


@dataclass(frozen=True)
class Seen:
    """The Lease's record as last seen, and when (the observer's monotonic clock)."""

    record: tuple[str, str]
    """(holderIdentity, renewTime): a change of either is a sign of life."""
    at: float


def record_of(lease: Mapping[str, Any]) -> tuple[str, str]:
    spec = lease.get("spec") or {}
    return str(spec.get("holderIdentity") or ""), str(spec.get("renewTime") or "")


def decide(
    lease: Mapping[str, Any] | None, me: str, seen: Seen | None, now: float, lease_s: float
) -> tuple[Step, Seen | None]:
    """The step for replica ``me`` given the Lease as read (None: none) and what it saw
    before; the new :class:`Seen` to keep."""
    if lease is None:
        return Step.CREATE, None
    record = record_of(lease)
    holder = record[0]
    if seen is None or seen.record != record:
        seen = Seen(record, now)
    if not holder or holder == me:
        return Step.TAKE, seen
    if now - seen.at >= lease_s:
        return Step.TAKE, seen
    return Step.WAIT, seen


class LeaderElector:
    """Acquire the Lease (:meth:`acquire`), then keep it from a thread (:meth:`keep`)."""

    def __init__(
        self,
        kube: Kube,
        namespace: str,
        identity: str,
        *,
        timings: Timings = Timings(),
        on_lost: Callable[[], None],
        name: str = LEASE_NAME,
    ) -> None:
        self.kube = kube
        self.namespace = namespace
        self.identity = identity
        self.timings = timings
        self.on_lost = on_lost
        self.name = name
        self._seen: Seen | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _manifest(self, lease: Mapping[str, Any] | None) -> Obj:
        now = micro_time(datetime.now(UTC))
        spec: Obj = dict((lease or {}).get("spec") or {})
        taking = spec.get("holderIdentity") != self.identity
        spec.update(
            {
                "holderIdentity": self.identity,
                "leaseDurationSeconds": max(1, round(self.timings.lease_s)),
                "renewTime": now,
            }
        )
        if taking:
            spec["acquireTime"] = now
            spec["leaseTransitions"] = int(spec.get("leaseTransitions") or 0) + (
                1 if lease is not None else 0
            )
        meta: Obj = {"name": self.name, "namespace": self.namespace}
        if lease is not None:
            meta["resourceVersion"] = lease["metadata"]["resourceVersion"]
        return {
            "apiVersion": LEASES.api_version,
            "kind": LEASES.kind,
            "metadata": meta,
            "spec": spec,
        }

    def try_once(self) -> bool:
        """One look at the Lease and, if the decision says so, one write; whether this
        replica holds it now."""
        lease = self.kube.get(LEASES, self.name, self.namespace)
        step, self._seen = decide(
            lease, self.identity, self._seen, time.monotonic(), self.timings.lease_s
        )
        if step is Step.WAIT:
            return False
        try:
            if step is Step.CREATE:
                self.kube.create(self._manifest(None))
            else:
                assert lease is not None
                patch = self._manifest(lease)
                self.kube.merge_patch(
                    LEASES,
                    self.name,
                    {"metadata": patch["metadata"], "spec": patch["spec"]},
                    namespace=self.namespace,
                )
        except ConflictError:
            return False  # another replica wrote first: look again
        return True

    def acquire(self) -> None:
        """Block until this replica holds the Lease or :meth:`cancel` is called."""
        announced = False
        while not self._stop.is_set():
            try:
                if self.try_once():
                    log.info("leader: %s holds Lease %s", self.identity, self.name)
                    return
            except ApiError as error:
                log.warning("leader election: %s", error)
            if not announced:
                holder = self._seen.record[0] if self._seen else "?"
                log.info("leader election: standing by (%s leads)", holder)
                announced = True
            self._stop.wait(self.timings.retry_s)

    def cancel(self) -> None:
        """Stop standing by (safe in a signal handler: it only sets an event); whoever
        called :meth:`acquire` checks :attr:`cancelled` before acting."""
        self._stop.set()

    @property
    def cancelled(self) -> bool:
        return self._stop.is_set()

    def keep(self) -> None:
        """Renew the Lease from a daemon thread until :meth:`stop`; call ``on_lost`` when
        it cannot be renewed within the deadline or another replica took it."""

        def renew() -> None:
            last = time.monotonic()
            while not self._stop.wait(self.timings.renew_s):
                try:
                    if self.try_once():
                        last = time.monotonic()
                        continue
                    log.error("leader: Lease %s taken by another replica", self.name)
                except ApiError as error:
                    log.warning("leader: renewing Lease %s: %s", self.name, error)
                    if time.monotonic() - last < self.timings.renew_deadline_s:
                        continue
                    log.error("leader: no renewal for %.0f s", self.timings.renew_deadline_s)
                if not self._stop.is_set():
                    self.on_lost()
                return

        self._thread = threading.Thread(target=renew, name="leader-lease", daemon=True)
        self._thread.start()

    def stop(self, *, release: bool = True) -> None:
        """Stop renewing; ``release``: hand the Lease over at once (a clean shutdown)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.timings.renew_s + 5)
        if not release:
            return
        try:
            lease = self.kube.get(LEASES, self.name, self.namespace)
            if lease is not None and record_of(lease)[0] == self.identity:
                self.kube.merge_patch(
                    LEASES,
                    self.name,
                    {
                        "metadata": {"resourceVersion": lease["metadata"]["resourceVersion"]},
                        "spec": {"holderIdentity": None, "renewTime": None},
                    },
                    namespace=self.namespace,
                )
        except ApiError as error:  # the standby takes over when the lease runs out
            log.warning("leader: releasing Lease %s: %s", self.name, error)
