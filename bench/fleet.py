"""The operator at fleet scale: one ``roost-operator`` process, 1,000 (and more) Vehicles.

A real control plane (``FLEET_SETTINGS``: sized for a thousand nodes) with one KWOK node
per vehicle, and the operator as its own process, as the chart runs it. Each Vehicle has
the default components (mavros, as a Pod KWOK "runs") and no RedundantAutopilot,
so no agent writes anything: once the fleet is Ready, nothing changes in the cluster and
any CPU the operator spends is its own overhead.

- ``fleet.ready_<N>_s``: ``kubectl apply --server-side`` of N Vehicles (one request
  each, in ``APPLY_STREAMS`` kubectl processes at once, as ``xargs -P`` would; nodes
  already Ready) until every Vehicle's ``Ready`` condition is True (labels and taint on
  its node, its ConfigMap, its mavros Pod Running and Ready), seen by a watch of the
  fleet's Vehicles (:func:`wait_all_ready`). The note says how long the apply alone
  took and where the CPU went meanwhile, by program.
- ``fleet.operator_rss_mb_<N>``: the operator's peak resident memory over the run.
- ``fleet.idle_cpu_pct_<N>``: the operator's CPU (user + system, % of one core) over
  ``IDLE_S`` once the fleet has been Ready for ``SETTLE_S`` and every node has started
  its status reports (kwok's nodes report like kubelets with leases, every 5 minutes:
  ``roost_localcluster.kwoknodes``), so the window holds the steady trickle of node
  events a real fleet sends.
- ``fleet.single_change_p99_s``: with the fleet idle, one Vehicle's spec changes (its
  mavros image) until its mavros Pod carries the new image (the operator deleted the
  old pod and created the new one); p99 over ``CHANGES``.
- ``fleet.control_plane_floor_<N>_s``: what the control plane alone needs for the same
  outcome. A fresh control plane of the same settings gets the same N nodes (with the
  labels the operator gave them) and, by the same ``kubectl apply`` streams, the very
  ConfigMaps and Pods the operator made (bound to their nodes), with no operator running;
  the figure is apply → every Pod Running and Ready. No operator can make the fleet Ready sooner on
  this machine, so it is the yardstick for ``fleet.ready_<N>_s``.

Sizes: ``ROOST_BENCH_FLEET`` (default 1000; ``1000,3000`` runs both, the larger one is
recorded with what happened). The machine's load average is recorded with every figure:
the operator shares the cores with the API server, etcd, the controller manager, the
scheduler and KWOK.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil

from bench.controlplane import FLEET_SETTINGS
from bench.core import Figure
from roost_api.wellknown import LABEL_VEHICLE
from roost_kube.client import Kube
from roost_kube.resources import CONFIGMAPS, NODES, PODS, VEHICLES
from roost_localcluster import binaries, nodes
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from roost_operator.engine.watches import Watcher
from roost_operator.vehicles.manifests import workload_name
from roost_operator.vehicles.pods import pod_state
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

COMMAND = "python -m bench fleet"
SIZES = tuple(int(n) for n in os.environ.get("ROOST_BENCH_FLEET", "1000").split(","))
NAMESPACE = "roost-bench"
FLEET_LABEL = "bench-fleet"
NODES_TIMEOUT_S = 900.0
READY_TIMEOUT_S = 900.0
APPLY_TIMEOUT_S = 900.0
SETTLE_S = 30.0
IDLE_S = 60.0
CHANGES = 20
APPLY_STREAMS = 4
CHANGE_TIMEOUT_S = 60.0


def vehicle_name(index: int) -> str:
    return f"fleet-{index:04d}"


def vehicle_manifest(index: int) -> dict[str, Any]:
    name = vehicle_name(index)
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": name, "labels": {"fleet": FLEET_LABEL}},
        "spec": {"nodeName": f"{name}-node", "sysid": 1 + index % 250},
    }


def _create_nodes(cluster: Cluster, labelled: list[tuple[str, dict[str, str]]]) -> None:
    """Create kwok nodes ``(name, labels)`` and wait until they are Ready."""

    def create(node: tuple[str, dict[str, str]]) -> None:
        manifest = nodes.fake_node(node[0], labels=node[1])
        cluster.admin.create(manifest)

    with ThreadPoolExecutor(max_workers=4) as pool:
        list(pool.map(create, labelled))
    cluster.wait_nodes_ready([name for name, _ in labelled], NODES_TIMEOUT_S)


def _apply_streams(cluster: Cluster, documents: list[str]) -> None:
    """``kubectl apply --server-side`` the JSON ``documents`` in ``APPLY_STREAMS`` streams,
    as ``xargs -P`` would."""

    def apply(stream: int) -> None:
        manifest = "\n---\n".join(documents[stream::APPLY_STREAMS])
        cluster.kubectl(
            "apply", "--server-side", "-f", "-", input_text=manifest, timeout_s=APPLY_TIMEOUT_S
        )

    with ThreadPoolExecutor(max_workers=APPLY_STREAMS) as pool:
        list(pool.map(apply, range(APPLY_STREAMS)))


def _is_ready(vehicle: Mapping[str, Any]) -> bool:
    return any(
        c["type"] == "Ready" and c["status"] == "True"
        for c in (vehicle.get("status") or {}).get("conditions", [])
    )


def wait_all_ready(kube: Kube, count: int, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Return once ``count`` of the fleet's Vehicles are Ready, seen by a watch (the
    operator's own :class:`~roost_operator.engine.watches.Watcher`): the moment the last one
    turns Ready is when its status write arrives (a poll would add up to its period), and
    the API server sends one event per status write instead of the whole fleet on every
    poll."""
    ready: set[str] = set()
    done = threading.Event()

    def on_event(kind: str, vehicle: Mapping[str, Any], news: bool = True) -> None:
        name = vehicle["metadata"]["name"]
        if kind != "DELETED" and _is_ready(vehicle):
            ready.add(name)
        else:
            ready.discard(name)
        if len(ready) >= count:
            done.set()

    def on_list(listed: list[Mapping[str, Any]], vanished: list[Mapping[str, Any]]) -> None:
        ready.clear()
        for vehicle in listed:
            on_event("ADDED", vehicle)

    watcher = Watcher(kube, VEHICLES, on_event, on_list, label_selector=f"fleet={FLEET_LABEL}")
    watcher.start()
    try:
        if not done.wait(timeout_s):
            raise TimeoutError(f"{count} Vehicles Ready: not within {timeout_s:.0f} s")
    finally:
        watcher.stop()


