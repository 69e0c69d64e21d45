"""``roost-agent``: run the node agent, in a cluster or standalone from a config file or flags.

In a cluster (``--cluster``; by default when there is neither ``--config`` nor
``--autopilot``, ``NODE_NAME`` is set and a service account or ``$KUBECONFIG`` is at
hand) the agent finds the Vehicle on its node and its RedundantAutopilot, flies with that
spec and reports status and Events to it (:mod:`roost_agent.publisher`); with the API
unreachable at start it flies on with the spec saved in ``--state-dir``.

Standalone the agent needs no Kubernetes: give it a RedundantAutopilot (the whole object
or just its spec, YAML or JSON) or describe the autopilots with ``--autopilot`` flags. It
keeps its last spec and decision state in ``--state-dir``; started with neither config
nor flags it flies on with the spec saved there (an agent restarted while the cluster is
unreachable).

Output: one JSON object per line on stdout, ``{"event": ...}`` for every event and
``{"status": ..., "links": ...}`` (status and per-link message counters) every
``--status-interval`` seconds. Logs go to stderr (so does
anything a library prints). SIGHUP re-reads the config file (thresholds, policy,
primary, and a ``command`` executed once per id); SIGTERM/SIGINT stop the agent.

A configuration the agent cannot fly with (an autopilot connection URL it could not
open, a signing key it cannot use) is refused at start with one line on stderr and exit
status 2, never a traceback. MAVLink signing: ``--signing`` and ``--signing-keys`` (see
:mod:`roost_agent.signing`). Optional local endpoints, both off by default: Prometheus
metrics (``--metrics-port``, :mod:`roost_agent.metrics`) and the live telemetry stream
``roost dashboard`` follows (``--telemetry-port``, :mod:`roost_agent.telemetry`). Flight
records (``--records-dir``, :mod:`roost_agent.records_recorder`), served over HTTP on
``--records-port``, announced on stdout as ``{"records": URL}``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import sys
import threading
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import yaml

from roost_agent.agent import Agent
from roost_agent.bridge import Bridge, GpioBridge, SimulatedBridge
from roost_agent.hub_policy import HubConfigError
from roost_agent.records import DEFAULT_BUDGET_MB, DEFAULT_KEEP_FREE_PERCENT, DEFAULT_PORT
from roost_agent.signing import (
    DEFAULT_KEY_DIR,
    KeyWatcher,
    SigningError,
    SigningMode,
    load_signing,
)
from roost_agent.spec_changes import connection_problems, restore_state
from roost_agent.state import STATE_FILE_NAME, StateFile
from roost_api.plain import AutopilotSpec, RedundantAutopilotSpec
from roost_api.plain_check import PlainValidationError

if TYPE_CHECKING:
    from roost_agent.kube import AgentKube
    from roost_agent.records_recorder import FlightRecorder
    from roost_agent.records_server import RecordsServer
    from roost_agent.telemetry import TelemetryServer

log = logging.getLogger("roost_agent")

DEFAULT_STATE_DIR = "/var/lib/roost-agent"


def load_spec(path: Path) -> tuple[RedundantAutopilotSpec, int | None]:
    """Read a RedundantAutopilot (or its bare spec) from YAML/JSON; returns (spec, generation)."""
    doc = yaml.safe_load(path.read_text())
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a mapping")
    generation = None
    if "spec" in doc:
        metadata = doc.get("metadata") or {}
        generation = metadata.get("generation")
        doc = doc["spec"]
    return RedundantAutopilotSpec.from_api(doc), generation


def parse_autopilot(text: str) -> AutopilotSpec:
    """``name=fc1,stack=px4,connection=udp://127.0.0.1:14541,sysid=1,channel=0[,component=1]``."""
    fields: dict[str, Any] = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected key=value in {part!r}")
        fields[key.strip()] = value.strip()
    renames = {"channel": "bridge_channel", "component": "component_id"}
    fields = {renames.get(k, k): v for k, v in fields.items()}
    try:
        return AutopilotSpec.from_api(fields)
    except PlainValidationError as exc:
        raise argparse.ArgumentTypeError(f"bad --autopilot {text!r}: {exc}") from exc


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="roost-agent",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--config", type=Path, help="RedundantAutopilot or its spec (YAML/JSON)")
    parser.add_argument(
        "--autopilot",
        action="append",
        type=parse_autopilot,
        default=[],
        metavar="name=..,stack=..,connection=..,sysid=..,channel=..",
        help="an autopilot (repeat; instead of --config)",
    )
    parser.add_argument("--primary", help="primary autopilot with --autopilot (default: first)")
    parser.add_argument("--vehicle", default=socket.gethostname(), help="vehicle name (flags)")
    parser.add_argument(
        "--state-dir",
        type=Path,
        default=Path(os.environ.get("ROOST_AGENT_STATE_DIR", DEFAULT_STATE_DIR)),
        help="where the last spec and decision state are kept",
    )
    parser.add_argument("--bridge", choices=("simulated", "gpio"), default="simulated")
    parser.add_argument("--gpio-chip", default="/dev/gpiochip0", help="GPIO character device")
    parser.add_argument("--gpio-active-low", action="store_true", help="invert the GPIO lines")
    parser.add_argument(
        "--status-interval", type=float, default=1.0, help="seconds between status lines (0: off)"
    )
    parser.add_argument("--node-name", default=os.environ.get("NODE_NAME", socket.gethostname()))
    parser.add_argument(
        "--cluster",
        choices=("auto", "on", "off"),
        default=os.environ.get("ROOST_AGENT_CLUSTER", "auto"),
        help="take the spec from Kubernetes and report there (auto: when neither --config "
        "nor --autopilot is given, NODE_NAME is set and a service account or $KUBECONFIG "
        "is available)",
    )
    parser.add_argument("--kubeconfig", type=Path, help="kubeconfig (default: in-cluster)")
    parser.add_argument(
        "--report-interval",
        type=float,
        help="seconds between status reports when nothing changes (cluster; default: "
        "PublisherSettings.refresh_s)",
    )
    parser.add_argument(
        "--api-retry-max",
        type=float,
        help="longest wait between API retries while the API is unreachable (cluster; "
        "default: PublisherSettings.retry_max_s)",
    )
    parser.add_argument(
        "--signing",
        type=SigningMode,
        choices=list(SigningMode),
        default=SigningMode(os.environ.get("ROOST_AGENT_SIGNING", "auto")),
        help="MAVLink 2 signing: require (sign, and drop unsigned frames), sign (sign, accept "
        "unsigned), off, or auto (require when the vehicle has a key, else off)",
    )
    parser.add_argument(
        "--signing-keys",
        type=Path,
        default=Path(os.environ.get("ROOST_AGENT_SIGNING_KEYS", DEFAULT_KEY_DIR)),
        help="directory with one signing key file per Vehicle, named after it (64 hex digits)",
    )
    parser.add_argument(
        "--metrics-port",
        type=int,
        default=int(os.environ.get("ROOST_AGENT_METRICS_PORT", "0")),
        help="serve Prometheus metrics on this port (0: off, the default; see docs/metrics.md)",
    )
    parser.add_argument(
        "--metrics-address",
        default=os.environ.get("ROOST_AGENT_METRICS_ADDRESS", "127.0.0.1"),
        help="address the metrics endpoint binds (the agent runs on the host network: "
        "127.0.0.1 keeps it on the vehicle; the node's address lets Prometheus scrape it)",
    )
    parser.add_argument(
        "--telemetry-port",
        type=telemetry_port,
        default=os.environ.get("ROOST_AGENT_TELEMETRY_PORT", "0"),
        help="serve the live telemetry stream (WebSocket, <= 10 Hz) on this port; auto: a "
        'free port, announced on stdout as {"telemetry": URL}; 0: off, the default '
        "(see docs/dashboard.md)",
    )
    parser.add_argument(
        "--telemetry-address",
        default=os.environ.get("ROOST_AGENT_TELEMETRY_ADDRESS", "127.0.0.1"),
        help="address the telemetry stream binds (127.0.0.1 keeps it on the vehicle)",
    )
    parser.add_argument(
        "--telemetry-origin",
        default=os.environ.get("ROOST_AGENT_TELEMETRY_ORIGIN") or None,
        metavar="LAT,LON",
        help="where the stream's north/east metres start (default: the first position)",
    )
    parser.add_argument(
        "--records-dir",
        type=Path,
        default=Path(os.environ["ROOST_AGENT_RECORDS_DIR"])
        if os.environ.get("ROOST_AGENT_RECORDS_DIR")
        else None,
        help="record every flight here (MAVLink tlog, decisions, parameters, the "
        "autopilots' logs; see docs/flight-records.md); off without it",
    )
    parser.add_argument(
        "--records-budget-mb",
        type=float,
        default=float(os.environ.get("ROOST_AGENT_RECORDS_BUDGET_MB", DEFAULT_BUDGET_MB)),
        help="disk budget of the records: the oldest flights are deleted first, never the "
        "current one",
    )
    parser.add_argument(
        "--records-keep-free-percent",
        type=float,
        default=float(
            os.environ.get("ROOST_AGENT_RECORDS_KEEP_FREE_PERCENT", DEFAULT_KEEP_FREE_PERCENT)
        ),
        help="the records never bring their filesystem below this much free: the oldest "
        "flights go first (the kubelet evicts pods below 10%%)",
    )
    parser.add_argument(
        "--records-port",
        type=int,
        default=int(os.environ.get("ROOST_AGENT_RECORDS_PORT", str(DEFAULT_PORT))),
        help="serve the records over HTTP on this port (0: not served)",
    )
    parser.add_argument(
        "--records-address",
        default=os.environ.get("ROOST_AGENT_RECORDS_ADDRESS", "127.0.0.1"),
        help="address the records server binds (127.0.0.1 keeps it on the vehicle)",
    )
    parser.add_argument(
        "--records-fetch-kbps",
        type=float,
        default=float(os.environ.get("ROOST_AGENT_RECORDS_FETCH_KBPS", "100")),
        help="the autopilots' logs are fetched after landing at most this fast (kB/s; "
        "0: not fetched)",
    )
    parser.add_argument("--log-level", default="INFO")
    return parser


