"""The agent's metric collectors on a real Agent whose links are bound UDP sockets, and a
real Publisher whose API server refuses connections (a closed loopback port).

The registry is rendered with prometheus_client's exposition and read back with its
parser; the pure event metrics are in ``tests/unit/test_agent_metrics.py``, the scraped
agent in ``tests/integration/test_agent_metrics_endpoint.py``.
"""

from __future__ import annotations

from roost_agent.agent import Agent
from roost_agent.bridge import SimulatedBridge
from roost_agent.hub_policy import NOT_ALLOWED
from roost_agent.kube import AgentKube
from roost_agent.metrics import (
    build_registry,
)
from roost_agent.publisher import Publisher, PublisherSettings
from roost_api.autopilot import HubEndpoint, HubSpec
from roost_api.ports import free_port
from roost_kube.client import Kube
from roost_kube.transport import Credentials, DirectTransport
from tests.support.feed import two_px4_spec
from tests.support.prometheus import samples
from tests.support.waiting import wait_until


def make_agent() -> Agent:
    """An agent (not started: no threads) on two UDP links nobody sends to."""
    spec = two_px4_spec(15000)
    return Agent(spec, SimulatedBridge([0, 1]))


def test_collector_reads_health_active_and_link_counters() -> None:
    agent = make_agent()
    agent.tick()  # assess: nothing heard yet
    link = agent.links["fc2"]
    link.counters.accepted = 120
    link.counters.bad_signature = 3
    link.counters.bytes = 9000
    link.counters.errors = 1
    link.counters.relocked = 2
    registry, unsubscribe = build_registry(agent)
    got = samples(registry)
    unsubscribe()
    assert got[("roost_agent_active_autopilot", (("autopilot", "fc1"),))] == 1
    assert got[("roost_agent_active_autopilot", (("autopilot", "fc2"),))] == 0
    assert got[("roost_agent_latched", ())] == 0
    # silent since start: STALE (4), and the state-set agrees
    assert got[("roost_agent_autopilot_health_level", (("autopilot", "fc2"),))] == 4
    assert got[("roost_agent_autopilot_health", (("autopilot", "fc2"), ("level", "STALE")))] == 1
    assert got[("roost_agent_autopilot_health", (("autopilot", "fc2"), ("level", "OK")))] == 0
    frames = "roost_agent_link_frames_total"
    assert got[(frames, (("autopilot", "fc2"), ("result", "accepted")))] == 120
    assert got[(frames, (("autopilot", "fc2"), ("result", "bad_signature")))] == 3
    assert got[(frames, (("autopilot", "fc1"), ("result", "accepted")))] == 0
    assert got[("roost_agent_link_received_bytes_total", (("autopilot", "fc2"),))] == 9000
    assert got[("roost_agent_link_errors_total", (("autopilot", "fc2"),))] == 1
    events = "roost_agent_link_events_total"
    assert got[(events, (("autopilot", "fc2"), ("event", "relocked")))] == 2
    assert ("roost_agent_publisher_pending_events", ()) not in got  # standalone: no publisher


def test_publisher_queue_and_api_errors_while_the_api_is_unreachable() -> None:
    """A real Publisher whose API server refuses connections (a closed loopback port)."""
    port = free_port()  # nobody listens on it: connections refused
    transport = DirectTransport(Credentials(host=f"http://127.0.0.1:{port}"), retries=0)
    kube = AgentKube(Kube(transport, "roost-agent", (1.0, 1.0)))
    agent = make_agent()
    publisher = Publisher(
        agent,
        kube,
        node_name="n1",
        settings=PublisherSettings(retry_min_s=0.05, retry_max_s=0.1),
    )
    registry, unsubscribe = build_registry(agent, publisher)
    publisher.start()
    agent.start()  # posts AgentStarted: queued, since nothing can be delivered
    try:
        wait_until(
            "discovery failed twice and the Started Event waits",
            lambda: publisher.api_errors >= 2 and publisher.pending_events >= 1,
            10,
        )
        got = samples(registry)
        assert got[("roost_agent_publisher_api_errors_total", ())] >= 2
        assert got[("roost_agent_publisher_pending_events", ())] >= 1
    finally:
        unsubscribe()
        agent.stop()
        publisher.stop()


def test_hub_drops_are_exported_per_endpoint_and_reason() -> None:
    spec = two_px4_spec(15010).model_copy(
        update={
            "hub": HubSpec(
                udp="127.0.0.1:0",
                endpoints=[HubEndpoint(name="ro", address="127.0.0.1:0", scope="ReadOnly")],
            )
        }
    )
    agent = Agent(spec, SimulatedBridge([0, 1]))
    try:
        hub = agent.hub
        assert hub is not None
        ro = next(e for e in hub.endpoints if e.name == "ro")
        ro.drops.note(("127.0.0.1", 40000), NOT_ALLOWED, 0.0)
        ro.drops.note(("127.0.0.1", 40001), NOT_ALLOWED, 1.0)
        registry, unsubscribe = build_registry(agent)
        got = samples(registry)
        unsubscribe()
    finally:
        hub = agent.hub
        if hub is not None:
            hub.close()
    dropped = "roost_agent_hub_dropped_frames_total"
    assert got[(dropped, (("endpoint", "ro"), ("reason", "not_allowed")))] == 2
    assert got[(dropped, (("endpoint", "udp"), ("reason", "unsigned")))] == 0
    assert (dropped, (("endpoint", "ro"), ("reason", "accepted"))) not in got
