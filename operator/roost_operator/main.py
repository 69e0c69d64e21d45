"""Entry point of the Roost operator: kopf settings, handler registration, ``main()``.

Settings are explicit rather than kopf's defaults, following operator practice:

* finalizer and annotation prefixes under ``roost.dev`` (kopf's own markers would leak
  ``kopf.zalando.org`` into users' objects); a deletion handler's progress is kept in
  annotations only, never in ``status`` (the Vehicle status schema would prune it, and
  status is ours);
* no diff base (:class:`NoDiffBase`): kopf would write the last handled configuration
  into an annotation of every Vehicle and Mission (a PATCH per object, and one more per
  spec change) for its create/update/resume handlers, and Roost registers none: its
  handlers watch events, run daemons and timers, and clean up behind the finalizer
  (Missions only: a Vehicle's leftovers carry its label and are found without one);
* a named peering (``Settings.peering``, default ``roost``) so two Roost deployments never
  pause each other, and peering is optional: without the peering CRD the operator runs
  standalone (the chart runs one replica with ``strategy: Recreate``);
* posting level WARNING: kopf would otherwise post a Kubernetes Event for every
  successful handler and timer run, which is an API write per vehicle per resync.
  Roost posts its own Events on meaningful transitions;
* watch ``server_timeout`` below the client timeout so a silently stalled watch is
  reopened (kopf #955, #1276), and request timeouts on every API call;
* a short ``background.cancellation_polling``: a deleted Mission whose (sync) timer or
  daemon happens to be running would otherwise keep its finalizer for a minute;
* a bounded ``queueing.worker_limit`` and ``execution.max_workers``
  (:class:`~roost_operator.settings.KopfTimings`): back-pressure on the watch streams
  instead of a worker per object, and a fixed thread pool for the handlers that block.
  The Vehicle controller's reconciles run in its own work queue
  (:mod:`roost_operator.engine.workqueue`), started here at startup and stopped at cleanup.

Nothing is registered on import: :func:`main` reads the settings (environment, then
flags) once, builds a kopf registry with every controller's handlers registered with
those settings (:func:`build_registry`), and passes the settings to kopf in the memo.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import threading
from collections.abc import Iterable, Mapping
from dataclasses import replace
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, cast
from urllib.parse import urlsplit

import kopf

from roost_api.wellknown import FINALIZER, PREFIX
from roost_kube.client import Kube
from roost_kube.resources import NAMESPACES
from roost_operator.edge import FIELD_MANAGER
from roost_operator.engine.leader import LeaderElector
from roost_operator.missions import handlers as mission_handlers
from roost_operator.runtime import Runtime, settings_of
from roost_operator.settings import Settings, load_settings
from roost_operator.vehicles import handlers as vehicle_handlers
from roost_operator.vehicles.handlers import reconcile_vehicle

HANDLER_MODULES = (vehicle_handlers, mission_handlers)
"""Each has ``register(registry, settings)``: one controller per resource."""
ANNOTATION_PREFIX = PREFIX.rstrip("/")


class NoDiffBase(kopf.DiffBaseStorage):
    """kopf's diff base, kept nowhere and never computed.

    kopf compares an object with the diff base to tell its create, update and resume
    handlers what changed, and stores a new one (a PATCH of the object) after handling.
    Roost registers no such handler, so nothing reads it: with no stored base every
    event is a "creation" with no handler to call, which kopf passes by without a write;
    deletion is told by the deletion mark, not by the diff base. The essence is empty so
    kopf does not deep-copy every object on every event to build one.
    """

    def build(
        self, *, body: kopf.Body, extra_fields: Iterable[Any] | None = None
    ) -> kopf.BodyEssence:
        return cast(kopf.BodyEssence, {})

    def fetch(self, *, body: kopf.Body) -> kopf.BodyEssence | None:
        return None

    def store(self, *, body: kopf.Body, patch: kopf.Patch, essence: kopf.BodyEssence) -> None:
        return None


def configure(settings: kopf.OperatorSettings, roost: Settings) -> None:
    """Apply Roost's kopf settings (see the module docstring for why each)."""
    settings.persistence.finalizer = FINALIZER
    settings.persistence.progress_storage = kopf.AnnotationsProgressStorage(
        prefix=ANNOTATION_PREFIX
    )
    settings.persistence.diffbase_storage = NoDiffBase()
    settings.peering.name = roost.peering
    settings.peering.clusterwide = True
    settings.peering.mandatory = False
    settings.peering.stealth = True
    settings.posting.level = logging.WARNING
    timings = roost.kopf
    settings.watching.server_timeout = timings.watch_server_timeout_seconds
    settings.watching.client_timeout = timings.watch_client_timeout_seconds
    settings.watching.connect_timeout = timings.connect_timeout_seconds
    settings.networking.request_timeout = timings.request_timeout_seconds
    settings.networking.connect_timeout = timings.connect_timeout_seconds
    settings.background.cancellation_polling = timings.cancellation_polling_seconds
    settings.queueing.worker_limit = timings.object_workers
    settings.execution.max_workers = timings.handler_threads


