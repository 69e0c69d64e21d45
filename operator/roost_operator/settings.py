"""Every setting of the operator, in one object built once at start.

Modelled on kopf's own ``OperatorSettings``: a frozen dataclass whose fields each carry
a docstring saying what they do, their unit and the environment variable or flag that
sets them. :func:`load_settings` builds it from the environment (which is how the chart
configures the operator) and command-line flags override it. :func:`roost_operator.main`
builds it before any handler is registered and hands it to kopf in the operator's
``memo``; handlers and their registration read it from there. No module reads the
environment on import and no handler module keeps a timing of its own.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path

from roost_operator.autopilots.conditions import DEFAULT_AGENT_STALE_AFTER
from roost_operator.autopilots.guards import TRUE_VALUES, FleetGuards
from roost_operator.records.s3 import BucketSettings
from roost_operator.records.settings import RecordsSettings, parse_agent_records


@dataclass(frozen=True)
class MissionTimings:
    """How often the Mission controller looks at a Mission without an event, how its
    work queue backs off, and how many workers it has."""

    resync_seconds: float = 10.0
    """Reconcile every Mission at least this often, even without an event: Jobs, agents
    and Vehicles wake it sooner (``ROOST_MISSION_RESYNC_SECONDS``)."""

    error_backoff_seconds: float = 5.0
    """First wait after a reconcile failed on a temporary error; doubles on each further
    failure up to :attr:`max_backoff_seconds` (``ROOST_MISSION_ERROR_BACKOFF_SECONDS``)."""

    max_backoff_seconds: float = 60.0
    """Longest wait between retries of a failing Mission reconcile."""

    workers: int = 4
    """Threads reconciling Missions from their work queue (``ROOST_MISSION_WORKERS``):
    how many Mission reconciles run at once, however many Missions there are."""

    delete_backoff_seconds: float = 2.0
    """kopf's backoff before retrying a Mission's deletion handler after a temporary
    error (the Mission keeps its finalizer meanwhile)."""


@dataclass(frozen=True)
class KopfTimings:
    """How the operator talks to the API server through kopf (set in kopf's settings at
    start-up by :func:`roost_operator.main.configure`)."""

    watch_server_timeout_seconds: int = 290
    """How long the API server keeps one watch request open before it ends it cleanly
    (``ROOST_WATCH_SERVER_TIMEOUT_SECONDS``; an integer, the API server wants one). kopf
    then re-lists and watches again; shorter means more list requests, longer means a
    silently dead connection is noticed later."""

    watch_client_timeout_seconds: float = 300.0
    """How long kopf waits on a watch before it gives up on the connection itself
    (``ROOST_WATCH_CLIENT_TIMEOUT_SECONDS``): a little more than the server's timeout, so
    the server normally ends the watch first."""

    connect_timeout_seconds: float = 10.0
    """TCP/TLS connect timeout of watches and requests (``ROOST_CONNECT_TIMEOUT_SECONDS``);
    kopf's default is none, which hangs a handler on an unreachable API server."""

    request_timeout_seconds: float = 60.0
    """Timeout of one non-watch request of kopf's (patches of progress and finalizers,
    Events; ``ROOST_REQUEST_TIMEOUT_SECONDS``)."""

    cancellation_polling_seconds: float = 1.0
    """How often kopf re-checks a sync timer or daemon it could not cancel when its object
    was deleted (kopf's default is 60 s, which would hold the finalizer that long)."""

    object_workers: int = 200
    """kopf's ``queueing.worker_limit``: at most this many objects have their events
    processed at once (kopf's default is unbounded: a re-list of 3,000 objects would start
    3,000 workers). Beyond it kopf stops reading the watch until a worker frees up, which
    is back-pressure on the API server's stream instead of an unbounded backlog in memory.
    Roost's event handlers only queue, so a worker is busy for microseconds."""

    handler_threads: int = 8
    """kopf's ``execution.max_workers``: threads for the handlers that block (deletion,
    the mission controller); the Vehicle reconciles have their own workers
    (``Settings.reconcile_workers``)."""