def telemetry_port(text: str) -> int | None:
    """``--telemetry-port``: a port, ``auto`` (None: the system picks) or 0 (off)."""
    if text == "auto":
        return None
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port, auto or 0, not {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port {port} is out of range")
    return port


def refuse(message: str) -> SystemExit:
    """A one-line refusal on stderr and exit status 2 (what argparse does for bad flags)."""
    print(f"roost-agent: {message}", file=sys.stderr)
    return SystemExit(2)


def cluster_client(args: argparse.Namespace) -> AgentKube | None:
    # roost_kube (urllib3, its minimal transport) is imported only in cluster mode; the
    # kubernetes package is never imported by the agent (docs/performance.md#memory).
    """The API client when the agent works with a cluster (see ``--cluster``), else None."""
    if args.cluster == "off":
        return None
    if args.cluster == "auto":
        standalone = args.config is not None or bool(args.autopilot)
        placed = "NODE_NAME" in os.environ  # the downward API names our node
        reachable = args.kubeconfig or os.environ.get("KUBERNETES_SERVICE_HOST")
        if standalone or not placed or not (reachable or os.environ.get("KUBECONFIG")):
            return None
    from roost_agent.kube import AgentKube  # noqa: PLC0415 - cluster mode only

    return AgentKube.from_environment(args.kubeconfig)


def resolve_spec(
    args: argparse.Namespace, state: StateFile
) -> tuple[RedundantAutopilotSpec, int | None]:
    """The spec to fly with: --config, else --autopilot flags, else the saved one."""
    if args.config is not None:
        return load_spec(args.config)
    if args.autopilot:
        primary = args.primary or args.autopilot[0].name
        flags = {"vehicleName": args.vehicle, "autopilots": args.autopilot, "primary": primary}
        return RedundantAutopilotSpec.from_api(flags), None  # validated as a --config would be
    saved = state.load()
    if saved is None:
        raise SystemExit(f"no --config, no --autopilot and no saved spec in {state.path}")
    log.warning("no config given: flying on with the spec saved in %s", state.path)
    return saved.spec, saved.generation


def make_bridge(args: argparse.Namespace, spec: RedundantAutopilotSpec, initial: int) -> Bridge:
    """The bridge driver chosen on the command line, already showing ``initial``."""
    channels = [a.bridge_channel for a in spec.autopilots]
    if args.bridge == "gpio":
        return GpioBridge(args.gpio_chip, channels, initial, active_low=args.gpio_active_low)
    return SimulatedBridge(channels, initial=initial)


class JsonLines:
    """Writes one JSON document per line, from any thread."""

    def __init__(self, out: TextIO) -> None:
        self._out = out
        self._lock = threading.Lock()

    def write(self, doc: dict[str, Any]) -> None:
        line = json.dumps(doc, default=str)
        with self._lock:
            self._out.write(line + "\n")
            self._out.flush()


def start_telemetry(
    args: argparse.Namespace, agent: Agent, out: JsonLines
) -> TelemetryServer | None:
    """The telemetry stream when ``--telemetry-port`` asks for it; flying goes on without it."""
    if args.telemetry_port == 0:
        return None
    # websockets is imported only when the stream is on (resident memory).
    from roost_agent.telemetry import TelemetryServer  # noqa: PLC0415
    from roost_api.telemetry import Origin  # noqa: PLC0415

    try:
        origin = Origin.parse(args.telemetry_origin) if args.telemetry_origin else None
        server = TelemetryServer(
            agent, address=args.telemetry_address, port=args.telemetry_port or 0, origin=origin
        )
    except (OSError, ValueError) as exc:
        log.error("cannot serve telemetry (%s); running without the stream", exc)
        return None
    log.info("telemetry on %s", server.url)
    out.write({"telemetry": server.url})
    return server


def start_records(
    args: argparse.Namespace, agent: Agent, out: JsonLines
) -> tuple[FlightRecorder | None, RecordsServer | None]:
    """The flight recorder and its HTTP server when ``--records-dir`` asks for them;
    flying goes on without them when they cannot start."""
    if args.records_dir is None:
        return None, None
    from roost_agent.records_logs import FetchSettings, LogFetcher  # noqa: PLC0415
    from roost_agent.records_recorder import FlightRecorder  # noqa: PLC0415
    from roost_agent.records_server import RecordsServer  # noqa: PLC0415

    fetcher = None
    if args.records_fetch_kbps > 0:
        settings = FetchSettings(rate_bytes_per_s=args.records_fetch_kbps * 1000)
        fetcher = LogFetcher(lambda: agent.links, settings=settings)
    try:
        recorder = FlightRecorder(
            agent,
            args.records_dir,
            budget_bytes=int(args.records_budget_mb * 1e6),
            keep_free=args.records_keep_free_percent / 100,
            fetch_logs=fetcher,
        )
    except OSError as exc:
        log.error("cannot record flights in %s (%s); flying without records", args.records_dir, exc)
        return None, None
    recorder.start()
    server = None
    if args.records_port:
        try:
            server = RecordsServer(
                args.records_dir,
                agent.vehicle_name,
                address=args.records_address,
                port=args.records_port,
            )
        except OSError as exc:
            log.error("cannot serve the records (%s); recording without serving", exc)
        else:
            log.info("records on %s", server.url)
            out.write({"records": server.url})
    return recorder, server


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # A thread waiting for the GIL waits up to the switch interval (5 ms by default) while
    # another holds it; 1 ms bounds how long the reader and decision loop (one thread) can
    # be held up by the hub, the heartbeat or the publisher.
    sys.setswitchinterval(0.001)
    logging.basicConfig(
        level=args.log_level.upper(),
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    # JSON goes to the real stdout; stray prints of any library go to stderr.
    out = JsonLines(os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1))
    sys.stdout = sys.stderr
    state = StateFile(args.state_dir / STATE_FILE_NAME)
    kube = cluster_client(args)
    if kube is None:
        try:
            spec, generation = resolve_spec(args, state)
        except (OSError, ValueError) as exc:  # PlainValidationError is a ValueError
            raise refuse(" ".join(str(exc).split())) from None
        target = None
    else:
        from roost_agent.publisher import startup_spec  # noqa: PLC0415 - cluster mode only

        spec, generation, target = startup_spec(kube, args.node_name, state)
    problems = connection_problems(spec)
    if problems:
        raise refuse("; ".join(problems))
    try:
        signing = load_signing(args.signing, args.signing_keys, spec.vehicle_name, args.state_dir)
    except SigningError as exc:
        raise refuse(str(exc)) from None
    if signing is None:
        log.info("MAVLink signing is off: any host that reaches a link can talk to it")
    restored = restore_state(spec, state.load())
    channel = next(a.bridge_channel for a in spec.autopilots if a.name == restored.active)
    bridge = make_bridge(args, spec, channel)
    try:
        agent = Agent(
            spec,
            bridge,
            state_file=state,
            generation=generation,
            node_name=args.node_name,
            signing=signing,
        )
    except OSError as exc:  # the hub's endpoint is taken or not an address of this node
        raise refuse(f"cannot serve the vehicle's MAVLink endpoint (spec.hub): {exc}") from None
    except HubConfigError as exc:  # an endpoint beyond loopback without a key
        raise refuse(f"spec.hub: {exc}") from None
    agent.subscribe(lambda event: out.write(event.to_json()))
    stop = threading.Event()

    def reload(*_: object) -> None:
        if args.config is None:
            return
        try:
            new_spec, new_generation = load_spec(args.config)
        except (OSError, ValueError) as exc:  # PlainValidationError is a ValueError
            log.error("cannot reload %s: %s", args.config, exc)
            return
        agent.apply_spec(new_spec, new_generation)

    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGHUP, lambda *_: threading.Thread(target=reload, daemon=True).start())
    agent.start()
    if signing is not None:  # a rotated key is taken without a restart
        watcher = KeyWatcher(args.signing_keys, spec.vehicle_name, signing, agent.rekey)
        threading.Thread(target=watcher.run, args=(stop,), name="signing-keys", daemon=True).start()
    telemetry = start_telemetry(args, agent, out)
    recorder, records_server = start_records(args, agent, out)
    publisher = None
    if kube is not None:
        from roost_agent.publisher import Publisher, PublisherSettings  # noqa: PLC0415

        given = {"refresh_s": args.report_interval, "retry_max_s": args.api_retry_max}
        settings = PublisherSettings(**{k: v for k, v in given.items() if v is not None})
        announce: dict[str, str] = {}
        if telemetry is not None:
            from roost_api.telemetry import telemetry_annotations  # noqa: PLC0415

            announce = telemetry_annotations(
                telemetry.address,
                telemetry.port,
                pod=os.environ.get("POD_NAME"),
                namespace=os.environ.get("POD_NAMESPACE"),
            )
        publisher = Publisher(
            agent,
            kube,
            node_name=args.node_name,
            target=target,
            settings=settings,
            announce=announce,
        )
        publisher.start()
    metrics = None
    if args.metrics_port:
        # prometheus_client is imported only when metrics are on (resident memory).
        from roost_agent.metrics import MetricsServer  # noqa: PLC0415

        try:
            metrics = MetricsServer(
                agent,
                address=args.metrics_address,
                port=args.metrics_port,
                publisher=publisher,
                recorder=recorder,
            )
        except OSError as exc:
            # Supervising the autopilots matters more than being observed: fly on.
            log.error(
                "cannot serve metrics on %s:%d (%s); running without metrics",
                args.metrics_address,
                args.metrics_port,
                exc,
            )
        else:
            log.info("metrics on http://%s:%d/metrics", args.metrics_address, metrics.port)
    try:
        while not stop.wait(args.status_interval or None):
            links = {name: asdict(link.counters) for name, link in agent.links.items()}
            out.write({"status": agent.status().to_api(), "links": links})
    finally:
        if telemetry is not None:
            telemetry.close()
        if metrics is not None:
            metrics.close()
        if records_server is not None:
            records_server.close()
        if recorder is not None:
            recorder.stop()
        if publisher is not None:
            publisher.stop()
        agent.stop()
        bridge.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
