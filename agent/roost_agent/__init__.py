"""Roost node agent: watches a vehicle's autopilots and keeps a healthy one on the motors.

Modules, from the wire up: :mod:`~roost_agent.transport` (byte pipes: UDP, TCP,
serial), :mod:`~roost_agent.trust` (the source lock), :mod:`~roost_agent.reader` (one
reader thread for every link, which also runs the decision loop),
:mod:`~roost_agent.link` (one MAVLink connection per autopilot; frames are read and
written by :mod:`roost_mavlink.codec`, the agent never imports pymavlink),
:mod:`~roost_agent.health` (messages -> OK/WARN/ERROR/STALE),
:mod:`~roost_agent.arbiter` (pure failover state machine), :mod:`~roost_agent.bridge`
(GPIO or simulated switch), :mod:`~roost_agent.safety` (hold, then land),
:mod:`~roost_agent.state` (durable state) and :mod:`~roost_agent.agent` (the wiring).
Never imports kopf: the agent must run on a vehicle that cannot reach the cluster.
"""

from roost_agent.agent import Agent
from roost_agent.events import AgentEvent, EventKind, FailoverEvent
from roost_agent.spec_changes import restore_state

__all__ = ["Agent", "AgentEvent", "EventKind", "FailoverEvent", "restore_state"]
