"""``roost-sim``: run simulated autopilots and inject faults into running ones.

    roost-sim run --stack px4 --sysid 1 --udp-out 127.0.0.1:14540 [--name fc1]
    roost-sim run --stack ardupilot --sysid 2 --pty
    roost-sim run --vehicle px4,ardupilot          # free ports, names fc1, fc2
    roost-sim run --config sims.yaml               # autopilots: [{name, stack, sysid,
                                                   #   udp_out, udp_bind, pty}, ...],
                                                   # fast_boot, preset_streams, battery,
                                                   # home_lat_deg, home_lon_deg
    roost-sim run --config fleet.yaml              # vehicles: [{name, autopilots: [...],
                                                   #   battery, home_lat_deg, ...}, ...]
    roost-sim run --vehicle px4,px4 --fast-boot    # boots in <1 s (default: as the
                                                   #   firmware: PX4 4 s, ArduCopter 41 s)
    roost-sim run --stack ardupilot --preset-streams --gcs-heartbeat
    roost-sim throttle fc1 0.5                     # pilot's stick; "none": no RC
    roost-sim fault fc1 sensor --value gyro
    roost-sim clear fc1 [sensor]                   # "all" as target: every autopilot
    roost-sim fly fc1 [--altitude 10]
    roost-sim status fc1                           # drone-1/px4-a: in a vehicles file
    roost-sim list

Timing options of ``run`` (also keys of the YAML file): ``--fast-boot``, ``--boot-s``,
``--position-wait-s``; ``--preset-streams`` makes ArduPilot stream without being asked
(as with its SRn_* parameters set); ``--gcs-heartbeat`` routes a ground station's
heartbeat onto ArduPilot links; ``--battery shared|per-autopilot`` for ``--vehicle`` and
config files (default shared).

One process can host many vehicles (a ``vehicles`` list: each has its own home,
battery and autopilots, and its autopilots' control sockets are
``<state dir>/<vehicle>/<autopilot>.sock``, so autopilot names may repeat across
vehicles): all its autopilots are ticked by one scheduler thread
(:mod:`roost_sim.scheduler`), which is what makes a 25-vehicle sandbox fit on two cores.

``run`` prints one JSON line per autopilot (vehicle when named, name, stack, sysid,
connection, device, control socket) and runs until SIGINT or SIGTERM. The other commands talk to the
autopilot's control socket (:mod:`roost_sim.control`) and print its state as JSON.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from roost_api.meta import Stack
from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.battery import Battery
from roost_sim.control import ControlServer, request, socket_path, state_dir
from roost_sim.faults import FaultKind
from roost_sim.model import SimConfig
from roost_sim.vehicle import BATTERY_LAYOUTS, start_vehicle_sims, stop_sims

ALL_TARGETS = "all"  # target name meaning every autopilot with a control socket


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host or "127.0.0.1", int(port)


def sim_config(options: dict[str, Any]) -> SimConfig:
    """The ``SimConfig`` for ``run`` options (command line or YAML keys)."""
    config = SimConfig.fast() if options.get("fast_boot") else SimConfig()
    for key in ("boot_s", "position_wait_s"):
        if options.get(key) is not None:
            setattr(config, key, float(options[key]))
    for key in _HOME_KEYS:
        if options.get(key) is not None:
            setattr(config, key, float(options[key]))
    config.preset_streams = bool(options.get("preset_streams"))
    config.gcs_heartbeat = bool(options.get("gcs_heartbeat"))
    return config


def _sim_from_entry(
    entry: dict[str, Any], defaults: dict[str, Any], battery: Battery
) -> SimulatedAutopilot:
    stack = Stack(entry.get("stack", "px4"))
    sysid = int(entry.get("sysid", 1))
    name = entry.get("name")
    config = sim_config({**defaults, **entry})
    if entry.get("pty"):
        return SimulatedAutopilot.pty(stack, sysid, name=name, config=config, battery=battery)
    out = _address(entry["udp_out"]) if entry.get("udp_out") else None
    host, port = _address(entry["udp_bind"]) if entry.get("udp_bind") else ("127.0.0.1", 0)
    return SimulatedAutopilot.udp(
        stack, sysid, target_port=out[1] if out else None, host=out[0] if out else host,
        bind_port=port, name=name, config=config, battery=battery,
    )  # fmt: skip


_OPTION_KEYS = ("fast_boot", "boot_s", "position_wait_s", "preset_streams", "gcs_heartbeat")
_HOME_KEYS = ("home_lat_deg", "home_lon_deg")  # config files only: where the vehicle starts
_VEHICLE_KEYS = (*_OPTION_KEYS, *_HOME_KEYS)  # a vehicle's own keys override the file's


@dataclass(frozen=True)
class VehicleEntry:
    """One vehicle of a ``run`` command: its autopilots share its options and battery."""

    name: str | None  # None: the single unnamed vehicle of a command line or flat file
    options: dict[str, Any]
    battery: str
    autopilots: list[dict[str, Any]]

    def target(self, autopilot: str) -> str:
        """The control-socket name of one of its autopilots (``vehicle/autopilot``)."""
        return f"{self.name}/{autopilot}" if self.name else autopilot


@dataclass(frozen=True)
class HostedAutopilot:
    """A started autopilot and its vehicle."""

    vehicle: str | None
    sim: SimulatedAutopilot

    @property
    def target(self) -> str:
        """The control target it is reached by (``vehicle/autopilot``, its label)."""
        return self.sim.label


def vehicle_entries(
    document: dict[str, Any], options: dict[str, Any], battery: str | None = None
) -> list[VehicleEntry]:
    """The vehicles a config document describes: a ``vehicles`` list (each with a
    ``name``, its ``autopilots`` and optionally its own ``battery``, home and timing
    keys), or a flat ``autopilots`` list (one unnamed vehicle). The file's top-level keys
    apply to every vehicle; ``options`` and ``battery`` come from the command line."""
    top = {**options, **{k: document[k] for k in _VEHICLE_KEYS if document.get(k) is not None}}
    described = document.get("vehicles")
    if described is None:
        described = [{"autopilots": document.get("autopilots", [])}]
    elif not described or not all(isinstance(v, dict) and v.get("name") for v in described):
        raise SystemExit("'vehicles' must be a list of vehicles, each with a 'name'")
    vehicles: list[VehicleEntry] = []
    for raw in described:
        name = str(raw["name"]) if raw.get("name") else None
        layout = battery or raw.get("battery") or document.get("battery") or "shared"
        if layout not in BATTERY_LAYOUTS:
            layouts = ", ".join(BATTERY_LAYOUTS)
            raise SystemExit(f"battery must be one of {layouts}, not {layout!r}")
        own = {k: raw[k] for k in _VEHICLE_KEYS if raw.get(k) is not None}
        autopilots = list(raw.get("autopilots") or [])
        vehicles.append(VehicleEntry(name, {**top, **own}, layout, autopilots))
    names = [v.name for v in vehicles]
    if len(set(names)) != len(names) or any(n and ("/" in n or n == ALL_TARGETS) for n in names):
        raise SystemExit(f"vehicle names must be unique, without '/', not {ALL_TARGETS!r}: {names}")
    return vehicles


def _check_unique(vehicle: VehicleEntry, sims: list[SimulatedAutopilot]) -> None:
    names = [s.name for s in sims]
    if len(set(names)) != len(names) or len({s.sysid for s in sims}) != len(sims):
        raise SystemExit(f"autopilot names and sysids must be unique in a vehicle: {names}")
    if ALL_TARGETS in (vehicle.target(n) for n in names) or any("/" in n for n in names):
        raise SystemExit(f"{ALL_TARGETS!r} is reserved as a target and '/' separates: {names}")


def build_sims(args: argparse.Namespace) -> list[HostedAutopilot]:
    """Start the autopilots a ``run`` command line (or its YAML config) describes."""
    options = {key: getattr(args, key) for key in _OPTION_KEYS}
    if args.vehicle:
        sims = start_vehicle_sims(
            args.vehicle.split(","),
            transport="pty" if args.pty else "udp",
            config=sim_config(options),
            battery=args.battery or "shared",
        )
        return [HostedAutopilot(None, sim) for sim in sims]
    if args.config:
        document = yaml.safe_load(Path(args.config).read_text()) or {}
    else:
        document = {
            "autopilots": [
                {
                    "stack": args.stack,
                    "sysid": args.sysid,
                    "name": args.name,
                    "udp_out": args.udp_out,
                    "udp_bind": args.udp_bind,
                    "pty": args.pty,
                }
            ]
        }
    hosted: list[HostedAutopilot] = []
    for vehicle in vehicle_entries(document, options, args.battery):
        shared = Battery()
        sims = [
            _sim_from_entry(
                entry, vehicle.options, shared if vehicle.battery == "shared" else Battery()
            )
            for entry in vehicle.autopilots
        ]
        _check_unique(vehicle, sims)
        for sim in sims:
            sim.label = vehicle.target(sim.name)
        hosted += [HostedAutopilot(vehicle.name, sim) for sim in sims]
    started: list[SimulatedAutopilot] = []
    try:
        for each in hosted:
            started.append(each.sim.start())
    except BaseException:
        stop_sims(started)
        raise
    return hosted


def _run(args: argparse.Namespace) -> int:
    directory = Path(args.state_dir) if args.state_dir else state_dir()
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    hosted = build_sims(args)
    servers: list[ControlServer] = []
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    try:
        for each in hosted:
            sim, path = each.sim, socket_path(each.target, directory)
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            server = ControlServer(sim, path).start()
            servers.append(server)
            line = {
                **({"vehicle": each.vehicle} if each.vehicle else {}),
                "name": sim.name,
                "stack": sim.stack.value,
                "sysid": sim.sysid,
                "connection": sim.connection,
                "device": sim.device,
                "control": str(server.path),
            }
            print(json.dumps(line), flush=True)
        done.wait()
    finally:
        for server in servers:
            server.stop()
        stop_sims([each.sim for each in hosted])
    return 0


def _control(args: argparse.Namespace, message: dict[str, Any]) -> int:
    wait = float(message.get("timeout") or 0.0)
    directory = Path(args.state_dir) if args.state_dir else state_dir()
    targets = _targets(directory) if args.target == ALL_TARGETS else [args.target]
    worst = 0
    for target in targets:
        path = socket_path(target, directory)
        try:
            answer = request(path, message, timeout=wait + 5.0)
        except OSError as exc:
            print(f"roost-sim: cannot reach {target} at {path}: {exc}", file=sys.stderr)
            worst = 2
            continue
        print(json.dumps(answer, indent=2))
        worst = max(worst, 0 if answer.get("ok") else 1)
    return worst


def _list(args: argparse.Namespace) -> int:
    directory = Path(args.state_dir) if args.state_dir else state_dir()
    for target in _targets(directory):
        print(target)
    return 0


def _targets(directory: Path) -> list[str]:
    """Every control target under ``directory``: ``name``, or ``vehicle/name``."""
    return sorted(str(p.relative_to(directory).with_suffix("")) for p in directory.rglob("*.sock"))


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``roost-sim``."""
    parser = argparse.ArgumentParser(prog="roost-sim", description=__doc__.split("\n")[0])
    parser.add_argument("--state-dir", help="directory of control sockets")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run simulated autopilots until interrupted")
    run.add_argument("--stack", choices=[s.value for s in Stack], default="px4")
    run.add_argument("--sysid", type=int, default=1)
    run.add_argument("--name", help="autopilot name (default <stack>-<sysid>)")
    run.add_argument("--udp-out", help="HOST:PORT the agent listens on (sim streams there)")
    run.add_argument("--udp-bind", help="HOST:PORT the sim binds (default 127.0.0.1:0)")
    run.add_argument("--pty", action="store_true", help="use a pseudo-terminal instead of UDP")
    run.add_argument("--vehicle", help="comma-separated stacks: one vehicle on free ports")
    run.add_argument("--config", help="YAML file with an 'autopilots' list")
    run.add_argument(
        "--fast-boot", action="store_true", help="boot in under a second (tests, sandbox)"
    )
    run.add_argument("--boot-s", type=float, help="seconds until STANDBY")
    run.add_argument("--position-wait-s", type=float, help="seconds until a position estimate")
    run.add_argument(
        "--preset-streams", action="store_true", help="ArduPilot streams without being asked"
    )
    run.add_argument(
        "--gcs-heartbeat", action="store_true", help="ArduPilot routes a GCS heartbeat here"
    )
    run.add_argument("--battery", choices=BATTERY_LAYOUTS, help="one shared battery (default)")
    run.set_defaults(func=_run)

    fault = sub.add_parser("fault", help="inject a fault into a running autopilot")
    fault.add_argument("target", help="autopilot name, or 'all'")
    fault.add_argument("kind", choices=[k.value for k in FaultKind])
    fault.add_argument("--value", help="fault parameter (see roost_sim.faults)")
    fault.set_defaults(
        func=lambda a: _control(a, {"op": "fault", "kind": a.kind, "value": a.value})
    )

    clear = sub.add_parser("clear", help="clear one fault kind or all faults")
    clear.add_argument("target", help="autopilot name, or 'all'")
    clear.add_argument("kind", nargs="?", choices=[k.value for k in FaultKind])
    clear.set_defaults(func=lambda a: _control(a, {"op": "clear", "kind": a.kind}))

    fly = sub.add_parser("fly", help="arm a running autopilot and take off")
    fly.add_argument("target", help="autopilot name")
    fly.add_argument("--altitude", type=float, help="metres (default: takeoff altitude)")
    fly.add_argument(
        "--wait", type=float, default=5.0, help="seconds to wait for start-up (default 5)"
    )
    fly.set_defaults(
        func=lambda a: _control(a, {"op": "fly", "value": a.altitude, "timeout": a.wait})
    )

    throttle = sub.add_parser("throttle", help="set the pilot's throttle stick")
    throttle.add_argument("target", help="autopilot name, or 'all'")
    throttle.add_argument("stick", help="0 (low) .. 1 (high), or 'none' for no RC")
    throttle.set_defaults(
        func=lambda a: _control(
            a, {"op": "throttle", "value": None if a.stick == "none" else a.stick}
        )
    )

    status = sub.add_parser("status", help="print an autopilot's state")
    status.add_argument("target", help="autopilot name, or 'all'")
    status.set_defaults(func=lambda a: _control(a, {"op": "status"}))

    listing = sub.add_parser("list", help="list autopilots with a control socket")
    listing.set_defaults(func=_list)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``roost-sim`` console script."""
    args = build_parser().parse_args(argv)
    result: int = args.func(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
