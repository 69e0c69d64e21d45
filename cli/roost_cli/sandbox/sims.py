"""The sandbox's simulated autopilots: a few ``roost-sim run`` processes, reached by socket.

The vehicles are split into groups of at most :data:`VEHICLES_PER_PROCESS`, and each
group runs in one ``roost-sim`` process (a ``vehicles`` config: each vehicle with its
own home, shared battery and two autopilots), streaming MAVLink over UDP to the ports
the agents listen on (the RedundantAutopilot's connection URLs). One process ticks all
its autopilots from one thread on a 2.5 ms grid (:mod:`roost_sim.scheduler`): a process
per vehicle, each waking at every stream's own due time, was most of a 25-vehicle
sandbox's CPU. Control sockets live in ``<dir>/sims/<vehicle>/`` because autopilot
names repeat across vehicles (every PX4 vehicle has a ``px4-a``).

Faults and take-off go through :mod:`roost_sim.control`, the same channel ``roost-sim
fault`` uses, so ``roost fault`` and the sandbox's scripted fault mean exactly what the
simulator documents (:mod:`roost_sim.faults`).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from roost_cli.errors import CliError
from roost_cli.sandbox import plan, state
from roost_cli.sandbox.processes import Launcher, console_script
from roost_localcluster.processes import ManagedProcess
from roost_sim.control import request, socket_path
from roost_sim.faults import FaultKind, check_value
from roost_sim.model import SimConfig

READY_TIMEOUT_S = 30.0
VEHICLES_PER_PROCESS = 10
"""A process's autopilots share one thread and one interpreter lock: ten vehicles (twenty
autopilots, about 8,000 MAVLink messages a second) keep it well under one core."""
SPACING_M = 8.0
"""Vehicles start this far apart on an east-west line (the dashboard's arena shows them)."""
CLEAR = "clear"
BIND_HOST = "127.0.0.1"


def home(index: int) -> tuple[float, float]:
    """Where sandbox vehicle ``index`` starts: :data:`SPACING_M` east of the one before."""
    base = SimConfig()
    metres_per_degree = 111_320.0 * math.cos(math.radians(base.home_lat_deg))
    return base.home_lat_deg, base.home_lon_deg + index * SPACING_M / metres_per_degree


def process_groups(
    fleet: Sequence[plan.VehiclePlan], per_process: int = VEHICLES_PER_PROCESS
) -> list[tuple[plan.VehiclePlan, ...]]:
    """The fleet in order, split into as few groups of at most ``per_process`` as can be,
    of sizes differing by at most one (25 vehicles: 8, 8 and 9)."""
    count = -(-len(fleet) // per_process)
    bounds = [k * len(fleet) // count for k in range(count + 1)]
    return [tuple(fleet[a:b]) for a, b in itertools.pairwise(bounds)]


def sim_config(vehicles: Sequence[plan.VehiclePlan]) -> dict[str, Any]:
    """``roost-sim run --config`` for some vehicles: their autopilots, each on a port it
    picks, each vehicle at its own home."""
    described = []
    for vehicle in vehicles:
        lat, lon = home(vehicle.index)
        autopilots = [
            {
                "name": autopilot.name,
                "stack": autopilot.stack.value,
                "sysid": autopilot.sysid,
                "udp_bind": f"{BIND_HOST}:0",
            }
            for autopilot in vehicle.autopilots
        ]
        described.append(
            {
                "name": vehicle.name,
                "home_lat_deg": lat,
                "home_lon_deg": round(lon, 9),
                "autopilots": autopilots,
            }
        )
    return {
        # A demo should not wait for GPS: sub-second start-up. ArduPilot streams as with
        # its SRn_* stream-rate parameters set, for agents that do not request streams.
        "fast_boot": True,
        "preset_streams": True,
        "vehicles": described,
    }


def start(
    launcher: Launcher, vehicles: Sequence[plan.VehiclePlan], directory: Path
) -> list[state.SandboxVehicle]:
    """Start one simulator process for ``vehicles``; return once each autopilot answers
    with the port it bound."""
    sims_dir = directory / "sims"
    sims_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    first, last = vehicles[0].name, vehicles[-1].name
    label = first if first == last else f"{first}..{last}"
    config = sims_dir / f"{label}.yaml"
    config.write_text(yaml.safe_dump(sim_config(vehicles), sort_keys=False))
    proc = launcher.start(
        f"roost-sim-{label}",
        [console_script("roost-sim"), "--state-dir", str(sims_dir), "run", "--config", str(config)],
        {},
    )
    deadline = time.monotonic() + READY_TIMEOUT_S
    return [_recorded(proc, vehicle, sims_dir, deadline) for vehicle in vehicles]


def _recorded(
    proc: ManagedProcess, vehicle: plan.VehiclePlan, sims_dir: Path, deadline: float
) -> state.SandboxVehicle:
    """What the state file records of one vehicle's started simulators."""
    controls = {
        a.name: socket_path(f"{vehicle.name}/{a.name}", sims_dir) for a in vehicle.autopilots
    }
    connections = {
        name: _reported_connection(proc, vehicle.name, name, control, deadline)
        for name, control in controls.items()
    }
    return state.SandboxVehicle(
        name=vehicle.name,
        node=vehicle.node,
        stack=vehicle.stack.value,
        autopilots=[
            state.SimulatedAutopilot(
                name=autopilot.name,
                stack=autopilot.stack.value,
                sysid=autopilot.sysid,
                connection=connections[autopilot.name],
                bridge_channel=autopilot.bridge_channel,
                control=str(controls[autopilot.name]),
            )
            for autopilot in vehicle.autopilots
        ],
    )


def _reported_connection(
    proc: ManagedProcess, vehicle: str, autopilot: str, control: Path, deadline: float
) -> str:
    """The connection URL a started simulator reports for the port it bound itself."""
    while True:
        try:
            answer = request(control, {"op": "status"}, timeout=1.0)
        except OSError:
            if not proc.alive():
                raise CliError(
                    f"the simulators of {vehicle} exited; log {proc.log}:\n{proc.log_tail()}"
                ) from None
            if time.monotonic() > deadline:
                raise CliError(
                    f"simulator {vehicle}/{autopilot} did not answer on {control} within "
                    f"{READY_TIMEOUT_S:.0f} s; log {proc.log}"
                ) from None
            time.sleep(0.1)
            continue
        connection = str(answer.get("state", {}).get("connection") or "")
        if not connection.startswith(f"udpout://{BIND_HOST}:"):
            raise CliError(f"simulator {vehicle}/{autopilot} reported no UDP port: {answer}")
        return connection


def _find(recorded: state.SandboxState, vehicle: str, autopilot: str) -> state.SimulatedAutopilot:
    found = recorded.vehicle(vehicle)
    if found is None:
        names = ", ".join(v.name for v in recorded.vehicles) or "none yet"
        raise CliError(f"{vehicle} is not a sandbox vehicle (sandbox vehicles: {names})")
    for candidate in found.autopilots:
        if candidate.name == autopilot:
            return candidate
    names = ", ".join(a.name for a in found.autopilots)
    raise CliError(f"{vehicle} has no autopilot {autopilot} (its autopilots: {names})")


def control(
    recorded: state.SandboxState, vehicle: str, autopilot: str, message: dict[str, Any]
) -> dict[str, Any]:
    """Send one control request to a sandbox simulator; its answer (``ok`` and ``state``)."""
    target = _find(recorded, vehicle, autopilot)
    try:
        answer = request(Path(target.control), message)
    except (OSError, ValueError) as error:
        raise CliError(
            f"cannot reach the simulator of {vehicle}/{autopilot} at {target.control}: "
            f"{error}. Is the sandbox still running? (`roost sandbox up`)"
        ) from error
    if not answer.get("ok"):
        raise CliError(f"{vehicle}/{autopilot} refused: {answer.get('error', answer)}")
    return answer


def fault_message(kind: str, value: str | None) -> dict[str, Any]:
    """The control request for ``roost fault``: a FaultKind, or ``clear`` (all faults)."""
    if kind == CLEAR:
        return {"op": "clear", "kind": None}
    try:
        FaultKind(kind)
    except ValueError:
        kinds = ", ".join([*(k.value for k in FaultKind), CLEAR])
        raise CliError(f"unknown fault {kind!r}: one of {kinds}") from None
    try:
        check_value(kind, value)
    except ValueError as error:
        raise CliError(f"--value: {error}") from None
    return {"op": "fault", "kind": kind, "value": value}


def fly(recorded: state.SandboxVehicle) -> None:
    """Arm and take off every autopilot of the vehicle (its standby flies along)."""
    for autopilot in recorded.autopilots:
        answer = request(Path(autopilot.control), {"op": "fly"})
        if not answer.get("ok"):
            raise CliError(f"{recorded.name}/{autopilot.name} did not take off: {answer}")
