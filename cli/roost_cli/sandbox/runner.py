"""``roost sandbox up`` and ``roost sandbox down``: bring the local fleet up, and take it down.

Up, in order (each step shown as it happens):

1. build or reuse the control-plane binaries, start the control plane (real kube-apiserver,
   etcd, controller manager, scheduler, kwok) in ``<dir>/cluster``;
2. install the CRDs and create one fake (kwok) node per vehicle;
3. start the simulated autopilots (two per vehicle, each binding a free UDP port itself and
   reporting it);
4. start the operator, then apply the Vehicles, RedundantAutopilots (each with the
   agent's MAVLink hub on a port of its own) and the Mission;
5. start one ``roost-agent`` per vehicle, with the simulated bridge;
6. show the fleet live, and after a pause inject a fault on one vehicle's active autopilot
   so the failover happens on screen;
7. keep running until Ctrl-C (or SIGTERM from ``roost sandbox down``), then stop every
   process it started, newest first, and the control plane last.

All programs are started from the main thread (see :mod:`.processes` for why) and are
recorded in ``<dir>/state.json`` (:mod:`.state`) as they start, so ``roost sandbox down``
from another terminal can stop them even if this process was killed.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import psutil
import yaml
from rich.console import Console, Group, RenderableType
from rich.text import Text

from roost_api.ports import ephemeral_range, port_free
from roost_cli import view
from roost_cli.cluster import Fleet, Target
from roost_cli.errors import CliError
from roost_cli.sandbox import kwok, missionrun, plan, sims, state
from roost_cli.sandbox.director import Cue, Director, Script
from roost_cli.sandbox.processes import Launcher, console_script
from roost_cli.sandbox.progress import build_control_plane, start_control_plane
from roost_kube.errors import ApiError
from roost_localcluster import nodes
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from roost_localcluster.processes import ManagedProcess

DEFAULT_VEHICLES = 3
DEFAULT_FAULT_AFTER_S = 15.0
MONITOR_LISTENING_TIMEOUT_S = 30.0
NODES_READY_TIMEOUT_S = 120.0
DOWN_TIMEOUT_S = 60.0
HEADLESS_POLL_S = 1.0
LIVE_EVENTS = 6
ANNOUNCE_TIMEOUT_S = 30.0
ANNOUNCE_PER_AGENT_S = 2.0
"""More time per agent to announce its telemetry: 25 Python agents starting at once
take the two cores of a small machine for tens of seconds."""
DEFAULT_DASHBOARD_PORT = 8765
DASHBOARD_ANNOUNCE = re.compile(r"Roost dashboard on (http://\S+/)")
RUN_DIRECTORIES = ("agents", "sims", "logs", "cluster")


@dataclass(frozen=True)
class Options:
    """What ``roost sandbox up`` was asked for."""

    directory: Path
    vehicles: int = DEFAULT_VEHICLES
    fault: bool = True
    fault_after_s: float = DEFAULT_FAULT_AFTER_S
    live: bool = True
    mission: str | None = None
    """Run that mission's own programs (see :mod:`.missionrun`) instead of the demo."""
    trajectories: Path | None = None
    """With ``mission``: a directory of ``<vehicle>.csv`` to fly instead of its own."""
    dashboard: bool = True
    """Run ``roost dashboard`` (read-write, the sandbox's kubeconfig) beside the fleet."""
    dashboard_port: int = DEFAULT_DASHBOARD_PORT


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