@dataclass
class Sampler:
    """Samples a process's RSS every half second in a thread; keeps the peak."""

    proc: psutil.Process
    peak_mb: float = 0.0
    _stop: threading.Event = field(default_factory=threading.Event)

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            try:
                self.peak_mb = max(self.peak_mb, self.proc.memory_info().rss / 1e6)
            except psutil.Error:
                return

    @contextmanager
    def running(self) -> Iterator[Sampler]:
        thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)
        thread.start()
        try:
            yield self
        finally:
            self._stop.set()
            thread.join()


def _cpu_s(proc: psutil.Process) -> float:
    times = proc.cpu_times()
    return float(times.user + times.system)


def _cpu_by_program() -> dict[str, float]:
    """CPU seconds so far of every process under this one, summed by program name."""
    totals: dict[str, float] = {}
    for proc in psutil.Process().children(recursive=True):
        try:
            name = proc.name()
            totals[name] = totals.get(name, 0.0) + _cpu_s(proc)
        except psutil.Error:
            continue
    return totals


def _cpu_spent(before: dict[str, float]) -> str:
    """Where the CPU went since ``before``: the busiest programs first."""
    after = _cpu_by_program()
    spent = {name: after[name] - before.get(name, 0.0) for name in after}
    top = sorted(spent.items(), key=lambda item: -item[1])[:6]
    return ", ".join(f"{name} {seconds:.0f} s" for name, seconds in top if seconds >= 0.5)


def _single_changes(kube: Kube, count: int) -> list[float]:
    """Change one Vehicle's mavros image at a time; seconds until its mavros Pod has it."""
    seconds: list[float] = []
    for attempt in range(CHANGES):
        index = (attempt * 37) % count
        name = vehicle_name(index)
        image = f"roost.dev/bench/mavros:change-{attempt}"
        patch = {"spec": {"components": {"mavros": {"enabled": True, "image": image}}}}
        started = time.monotonic()
        kube.merge_patch(VEHICLES, name, patch)

        def rolled(name: str = name, image: str = image) -> bool:
            pod = kube.get(PODS, workload_name(name, "mavros"), NAMESPACE)
            return pod is not None and any(
                c.get("image") == image for c in pod["spec"]["containers"]
            )

        wait_until(f"{name}'s mavros image", rolled, CHANGE_TIMEOUT_S, poll_s=0.02)
        seconds.append(time.monotonic() - started)
    return seconds


