"""Kill the leading operator in the middle of a fleet rollout and a Mission start, and see
what the standby does: how long it takes the Lease, and whether anything was done twice.

Two ``roost-operator --leader-election`` processes watch the same cluster; the first
leads. A fleet of Vehicles is applied; once a tenth of its pods exist, a Mission for two
other vehicles (Ready, stand-in agents report for them) with a geofence is created, and
at its first claim the leader is killed (SIGKILL).
The standby takes the Lease and finishes the rollout and the Mission's
start. Watches record every action of either leader, and any action done twice is a
double action:

* objects made (component Pods, claim Leases, the Mission's Jobs), by name and uid: an
  object made twice (a second uid), or deleted though it should stay;
* status transitions: each Vehicle's ``Ready`` condition and the Mission's phase, in the
  order written; a state entered twice (``Ready`` True written again with a new
  ``lastTransitionTime``, the Mission back in a phase it had left), and the Mission's
  transition Events (named by their time, so a transition made again posts a second
  one with the same reason and message);
* commands sent: the fence written into each crew vehicle's RedundantAutopilot
  (``spec.fence``, the command its agent uploads to the autopilots): each spec change
  bumps the RedundantAutopilot's generation, which must move exactly once.

Used by ``tests/integration/test_operator_leader_takeover.py`` (the verdicts) and ``python
-m bench leader`` (the figures).
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Callable, Hashable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roost_api.wellknown import LABEL_MANAGED_BY, MANAGED_BY
from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.resources import (
    EVENTS,
    JOBS,
    LEASES,
    MISSIONS,
    PODS,
    REDUNDANT_AUTOPILOTS,
    VEHICLES,
    Resource,
)
from roost_localcluster import nodes
from roost_localcluster.cluster import Cluster
from roost_operator.engine.leader import LEASE_NAME
from tests.support.fakeagents import FakeAgents, redundant_autopilot
from tests.support.operator import OperatorProcess
from tests.support.waiting import unique, wait_until

NAMESPACE = "roost-it-leader"
FLIGHTS = "roost-it-leader-flights"
HOLD_GATE = "roost.dev/test-hold"
WAIT_S = 300.0


@dataclass(frozen=True)
class Moment:
    """How far the rollout and the Mission's start had come when the leader died."""

    pods: int
    claims: int
    jobs: int
    phase: str

    def __str__(self) -> str:
        return (
            f"{self.pods} pods, {self.claims} claims, {self.jobs} Jobs, "
            f"Mission {self.phase or 'new'}"
        )


@dataclass(frozen=True)
class Takeover:
    """What one kill showed."""

    takeover_s: float
    """From the SIGKILL to the standby holding the Lease."""
    doubles: list[str]
    """Objects made twice (or removed though they should stay)."""
    pods: int
    claims: int
    jobs: int
    at_kill: Moment
    fences: int = 0
    """Fence writes into the crew's RedundantAutopilots."""
    standby_acted: tuple[str, ...] = ()
    """What the standby logged, other than its Lease attempts, before it led."""


State = Callable[[dict[str, Any]], tuple[Hashable, Hashable] | None]
"""An object's state and when it was entered (None: no state yet)."""