class Sandbox:
    """One run of ``roost sandbox up``; :meth:`run` returns when it has been stopped."""

    def __init__(self, options: Options, console: Console) -> None:
        self.options = options
        self.console = console
        self.directory = options.directory
        me = psutil.Process()
        self.state = state.SandboxState(
            pid=me.pid, create_time=me.create_time(), directory=str(self.directory)
        )
        self.launcher = Launcher(self.directory / "logs", self._save)
        self.plane: ControlPlane | None = None
        self.fleet_plan: tuple[plan.VehiclePlan, ...] = ()
        self.script = Script()
        self.director: Director | None = None
        self.mission_ref = (plan.MISSION_NAMESPACE, plan.MISSION_NAME)
        self.followers: dict[str, ManagedProcess] = {}
        """A mission's onboard programs by vehicle (``--mission`` only)."""
        self.trajectories: Path | None = None
        """The trajectories the mission's followers fly (``--mission`` only)."""
        self._mission_fleet: Fleet | None = None
        self._stop = threading.Event()

    # ---- lifecycle ---------------------------------------------------------------------
    def run(self) -> None:
        """Bring everything up, show it, wait for Ctrl-C or SIGTERM, tear everything down."""
        self._refuse_second_sandbox()
        self._forget_previous_run()
        previous = signal.signal(signal.SIGTERM, _interrupt)
        try:
            self._save()
            self._up()
            self._announce()
            self.state.phase = state.Phase.RUNNING
            self._save()
            self._direct()
            self._watch()
        except KeyboardInterrupt:
            self.console.print("\n[bold]Stopping the sandbox…[/]")
        finally:
            self._stop.set()
            if self.director is not None:
                self.director.stop()
                self.director.join()
            self._down()
            signal.signal(signal.SIGTERM, previous)

    def _refuse_second_sandbox(self) -> None:
        existing = state.running(self.directory)
        if existing is not None and existing.pid != self.state.pid:
            raise CliError(
                f"a sandbox is already running in {self.directory} (pid {existing.pid}): "
                "use it (`roost status`), or stop it first with `roost sandbox down`"
            )
        stale = state.load(self.directory)
        if stale is not None:
            self.console.print("Cleaning up after a sandbox that did not stop cleanly…")
            stop_recorded(stale)

    def _forget_previous_run(self) -> None:
        """A new sandbox is a new fleet: drop the last run's agent state, sockets and logs.

        An agent restores its decision state from its directory (as a rebooted vehicle
        must), so a kept directory would start this run already failed over and latched.
        """
        for name in RUN_DIRECTORIES:
            shutil.rmtree(self.directory / name, ignore_errors=True)

    def _save(self) -> None:
        self.state.processes = self.launcher.states()
        state.save(self.state)

    def _up(self) -> None:
        try:
            self._bring_up()
        except subprocess.CalledProcessError as error:
            command = " ".join(str(arg) for arg in error.cmd)
            raise CliError(
                f"`{command}` failed (exit {error.returncode}):\n{error.stderr or error.output}"
            ) from error
        except (TimeoutError, subprocess.TimeoutExpired, ApiError) as error:
            logs = self.plane.logs_dir if self.plane is not None else self.directory
            raise CliError(
                f"the sandbox did not come up: {error}. Logs: {self.directory / 'logs'} and {logs}"
            ) from error

    def _bring_up(self) -> None:
        self.fleet_plan = plan.plan_fleet(self.options.vehicles)
        if self.options.mission is not None:  # refused before anything starts
            try:
                self.trajectories = missionrun.check(
                    self.options.mission,
                    [v.name for v in self.fleet_plan],
                    trajectories=self.options.trajectories,
                )
            except ValueError as error:
                raise CliError(str(error)) from None
        bin_dir = build_control_plane(self.console)
        stages = self.directory / "kwok-stages.yaml"
        stages.write_text(yaml.safe_dump_all(kwok.pod_stages(), sort_keys=False))
        self.plane = ControlPlane(
            self.state.cluster_dir, bin_dir=bin_dir, settings=Settings(kwok_config=stages)
        )
        start_control_plane(self.console, self.plane)
        self.state.kubeconfig = str(self.plane.kubeconfig)
        self.state.server = self.plane.server
        self._save()
        cluster = Cluster.of(self.plane)
        with self.console.status("Installing the Roost CRDs…"):
            cluster.install_crds()
        self._step("CRDs installed (Vehicle, RedundantAutopilot, Mission)")
        self._add_nodes(cluster)
        self._start_sims()
        self._start_operator()
        self._apply(cluster)
        self._start_agents()
        self._await_telemetry()
        if self.options.dashboard:
            self._start_dashboard()
        if self.options.mission is not None:
            self._start_mission(self.options.mission)

    def _step(self, message: str) -> None:
        self.console.print(f"[green]✓[/] {message}")

    def _add_nodes(self, cluster: Cluster) -> None:
        names = [vehicle.node for vehicle in self.fleet_plan]
        with self.console.status(f"Creating {len(names)} fake vehicle nodes (kwok)…"):
            for name in names:
                cluster.add_node(name, labels={plan.FLEET_LABEL: plan.FLEET_VALUE}, wait=False)
            nodes.wait_nodes_ready(cluster.admin, names, NODES_READY_TIMEOUT_S)
        self._step(f"nodes Ready: {', '.join(names)}")

    def _start_sims(self) -> None:
        with self.console.status("Starting the simulated autopilots…"):
            for group in sims.process_groups(self.fleet_plan):
                self.state.vehicles += sims.start(self.launcher, group, self.directory)
                self._save()
        described = ", ".join(
            f"{v.name} ({'+'.join(a.name for a in v.autopilots)})" for v in self.state.vehicles
        )
        self._step(f"simulated autopilots running: {described}")

    def _env(self) -> dict[str, str]:
        assert self.plane is not None
        return {"KUBECONFIG": str(self.plane.kubeconfig)}

    def _start_operator(self) -> None:
        self.launcher.start(
            "roost-operator", [console_script("roost-operator"), "--standalone"], self._env()
        )
        self._step("roost-operator started")

    def _apply(self, cluster: Cluster) -> None:
        documents: list[dict[str, Any]] = []
        try:
            ports = plan.hub_ports(len(self.fleet_plan), udp_port_free, ephemeral_range()[0])
        except ValueError as error:
            raise CliError(str(error)) from None
        for vehicle, running, port in zip(self.fleet_plan, self.state.vehicles, ports, strict=True):
            running.hub = f"{plan.HUB_HOST}:{port}"
            connections = {a.name: a.connection for a in running.autopilots}
            documents += [
                plan.vehicle_manifest(vehicle),
                plan.autopilot_manifest(vehicle, connections, running.hub),
            ]
        self._save()
        if self.options.mission is None:
            documents.append(plan.mission_manifest(len(self.fleet_plan)))
            self.mission_ref = (plan.MISSION_NAMESPACE, plan.MISSION_NAME)
        else:
            runtime = {kwok.RUNTIME_ANNOTATION: plan.MISSION_RUNTIME}
            own = missionrun.mission_manifests(self.options.mission, len(ports), runtime)
            documents += own
            self.mission_ref = missionrun.mission_ref(own)
        manifest = self.directory / "fleet.yaml"
        manifest.write_text(yaml.safe_dump_all(documents, sort_keys=False))
        cluster.kubectl("apply", "-f", str(manifest))
        namespace, name = self.mission_ref
        self._step(
            f"applied {len(self.fleet_plan)} Vehicles, their RedundantAutopilots and "
            f"Mission {namespace}/{name} ({manifest})"
        )

    def _start_agents(self) -> None:
        """One ``roost-agent`` per vehicle, as its node's DaemonSet pod would run.

        Cluster mode: it finds its Vehicle and RedundantAutopilot from its node name, flies
        with that spec (the ports its simulators bound and reported), drives a simulated
        bridge and reports status and Events. Its decision state lives in its own
        directory, as on a vehicle.
        """
        for vehicle in self.fleet_plan:
            self.launcher.start(
                f"roost-agent-{vehicle.name}",
                agent_argv(vehicle, self.directory / "agents" / vehicle.name),
                {**self._env(), "NODE_NAME": vehicle.node},
            )
        self._step(f"roost-agent running on {', '.join(v.node for v in self.fleet_plan)}")

    def _await_telemetry(self) -> None:
        """Record the telemetry URL each agent announces (it binds a free port itself)."""
        logs = {
            v.name: self.directory / "logs" / f"roost-agent-{v.name}.log" for v in self.fleet_plan
        }
        patience = ANNOUNCE_TIMEOUT_S + ANNOUNCE_PER_AGENT_S * len(self.state.vehicles)
        deadline = time.monotonic() + patience
        for vehicle in self.state.vehicles:
            while vehicle.telemetry is None and time.monotonic() < deadline:
                with contextlib.suppress(OSError):
                    vehicle.telemetry = announced_telemetry(logs[vehicle.name].read_text())
                if vehicle.telemetry is None:
                    time.sleep(0.1)
            if vehicle.telemetry is None:
                self.script.warn(f"the agent of {vehicle.name} announced no telemetry stream")
        self._save()

    def _start_dashboard(self) -> None:
        """``roost dashboard`` on the sandbox's cluster and agents; its URL is announced."""
        assert self.plane is not None
        port = self.options.dashboard_port
        if port and not port_free(port):  # another sandbox has it: any free port will do
            port = 0
        argv = [
            console_script("roost"),
            "--kubeconfig",
            str(self.plane.kubeconfig),
            "dashboard",
            "--port",
            str(port),
        ]
        for vehicle in self.state.vehicles:
            if vehicle.telemetry:
                argv += ["--agent", f"{vehicle.name}={vehicle.telemetry}"]
        proc = self.launcher.start("roost-dashboard", argv, {"COLUMNS": "400"})
        deadline = time.monotonic() + ANNOUNCE_TIMEOUT_S
        while self.state.dashboard is None:
            with contextlib.suppress(OSError):
                found = DASHBOARD_ANNOUNCE.search(proc.log.read_text())
                self.state.dashboard = found.group(1) if found else None
            if self.state.dashboard is not None:
                break
            if not proc.alive() or time.monotonic() > deadline:
                self.script.warn(f"the dashboard did not start; its log: {proc.log}")
                return
            time.sleep(0.1)
        self._save()
        self._step(f"dashboard on {self.state.dashboard}")

    def _start_mission(self, mission: str) -> None:
        """The mission's monitor, then one follower per vehicle flying through its hub."""
        names = [vehicle.name for vehicle in self.state.vehicles]
        connections = {
            vehicle.name: missionrun.hub_url(vehicle.hub)
            for vehicle in self.state.vehicles
            if vehicle.hub is not None
        }
        output = self.directory / "mission-results"
        try:
            monitor = missionrun.monitor_program(
                mission, names, output, trajectories=self.trajectories
            )
        except ValueError as error:
            raise CliError(str(error)) from None
        proc = self.launcher.start(monitor.name, list(monitor.argv), monitor.env)
        deadline = time.monotonic() + MONITOR_LISTENING_TIMEOUT_S
        address = None
        while address is None:
            if not proc.alive() or time.monotonic() > deadline:
                raise CliError(f"the {mission} monitor did not start; its log: {proc.log}")
            with contextlib.suppress(OSError):
                address = missionrun.listening_address(proc.log.read_text())
            time.sleep(0.1)
        for program in missionrun.follower_programs(
            mission, connections, address, trajectories=self.trajectories
        ):
            self.followers[program.env["SYNC_VEHICLE"]] = self.launcher.start(
                program.name, list(program.argv), program.env
            )
        self._step(
            f"{mission}: monitor on {address}, followers on {', '.join(names)}; "
            f"Table I and paths will be in {output}"
        )

    # ---- while running -----------------------------------------------------------------
    def _announce(self) -> None:
        assert self.plane is not None
        self.console.print(
            Group(
                Text.from_markup(
                    "\n[bold green]The Roost sandbox is running.[/] In another terminal:"
                ),
                Text(f"  export KUBECONFIG={self.plane.kubeconfig}", style="bold"),
                *(
                    [Text(f"  open {self.state.dashboard}   # the live dashboard", style="bold")]
                    if self.state.dashboard
                    else []
                ),
                Text("  kubectl get roost            # every Roost object", style="dim"),
                Text("  roost status --watch         # this fleet view", style="dim"),
                Text("  roost sandbox down           # stop it (or Ctrl-C here)", style="dim"),
                Text(
                    "MAVLink (each agent's hub; e.g. mavproxy.py --master=udpout:HOST:PORT): "
                    + ", ".join(f"{v.name} {v.hub}" for v in self.state.vehicles if v.hub)
                ),
                Text(f"Logs: {self.directory / 'logs'}, control plane: {self.plane.logs_dir}\n"),
            )
        )

    def _direct(self) -> None:
        """Start the script: take-off, then (unless --no-fault) the fault on the first vehicle.

        With a mission its followers take off themselves; the sandbox only slows vehicles
        with the mission's ``lag`` schedule (and ``roost fault`` breaks one by hand).
        """
        if self.options.mission is not None:
            primaries = {vehicle.name: vehicle.primary.name for vehicle in self.fleet_plan}

            def send(vehicle: str, message: dict[str, object]) -> None:
                sims.control(self.state, vehicle, primaries[vehicle], dict(message))

            monitor_log = self.directory / "logs" / "sync-monitor.log"

            def has_started() -> bool:
                with contextlib.suppress(OSError):
                    return missionrun.started(monitor_log.read_text())
                return False

            assert self.trajectories is not None
            schedule = (
                missionrun.lag_schedule(tuple(primaries), self.trajectories)
                if self.options.fault
                else ()
            )
            missionrun.LagInjector(schedule, send, self._stop, has_started).start()
            return
        cue = (
            Cue(vehicle=self.fleet_plan[0].name, after_s=self.options.fault_after_s)
            if self.options.fault
            else None
        )
        self.director = Director(self._fleet, self.state, self.script, cue)
        self.director.start()

    def _fleet(self) -> Fleet:
        assert self.plane is not None
        return Fleet(Target(self.plane.kubeconfig, "sandbox"))

    def _watch(self) -> None:
        """The live view (or, headless, each new line of the script) until stopped."""
        fleet = self._fleet()
        if self.options.live:
            view.live(
                self.console,
                fleet,
                interval_s=1.0,
                events=LIVE_EVENTS,
                story=self._story,
                stop=self._stop,
            )
            return
        shown = 0
        while not self._stop.wait(HEADLESS_POLL_S):
            self._check_processes()
            lines = self.script.lines()
            for message, _ in lines[shown:]:
                self.console.print(message, highlight=False)
            shown = len(lines)

    def _story(self) -> RenderableType | None:
        self._check_processes()
        return self.script.renderable()

    def _check_processes(self) -> None:
        self._stop_followers_out_of_mission()
        for proc in self.launcher.dead():
            if proc.name.startswith(MISSION_PROGRAM_PREFIX) and proc.returncode == 0:
                self.script.once(f"{proc.name} finished; its log: {proc.log}")
            else:
                self.script.warn(f"{proc.name} exited; its log: {proc.log}")

    def _stop_followers_out_of_mission(self) -> None:
        """Stop the follower of each vehicle the Mission took out, as the kubelet would
        stop its pod: the follower tells the monitor it leaves, and the others go on."""
        if not self.followers:
            return
        namespace, name = self.mission_ref
        if self._mission_fleet is None:
            self._mission_fleet = self._fleet()
        try:
            mission = self._mission_fleet.mission(namespace, name)
        except CliError:  # the API is briefly unreachable: look again next time
            return
        for vehicle in sorted(missionrun.vehicles_out(mission)):
            proc = self.followers.pop(vehicle, None)
            if proc is not None and proc.alive():
                self.launcher.stop(proc)
                self.script.say(
                    f"{vehicle} left mission {namespace}/{name}: its follower was stopped "
                    "(the others do not wait for it)",
                    "yellow",
                )

    # ---- teardown ----------------------------------------------------------------------
    def _down(self) -> None:
        self.state.phase = state.Phase.STOPPING
        self._save()
        pids = self.launcher.stop_all()
        if self.plane is not None:
            pids += list(self.plane.pids().values())
            self.plane.stop()
        state.remove(self.directory)
        self.console.print(f"[green]✓[/] sandbox stopped ({len(pids)} processes: {pids})")