@dataclass(frozen=True)
class Made:
    """What the operator made for the fleet, as manifests to apply elsewhere."""

    node_labels: dict[str, dict[str, str]]
    objects: list[dict[str, Any]]  # ConfigMaps and Pods, server fields removed


def _as_manifest(obj: dict[str, Any]) -> dict[str, Any]:
    """``obj`` as one would write it: no status, no server-set metadata, no owners (the
    Vehicles are not there to own it)."""
    meta = obj["metadata"]
    kept = {k: meta[k] for k in ("name", "namespace", "labels", "annotations") if k in meta}
    manifest = {k: v for k, v in obj.items() if k not in ("status", "metadata")}
    if obj.get("kind") == "Pod":  # the service-account token volume admission added
        manifest["spec"] = _without_token_volume(obj["spec"])
    return manifest | {"metadata": kept}


def _without_token_volume(spec: dict[str, Any]) -> dict[str, Any]:
    """A pod spec without the ``kube-api-access-*`` volume admission adds (it adds it
    again on the other control plane)."""

    def ours(volume: dict[str, Any]) -> bool:
        return not str(volume.get("name", "")).startswith("kube-api-access-")

    containers = [
        {**c, "volumeMounts": [m for m in c.get("volumeMounts") or [] if ours(m)]}
        for c in spec.get("containers") or []
    ]
    volumes = [v for v in spec.get("volumes") or [] if ours(v)]
    return {**spec, "containers": containers, "volumes": volumes}


def _made(kube: Kube) -> Made:
    node_labels = {
        node["metadata"]["name"]: dict(node["metadata"].get("labels") or {})
        for node in kube.list_objects(NODES)
    }
    objects = [
        _as_manifest(obj)
        for resource in (CONFIGMAPS, PODS)
        for obj in kube.list_objects(resource, namespace=NAMESPACE)
        if LABEL_VEHICLE in (obj["metadata"].get("labels") or {})
    ]
    return Made(node_labels, objects)


def _pods_ready(kube: Kube) -> int:
    """Pods Running and Ready (as the operator judges a component)."""
    return sum(
        1 for pod in kube.list_objects(PODS, namespace=NAMESPACE) if pod_state("", pod).ready
    )