class Births:
    """Every object of a kind seen by a watch, by name: its uids and deletions, and the
    states ``state`` reads from it, in order (repeats of the last one dropped)."""

    def __init__(
        self,
        kube: Kube,
        resource: Resource,
        namespace: str | None,
        selector: str = "",
        state: State | None = None,
    ) -> None:
        self.kube, self.resource, self.namespace, self.selector = (
            kube,
            resource,
            namespace,
            selector,
        )
        self.state = state
        self.uids: dict[str, set[str]] = defaultdict(set)
        self.deleted: dict[str, int] = defaultdict(int)
        self.states: dict[str, list[tuple[Hashable, Hashable]]] = defaultdict(list)
        self.events: dict[str, dict[str, Any]] = {}
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="births")

    def _see(self, kind: str, obj: dict[str, Any]) -> None:
        meta = obj.get("metadata") or {}
        if "name" not in meta or kind == "BOOKMARK":
            return
        with self.lock:
            self.uids[meta["name"]].add(meta.get("uid", ""))
            if kind == "DELETED":
                self.deleted[meta["name"]] += 1
                return
            if self.resource is EVENTS:
                self.events[meta["name"]] = obj
            entered = self.state(obj) if self.state else None
            history = self.states[meta["name"]]
            if entered is not None and (not history or history[-1] != entered):
                history.append(entered)

    def _run(self) -> None:
        while not self.stopping.is_set():
            try:
                items, version = self.kube.list_with_version(
                    self.resource, namespace=self.namespace, label_selector=self.selector
                )
                for item in items:
                    self._see("ADDED", item)
                for kind, obj in self.kube.watch_collection(
                    self.resource,
                    resource_version=version,
                    namespace=self.namespace,
                    label_selector=self.selector,
                    timeout_s=20,
                ):
                    self._see(kind, obj)
                    if self.stopping.is_set():
                        return
            except ApiError:
                time.sleep(0.5)  # a gone resourceVersion or a dropped watch: list again

    def count(self) -> int:
        with self.lock:
            return sum(1 for name in self.uids if not self.deleted.get(name))

    def doubles(self, keep: set[str]) -> list[str]:
        """Objects made more than once, and objects of ``keep`` deleted."""
        kind = self.resource.kind
        with self.lock:
            made = [f"{kind} {n} made {len(u)} times" for n, u in self.uids.items() if len(u) > 1]
            gone = [f"{kind} {n} deleted" for n in keep if self.deleted.get(n)]
        return made + gone

    def entered_twice(self, names: Iterable[str] | None = None) -> list[str]:
        """Objects that entered one state twice (at two different times)."""
        kind = self.resource.kind
        found = []
        with self.lock:
            for name in self.states if names is None else names:
                entered = [state for state, _ in self.states.get(name, [])]
                again = sorted({str(s) for s in entered if entered.count(s) > 1})
                if again:
                    found.append(f"{kind} {name} entered {', '.join(again)} twice")
        return found

    def changes(self, name: str) -> int:
        """How often the state of ``name`` changed after it was first seen."""
        with self.lock:
            return max(0, len(self.states.get(name, [])) - 1)

    def events_twice(self) -> list[str]:
        """Events (of an Events watch) posted twice for one reason and message."""
        seen: dict[tuple[str, str, str], int] = defaultdict(int)
        with self.lock:
            for event in self.events.values():
                about = event.get("involvedObject") or {}
                seen[
                    (str(about.get("name")), event.get("reason", ""), event.get("message", ""))
                ] += 1
        return [
            f"Event {r} ({m}) on {n} posted {c} times" for (n, r, m), c in seen.items() if c > 1
        ]

    def __enter__(self) -> Births:
        self.thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stopping.set()


def ready_condition(vehicle: dict[str, Any]) -> tuple[Hashable, Hashable] | None:
    for condition in (vehicle.get("status") or {}).get("conditions") or []:
        if condition.get("type") == "Ready":
            return condition.get("status"), condition.get("lastTransitionTime")
    return None


def mission_phase(body: dict[str, Any]) -> tuple[Hashable, Hashable] | None:
    found = (body.get("status") or {}).get("phase")
    return None if not found else (found, found)


def generation(body: dict[str, Any]) -> tuple[Hashable, Hashable] | None:
    found = (body.get("metadata") or {}).get("generation")
    return None if found is None else (found, found)


FENCE = {"circle": {"latitude": 47.3977, "longitude": 8.5456, "radiusM": 80}, "maxAltitudeM": 30}


def claimed(leases: Births) -> int:
    """Claim Leases (every Lease in the namespace but the leader's)."""
    with leases.lock:
        return sum(1 for n in leases.uids if n != LEASE_NAME and not leases.deleted.get(n))


def leader(kube: Kube) -> str:
    lease = kube.get(LEASES, LEASE_NAME, NAMESPACE) or {}
    return str((lease.get("spec") or {}).get("holderIdentity") or "")