MISSION_PROGRAM_PREFIX = "sync-"
"""Names of a mission's programs (:mod:`.missionrun`), which end by themselves."""


def udp_port_free(port: int) -> bool:
    """Whether a UDP port of the hubs' host is free now (:func:`plan.hub_ports`)."""
    return port_free(port, socket.SOCK_DGRAM, plan.HUB_HOST)


def agent_argv(vehicle: plan.VehiclePlan, state_dir: Path) -> list[str]:
    """Command line of the agent of one sandbox vehicle (KUBECONFIG and NODE_NAME in env)."""
    return [
        console_script("roost-agent"),
        "--cluster",
        "on",
        "--node-name",
        vehicle.node,
        "--state-dir",
        str(state_dir),
        "--bridge",
        "simulated",
        "--status-interval",
        "0",
        "--telemetry-port",
        "auto",
    ]


def announced_telemetry(log: str) -> str | None:
    """The telemetry URL an agent printed (``{"telemetry": URL}``), None before it did."""
    for line in log.splitlines():
        if line.startswith('{"telemetry"'):
            with contextlib.suppress(ValueError):
                return str(json.loads(line)["telemetry"])
    return None


def stop_recorded(recorded: state.SandboxState) -> list[int]:
    """Stop every process a (possibly dead) sandbox recorded, then its control plane.

    Identity is pid plus start time, so a pid the system has since reused is left alone.
    """
    stopped: list[int] = []
    for entry in reversed(recorded.processes):
        proc = ManagedProcess.from_state(entry)
        if proc.alive() and proc.pid is not None:
            stopped.append(proc.pid)
        proc.stop()
    plane = ControlPlane.attach(recorded.cluster_dir)
    if plane is not None:
        stopped += [p for n, p in plane.pids().items() if plane.alive().get(n)]
        plane.stop()
    state.remove(Path(recorded.directory))
    return stopped


def down(directory: Path, console: Console) -> None:
    """Stop the sandbox recorded in ``directory``: ask its ``up`` to stop, then make sure."""
    recorded = state.load(directory)
    if recorded is None:
        console.print(f"No sandbox recorded in {directory}: nothing to stop.")
        return
    if state.process_alive(recorded.pid, recorded.create_time):
        console.print(f"Asking the sandbox (pid {recorded.pid}) to stop…")
        with contextlib.suppress(ProcessLookupError):
            os.kill(recorded.pid, signal.SIGTERM)
        deadline = time.monotonic() + DOWN_TIMEOUT_S
        while state.process_alive(recorded.pid, recorded.create_time):
            if time.monotonic() > deadline:
                console.print(f"It did not stop within {DOWN_TIMEOUT_S:.0f} s; stopping it.")
                with contextlib.suppress(ProcessLookupError):
                    os.kill(recorded.pid, signal.SIGKILL)
                break
            time.sleep(0.2)
    leftovers = stop_recorded(state.load(directory) or recorded)
    if leftovers:
        console.print(f"Stopped leftover processes: {leftovers}")
    console.print("[green]✓[/] sandbox stopped")