@dataclass(frozen=True)
class Settings:
    """What the operator is configured with; see the module docstring."""

    namespace: str = "roost-system"
    """Namespace of the objects the operator owns for vehicles: config ConfigMaps,
    component Pods, mission claim Leases (``ROOST_NAMESPACE``). Created at
    startup when missing."""

    peering: str = "roost"
    """Name of the kopf peering object, one per operator deployment (``ROOST_PEERING``)."""

    agent_image: str = "roost-agent:latest"
    """Image of a Vehicle's key pod (``spec.components.signingKeys``) when the Vehicle
    names none: the node agent's image, which the chart passes (``ROOST_AGENT_IMAGE``)."""

    resync_seconds: float = 0.0
    """Period of a fleet sweep that queues every Vehicle for a reconcile
    (``ROOST_RESYNC_SECONDS``; 0, the default: none). Everything the Vehicle controller
    reads or writes is watched, so hand edits are put back on their own event; a sweep is
    a safety net whose cost grows with the fleet and almost always finds nothing."""

    reconcile_workers: int = 16
    """Threads reconciling Vehicles from the work queue (``ROOST_RECONCILE_WORKERS``):
    how many reconciles, and so how many API requests, run at once, whatever the event
    rate (kopf's event handlers only queue). A reconcile mostly waits for the API server
    (about a fifth of its time is the operator's CPU at fleet scale), so more threads
    than cores keep the API server busy when a thousand Vehicles arrive at once."""

    @property
    def api_connections(self) -> int:
        """Connections Roost's API client keeps open: one per thread that may send at
        once — the Vehicle and Mission reconcile workers, kopf's handler threads, and
        Roost's own watches (nodes, claims, ConfigMaps, component Pods), each holding one
        for its whole length —
        plus a few for the rest. A request beyond the pool opens, and then throws away,
        a connection of its own: a TLS handshake per request on both ends."""
        return self.reconcile_workers + self.missions.workers + self.kopf.handler_threads + 8

    retry_backoff_seconds: float = 2.0
    """First wait before retrying a Vehicle reconcile (or kopf's handler for a Vehicle's
    deletion) that failed on a temporary error; doubles per failure up to
    :attr:`max_backoff_seconds`."""

    max_backoff_seconds: float = 60.0
    """Longest wait between retries of a failing Vehicle reconcile."""

    first_report_hold: timedelta = timedelta(seconds=5)
    """How long after its creation a new Vehicle whose components are only starting may
    go without a status (``ROOST_FIRST_REPORT_HOLD_SECONDS``; 0 writes every report at
    once): usually its pods are Ready by then and its first status is its only write on
    the way to Ready. Any problem is written at once
    (:func:`~roost_operator.vehicles.status.first_report_due`)."""

    agent_stale_after: timedelta = DEFAULT_AGENT_STALE_AFTER
    """Age of an agent's last report after which its Vehicle's ``AgentConnected`` turns
    Unknown (``ROOST_AGENT_STALE_SECONDS``); keep it at least three times the agents'
    report interval."""

    failover_poll_seconds: float = 2.0
    """Re-check period of a vehicle while a cluster-side failover action runs or a fleet
    guard holds one back (end of the mavros rollout, timeout, guard lifting)."""

    guards: FleetGuards = field(default_factory=FleetGuards)
    """Fleet guards on cluster-side failover actions (``ROOST_FAILOVER_*``, see
    :class:`~roost_operator.autopilots.guards.FleetGuards`)."""

    missions: MissionTimings = field(default_factory=MissionTimings)
    """Timings and workers of the Mission controller (``ROOST_MISSION_*``)."""

    kopf: KopfTimings = field(default_factory=KopfTimings)
    """Watch and request timeouts of kopf (``ROOST_WATCH_*``, ``ROOST_*_TIMEOUT_SECONDS``)."""

    records: RecordsSettings = field(default_factory=RecordsSettings)
    """Where and how Mission records are gathered and kept (``ROOST_RECORDS_*``)."""


def _seconds(environ: Mapping[str, str], key: str, default: timedelta) -> timedelta:
    value = environ.get(key)
    return timedelta(seconds=float(value)) if value else default


def load_guards(environ: Mapping[str, str]) -> FleetGuards:
    """:class:`FleetGuards` from ``ROOST_FAILOVER_*``, defaults for what is unset."""
    defaults = FleetGuards()
    return FleetGuards(
        max_concurrent_actions=int(
            environ.get("ROOST_FAILOVER_MAX_CONCURRENT", defaults.max_concurrent_actions)
        ),
        latch_after=int(environ.get("ROOST_FAILOVER_LATCH_AFTER", defaults.latch_after)),
        latch_window=_seconds(
            environ, "ROOST_FAILOVER_LATCH_WINDOW_SECONDS", defaults.latch_window
        ),
        action_timeout=_seconds(
            environ, "ROOST_FAILOVER_ACTION_TIMEOUT_SECONDS", defaults.action_timeout
        ),
        paused=environ.get("ROOST_FAILOVER_PAUSED", "false").strip().lower() in TRUE_VALUES,
    )


