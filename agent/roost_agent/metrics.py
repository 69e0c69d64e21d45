"""Prometheus metrics of the node agent, collected without touching the decision loop.

The decision loop must never wait for a scrape, so nothing here runs on it:

* gauges and the link counters are read from the agent's existing state at scrape time
  by a custom collector (:class:`AgentCollector`): the latest assessments (a dict copy
  under the agent's lock, microseconds), the active autopilot and latch (plain attribute
  reads) and the per-link counters the reader threads keep anyway;
* counters and histograms of things that happen (failovers and their latency, safety
  routine phases, command results, every other agent event) are updated by an event
  listener (:class:`EventMetrics`), which runs on the agent's notifier thread — the
  thread that already logs every event, after the decision was carried out.

The exposition is prometheus_client's; :func:`serve` runs its HTTP server in a daemon
thread. This module imports prometheus_client at the top, so ``roost_agent.main`` imports
it only when metrics are enabled: a standalone agent without metrics stays as small as it
was. Labels are bounded by the spec and by code: autopilot names, event reasons, safety
phases, command results — never object UIDs or free text. docs/metrics.md lists every
metric.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Protocol

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Histogram,
    ProcessCollector,
    start_http_server,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from roost_agent.events import AgentEvent, EventKind
from roost_agent.hub import Hub
from roost_agent.hub_policy import REASONS
from roost_agent.link import LinkCounters
from roost_api.core import HealthLevel

if TYPE_CHECKING:
    from wsgiref.simple_server import WSGIServer

    from roost_agent.health import Assessment
    from roost_agent.link import AutopilotLink

PREFIX = "roost_agent"
DEFAULT_ADDRESS = "127.0.0.1"
DEFAULT_PORT = 9465

# Detection -> bridge switched is a few hundred microseconds on a loaded companion
# computer; the buckets resolve 50 µs to 100 ms.
DETECTION_BUCKETS = (
    0.00005,
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
)
# Onset -> switched includes the detection window (a silence threshold, a debounce):
# tens to thousands of milliseconds.
ONSET_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)

LEVEL_VALUES = {level: level.rank for level in HealthLevel}
# Frame outcomes of a link, as LinkCounters counts them; the rest are link events.
FRAME_RESULTS = (
    "accepted",
    "foreign",
    "unlocked",
    "other",
    "bad",
    "unknown",
    "truncated",
    "unsigned",
    "bad_signature",
)
LINK_EVENTS = ("reopened", "relocked")
# Every LinkCounters field is exported: the frame results, the link events and these.
LINK_TOTALS = ("bytes", "errors")


class MetricsAgent(Protocol):
    """What the collector reads of :class:`roost_agent.agent.Agent`."""

    @property
    def active(self) -> str: ...

    @property
    def latched(self) -> bool: ...

    @property
    def links(self) -> Mapping[str, AutopilotLink]: ...

    @property
    def hub(self) -> Hub | None: ...

    def assessments(self) -> dict[str, Assessment]: ...

    def subscribe(self, listener: Callable[[AgentEvent], None]) -> Callable[[], None]: ...


class PublisherGauges(Protocol):
    """What the collector reads of :class:`roost_agent.publisher.Publisher`."""

    @property
    def pending_events(self) -> int: ...

    @property
    def api_errors(self) -> int: ...


class RecorderGauges(Protocol):
    """What the collector reads of :class:`roost_agent.records_recorder.FlightRecorder`."""

    @property
    def dropped_frames(self) -> int: ...

    @property
    def decisions_dropped(self) -> int: ...

    @property
    def flights_recorded(self) -> int: ...


class AgentCollector(Collector):
    """Reads the agent's state at scrape time (health, links, active autopilot, publisher,
    flight recorder)."""

    def __init__(
        self,
        agent: MetricsAgent,
        publisher: PublisherGauges | None = None,
        recorder: RecorderGauges | None = None,
    ) -> None:
        self._agent = agent
        self._publisher = publisher
        self._recorder = recorder

    def collect(self) -> Iterable[GaugeMetricFamily | CounterMetricFamily]:
        agent = self._agent
        links = agent.links
        assessments = agent.assessments()
        active = agent.active
        level = GaugeMetricFamily(
            f"{PREFIX}_autopilot_health_level",
            "Health level of each autopilot: 0 OK, 1 WARN, 2 STARTING, 3 ERROR, 4 STALE.",
            labels=["autopilot"],
        )
        state = GaugeMetricFamily(
            f"{PREFIX}_autopilot_health",
            "1 for the autopilot's current health level, 0 for the others.",
            labels=["autopilot", "level"],
        )
        age = GaugeMetricFamily(
            f"{PREFIX}_autopilot_message_age_seconds",
            "Time since the last accepted message of each autopilot.",
            labels=["autopilot"],
        )
        heartbeat = GaugeMetricFamily(
            f"{PREFIX}_autopilot_heartbeat_age_seconds",
            "Time since the last HEARTBEAT of each autopilot.",
            labels=["autopilot"],
        )
        for name, a in assessments.items():
            level.add_metric([name], LEVEL_VALUES[a.level])
            for each in HealthLevel:
                state.add_metric([name, each.value], 1.0 if each == a.level else 0.0)
            if a.message_age_s is not None:
                age.add_metric([name], a.message_age_s)
            if a.heartbeat_age_s is not None:
                heartbeat.add_metric([name], a.heartbeat_age_s)
        yield from (level, state, age, heartbeat)
        on_motors = GaugeMetricFamily(
            f"{PREFIX}_active_autopilot",
            "1 for the autopilot connected to the motors, 0 for the others.",
            labels=["autopilot"],
        )
        for name in links:
            on_motors.add_metric([name], 1.0 if name == active else 0.0)
        yield on_motors
        yield GaugeMetricFamily(
            f"{PREFIX}_latched",
            "1 after an automatic failover: the agent will not switch back by itself.",
            value=1.0 if agent.latched else 0.0,
        )
        yield from link_families({name: link.counters for name, link in links.items()})
        hub = agent.hub
        if hub is not None:
            yield hub_family(hub)
        if self._publisher is not None:
            yield GaugeMetricFamily(
                f"{PREFIX}_publisher_pending_events",
                "Kubernetes Events queued while the API server is unreachable.",
                value=self._publisher.pending_events,
            )
            yield CounterMetricFamily(
                f"{PREFIX}_publisher_api_errors",
                "Failed API calls of the status publisher (discovery, status, Events).",
                value=self._publisher.api_errors,
            )
        if self._recorder is not None:
            dropped = CounterMetricFamily(
                f"{PREFIX}_records_dropped",
                "What the flight recorder dropped rather than slow the hub (its queue "
                "full): MAVLink frames (tlog) and agent events (decisions).",
                labels=["file"],
            )
            dropped.add_metric(["tlog"], self._recorder.dropped_frames)
            dropped.add_metric(["decisions"], self._recorder.decisions_dropped)
            yield dropped
            yield CounterMetricFamily(
                f"{PREFIX}_records_flights",
                "Flights the recorder began (arm to disarm) since the agent started.",
                value=self._recorder.flights_recorded,
            )


def hub_family(hub: Hub) -> CounterMetricFamily:
    """Client frames each hub endpoint dropped, by reason (never forwarded)."""
    dropped = CounterMetricFamily(
        f"{PREFIX}_hub_dropped_frames",
        "Client frames a hub endpoint dropped: unsigned, bad_signature, replayed or "
        "not_allowed (outside the endpoint's scope).",
        labels=["endpoint", "reason"],
    )
    for endpoint in hub.endpoints:
        counts = endpoint.drops.by_reason
        for reason in range(1, len(REASONS)):
            dropped.add_metric([endpoint.name, REASONS[reason]], counts[reason])
    return dropped


def link_families(counters: Mapping[str, LinkCounters]) -> list[CounterMetricFamily]:
    """The per-link counters as metric families (frames by result, bytes, errors, events)."""
    frames = CounterMetricFamily(
        f"{PREFIX}_link_frames",
        "Datagrams and frames a link received, by what became of them "
        "(accepted: from the autopilot; the rest were dropped).",
        labels=["autopilot", "result"],
    )
    data = CounterMetricFamily(
        f"{PREFIX}_link_received_bytes",
        "Bytes received on each link, dropped or not.",
        labels=["autopilot"],
    )
    errors = CounterMetricFamily(
        f"{PREFIX}_link_errors",
        "Transport and parser failures of each link.",
        labels=["autopilot"],
    )
    events = CounterMetricFamily(
        f"{PREFIX}_link_events",
        "Link reopens (after a failure) and relocks (the autopilot moved address).",
        labels=["autopilot", "event"],
    )
    for name, c in counters.items():
        for result in FRAME_RESULTS:
            frames.add_metric([name, result], getattr(c, result))
        data.add_metric([name], c.bytes)
        errors.add_metric([name], c.errors)
        for event in LINK_EVENTS:
            events.add_metric([name, event], getattr(c, event))
    return [frames, data, errors, events]


class EventMetrics:
    """Counters and histograms of agent events, fed on the agent's notifier thread."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.failovers = Counter(
            f"{PREFIX}_failovers",
            "Bridge switches, by event reason (FailedOver, SwitchedByCommand, FailedBack) "
            "and the autopilots switched from and to.",
            ["reason", "from_autopilot", "to_autopilot"],
            registry=registry,
        )
        self.detection = Histogram(
            f"{PREFIX}_failover_detection_to_switch_seconds",
            "From the decision loop seeing the failure to the bridge switched.",
            buckets=DETECTION_BUCKETS,
            registry=registry,
        )
        self.onset = Histogram(
            f"{PREFIX}_failover_onset_to_switch_seconds",
            "From the failure's onset (as the health findings date it) to the bridge switched.",
            buckets=ONSET_BUCKETS,
            registry=registry,
        )
        self.safety = Counter(
            f"{PREFIX}_safety_routine_phases",
            "Safety routine phases reached (Started, Holding, Landing, Landed, Failed, ...).",
            ["autopilot", "phase"],
            registry=registry,
        )
        self.commands = Counter(
            f"{PREFIX}_commands",
            "Commands executed once per id, by result (Executed, Rejected, Expired).",
            ["result"],
            registry=registry,
        )
        self.events = Counter(
            f"{PREFIX}_events",
            "Every agent event, by kind and reason (the Kubernetes Event reasons).",
            ["kind", "reason"],
            registry=registry,
        )

    def observe(self, event: AgentEvent) -> None:
        """Count one event (a subscriber of :meth:`roost_agent.agent.Agent.subscribe`)."""
        self.events.labels(event.kind.value, event.reason).inc()
        if event.kind == EventKind.FAILOVER and event.failover is not None:
            f = event.failover
            record = f.record
            self.failovers.labels(event.reason, record.from_autopilot, record.to_autopilot).inc()
            self.detection.observe(f.switched_at - f.detected_at)
            if f.onset_at is not None:
                self.onset.observe(f.switched_at - f.onset_at)
        elif event.kind == EventKind.SAFETY and event.autopilot is not None:
            phase = event.reason.removeprefix("SafetyRoutine")
            self.safety.labels(event.autopilot, phase).inc()
        elif event.kind == EventKind.COMMAND and event.command is not None:
            self.commands.labels(event.command.result).inc()