def control_plane_floor(made: Made) -> tuple[float, str]:
    """Seconds from applying ``made`` to a fresh control plane (same nodes, no operator)
    until every Pod is Running and Ready, and where the CPU went."""
    pods = sum(1 for obj in made.objects if obj["kind"] == "Pod")
    with (
        tempfile.TemporaryDirectory(prefix="bench-fleet-floor-") as tmp,
        ControlPlane(Path(tmp), settings=FLEET_SETTINGS) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.kubectl("create", "namespace", NAMESPACE)
        _create_nodes(cluster, list(made.node_labels.items()))
        with cluster.kube("roost-bench") as kube:
            cpu_before = _cpu_by_program()
            started = time.monotonic()
            _apply_streams(cluster, [json.dumps(obj) for obj in made.objects])
            wait_until(
                f"{pods} Pods Running and Ready",
                lambda: _pods_ready(kube) >= pods,
                READY_TIMEOUT_S,
                poll_s=1.0,
            )
            return time.monotonic() - started, _cpu_spent(cpu_before)


@dataclass(frozen=True)
class Fleet:
    """A control plane with the fleet's nodes Ready and the operator running."""

    cluster: Cluster
    plane: ControlPlane
    operator: OperatorProcess
    operator_log: Path


@contextmanager
def fleet_with_operator(
    count: int, settings: Settings = FLEET_SETTINGS, prefix: str = "bench-fleet-"
) -> Iterator[Fleet]:
    """A fresh control plane of ``settings`` with ``count`` Ready KWOK nodes (one per
    vehicle) and the operator as its own process; all gone on leaving."""
    with (
        tempfile.TemporaryDirectory(prefix=prefix) as tmp,
        ControlPlane(Path(tmp), settings=settings) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        _create_nodes(cluster, [(f"{vehicle_name(i)}-node", {}) for i in range(count)])
        log = Path(tmp) / "operator.log"
        operator = OperatorProcess(cluster, log, namespace=NAMESPACE)
        operator.start()
        try:
            yield Fleet(cluster, plane, operator, log)
        finally:
            operator.stop()


def apply_until_ready(cluster: Cluster, kube: Kube, count: int) -> float:
    """Apply ``count`` Vehicles and wait until every one is Ready; the seconds the apply
    itself took."""
    started = time.monotonic()
    _apply_streams(cluster, [json.dumps(vehicle_manifest(i)) for i in range(count)])
    applied_s = time.monotonic() - started
    wait_all_ready(kube, count)
    return applied_s


def measure(count: int) -> tuple[dict[str, float], str, Made]:
    """The figures at ``count`` vehicles, a note on how the run went, and what the
    operator made."""
    with fleet_with_operator(count) as fleet:
        reports_from = time.monotonic() + FLEET_SETTINGS.node_status_report_s * 1.1
        proc = psutil.Process(fleet.operator.process.pid)
        with Sampler(proc).running() as rss, fleet.cluster.kube("roost-bench") as kube:
            cpu_before = _cpu_by_program()
            started = time.monotonic()
            applied_s = apply_until_ready(fleet.cluster, kube, count)
            ready_s = time.monotonic() - started
            ready_cpu = _cpu_spent(cpu_before)
            time.sleep(max(SETTLE_S, reports_from - time.monotonic()))
            cpu0, t0 = _cpu_s(proc), time.monotonic()
            time.sleep(IDLE_S)
            idle_pct = (_cpu_s(proc) - cpu0) / (time.monotonic() - t0) * 100
            changes = _single_changes(kube, count)
            load = os.getloadavg()[0]
            made = _made(kube)
        log = fleet.operator_log.read_text(errors="replace")
    orphaned = log.count("Leaving it orphaned")
    figures = {
        "ready_s": ready_s,
        "rss_mb": rss.peak_mb,
        "idle_cpu_pct": idle_pct,
        "single_change_p99_s": sorted(changes)[max(0, round(0.99 * len(changes)) - 1)],
        "single_change_median_s": statistics.median(changes),
    }
    note = (
        f"{count} Vehicles (default components, no RedundantAutopilot) on {count} KWOK "
        f"nodes; 1-min load average {load:.1f} on {os.cpu_count()} cores; "
        f"{orphaned} orphaned handlers logged; the apply took {applied_s:.1f} s; CPU until "
        f"Ready: {ready_cpu}"
    )
    return figures, note, made


def run() -> list[Figure]:
    binaries.ensure_built()
    out: list[Figure] = []
    for count in SIZES:
        figures, note, made = measure(count)
        print(f"bench fleet {count}: {figures} ({note})", flush=True)
        target = count == 1000
        floor_s, floor_cpu = control_plane_floor(made)
        print(f"bench fleet {count}: control plane floor {floor_s:.1f} s", flush=True)
        out.append(
            Figure(
                f"fleet.control_plane_floor_{count}_s",
                round(floor_s, 1),
                "s",
                "informational",
                COMMAND,
                f"the {len(made.objects)} ConfigMaps and Pods the operator made for "
                f"{count} Vehicles, applied in {APPLY_STREAMS} kubectl streams to a fresh "
                f"control plane with the same {count} KWOK nodes and no operator, until "
                f"every Pod is Running and Ready (fleet.ready_{count}_s: "
                f"{figures['ready_s']:.1f} s); 1-min load average {os.getloadavg()[0]:.1f}; "
                f"CPU: {floor_cpu}",
            )
        )
        idle_note = f"operator CPU over {IDLE_S:.0f} s after {SETTLE_S:.0f} s settled; {note}"
        out += [
            Figure(
                f"fleet.{name}_{count}{suffix}",
                round(figures[key], digits),
                unit,
                goal if target else "informational",
                COMMAND,
                idle_note if key == "idle_cpu_pct" else note,
            )
            for name, suffix, key, unit, goal, digits in (
                ("ready", "_s", "ready_s", "s", "<= 30", 1),
                ("operator_rss_mb", "", "rss_mb", "MB", "<= 250", 1),
                ("idle_cpu_pct", "", "idle_cpu_pct", "%", "<= 2", 2),
            )
        ]
        if target:
            out.append(
                Figure(
                    "fleet.single_change_p99_s",
                    round(figures["single_change_p99_s"], 3),
                    "s",
                    "<= 1",
                    COMMAND,
                    f"{CHANGES} mavros image changes, one at a time, until the mavros Pod "
                    f"has the image (median {figures['single_change_median_s']:.3f} s); "
                    f"{note}",
                )
            )
    return out
