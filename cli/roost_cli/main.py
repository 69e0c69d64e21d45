"""``roost``: the fleet at a glance, safety requests, and the local sandbox.

Commands are thin: they resolve the cluster, call :mod:`roost_cli.actions` or
:mod:`roost_cli.view`, and print. Failures the user can fix are
:class:`~roost_cli.errors.CliError` with a message saying how.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
from collections.abc import Callable
from dataclasses import asdict
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text
from typer._click.exceptions import NoArgsIsHelpError  # typer >= 0.29 vendors click

from roost_api.autopilot import CommandAction
from roost_api.telemetry import Origin
from roost_cli import actions, keys, records, render, tables, view
from roost_cli.cluster import Fleet, in_cluster_target, resolve_kubeconfig
from roost_cli.errors import CliError
from roost_cli.sandbox import plan, runner, sims
from roost_cli.sandbox import state as sandbox_state


def _error(message: str, code: int) -> SystemExit:
    line = Text.assemble(("error:", "bold red"), " ", message)  # no markup read from message
    Console(stderr=True).print(line, highlight=False, soft_wrap=True)
    return SystemExit(code)


class RoostApp(typer.Typer):
    """The typer app: every user error is one line on stderr and a non-zero exit.

    :class:`CliError` exits 1; a bad command line (unknown option, a value out of range)
    exits 2 with the parser's message and where to find help, not a usage panel.
    """

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        kwargs.setdefault("standalone_mode", False)  # parser errors come back here
        try:
            result = super().__call__(*args, **kwargs)
        except CliError as error:
            raise _error(str(error), 1) from None
        except NoArgsIsHelpError as error:
            error.show()
            raise SystemExit(error.exit_code) from None
        except typer.TyperException as error:
            context = getattr(error, "ctx", None)
            hint = f" (see `{context.command_path} --help`)" if context is not None else ""
            message = " ".join(error.format_message().split())
            raise _error(f"{message}{hint}", error.exit_code) from None
        except typer.Abort:
            raise _error("aborted", 1) from None
        if isinstance(result, int):  # typer.Exit(code) and --help, outside standalone mode
            raise SystemExit(result)
        return result


def finite(low: float, high: float) -> Callable[[str], float]:
    """A typer parser for a finite number from ``low`` to ``high`` (inf and nan refused)."""

    def parse(text: str) -> float:
        try:
            number = float(text)
        except ValueError:
            raise typer.BadParameter(f"{text!r} is not a number") from None
        if not math.isfinite(number) or not low <= number <= high:
            raise typer.BadParameter(f"{text} is not a number from {low:g} to {high:g}")
        return number

    return parse


app = RoostApp(
    name="roost",
    help="Roost: a Kubernetes operator for drone fleets with redundant autopilots.",
    no_args_is_help=True,
    rich_markup_mode="rich",
    pretty_exceptions_show_locals=False,
)
sandbox_app = typer.Typer(
    help="A local fleet: a real control plane, simulated vehicles, the operator and agents.",
    no_args_is_help=True,
)
app.add_typer(sandbox_app, name="sandbox")
keys_app = typer.Typer(
    help="Each Vehicle's MAVLink signing key, in a Secret of its own (docs/mavlink-signing.md).",
    no_args_is_help=True,
)
app.add_typer(keys_app, name="keys")
console = Console()


class Output(StrEnum):
    """How ``status``, ``missions`` and ``records list`` print."""

    TABLE = "table"
    JSON = "json"


OutputOption = Annotated[Output, typer.Option("--output", "-o")]
NamespaceOption = Annotated[
    str | None, typer.Option("--namespace", "-n", help="Only this namespace.")
]
RecordsUrlOption = Annotated[
    str | None,
    typer.Option(
        "--records-url",
        envvar="ROOST_RECORDS_URL",
        help="The operator's records server, when reachable directly (else the pod proxy).",
    ),
]
OperatorNamespaceOption = Annotated[
    str, typer.Option("--operator-namespace", help="Where the operator runs.")
]


class Context:
    """Options common to every command (set by the callback)."""

    def __init__(
        self, kubeconfig: Path | None, sandbox_dir: Path, context: str | None = None
    ) -> None:
        self.kubeconfig = kubeconfig
        self.sandbox_dir = sandbox_dir
        self.context = context

    def fleet(self) -> Fleet:
        running = sandbox_state.running(self.sandbox_dir)
        kubeconfig = Path(running.kubeconfig) if running and running.kubeconfig else None
        return Fleet(
            resolve_kubeconfig(self.kubeconfig, os.environ, kubeconfig, Path.home(), self.context)
        )


@app.callback()
def main(
    ctx: typer.Context,
    kubeconfig: Annotated[
        Path | None,
        typer.Option(help="Kubeconfig to use (default: $KUBECONFIG, a running sandbox, ~/.kube)."),
    ] = None,
    context: Annotated[
        str | None,
        typer.Option(help="Kubeconfig context to use (default: its current-context)."),
    ] = None,
    sandbox_dir: Annotated[
        Path | None,
        typer.Option(
            envvar=sandbox_state.DIR_ENV, help="Sandbox state directory (default ./.sandbox)."
        ),
    ] = None,
) -> None:
    """Roost: a Kubernetes operator for drone fleets with redundant autopilots."""
    ctx.obj = Context(kubeconfig, sandbox_state.sandbox_dir(sandbox_dir), context)


def _context(ctx: typer.Context) -> Context:
    obj = ctx.find_object(Context)
    assert obj is not None, "the callback always sets the context"
    return obj


def _print_json(rows: object) -> None:
    sys.stdout.write(json.dumps(rows, indent=2, default=str) + "\n")


def _missions(ctx: typer.Context, namespace: str | None) -> list[dict[str, Any]]:
    """The Missions a listing command shows (one namespace's, if given and existing)."""
    fleet = _context(ctx).fleet()
    if namespace is not None:
        fleet.require_namespace(namespace)
    return fleet.missions(namespace)


@app.command()
def status(
    ctx: typer.Context,
    watch: Annotated[bool, typer.Option("--watch", "-w", help="Refresh until Ctrl-C.")] = False,
    interval: Annotated[
        float, typer.Option(parser=finite(0.2, 3600), help="Seconds between refreshes.")
    ] = 1.0,
    events: Annotated[
        int, typer.Option(min=0, max=view.MAX_EVENTS, help="Recent Roost events to show.")
    ] = 0,
    output: OutputOption = Output.TABLE,
) -> None:
    """The fleet: each vehicle's node, active autopilot, health, mission and last failover."""
    fleet = _context(ctx).fleet()
    if watch:
        with contextlib.suppress(KeyboardInterrupt):
            view.live(console, fleet, interval_s=interval, events=events or view.DEFAULT_EVENTS)
        return
    snapshot = view.read(fleet, events)
    if output is Output.JSON:
        _print_json([asdict(row) | {"health": row.health} for row in snapshot.fleet])
        return
    console.print(render.fleet_table(snapshot.fleet, title=view.title_for(fleet)))
    if snapshot.events:
        console.print(render.events_table(snapshot.events))


@app.command()
def missions(
    ctx: typer.Context,
    namespace: NamespaceOption = None,
    output: OutputOption = Output.TABLE,
) -> None:
    """Missions: phase, assigned vehicles and their state, why."""
    rows = tables.mission_rows(_missions(ctx, namespace), datetime.now(UTC))
    if output is Output.JSON:
        _print_json([asdict(row) for row in rows])
        return
    console.print(render.missions_table(rows))


records_app = typer.Typer(
    help="Flight records: one bundle per Mission that flew (docs/mission-records.md).",
    no_args_is_help=True,
)
app.add_typer(records_app, name="records")


@records_app.command("list")
def records_list(
    ctx: typer.Context,
    namespace: NamespaceOption = None,
    output: OutputOption = Output.TABLE,
) -> None:
    """Missions with a flight record: its state, bundle and what is pending or missing."""
    rows = records.record_rows(_missions(ctx, namespace))
    if output is Output.JSON:
        _print_json([asdict(row) for row in rows])
        return
    table = Table(
        "NAMESPACE", "MISSION", "PHASE", "RECORD", "VEHICLES", "BUNDLE", "UPLOAD", "MESSAGE"
    )
    for row in rows:
        table.add_row(
            row.namespace,
            row.mission,
            row.phase,
            row.records,
            row.vehicles,
            row.bundle,
            row.upload or "-",
            row.message,
        )
    console.print(table if rows else "no Mission has a flight record yet")


@records_app.command("get")
def records_get(
    ctx: typer.Context,
    *,
    ref: Annotated[str, typer.Argument(help="mission/NAME or mission/NAMESPACE/NAME.")],
    out: Annotated[Path, typer.Option("--output-dir", "-o", help="Where to write the bundle.")],
    namespace: Annotated[str, typer.Option("--namespace", "-n")] = "default",
    operator_namespace: OperatorNamespaceOption = "roost-system",
    records_url: RecordsUrlOption = None,
) -> None:
    """Fetch a Mission's record (its bundle) into a directory; resumes when run again."""
    kind, _, rest = ref.partition("/")
    if kind not in ("mission", "missions") or not rest:
        raise CliError(f"{ref!r}: write mission/NAME or mission/NAMESPACE/NAME")
    ns, name = actions.split_mission_ref(rest, namespace)
    fleet = _context(ctx).fleet()
    bundle = records.bundle_of(fleet.mission(ns, name))
    server: records.Server
    if records_url:
        server = records.DirectServer(records_url)
    else:
        pod = fleet.operator_pod(operator_namespace)
        server = records.ProxyServer(fleet.kube, operator_namespace, pod)
    fetched = records.download(server, bundle, out)
    console.print(
        f"[bold]mission {ns}/{name}[/]: bundle {bundle}: {fetched.files} files, "
        f"{fetched.bytes} bytes in {out} (manifest.json lists them)"
    )
    for line in fetched.missing:
        console.print(Text.assemble(("missing: ", "yellow"), line), highlight=False)


@app.command()
def abort(
    ctx: typer.Context,
    mission: Annotated[str, typer.Argument(help="NAME or NAMESPACE/NAME of the Mission.")],
    namespace: Annotated[str, typer.Option("--namespace", "-n")] = "default",
) -> None:
    """Abort a mission: every assigned vehicle runs its safety routine (hold, then land)."""
    ns, name = actions.split_mission_ref(mission, namespace)
    actions.request_abort(_context(ctx).fleet(), ns, name)
    console.print(
        f"[bold]mission {ns}/{name}[/]: abort requested. The operator asks every assigned "
        "vehicle's agent to run its safety routine; follow it with `roost missions`."
    )


@app.command()
def estop(
    ctx: typer.Context,
    vehicle: Annotated[
        list[str] | None, typer.Option("--vehicle", "-v", help="Vehicle to stop (repeatable).")
    ] = None,
    all_vehicles: Annotated[bool, typer.Option("--all", help="Stop every vehicle.")] = False,
    yes: Annotated[bool, typer.Option("--yes", "-y", help="Do not ask for confirmation.")] = False,
    wait: Annotated[
        float,
        typer.Option(
            parser=finite(0, 3600), help="Seconds to wait for the agents' acknowledgement."
        ),
    ] = actions.ACK_TIMEOUT_S,
) -> None:
    """EMERGENCY STOP: force-disarm the active autopilot. Motors stop, even in flight."""
    fleet = _context(ctx).fleet()
    targets = actions.select_targets(
        actions.autopilots_by_vehicle(fleet.autopilots()), vehicle or [], all_vehicles
    )
    names = ", ".join(targets)
    if not yes:
        if not sys.stdin.isatty():
            raise CliError(f"refusing to e-stop {names} without confirmation: add --yes")
        typer.confirm(
            f"Force-disarm {names}? Motors stop immediately; a flying vehicle falls.", abort=True
        )
    sent = actions.send_command(fleet, targets, CommandAction.EMERGENCY_STOP)
    console.print(f"[bold red]EmergencyStop[/] sent to {names}")
    if wait <= 0:
        return
    table = Table(header_style="bold")
    table.add_column("VEHICLE", no_wrap=True)
    table.add_column("REDUNDANTAUTOPILOT", no_wrap=True)
    table.add_column("COMMAND ID", no_wrap=True)
    table.add_column("RESULT", no_wrap=True)
    table.add_column("MESSAGE")
    acks = actions.await_acknowledgements(fleet, targets, sent, timeout_s=wait)
    for ack in acks:
        style = "green" if ack.result == "Executed" else "bold red"
        table.add_row(
            ack.vehicle, ack.autopilot, ack.command_id, f"[{style}]{ack.result}[/]", ack.message
        )
    console.print(table)
    if any(ack.result != "Executed" for ack in acks):
        raise typer.Exit(code=2)


@app.command()
def fault(
    ctx: typer.Context,
    vehicle: Annotated[str, typer.Argument(help="Sandbox vehicle, e.g. drone-1.")],
    autopilot: Annotated[str, typer.Argument(help="Its autopilot, e.g. px4-a.")],
    kind: Annotated[
        str,
        typer.Argument(
            help="silence, freeze, sensor, state, reboot, garbage, loss, jitter, spoof, "
            "battery, lag (--value percent of the normal speed), or clear (remove every fault)."
        ),
    ],
    value: Annotated[
        str | None, typer.Option(help="Fault parameter, e.g. --value gyro for sensor.")
    ] = None,
) -> None:
    """Inject a fault into a sandbox vehicle's simulated autopilot (or clear its faults)."""
    message = sims.fault_message(kind, value)  # a bad kind or value is refused first
    directory = _context(ctx).sandbox_dir
    recorded = sandbox_state.running(directory)
    if recorded is None:
        raise CliError(
            f"no sandbox is running in {directory}: `roost fault` works on sandbox vehicles. "
            "Start one with `roost sandbox up` (or pass --sandbox-dir)"
        )
    answer = sims.control(recorded, vehicle, autopilot, message)
    faults = answer.get("state", {}).get("faults") or {}
    shown = ", ".join(f"{k}={v}" if v else k for k, v in faults.items()) or "none"
    console.print(f"{vehicle}/{autopilot}: faults now {shown}. Watch with `roost status -w`.")


def _agent_flag(text: str) -> tuple[str, str]:
    vehicle, sep, url = text.partition("=")
    if not sep or not vehicle or not url.startswith(("ws://", "wss://")):
        raise typer.BadParameter(f"expected VEHICLE=ws://HOST:PORT/, not {text!r}")
    return vehicle, url


def _origin_flag(text: str) -> Origin:
    try:
        return Origin.parse(text)
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None


@app.command()
def dashboard(
    ctx: typer.Context,
    *,
    host: Annotated[str, typer.Option(help="Address to serve on.")] = "127.0.0.1",
    port: Annotated[
        int, typer.Option(min=0, max=65535, help="Port to serve on (0: a free one).")
    ] = 8765,
    read_only: Annotated[
        bool, typer.Option("--read-only", help="No actions: only watch the fleet.")
    ] = False,
    agent: Annotated[
        list[str] | None,
        typer.Option(
            help="VEHICLE=ws://HOST:PORT/: where a vehicle's agent streams its telemetry "
            "(repeatable; default: the sandbox's agents, then each Vehicle's "
            "roost.dev/telemetry annotation)."
        ),
    ] = None,
    origin: Annotated[
        str | None,
        typer.Option(help="LAT,LON of the arena's 0,0 (default: the first agent's origin)."),
    ] = None,
    tiles: Annotated[
        str | None,
        typer.Option(help="XYZ tile URL template ({z}/{x}/{y}) drawn under the arena."),
    ] = None,
    cluster: Annotated[
        bool,
        typer.Option(
            help="Read the cluster (--no-cluster: only the --agent streams, read-only; "
            "for standalone agents)."
        ),
    ] = True,
    in_cluster: Annotated[
        bool,
        typer.Option(
            "--in-cluster", help="Use the pod's service account (the chart's Deployment)."
        ),
    ] = False,
    records_url: RecordsUrlOption = None,
    operator_namespace: OperatorNamespaceOption = "roost-system",
) -> None:
    """A live fleet view in the browser: arena, fleet, missions, timeline, guarded actions.

    It acts (abort, e-stop) with your kubeconfig's identity; --read-only removes the
    actions. See docs/dashboard.md.
    """
    from roost_cli.dashboard import server  # noqa: PLC0415 - imports starlette and uvicorn
    from roost_cli.dashboard.sources import Endpoints  # noqa: PLC0415

    context = _context(ctx)
    if not cluster:
        fleet = None
    elif in_cluster:
        fleet = Fleet(in_cluster_target())
    else:
        fleet = context.fleet()
    flags = dict(_agent_flag(text) for text in agent or [])
    if fleet is None and not flags and not records_url:
        raise CliError(
            "--no-cluster shows only the agents' streams (name them with --agent) "
            "and the records at --records-url"
        )

    def sandbox_endpoints() -> dict[str, str]:
        recorded = sandbox_state.running(context.sandbox_dir)
        if recorded is None or fleet is None or recorded.kubeconfig is None:
            return {}
        if Path(recorded.kubeconfig).resolve() not in {
            path.resolve() for path in fleet.target.all_files
        }:
            return {}  # another cluster than the sandbox's
        return {v.name: v.telemetry for v in recorded.vehicles if v.telemetry}

    settings = server.Settings(
        host=host,
        port=port,
        read_only=read_only,
        origin=_origin_flag(origin) if origin else None,
        tiles=tiles,
        records_url=records_url,
        operator_namespace=operator_namespace,
    )
    if fleet is None:
        where, mode = server.NO_CLUSTER, "read-only"
    else:
        where = fleet.server
        mode = (
            "read-only" if read_only else f"acting as the kubeconfig's user ({fleet.target.shown})"
        )
    with contextlib.suppress(KeyboardInterrupt):
        server.serve(
            fleet,
            settings,
            Endpoints(flags, sandbox_endpoints, fleet.api_proxy() if fleet else None),
            announce=lambda url: console.print(
                f"Roost dashboard on {url} — {where}, {mode}. Ctrl-C stops it.",
                highlight=False,
                soft_wrap=True,
            ),
        )


@sandbox_app.command("up")
def sandbox_up(
    ctx: typer.Context,
    *,
    vehicles: Annotated[
        int, typer.Option(min=1, max=plan.MAX_VEHICLES, help="Simulated vehicles to run.")
    ] = runner.DEFAULT_VEHICLES,
    fault: Annotated[
        bool, typer.Option(help="Inject an autopilot fault on one vehicle to show a failover.")
    ] = True,
    fault_after: Annotated[
        float,
        typer.Option(parser=finite(0, 86400), help="Seconds of normal flight before the fault."),
    ] = runner.DEFAULT_FAULT_AFTER_S,
    live: Annotated[
        bool, typer.Option(help="Show the live fleet view (--no-live prints plain lines).")
    ] = True,
    mission: Annotated[
        str | None,
        typer.Option(
            help="Run a reference mission's own programs (sync-paths) with lag faults "
            "creating delays (--no-fault: none)."
        ),
    ] = None,
    trajectories: Annotated[
        Path | None,
        typer.Option(
            help="With --mission: a directory of <vehicle>.csv trajectories to fly instead "
            "of the mission's own (the lag faults follow their legs)."
        ),
    ] = None,
    dashboard: Annotated[
        bool, typer.Option(help="Serve `roost dashboard` for the sandbox (its URL is printed).")
    ] = True,
    dashboard_port: Annotated[
        int, typer.Option(min=0, max=65535, help="The dashboard's port (0: a free one).")
    ] = runner.DEFAULT_DASHBOARD_PORT,
) -> None:
    """Start the sandbox and keep it running until Ctrl-C (`make demo` runs this)."""
    if trajectories is not None and mission is None:
        raise CliError("--trajectories is for a mission's own programs: add --mission")
    options = runner.Options(
        directory=_context(ctx).sandbox_dir,
        vehicles=vehicles,
        fault=fault,
        fault_after_s=fault_after,
        live=live and console.is_terminal,
        mission=mission,
        trajectories=trajectories.resolve() if trajectories is not None else None,
        dashboard=dashboard,
        dashboard_port=dashboard_port,
    )
    runner.Sandbox(options, console).run()


@sandbox_app.command("down")
def sandbox_down(ctx: typer.Context) -> None:
    """Stop a running sandbox (from another terminal) and every process it started."""
    runner.down(_context(ctx).sandbox_dir, console)


KeysNamespace = Annotated[
    str, typer.Option("--namespace", "-n", help="Namespace of the agents (the chart's release).")
]


def _passphrase_hint(namespace: str, name: str) -> str:
    return (
        f"for a ground station: kubectl -n {namespace} get secret {name} "
        "-o jsonpath='{.data.passphrase}' | base64 -d"
    )


@keys_app.command("create")
def keys_create(
    ctx: typer.Context, vehicle: str, namespace: KeysNamespace = "roost-system"
) -> None:
    """Create VEHICLE's signing key (a random passphrase and its SHA-256 as the key)."""
    fleet = _context(ctx).fleet()
    name = keys.secret_name(vehicle)
    if fleet.secret(namespace, name) is not None:
        raise CliError(f"{namespace}/{name} exists: `roost keys rotate {vehicle}` replaces it")
    fleet.create_secret(keys.key_secret(vehicle, namespace, keys.new_passphrase()))
    console.print(
        f"created Secret {namespace}/{name}; {_passphrase_hint(namespace, name)}. "
        f"Its agent gets the key once Vehicle {vehicle} has spec.components.signingKeys "
        "enabled (its key pod hands the key to that vehicle's node only)"
    )


@keys_app.command("rotate")
def keys_rotate(
    ctx: typer.Context, vehicle: str, namespace: KeysNamespace = "roost-system"
) -> None:
    """Give VEHICLE a new key; the old one stays accepted (as ``previous``) until the
    next rotation, so autopilots and ground stations can be moved over one by one."""
    fleet = _context(ctx).fleet()
    name = keys.secret_name(vehicle)
    current = fleet.secret(namespace, name)
    if current is None:
        raise CliError(f"{namespace}/{name} does not exist: `roost keys create {vehicle}`")
    fleet.patch_secret(namespace, name, keys.rotation_patch(current, keys.new_passphrase()))
    console.print(
        f"rotated Secret {namespace}/{name}: the agent takes the new key within about a "
        f"minute, without a restart; {_passphrase_hint(namespace, name)}"
    )
