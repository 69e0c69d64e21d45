"""Roost's chart on real harness nodes: a ground node, a vehicle node, simulated autopilots.

Shared by the real-node suite (``tests/e2e_node``) and ``bench/node.py``, which measure
the same steps. The layout is a small fleet's: the operator on a ground node (the chart
keeps it off vehicle nodes), the agent DaemonSet on the vehicle node the operator labels
from the Vehicle, and the vehicle's two simulated autopilots (``roost-sim``, started the
way ``roost sandbox up`` starts them) inside the vehicle node's network namespace, where
the agent on the host network reaches them on the node's loopback as on a companion
computer. Images are the ``make images`` archives, imported into each node's containerd
as ``localhost/roost-<target>:<version>`` and never pulled.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import subprocess
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import yaml

from roost_api.wellknown import LABEL_VEHICLE
from roost_cli.sandbox import plan, sims, state
from roost_cli.sandbox.processes import Launcher
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.processes import ManagedProcess
from roost_localcluster.realnode import RealNode, RealNodes
from roost_sim.control import request
from tests.support.chart import install_args
from tests.support.images import archive, build_images
from tests.support.waiting import wait_until

GROUND_NODE = "real-ground"
VEHICLE = "real-drone-1"
WAIT_S = 180.0
# qemu-user implements no seccomp (prctl PR_GET_SECCOMP fails), so the arm64 containerd
# refuses any seccomp profile but for a privileged pod ("failed to generate seccomp spec
# opts: seccomp is not supported"; a pod-level Unconfined was still refused for the
# sandbox). On the emulated node the agent runs as values-hardware.yaml runs it on a Pi:
# devices.access=privileged with the machine's one serial port (the chart needs a device
# listed; the agent opens none here), which carries no seccomp profile.
EMULATED_NODE_AGENT = {"devices": {"access": "privileged", "paths": ["/dev/ttyS0"]}}
"""Agent values for a vehicle node under qemu-user emulation (the arm64 node)."""


def chart_values(ground: str, **agent: Any) -> dict[str, Any]:
    """Values for the locally built images: imported, so IfNotPresent never pulls; the
    operator on the ground node. ``agent`` adds keys under ``agent``."""
    return {
        "operator": {
            "image": {"repository": "localhost/roost-operator", "pullPolicy": "IfNotPresent"},
            "nodeSelector": {"kubernetes.io/hostname": ground},
        },
        "agent": {
            "image": {"repository": "localhost/roost-agent", "pullPolicy": "IfNotPresent"},
            **agent,
        },
    }


class NamespaceLauncher(Launcher):
    """The sandbox's process launcher, starting everything in a real node's network
    namespace (the simulators the node's agent talks to over its loopback)."""

    def __init__(self, node: RealNode, logs_dir: Path) -> None:
        super().__init__(logs_dir, lambda: None)
        self.node = node

    def start(self, name: str, argv: list[str], env: Mapping[str, str]) -> ManagedProcess:
        return super().start(name, self.node.run_in_namespace(argv), env)


@dataclass
class VehicleRig:
    """One vehicle of a real fleet: its plan, its real node and its simulated autopilots
    (in the node's network namespace)."""

    plan: plan.VehiclePlan
    node: RealNode
    simulated: state.SandboxVehicle
    launcher: NamespaceLauncher


@dataclass
class Timings:
    """Seconds between the steps of :class:`RealFleet` (what bench/node.py reports)."""

    ground_start_to_ready_s: float = 0.0
    vehicle_start_to_ready_s: float = 0.0
    install_to_operator_ready_s: float = 0.0
    agent_pod_to_first_report_s: float = 0.0


@dataclass
class RealFleet:
    """Two real nodes with the chart installed and one vehicle flying simulated autopilots.

    ``start`` brings it up step by step (recording :class:`Timings`); ``stop`` removes
    the vehicle's objects and simulators and uninstalls the chart when still installed.
    The nodes stay in ``pool`` (the caller's), so a test can look at them afterwards.
    """

    cluster: Cluster
    pool: RealNodes
    directory: Path
    release: str = "real"
    namespace: str = "roost-real"
    timings: Timings = field(default_factory=Timings)
    ground: RealNode | None = None
    vehicle_node: RealNode | None = None
    vehicle: plan.VehiclePlan = field(
        default_factory=lambda: dataclasses.replace(plan.plan_fleet(1)[0], name=VEHICLE)
    )
    simulated: state.SandboxVehicle | None = None
    launcher: NamespaceLauncher | None = None
    installed: bool = False
    components: dict[str, Any] = field(default_factory=lambda: {"mavros": {"enabled": False}})
    """The Vehicle's ``spec.components`` (by default none: see :meth:`vehicle_manifest`)."""
    vehicle_arch: str = binaries.HOST_ARCH
    """The vehicle node's architecture: ``arm64`` is a Raspberry Pi's node (its programs
    and the agent image's arm64 build under emulation); the ground node is this machine's."""
    wait_s: float = WAIT_S
    agent_values: dict[str, Any] = field(default_factory=dict)
    """Extra chart values under ``agent`` (its telemetry stream; the emulated arm64 node
    needs one: see tests/e2e_node/test_arm64_node.py)."""
    hub: str | None = None
    """``HOST:PORT`` of each vehicle's MAVLink hub (RedundantAutopilot ``spec.hub.udp``);
    None: the agent serves none."""
    extra_images: list[Path] = field(default_factory=list)
    """OCI archives imported on every node besides Roost's own (a mission's image)."""
    more: list[VehicleRig] = field(default_factory=list)
    """Vehicles after the first (``start(*more)``)."""
    images: Path = field(default_factory=Path)
    """The directory of Roost's image archives (set by :meth:`start`)."""

    # ---- bring-up ------------------------------------------------------------------------
    def start(self, *more: tuple[plan.VehiclePlan, str]) -> None:
        """Ground node, the first vehicle's node, the chart, and the vehicle reporting.

        ``more``: further vehicles (plan, architecture), in :attr:`more`. Their nodes start
        before the chart is installed and their objects are applied with the first's, so
        every agent starts at once instead of each after the one before; returns once all
        reported. :attr:`timings` stay the first vehicle's."""
        self.images = images = build_images()
        t0 = time.monotonic()
        self.ground = self.pool.add(
            GROUND_NODE, images=[archive(images, "operator"), *self.extra_images]
        )
        self.timings.ground_start_to_ready_s = time.monotonic() - t0
        t0 = time.monotonic()
        rig = self.start_vehicle(self.vehicle, self.vehicle_arch)
        self.timings.vehicle_start_to_ready_s = time.monotonic() - t0
        self.vehicle_node, self.simulated, self.launcher = rig.node, rig.simulated, rig.launcher
        self.more.extend(self.start_vehicle(vehicle, arch) for vehicle, arch in more)
        self.install()
        self.timings.install_to_operator_ready_s = self.wait_operator_ready()
        for extra in self.more:
            self.apply_vehicle(extra.plan, extra.simulated)
        self.timings.agent_pod_to_first_report_s = self.add_vehicle()
        for extra in self.more:
            self.await_report(extra.plan)

    def start_vehicle(self, vehicle: plan.VehiclePlan, arch: str) -> VehicleRig:
        """A vehicle node of ``arch`` (Ready) and the vehicle's simulated autopilots in it."""
        node = self.pool.add(
            vehicle.node,
            images=[archive(self.images, "agent"), *self.extra_images],
            arch=arch,
            timeout_s=self.wait_s,
        )
        launcher = NamespaceLauncher(node, self.directory / "logs")
        [simulated] = sims.start(launcher, [vehicle], self.directory)
        return VehicleRig(vehicle, node, simulated, launcher)

    def await_report(self, vehicle: plan.VehiclePlan) -> None:
        """Returns once ``vehicle``'s agent reported both autopilots healthy."""
        wait_until(
            f"{vehicle.name}'s agent's first report", lambda: self.reported(vehicle), self.wait_s
        )

    def helm(self, values: Mapping[str, Any], *extra: str) -> None:
        args = install_args(self.release, self.namespace, values, self.directory)
        args = [a for a in args if a != "--wait"]  # the steps are waited for (and timed) here
        self.cluster.helm(*args, *extra)

    def values(self, **agent: Any) -> dict[str, Any]:
        """:func:`chart_values` for this fleet: the agents record their flights (the
        chart's default) under this fleet's directory, not the machine's
        /var/lib/roost/records."""
        assert self.ground is not None
        records = {"dir": str(self.directory / "agent-records")}
        return chart_values(self.ground.name, records=records, **{**self.agent_values, **agent})

    def install(self) -> None:
        self.helm(self.values())
        self.installed = True

    def wait_operator_ready(self) -> float:
        """Seconds until the operator Deployment has an available pod."""
        t0 = time.monotonic()
        wait_until(
            "the operator Deployment available",
            lambda: (
                self.get("deployment", self.operator_deployment, namespaced=True)
                .get("status", {})
                .get("availableReplicas")
            ),
            WAIT_S,
        )
        return time.monotonic() - t0

    def add_vehicle(self) -> float:
        """Apply the Vehicle and its RedundantAutopilot; seconds from the agent pod's
        appearance on the vehicle node to the agent's first report in the status."""
        assert self.simulated is not None
        self.apply_vehicle(self.vehicle, self.simulated)
        wait_until("the agent pod on the vehicle node", self.agent_pod, self.wait_s, poll_s=0.05)
        t0 = time.monotonic()
        wait_until("the agent's first report", self.reported, self.wait_s, poll_s=0.05)
        return time.monotonic() - t0

    def apply_vehicle(self, vehicle: plan.VehiclePlan, simulated: state.SandboxVehicle) -> None:
        """Apply ``vehicle``'s Vehicle and RedundantAutopilot (its simulators' links)."""
        connections = {a.name: a.connection for a in simulated.autopilots}
        manifests = [
            self.vehicle_manifest(vehicle),
            plan.autopilot_manifest(vehicle, connections, self.hub),
        ]
        text = "\n---\n".join(yaml.safe_dump(m) for m in manifests)
        self.cluster.kubectl("apply", "-f", "-", input_text=text)

    def vehicle_manifest(self, vehicle: plan.VehiclePlan | None = None) -> dict[str, Any]:
        """The sandbox's Vehicle without its simulation block and mavros: its autopilots
        are the simulators started here (as a vehicle's flight controllers are hardware),
        and neither SITL nor mavros images exist on the node."""
        manifest = plan.vehicle_manifest(vehicle or self.vehicle)
        manifest["spec"].pop("simulation", None)
        manifest["spec"]["components"] = self.components
        return manifest

    # ---- reading -------------------------------------------------------------------------
    @property
    def operator_deployment(self) -> str:
        return f"{self.release}-roost-operator"

    @property
    def agent_daemonset(self) -> str:
        return f"{self.release}-roost-agent"

    def get(self, *args: str, namespaced: bool = False) -> dict[str, Any]:
        extra = ["-n", self.namespace] if namespaced else []
        found: dict[str, Any] = json.loads(
            self.cluster.kubectl("get", *args, *extra, "-o", "json").stdout
        )
        return found

    def pods(self, component: str) -> list[dict[str, Any]]:
        selector = (
            f"app.kubernetes.io/instance={self.release},app.kubernetes.io/component={component}"
        )
        items: list[dict[str, Any]] = self.get("pods", "-l", selector, namespaced=True)["items"]
        return items

    def agent_pod(self) -> dict[str, Any] | None:
        """The agent pod on the vehicle node, once it exists."""
        return next(
            (p for p in self.pods("agent") if p["spec"].get("nodeName") == self.vehicle.node),
            None,
        )

    def autopilot_status(self, name: str | None = None) -> dict[str, Any]:
        """The RedundantAutopilot status of vehicle ``name`` (default: the first)."""
        found = self.get("redundantautopilot", name or self.vehicle.name)
        status: dict[str, Any] = found.get("status") or {}
        return status

    def reported(self, vehicle: plan.VehiclePlan | None = None) -> bool:
        """The agent reported from the vehicle's node, every autopilot healthy."""
        vehicle = vehicle or self.vehicle
        status = self.autopilot_status(vehicle.name)
        levels = {a.get("level") for a in status.get("autopilots", [])}
        return status.get("nodeName") == vehicle.node and levels == {"OK"}

    def node_labelled(self) -> bool:
        assert self.vehicle_node is not None
        node = self.get("node", self.vehicle_node.name)
        labels: dict[str, str] = node["metadata"].get("labels", {})
        return labels.get(LABEL_VEHICLE) == self.vehicle.name

    def control(self, autopilot: str, message: dict[str, Any]) -> dict[str, Any]:
        """A request to one simulated autopilot (``roost fault``'s channel)."""
        assert self.simulated is not None
        target = next(a for a in self.simulated.autopilots if a.name == autopilot)
        return request(Path(target.control), message)

    def fly(self) -> None:
        assert self.simulated is not None
        sims.fly(self.simulated)

    def containers(self) -> list[str]:
        """Images of the containers the vehicle node's containerd holds."""
        assert self.vehicle_node is not None
        done = subprocess.run(
            self.vehicle_node.ctr("containers", "list"),
            capture_output=True,
            text=True,
            check=True,
        )
        return [line.split()[1] for line in done.stdout.splitlines()[1:] if line.strip()]

    def agent_process(self) -> psutil.Process | None:
        """The agent container's process on the vehicle node (under emulation its
        interpreter runs it: the command line still names roost-agent)."""
        assert self.vehicle_node is not None
        for pid in self.vehicle_node.pids():
            with contextlib.suppress(psutil.Error):
                proc = psutil.Process(pid)
                if any(arg.endswith("roost-agent") for arg in proc.cmdline()):
                    return proc
        return None

    # ---- teardown ------------------------------------------------------------------------
    def uninstall(self) -> None:
        self.cluster.helm("uninstall", self.release, "--namespace", self.namespace, "--wait")
        self.installed = False

    def stop(self) -> None:
        names = [self.vehicle.name, *(rig.plan.name for rig in self.more)]
        objects = ("redundantautopilot,vehicle", *names)
        self.cluster.kubectl("delete", *objects, "--ignore-not-found", "--timeout=60s", check=False)
        if self.installed:
            self.uninstall()
        for launcher in (self.launcher, *(rig.launcher for rig in self.more)):
            if launcher is not None:
                launcher.stop_all()
        for node in (self.vehicle_node, *(rig.node for rig in self.more), self.ground):
            if node is not None:
                self.pool.remove(node.name)