def build_registry(
    agent: MetricsAgent,
    publisher: PublisherGauges | None = None,
    recorder: RecorderGauges | None = None,
) -> tuple[CollectorRegistry, Callable[[], None]]:
    """A registry with the agent's metrics; returns it and the unsubscribe function."""
    registry = CollectorRegistry(auto_describe=False)
    ProcessCollector(registry=registry)
    registry.register(AgentCollector(agent, publisher, recorder))
    events = EventMetrics(registry)
    return registry, agent.subscribe(events.observe)


class MetricsServer:
    """The agent's metrics endpoint: an HTTP server on its own daemon thread."""

    def __init__(
        self,
        agent: MetricsAgent,
        *,
        address: str = DEFAULT_ADDRESS,
        port: int = DEFAULT_PORT,
        publisher: PublisherGauges | None = None,
        recorder: RecorderGauges | None = None,
    ) -> None:
        self.registry, self._unsubscribe = build_registry(agent, publisher, recorder)
        server: WSGIServer
        try:
            server, self._thread = start_http_server(port, address, self.registry)
        except OSError:
            self._unsubscribe()
            raise
        self._server = server
        self.address = address
        self.port = int(server.server_address[1])

    def close(self) -> None:
        """Stop serving and stop counting events."""
        self._unsubscribe()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2)
