"""What the agent's parts share: the configuration and state they work on, and the two
outlets every part reports through (events to subscribers, the state file).

Why this module exists: the agent (:class:`roost_agent.agent.Agent`) is one object with
one lock, and its code is kept in three modules a newcomer can read on their own: the
decision loop (:mod:`roost_agent.agent`), what its actions do
(:mod:`roost_agent.actions`) and how it adopts a new spec
(:mod:`roost_agent.spec_changes`). Each of those declares what it touches; this holds
what they all touch, so the declarations are made once and mypy checks every part
against the same types. Agent's ``__init__`` sets every attribute declared here.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime

from roost_agent.arbiter import ArbiterState, Policy
from roost_agent.events import AgentEvent, EventKind, FailoverEvent
from roost_agent.hub import Hub
from roost_agent.link import AutopilotLink
from roost_agent.state import PersistedState, SafetyProgress, StateFile
from roost_api.plain import AutopilotHealth, CommandResult, FailoverRecord, RedundantAutopilotSpec

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Running:
    """The configuration the decision loop works with; swapped as one object."""

    spec: RedundantAutopilotSpec
    generation: int | None
    policy: Policy
    links: Mapping[str, AutopilotLink]
    channels: Mapping[str, int]


class AgentParts:
    """The state every part of the agent works on (set by ``Agent.__init__``) and the
    outlets they report through."""

    _lock: threading.RLock
    _persist_lock: threading.Lock
    _cfg: Running
    _state: ArbiterState
    _hub: Hub | None
    _clock: Callable[[], float]
    _wall_clock: Callable[[], datetime]
    _state_file: StateFile | None
    _events: queue.SimpleQueue[AgentEvent | None]
    _last_failover: FailoverRecord | None
    _processed: OrderedDict[str, CommandResult]
    _safety: SafetyProgress | None

    def _persist(self) -> None:
        if self._state_file is None:
            return
        with self._lock:
            cfg, state = self._cfg, self._state
            snapshot = PersistedState(
                spec=cfg.spec,
                generation=cfg.generation,
                active=state.active,
                latched=state.latched,
                failed_from=sorted(state.failed_from),
                failover_count=state.failover_count,
                last_failover=self._last_failover,
                commands=list(self._processed.values()),
                safety=self._safety,
                saved_at=self._wall_clock(),
            )
        with self._persist_lock:
            try:
                self._state_file.save(snapshot)
            except OSError:
                log.exception("cannot write the state file %s", self._state_file.path)

    def _emit(
        self,
        kind: EventKind,
        reason: str,
        message: str,
        *,
        warning: bool = False,
        autopilot: str | None = None,
        failover: FailoverEvent | None = None,
        health: AutopilotHealth | None = None,
        command: CommandResult | None = None,
    ) -> None:
        self._events.put(
            AgentEvent(
                kind,
                reason,
                message,
                warning,
                self._wall_clock(),
                autopilot,
                failover,
                health,
                command,
            )
        )
