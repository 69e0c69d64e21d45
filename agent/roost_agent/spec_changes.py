"""A new spec for a running agent, and the state a starting agent resumes from it.

Why this module exists apart from the decision loop (:mod:`roost_agent.agent`): what may
change while the agent runs is a set of rules of its own. The set of autopilots and
their bridge channels cannot change (the bridge hardware is claimed per channel; the
agent restarts), nor can the hub's endpoints or identity; connection details change
only on the ground (a reopened link starts without data); thresholds, policy and the
hub's mirroring settings change at once. The loop works with one :class:`Running`
configuration, swapped as one object, so a tick never sees half a change.

:class:`SpecChanges` is a part of :class:`roost_agent.agent.Agent` (its methods work on
the agent's links and configuration under its spec lock); it is kept here so the loop,
its actions and spec changes can each be read on their own.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

from roost_agent.arbiter import ArbiterState, Policy
from roost_agent.events import EventKind
from roost_agent.health import Assessment, HealthTracker
from roost_agent.hub import hub_identity
from roost_agent.link import AutopilotLink
from roost_agent.parts import AgentParts, Running
from roost_agent.reader import LinkReader
from roost_agent.signing import LinkSigning
from roost_agent.state import PersistedState
from roost_api.plain import AutopilotSpec, RedundantAutopilotSpec
from roost_mavlink import pymavlink_device


def restore_state(spec: RedundantAutopilotSpec, saved: PersistedState | None) -> ArbiterState:
    """The arbiter state to start from: the saved one when it fits the spec, else primary.

    Only durable facts are restored (active, latch, failed-from, count); timers and the
    flight state are rebuilt from live telemetry, so nothing is decided on stale data.
    """
    names = {a.name for a in spec.autopilots}
    if saved is None or saved.active not in names:
        return ArbiterState(active=spec.primary)
    return ArbiterState(
        active=saved.active,
        latched=saved.latched,
        failed_from=frozenset(saved.failed_from) & names,
        failover_count=saved.failover_count,
    )


def connection_problems(spec: RedundantAutopilotSpec) -> list[str]:
    """One line per autopilot whose connection URL the agent could not open."""
    problems = []
    for autopilot in spec.autopilots:
        try:
            pymavlink_device(autopilot.connection)
        except ValueError as exc:
            problems.append(f"autopilot {autopilot.name}: {exc}")
    return problems


class SpecChanges(AgentParts):
    """The agent's side that adopts a new spec (see the module docstring)."""

    # What spec changes touch of the agent besides its shared parts (set by Agent).
    _spec_lock: threading.Lock
    _reader: LinkReader
    _signing: LinkSigning | None

    if TYPE_CHECKING:

        def assessments(self) -> dict[str, Assessment]:
            """The decision loop's latest judgement of every autopilot (roost_agent.agent)."""

    def _new_link(self, spec_ap: AutopilotSpec, spec: RedundantAutopilotSpec) -> AutopilotLink:
        tracker = HealthTracker(spec_ap.name, spec_ap.stack, spec.failover_policy.thresholds)
        name = spec_ap.name

        def link_event(reason: str, message: str, warning: bool) -> None:
            self._emit(EventKind.LINK, reason, message, warning=warning, autopilot=name)

        return AutopilotLink(
            spec_ap,
            tracker,
            on_change=self._reader.poke,
            clock=self._clock,
            signing=self._signing,
            on_event=link_event,
            reader=self._reader,
        )

    def _apply_spec(self, spec: RedundantAutopilotSpec, generation: int | None) -> str | None:
        with self._spec_lock:
            cfg = self._cfg
            old = {a.name: a for a in cfg.spec.autopilots}
            new = {a.name: a for a in spec.autopilots}
            channels = {a.name: a.bridge_channel for a in spec.autopilots}
            if set(old) != set(new) or channels != dict(cfg.channels):
                return "the autopilots or their bridge channels changed; restart the agent"
            if hub_identity(spec) != hub_identity(cfg.spec):
                return "the hub's endpoints or identity changed; restart the agent"
            unusable = connection_problems(spec)
            if unusable:
                return "; ".join(unusable)
            changed = [n for n in new if new[n] != old[n]]
            in_flight = self._state.in_flight is True or any(
                a.in_air is True for a in self.assessments().values()
            )
            if changed and in_flight:
                return f"connection details of {', '.join(changed)} change only on the ground"
            links = dict(cfg.links)
            retired = [links[n] for n in changed]
            for name in changed:
                links[name] = self._new_link(new[name], spec)
                if self._hub is not None:
                    self._hub.attach(links[name])
                links[name].start()
            for link in links.values():
                link.tracker.set_thresholds(spec.failover_policy.thresholds)
            if self._hub is not None and spec.hub is not None:
                self._hub.configure(spec.hub)
            self._cfg = Running(
                spec=spec,
                generation=generation,
                policy=Policy.from_spec(spec),
                links=links,
                channels=channels,
            )
        for link in retired:
            link.stop()
        self._persist()
        return None