def before_leading(log: Path) -> tuple[str, ...]:
    """The lines a replica logged before it held the Lease, other than its election's:
    a standby that watched, queued or reconciled anything would log it (kopf's start,
    a handler, a controller)."""
    lines = []
    for line in log.read_text().splitlines():
        if "holds Lease" in line:
            break
        acting = " roost_operator." in line or " kopf." in line
        if acting and " roost_operator.engine.leader:" not in line:
            lines.append(line)
    return tuple(lines)


def replica(
    cluster: Cluster, log_dir: Path, identity: str, workers: int | None = None
) -> OperatorProcess:
    """A replica; ``workers``: its reconcile workers (None: the operator's default)."""
    return OperatorProcess(
        cluster,
        log_dir / f"operator-{identity}.log",
        namespace=NAMESPACE,
        args=["--leader-election", f"--identity={identity}"],
        environment={} if workers is None else {"ROOST_RECONCILE_WORKERS": str(workers)},
    )


def vehicle(name: str, node: str, sysid: int, **spec: Any) -> dict[str, Any]:
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": name},
        "spec": {"nodeName": node, "sysid": sysid, **spec},
    }


def mission(name: str, vehicles: list[str]) -> dict[str, Any]:
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": name, "namespace": FLIGHTS},
        "spec": {
            "vehicles": {"names": vehicles, "count": len(vehicles)},
            "fence": FENCE,
            "onboard": {
                "spec": {
                    "restartPolicy": "Never",
                    "schedulingGates": [{"name": HOLD_GATE}],  # the Job stays active
                    "containers": [{"name": "controller", "image": "example.org/controller:1"}],
                }
            },
        },
    }


def ready(kube: Kube, name: str) -> bool:
    conditions = ((kube.get(VEHICLES, name) or {}).get("status") or {}).get("conditions") or []
    return any(c["type"] == "Ready" and c["status"] == "True" for c in conditions)


def phase(kube: Kube, name: str) -> str:
    body = kube.get(MISSIONS, name, FLIGHTS) or {}
    return str((body.get("status") or {}).get("phase") or "")


def _gone(kube: Kube, names: list[str]) -> bool:
    """None of the Vehicles ``names`` exists any more."""
    return not {v["metadata"]["name"] for v in kube.list_objects(VEHICLES)} & set(names)


@contextmanager
def _nodes(cluster: Cluster, names: list[str]) -> Iterator[None]:
    with ThreadPoolExecutor(max_workers=4) as pool:
        list(pool.map(lambda n: cluster.admin.create(nodes.fake_node(n)), names))
    try:
        cluster.wait_nodes_ready(names, WAIT_S)
        yield
    finally:
        with ThreadPoolExecutor(max_workers=4) as pool:
            list(pool.map(cluster.delete_node, names))