def load_kopf_timings(environ: Mapping[str, str]) -> KopfTimings:
    """:class:`KopfTimings` from the environment, defaults for what is unset."""
    defaults = KopfTimings()
    return KopfTimings(
        watch_server_timeout_seconds=int(
            environ.get("ROOST_WATCH_SERVER_TIMEOUT_SECONDS", defaults.watch_server_timeout_seconds)
        ),
        watch_client_timeout_seconds=float(
            environ.get("ROOST_WATCH_CLIENT_TIMEOUT_SECONDS", defaults.watch_client_timeout_seconds)
        ),
        connect_timeout_seconds=float(
            environ.get("ROOST_CONNECT_TIMEOUT_SECONDS", defaults.connect_timeout_seconds)
        ),
        request_timeout_seconds=float(
            environ.get("ROOST_REQUEST_TIMEOUT_SECONDS", defaults.request_timeout_seconds)
        ),
        cancellation_polling_seconds=defaults.cancellation_polling_seconds,
    )


def load_settings(environ: Mapping[str, str]) -> Settings:
    """Settings from ``environ`` with defaults for what is unset."""
    defaults = Settings()
    timings = MissionTimings()
    return Settings(
        namespace=environ.get("ROOST_NAMESPACE", defaults.namespace),
        peering=environ.get("ROOST_PEERING", defaults.peering),
        agent_image=environ.get("ROOST_AGENT_IMAGE") or defaults.agent_image,
        resync_seconds=float(environ.get("ROOST_RESYNC_SECONDS", defaults.resync_seconds)),
        reconcile_workers=int(environ.get("ROOST_RECONCILE_WORKERS", defaults.reconcile_workers)),
        agent_stale_after=_seconds(
            environ, "ROOST_AGENT_STALE_SECONDS", defaults.agent_stale_after
        ),
        first_report_hold=_seconds(
            environ, "ROOST_FIRST_REPORT_HOLD_SECONDS", defaults.first_report_hold
        ),
        guards=load_guards(environ),
        missions=MissionTimings(
            resync_seconds=float(
                environ.get("ROOST_MISSION_RESYNC_SECONDS", timings.resync_seconds)
            ),
            error_backoff_seconds=float(
                environ.get("ROOST_MISSION_ERROR_BACKOFF_SECONDS", timings.error_backoff_seconds)
            ),
            workers=int(environ.get("ROOST_MISSION_WORKERS", timings.workers)),
        ),
        kopf=load_kopf_timings(environ),
        records=load_records(environ),
    )


def load_records(environ: Mapping[str, str]) -> RecordsSettings:
    """:class:`RecordsSettings` from the environment, defaults for what is unset."""
    defaults = RecordsSettings()
    directory = environ.get("ROOST_RECORDS_DIR")
    days = float(environ.get("ROOST_RECORDS_KEEP_DAYS", 30))
    return RecordsSettings(
        directory=Path(directory) if directory else None,
        agent_port=int(environ.get("ROOST_RECORDS_AGENT_PORT", defaults.agent_port)),
        agents=parse_agent_records(environ.get("ROOST_RECORDS_AGENTS") or defaults.agents),
        agent_namespace=environ.get("ROOST_RECORDS_AGENT_NAMESPACE", defaults.agent_namespace),
        retry_seconds=float(environ.get("ROOST_RECORDS_RETRY_SECONDS", defaults.retry_seconds)),
        settle_after=_seconds(environ, "ROOST_RECORDS_SETTLE_SECONDS", defaults.settle_after),
        give_up_after=_seconds(environ, "ROOST_RECORDS_GIVE_UP_SECONDS", defaults.give_up_after),
        keep_count=int(environ.get("ROOST_RECORDS_KEEP", defaults.keep_count)),
        keep_for=timedelta(days=days) if days > 0 else None,
        bucket=load_bucket(environ),
    )


def load_bucket(environ: Mapping[str, str]) -> BucketSettings | None:
    """The bucket bundles are copied to; None unless both endpoint and bucket are set."""
    endpoint = environ.get("ROOST_RECORDS_S3_ENDPOINT", "")
    bucket = environ.get("ROOST_RECORDS_S3_BUCKET", "")
    if not (endpoint and bucket):
        return None
    credentials = environ.get("ROOST_RECORDS_S3_CREDENTIALS_DIR")
    defaults = BucketSettings(endpoint, bucket)
    return BucketSettings(
        endpoint=endpoint,
        bucket=bucket,
        region=environ.get("ROOST_RECORDS_S3_REGION") or defaults.region,
        prefix=environ.get("ROOST_RECORDS_S3_PREFIX", ""),
        credentials_dir=Path(credentials) if credentials else defaults.credentials_dir,
    )
