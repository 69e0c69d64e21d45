"""The KinD fleet's simulated autopilots: ``roost-sim`` in each worker's network namespace.

On the podman path of ``make e2e-kind`` (tests/e2e/kind/run.sh) no SITL image can be
pulled, so each vehicle's two autopilots are the sandbox's simulators, started on this
machine inside the network namespace of the vehicle's KinD worker container (``nsenter
--net`` on the container's pid). The agent DaemonSet pod runs on the worker's host
network, so it reaches them on its loopback, exactly as it reaches a flight controller
on a companion computer. The Vehicles and RedundantAutopilots are those of
tests/e2e/kind/fleet.yaml, with the connections the simulators report and without the
SITL block (the autopilots exist; nothing has to be scheduled for them).
"""

from __future__ import annotations

import copy
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from roost_api.meta import Stack
from roost_cli.sandbox import plan, sims, state
from roost_cli.sandbox.processes import Launcher
from roost_localcluster.processes import ManagedProcess
from roost_sim.control import request

FLEET_FILE = Path(__file__).resolve().parents[1] / "e2e" / "kind" / "fleet.yaml"


def fleet_documents() -> list[dict[str, Any]]:
    """The Vehicles and RedundantAutopilots of tests/e2e/kind/fleet.yaml, in file order."""
    return [doc for doc in yaml.safe_load_all(FLEET_FILE.read_text()) if doc]


def container_pid(engine: str, container: str) -> int:
    """The host pid of a running node container's init (its namespaces' handle)."""
    done = subprocess.run(
        [engine, "inspect", "--format", "{{.State.Pid}}", container],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    return int(done.stdout.strip())


class ContainerNetLauncher(Launcher):
    """The sandbox's process launcher, starting processes in a container's network
    namespace only (files, users and the process tree stay this machine's)."""

    def __init__(self, pid: int, logs_dir: Path) -> None:
        super().__init__(logs_dir, lambda: None)
        self.pid = pid

    def start(self, name: str, argv: list[str], env: Mapping[str, str]) -> ManagedProcess:
        return super().start(name, ["nsenter", f"--net=/proc/{self.pid}/ns/net", "--", *argv], env)


def vehicle_plan(vehicle: dict[str, Any], autopilot: dict[str, Any]) -> plan.VehiclePlan:
    """The sandbox plan of one fleet.yaml vehicle (for :func:`sims.start`)."""
    return plan.VehiclePlan(
        name=vehicle["metadata"]["name"],
        index=0,
        stack=Stack(vehicle["spec"]["simulation"]["stack"]),
        sysid=vehicle["spec"]["sysid"],
        autopilots=tuple(
            plan.AutopilotPlan(
                name=a["name"],
                stack=Stack(a["stack"]),
                sysid=a["sysid"],
                bridge_channel=a["bridgeChannel"],
            )
            for a in autopilot["spec"]["autopilots"]
        ),
    )


def manifests(
    vehicle: dict[str, Any], autopilot: dict[str, Any], connections: Mapping[str, str]
) -> list[dict[str, Any]]:
    """The Vehicle without its SITL block (and without mavros, whose image is not here)
    and its RedundantAutopilot pointing at the simulators."""
    v = copy.deepcopy(vehicle)
    v["spec"].pop("simulation", None)
    v["spec"]["components"] = {"mavros": {"enabled": False}}
    a = copy.deepcopy(autopilot)
    for entry in a["spec"]["autopilots"]:
        entry["connection"] = connections[entry["name"]]
    return [v, a]


@dataclass
class SimulatedKindFleet:
    """The simulators of every fleet.yaml vehicle, each in its worker's namespace."""

    engine: str
    directory: Path
    launchers: list[ContainerNetLauncher] = field(default_factory=list)
    vehicles: dict[str, state.SandboxVehicle] = field(default_factory=dict)

    def start(self) -> list[dict[str, Any]]:
        """Start the simulators; the manifests to apply for them."""
        docs = fleet_documents()
        found = {(d["kind"], d["metadata"]["name"]): d for d in docs}
        out: list[dict[str, Any]] = []
        for vehicle in (d for d in docs if d["kind"] == "Vehicle"):
            name = vehicle["metadata"]["name"]
            autopilot = found[("RedundantAutopilot", name)]
            pid = container_pid(self.engine, vehicle["spec"]["nodeName"])
            launcher = ContainerNetLauncher(pid, self.directory / name / "logs")
            self.launchers.append(launcher)
            [simulated] = sims.start(
                launcher, [vehicle_plan(vehicle, autopilot)], self.directory / name
            )
            self.vehicles[name] = simulated
            connections = {a.name: a.connection for a in simulated.autopilots}
            out.extend(manifests(vehicle, autopilot, connections))
        return out

    def control(self, vehicle: str, autopilot: str, message: dict[str, Any]) -> dict[str, Any]:
        """A request to one simulator (``roost fault``'s channel)."""
        target = next(a for a in self.vehicles[vehicle].autopilots if a.name == autopilot)
        return request(Path(target.control), message)

    def fly(self, names: Sequence[str]) -> None:
        for name in names:
            sims.fly(self.vehicles[name])

    def stop(self) -> None:
        for launcher in self.launchers:
            launcher.stop_all()