def kill_the_leader(cluster: Cluster, log_dir: Path, fleet: int = 100) -> Takeover:
    """Run the scenario of the module docstring on ``cluster``."""
    kube = cluster.kube("roost-tests")
    cluster.kubectl("create", "namespace", NAMESPACE, check=False)
    cluster.kubectl("create", "namespace", FLIGHTS, check=False)
    run = unique("lead")
    fleet_names = [f"{run}-{i:03d}" for i in range(fleet)]
    crew = [f"{run}-crew-{i}" for i in range(2)]
    one, two = f"{run}-a", f"{run}-b"
    # The first leader has two reconcile workers instead of 16: the 100-Vehicle rollout
    # then spans seconds, long enough to kill it in the middle. The standby has the
    # default, as a real replica does: it finishes the rollout (and the clean-up's
    # deletions) as fast as the operator can, with as many reconciles racing as in use.
    first, second = replica(cluster, log_dir, one, workers=2), replica(cluster, log_dir, two)
    objects = [*[vehicle(n, f"{n}-node", 1 + i % 250) for i, n in enumerate(fleet_names)]]
    with (
        _nodes(cluster, [f"{n}-node" for n in [*fleet_names, *crew]]),
        FakeAgents(cluster) as agents,
    ):
        first.start()
        wait_until("the first replica to lead", lambda: leader(kube) == one, WAIT_S)
        second.start()  # answers its liveness URL while it stands by
        try:
            for i, name in enumerate(crew):
                off = {"components": {"mavros": {"enabled": False}}}
                kube.create(vehicle(name, f"{name}-node", 251 + i, **off))
                kube.create(redundant_autopilot(name))
                agents.add(name, name, f"{name}-node")
            wait_until("the crew Ready", lambda: all(ready(kube, n) for n in crew), WAIT_S)
            owned = f"{LABEL_MANAGED_BY}={MANAGED_BY}"
            with (
                Births(kube, PODS, NAMESPACE, owned) as pods,
                Births(kube, LEASES, NAMESPACE) as leases,
                Births(kube, JOBS, FLIGHTS) as jobs,
                Births(kube, VEHICLES, None, state=ready_condition) as vehicles,
                Births(kube, MISSIONS, FLIGHTS, state=mission_phase) as missions,
                Births(kube, EVENTS, FLIGHTS) as events,
                Births(kube, REDUNDANT_AUTOPILOTS, None, state=generation) as autopilots,
            ):
                # created side by side (one kubectl apply sends them one at a time): the
                # whole fleet is queued within a second or two, while the leader's two
                # workers roll it out
                with ThreadPoolExecutor(max_workers=8) as pool:
                    list(pool.map(kube.create, objects))
                under_way = lambda: pods.count() >= fleet // 10  # noqa: E731
                wait_until("the rollout under way", under_way, WAIT_S, 0.02)
                name = f"{run}-mission"
                kube.create(mission(name, crew))
                wait_until("the Mission's first claim", lambda: claimed(leases), WAIT_S, 0.02)
                first.crash()
                killed = time.monotonic()
                at_kill = Moment(pods.count(), claimed(leases), jobs.count(), phase(kube, name))
                wait_until("the standby to lead", lambda: leader(kube) == two, WAIT_S, 0.05)
                takeover_s = time.monotonic() - killed
                wait_until(
                    "the fleet Ready", lambda: all(ready(kube, n) for n in fleet_names), WAIT_S
                )
                wait_until("the Mission Running", lambda: phase(kube, name) == "Running", WAIT_S)
                wait_until("both Jobs seen", lambda: jobs.count() >= len(crew), WAIT_S)
                claims = [c for c in leases.uids if c != LEASE_NAME]
                fences = [autopilots.changes(n) for n in crew]
                doubles = [
                    *pods.doubles(set(pods.uids)),
                    *leases.doubles(set(claims)),
                    *jobs.doubles(set(jobs.uids)),
                    *vehicles.entered_twice([*fleet_names, *crew]),
                    *missions.entered_twice(),
                    *events.events_twice(),
                    *[
                        f"fence sent {n} times to {v}"
                        for v, n in zip(crew, fences, strict=True)
                        if n > 1
                    ],
                ]
                result = Takeover(
                    takeover_s=takeover_s,
                    doubles=doubles,
                    pods=pods.count(),
                    claims=len(claims),
                    jobs=jobs.count(),
                    at_kill=at_kill,
                    fences=sum(fences),
                    standby_acted=before_leading(log_dir / f"operator-{two}.log"),
                )
            cluster.kubectl("delete", "mission", name, "-n", FLIGHTS, "--timeout=120s")
            for n in crew:
                agents.forget(n)
                cluster.kubectl("delete", "redundantautopilot", n, check=False)
            # side by side (one kubectl delete sends them one at a time), then until gone
            everyone = [*fleet_names, *crew]
            with ThreadPoolExecutor(max_workers=8) as pool:
                list(pool.map(lambda n: kube.delete(VEHICLES, n), everyone))
            wait_until("the Vehicles gone", lambda: _gone(kube, everyone), WAIT_S)
        finally:
            first.stop()
            second.stop()
    return result