def startup(settings: kopf.OperatorSettings, memo: kopf.Memo, **_: Any) -> None:
    """Configure kopf, connect to the API and make sure the operator's namespace exists."""
    roost = settings_of(memo)
    configure(settings, roost)
    kube = Kube.from_environment(FIELD_MANAGER, connections=roost.api_connections)
    # Only when missing: under the chart the namespace exists and the operator may only
    # read it (a right to patch it would let the operator relax its own Pod Security
    # labels). The sandbox, with admin rights, gets it created.
    if kube.get(NAMESPACES, roost.namespace) is None:
        kube.apply({"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": roost.namespace}})
    memo.runtime = Runtime.start(
        kube, roost, reconcile_vehicle, timing=getattr(memo, "handler_timing", None)
    )


def cleanup(memo: kopf.Memo, **_: Any) -> None:
    """Stop the Vehicle queue's workers after the reconciles they are running."""
    rt = getattr(memo, "runtime", None)
    if rt is not None:
        rt.stop()


def build_registry(settings: Settings) -> kopf.OperatorRegistry:
    """A kopf registry with the startup hook and every controller's handlers."""
    registry = kopf.OperatorRegistry()
    # kopf authenticates like Roost's own client does: from the kubernetes client's config
    # (a fresh registry has none of the default registry's login handlers).
    kopf.on.login(registry=registry)(kopf.login_via_client)
    kopf.on.startup(registry=registry)(startup)
    kopf.on.cleanup(registry=registry)(cleanup)
    for module in HANDLER_MODULES:
        module.register(registry, settings)
    return registry


def parse_args(argv: list[str] | None, environ: Mapping[str, str]) -> tuple[Any, Settings]:
    """Flags, and the settings from ``environ`` with the flags' overrides."""
    parser = argparse.ArgumentParser(prog="roost-operator", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--standalone", action="store_true", help="run without peering even if it exists"
    )
    parser.add_argument(
        "--liveness",
        metavar="URL",
        default=None,
        help="serve kopf's health endpoint, e.g. http://0.0.0.0:8080/healthz",
    )
    parser.add_argument(
        "--leader-election",
        action="store_true",
        help="act only while holding the Lease roost-operator-leader in the operator's "
        "namespace; stand by otherwise (the chart's replicas)",
    )
    parser.add_argument(
        "--identity",
        default=environ.get("POD_ID") or f"{socket.gethostname()}-{os.getpid()}",
        help="this replica's name in the Lease (default: $POD_ID, else host and pid)",
    )
    parser.add_argument("--namespace", help="operator namespace (overrides ROOST_NAMESPACE)")
    parser.add_argument(
        "--resync-seconds", type=float, help="fleet sweep period, 0: none (ROOST_RESYNC_SECONDS)"
    )
    parser.add_argument(
        "--metrics-port",
        type=int,
        default=int(environ.get("ROOST_OPERATOR_METRICS_PORT", "0")),
        help="serve Prometheus metrics on this port (0: off; see docs/metrics.md)",
    )
    parser.add_argument(
        "--metrics-address",
        default=environ.get("ROOST_OPERATOR_METRICS_ADDRESS", "127.0.0.1"),
        help="address the metrics endpoint binds (0.0.0.0 in a pod)",
    )
    parser.add_argument(
        "--records-port",
        type=int,
        default=int(environ.get("ROOST_RECORDS_PORT", "0")),
        help="serve the Mission records read-only on this port (0: off; docs/mission-records.md)",
    )
    parser.add_argument(
        "--records-address",
        default=environ.get("ROOST_RECORDS_ADDRESS", "127.0.0.1"),
        help="address the records server binds (0.0.0.0 in a pod)",
    )
    parser.add_argument("--verbose", action="store_true", help="debug logging")
    args = parser.parse_args(argv)
    settings = load_settings(environ)
    if args.namespace:
        settings = replace(settings, namespace=args.namespace)
    if args.resync_seconds is not None:
        settings = replace(settings, resync_seconds=args.resync_seconds)
    return args, settings


