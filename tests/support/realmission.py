"""The sync-paths reference mission on real harness nodes, as the Starling paper flew it.

"The exact same deployment file" in simulation and on the vehicles: the example's own
``mission.yaml`` (sized to the fleet by the sandbox's :func:`mission_manifests`) is
applied to a cluster of real nodes (:mod:`tests.support.realfleet`): the chart's operator
on the ground node, the agent DaemonSet and two simulated autopilots on each vehicle
node, the example's image (``docker/build-images.sh --mission``, one index for amd64 and
arm64) imported on every node. The operator creates the onboard follower pods on the
vehicle nodes and the offboard monitor pod on the ground node; each follower flies its
vehicle through the agent's MAVLink hub on the vehicle's loopback (hostNetwork) and talks
to the monitor through the ``sync-monitor`` Service, as in a cluster. The sandbox's
``lag`` schedule slows chosen vehicles on chosen legs (through their simulators' control
sockets: the followers know nothing of it), so the monitor has delays to absorb; the
results are read back from the finished monitor pod's log and make the paper's Table I.

A test flies shorter trajectories than the image's own (``trajectories``: a directory of
``<vehicle>.csv``) without rebuilding the image: they go into a ConfigMap mounted into the
onboard pods, and ``SYNC_TRAJECTORY_DIR`` points the followers at it
(:func:`with_trajectories`); the lag schedule follows the same legs. The monitor reads no
trajectory (each follower sends its plan with its results).

One difference from a production cluster, and why: the harness runs no cluster DNS
(kubelets have no ``clusterDNS``; CoreDNS is not among the node programs), so the
Service's name does not resolve in the pods. The followers are given the Service's
ClusterIP instead of its name (:func:`through_cluster_ip`); everything else about the
path is a cluster's: kube-proxy on the vehicle node rewrites the ClusterIP to the monitor
pod on the ground node, reached over the harness's host-gateway pod routes.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from roost_cli.sandbox import missionrun, plan
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.realnode import RealNodes
from roost_sim.control import request
from tests.support.images import run_build_script
from tests.support.realfleet import EMULATED_NODE_AGENT, RealFleet, VehicleRig
from tests.support.syncrun import EXAMPLE, results_from_log
from tests.support.waiting import wait_until

HUB = "127.0.0.1:14550"
"""Where each vehicle's agent serves its MAVLink hub: what ``mission.yaml``'s followers use."""
MONITOR_SELECTOR = "app=sync-monitor"
FOLLOWER_SELECTOR = "app=sync-follower"
FINISHED_PHASES = ("Succeeded", "Failed")
FLIGHT_S = 900.0
"""Upper bound on the whole flight, from the Mission applied to the monitor's results
(about 45 s with the tests' four 6 s legs plus delays, take-off and landing; the
example's 20 s legs take about a minute more)."""
TRAJECTORIES_CONFIGMAP = "sync-trajectories"
TRAJECTORIES_MOUNT = "/sync-trajectories"
FIRST_KINDS = ("Service", "ConfigMap")
"""Applied before the Mission: its pods need the Service's address and the ConfigMap."""


def mission_image() -> Path:
    """The example's image archive (built unless cached; ``$ROOST_IMAGES_DIR`` first)."""
    name = "roost-syncpaths.oci.tar"
    given = os.environ.get("ROOST_IMAGES_DIR")
    if given and (Path(given) / name).is_file():
        return Path(given) / name
    return run_build_script("--mission", str(EXAMPLE), timeout_s=3600) / name


EMULATED_ONBOARD = {"privileged": True}
"""The onboard containers' securityContext when a vehicle node runs under qemu-user: the
kubelet always asks for the RuntimeDefault seccomp profile for a pod's sandbox (whatever
the pod says), and containerd under qemu-user, which implements no seccomp, refuses that
for every unprivileged pod; a privileged pod carries no profile. The agent runs so there
for the same reason (``EMULATED_NODE_AGENT``); a real arm64 board has seccomp and needs
neither."""


def privileged_onboard(documents: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``documents`` with the Mission's onboard containers privileged (:data:`EMULATED_ONBOARD`)."""
    for doc in documents:
        if doc.get("kind") == "Mission":
            for container in doc["spec"]["onboard"]["spec"]["containers"]:
                container.setdefault("securityContext", {}).update(EMULATED_ONBOARD)
    return documents


def through_cluster_ip(documents: list[dict[str, Any]], address: str) -> list[dict[str, Any]]:
    """``documents`` with the followers' ``SYNC_MONITOR`` host replaced by ``address``
    (the Service's ClusterIP: the harness has no cluster DNS, see the module docstring)."""
    for doc in documents:
        if doc.get("kind") != "Mission":
            continue
        for container in doc["spec"]["onboard"]["spec"]["containers"]:
            for env in container.get("env", []):
                if env["name"] == "SYNC_MONITOR":
                    _, _, port = env["value"].rpartition(":")
                    env["value"] = f"{address}:{port}"
    return documents


def with_trajectories(documents: list[dict[str, Any]], directory: Path) -> list[dict[str, Any]]:
    """``documents`` and a ConfigMap of ``directory``'s ``<vehicle>.csv`` files, which the
    Mission's onboard containers mount at :data:`TRAJECTORIES_MOUNT` and fly
    (``SYNC_TRAJECTORY_DIR``) instead of the image's own trajectories."""
    for doc in documents:
        if doc.get("kind") != "Mission":
            continue
        pod = doc["spec"]["onboard"]["spec"]
        pod.setdefault("volumes", []).append(
            {"name": "trajectories", "configMap": {"name": TRAJECTORIES_CONFIGMAP}}
        )
        for container in pod["containers"]:
            container.setdefault("volumeMounts", []).append(
                {"name": "trajectories", "mountPath": TRAJECTORIES_MOUNT, "readOnly": True}
            )
            container.setdefault("env", []).append(
                {"name": "SYNC_TRAJECTORY_DIR", "value": TRAJECTORIES_MOUNT}
            )
    configmap = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": TRAJECTORIES_CONFIGMAP, "namespace": "default"},
        "data": {path.name: path.read_text() for path in sorted(directory.glob("*.csv"))},
    }
    return [configmap, *documents]


@dataclass
class MissionRun:
    """What one flight on real pods produced."""

    results: dict[str, dict[str, Any]]
    follower_nodes: dict[str, str]
    """vehicle -> the node its follower pod ran on."""
    monitor_node: str
    lags_sent: list[tuple[float, str, dict[str, object]]] = field(default_factory=list)
    flight_s: float = 0.0


@dataclass
class RealMission:
    """The chart on real nodes with ``len(arches)`` vehicles (``drone-1`` …, one node each
    of the given architecture), and the sync-paths Mission flown on them."""

    cluster: Cluster
    pool: RealNodes
    directory: Path
    arches: Sequence[str] = (binaries.HOST_ARCH, binaries.HOST_ARCH)
    trajectories: Path | None = None
    """A directory of ``<vehicle>.csv`` to fly instead of the image's own (see the module
    docstring)."""
    wait_s: float = 180.0
    fleet: RealFleet | None = None
    documents: list[dict[str, Any]] = field(default_factory=list)

    @property
    def emulated(self) -> bool:
        """Whether a vehicle node runs under emulation (another architecture's)."""
        return any(arch != binaries.HOST_ARCH for arch in self.arches)

    @property
    def plans(self) -> tuple[plan.VehiclePlan, ...]:
        return plan.plan_fleet(len(self.arches))

    def start(self) -> None:
        """Ground node, chart, and every vehicle reporting both autopilots healthy."""
        first, *rest = self.plans
        self.fleet = RealFleet(
            self.cluster,
            self.pool,
            self.directory,
            release="sync",
            namespace="roost-sync",
            vehicle=first,
            vehicle_arch=self.arches[0],
            wait_s=self.wait_s,
            agent_values=EMULATED_NODE_AGENT if self.emulated else {},
            hub=HUB,
            extra_images=[mission_image()],
        )
        self.fleet.start(*zip(rest, self.arches[1:], strict=True))

    @property
    def rigs(self) -> list[VehicleRig]:
        assert self.fleet is not None and self.fleet.vehicle_node is not None
        assert self.fleet.simulated is not None and self.fleet.launcher is not None
        first = VehicleRig(
            self.fleet.vehicle,
            self.fleet.vehicle_node,
            self.fleet.simulated,
            self.fleet.launcher,
        )
        return [first, *self.fleet.more]

    @property
    def trajectory_dir(self) -> Path:
        """The trajectories flown: :attr:`trajectories`, else the example's own."""
        return missionrun.check(
            missionrun.SYNC_PATHS, [p.name for p in self.plans], trajectories=self.trajectories
        )

    def apply(self) -> None:
        """``mission.yaml`` sized to the fleet: its Service (and the trajectories'
        ConfigMap) first, then its Mission with the Service's ClusterIP for the monitor's
        address."""
        documents = missionrun.mission_manifests(missionrun.SYNC_PATHS, len(self.arches), {})
        if self.trajectories is not None:
            documents = with_trajectories(documents, self.trajectory_dir)
        first = [d for d in documents if d.get("kind") in FIRST_KINDS]
        self._kubectl_apply(first)
        (service,) = [d for d in first if d.get("kind") == "Service"]
        meta = service["metadata"]
        found = self._get("service", meta["name"], "-n", meta.get("namespace", "default"))
        documents = through_cluster_ip(documents, found["spec"]["clusterIP"])
        if self.emulated:
            documents = privileged_onboard(documents)
        self._kubectl_apply([d for d in documents if d.get("kind") not in FIRST_KINDS])
        self.documents = documents

    def fly(self) -> MissionRun:
        """Apply the Mission, slow vehicles on the sandbox's schedule, and return once the
        monitor pod has finished, with its results."""
        assert self.fleet is not None
        primaries = {rig.plan.name: rig.plan.primary.name for rig in self.rigs}
        stop = threading.Event()

        def send(vehicle: str, message: dict[str, object]) -> None:
            rig = next(r for r in self.rigs if r.plan.name == vehicle)
            target = next(a for a in rig.simulated.autopilots if a.name == primaries[vehicle])
            request(Path(target.control), dict(message))

        def has_started() -> bool:
            return missionrun.started(self.monitor_log())

        lags = missionrun.LagInjector(
            missionrun.lag_schedule(tuple(primaries), self.trajectory_dir),
            send,
            stop,
            has_started,
        )
        started = time.monotonic()
        self.apply()
        lags.start()
        # The operator stops the offboard workload (the monitor) as soon as the Mission
        # has succeeded, which can be right after the monitor printed its results: its
        # log and node are kept as they are seen, not read once it has finished.
        seen: dict[str, str] = {"log": "", "node": ""}

        def results_seen() -> bool:
            pods = self._pods(MONITOR_SELECTOR)
            if pods:
                seen["node"] = pods[0]["spec"].get("nodeName", "") or seen["node"]
            log = self.monitor_log()
            if log:
                seen["log"] = log
            finished = bool(pods) and pods[0]["status"].get("phase") in FINISHED_PHASES
            return finished or results_from_log(seen["log"]) is not None

        try:
            wait_until("the monitor's results", results_seen, FLIGHT_S, poll_s=1.0)
        finally:
            stop.set()
        results = results_from_log(seen["log"])
        assert results is not None, seen["log"][-3000:]
        return MissionRun(
            results=results,
            follower_nodes={
                name: pod["spec"]["nodeName"] for name, pod in self.followers().items()
            },
            monitor_node=seen["node"],
            lags_sent=lags.sent,
            flight_s=time.monotonic() - started,
        )

    # ---- reading -------------------------------------------------------------------------
    def _get(self, *args: str) -> dict[str, Any]:
        found: dict[str, Any] = json.loads(self.cluster.kubectl("get", *args, "-o", "json").stdout)
        return found

    def _kubectl_apply(self, documents: list[dict[str, Any]]) -> None:
        text = "\n---\n".join(yaml.safe_dump(d) for d in documents)
        self.cluster.kubectl("apply", "-f", "-", input_text=text)

    def _pods(self, selector: str) -> list[dict[str, Any]]:
        items: list[dict[str, Any]] = self._get("pods", "-n", "default", "-l", selector)["items"]
        return items

    def followers(self) -> dict[str, dict[str, Any]]:
        """The follower pods by the vehicle each flies (from the env the operator gave it)."""
        found = {}
        for pod in self._pods(FOLLOWER_SELECTOR):
            env = {e["name"]: e.get("value") for e in pod["spec"]["containers"][0]["env"]}
            names = str(env["ROOST_MISSION_VEHICLES"]).split(",")
            found[names[int(str(env["ROOST_MISSION_VEHICLE_INDEX"]))]] = pod
        return found

    def monitor_log(self) -> str:
        done = self.cluster.kubectl(
            "logs", "-n", "default", "-l", MONITOR_SELECTOR, "--tail=-1", check=False
        )
        return done.stdout if done.returncode == 0 else ""

    # ---- teardown ------------------------------------------------------------------------
    def stop(self) -> None:
        if self.documents:
            text = "\n---\n".join(yaml.safe_dump(d) for d in self.documents)
            self.cluster.kubectl(
                "delete", "-f", "-", "--ignore-not-found", "--timeout=120s",
                input_text=text, check=False,
            )  # fmt: skip
        if self.fleet is not None:
            self.fleet.stop()