def main(argv: list[str] | None = None) -> int:
    """Run the operator in the foreground until interrupted."""
    args, settings = parse_args(argv, os.environ)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    # kopf logs every handler run at INFO ("Handler 'owned_event' succeeded."): a line per
    # watch event, most of the log's volume and a measurable cost at fleet scale. Its
    # warnings and errors (and the Events kopf posts for them) stay.
    logging.getLogger("kopf.objects").setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    registry = build_registry(settings)
    memo = kopf.Memo(settings=settings)
    if args.metrics_port:
        from roost_operator.metrics import OperatorMetrics  # noqa: PLC0415

        metrics = OperatorMetrics(Kube.from_environment(FIELD_MANAGER))
        memo.handler_timing = metrics.reconciles  # every handler_edge run reports here
        port = metrics.serve(args.metrics_address, args.metrics_port)
        logging.getLogger(__name__).info(
            "metrics on http://%s:%d/metrics", args.metrics_address, port
        )
    if args.records_port and settings.records.directory is not None:
        from roost_operator.records.server import serve  # noqa: PLC0415

        server = serve(settings.records.directory, args.records_address, args.records_port)
        logging.getLogger(__name__).info(
            "records on http://%s:%d/bundles", args.records_address, server.server_address[1]
        )
    elector = None
    if args.leader_election:
        elector = LeaderElector(
            Kube.from_environment(FIELD_MANAGER),
            settings.namespace,
            args.identity,
            on_lost=lose_leadership,
        )
        with standing_by(args.liveness, elector):
            elector.acquire()
        if elector.cancelled:
            elector.stop()  # hands back a Lease taken just before the signal
            logging.getLogger(__name__).info("leader election: stopped while standing by")
            return 0
        elector.keep()
    try:
        kopf.run(
            registry=registry,
            memo=memo,
            clusterwide=True,
            standalone=args.standalone or None,
            peering_name=settings.peering,
            liveness_endpoint=args.liveness,
        )
    finally:
        if elector is not None:
            elector.stop()
    return 0


def lose_leadership() -> None:
    """The Lease could not be kept: stop at once, acting on nothing more (the pod's
    restart makes this replica a standby)."""
    logging.getLogger(__name__).critical("leader: lost the Lease; exiting")
    logging.shutdown()
    os._exit(3)


class _Healthy(BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.end_headers()
        self.wfile.write(b'{"standby": true}')

    def log_message(self, *_: Any) -> None:
        return


class standing_by:  # noqa: N801 (a context manager used as a function)
    """While a replica stands by (kopf not started): answer the liveness URL itself, and
    stop standing by on SIGTERM or SIGINT.

    kopf handles those signals once it runs; before that, Python's default would apply,
    and in a container the operator is its PID namespace's init, for which the kernel
    drops a signal that has no handler: a standby pod would sit out its whole
    termination grace period (30 s) on every rollout, scale-down and uninstall, and then
    be killed. The handler only cancels the election; :func:`main` returns.
    """

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self, url: str | None, elector: LeaderElector) -> None:
        self.elector = elector
        self.previous: dict[int, Any] = {}
        self.server: ThreadingHTTPServer | None = None
        if url:
            parts = urlsplit(url)
            self.server = ThreadingHTTPServer((parts.hostname or "", parts.port or 80), _Healthy)

    def _stop(self, signum: int, _frame: object) -> None:
        self.elector.cancel()

    def __enter__(self) -> None:
        for signum in self.SIGNALS:
            self.previous[signum] = signal.signal(signum, self._stop)
        if self.server is not None:
            threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def __exit__(self, *_: object) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)


if __name__ == "__main__":
    raise SystemExit(main())
