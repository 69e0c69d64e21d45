"""Connects the node agent to Kubernetes: status out, spec and commands in.

The agent decides and switches on its own; this module only reports and listens, on
threads of its own, so nothing here can delay a switch (the agent's notifier hands
events over; the listener below only queues them and wakes a thread).

**Identity.** :func:`discover` finds the Vehicle whose ``spec.nodeName`` is this node
(``NODE_NAME`` from the downward API) and the RedundantAutopilot whose
``spec.vehicleName`` is that Vehicle. Until both exist the publisher keeps looking; when
the operator relabels the RedundantAutopilot for another node (a hot swap), it lets go.

**Status out** (thread ``publisher``). The status is a level, not a log: every write is
the agent's complete :meth:`~roost_agent.agent.Agent.status` (active autopilot, health,
last failover, failover count, latch, last command, conditions), so a write that follows
an outage carries everything that happened during it. When to write is decided by
:func:`roost_agent.report.change_class`:

* a switch, a latch change or a command result is written at once (target: visible in
  the API within 200 ms of the bridge switching);
* routine changes (a health level, mode, armed, landed state) at most once per
  ``min_interval_s``, so a flapping link costs one write per interval, not one per flap;
* nothing new: a refresh every ``refresh_s`` (10 s) so ``reportedAt`` shows the agent is
  alive; the operator calls reports older than three periods stale.

Failed writes are retried with exponential backoff (``retry_min_s`` to ``retry_max_s``);
the state is never queued, only the latest is sent. Condition transition times carry
over from what was last written (read back at discovery), so an agent restart does not
reset them.

**Telemetry announcement.** With ``announce`` (the live stream served where a dashboard
off the vehicle can reach it, :func:`roost_api.telemetry.telemetry_annotations`), the
Vehicle is annotated with it once discovered, unless it already carries it, so nobody
has to annotate Vehicles by hand and a new agent pod corrects a stale pod name.

**Events.** One Kubernetes Event per failover, and per command result, landing order,
emergency stop, safety-routine phase, refused spec and bridge error — never per health
change (those are conditions; Events for them would be a storm under a flapping link).
Events queue while the API is away (the newest ``max_pending_events``) and are posted on
return with their original time; deterministic names make a re-post a no-op.

**Spec and commands in** (thread ``spec-follower``). A watch on the RedundantAutopilot
(field selector on its name): a new ``metadata.generation`` goes to
:meth:`~roost_agent.agent.Agent.apply_spec` (which keeps the spec on disk, so a restart
without the API flies on with it), a new ``spec.command`` to
:meth:`~roost_agent.agent.Agent.submit`, which executes each id at most once (the ids
are kept on disk) and lets the arbiter expire commands seen after their deadline — the
case of a command issued before a partition and seen after it. Every watch starts with
the object as it is, so a dropped watch loses nothing.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from roost_agent.events import AgentEvent, EventKind
from roost_agent.kube import AgentKube
from roost_agent.report import change_class, set_condition, write_delay
from roost_agent.state import StateFile
from roost_api.plain import (
    AutopilotCommand,
    CommandResult,
    Condition,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.plain_check import PlainValidationError
from roost_api.wellknown import LABEL_NODE
from roost_kube.errors import ApiError, ApiUnavailableError
from roost_kube.patches import Obj, merge_patch_fields

log = logging.getLogger(__name__)

# Agent events that become Kubernetes Events; health changes deliberately do not.
POSTED_KINDS = frozenset(
    {
        EventKind.STARTED,
        EventKind.FAILOVER,
        EventKind.COMMAND,
        EventKind.SAFETY,
        EventKind.LAND_ORDERED,
        EventKind.NO_HEALTHY_STANDBY,
        EventKind.EMERGENCY_STOP,
        EventKind.BRIDGE_ERROR,
        EventKind.LINK,
    }
)
URGENT_KINDS = frozenset({EventKind.FAILOVER, EventKind.COMMAND, EventKind.EMERGENCY_STOP})
REJECTED_SPEC = "SpecRejected"
PARAMETER_DRIFTED = "ParameterDrifted"
# Events of other kinds posted by reason: a refused spec, and a parameter someone else
# changed (once per change; the other parameter events are the condition's steps).
POSTED_REASONS = frozenset(
    {(EventKind.SPEC, REJECTED_SPEC), (EventKind.PARAMETERS, PARAMETER_DRIFTED)}
)


def posted(event: AgentEvent) -> bool:
    """Whether an agent event becomes a Kubernetes Event."""
    return event.kind in POSTED_KINDS or (event.kind, event.reason) in POSTED_REASONS


class ReportingAgent(Protocol):
    """What the publisher needs of :class:`roost_agent.agent.Agent`."""

    def status(self) -> RedundantAutopilotStatus: ...

    def subscribe(self, listener: Callable[[AgentEvent], None]) -> Callable[[], None]: ...

    def submit(self, command: AutopilotCommand) -> Future[CommandResult]: ...

    def apply_spec(
        self, spec: RedundantAutopilotSpec, generation: int | None = None
    ) -> str | None: ...


@dataclass(frozen=True)
class PublisherSettings:
    """Timing of the publisher; the defaults suit a fleet, tests shorten them."""

    refresh_s: float = 10.0
    """Re-report at least this often; the operator's staleness window is 3x this."""
    min_interval_s: float = 1.0
    """Routine (non-urgent) changes are coalesced to at most one write per interval."""
    retry_min_s: float = 0.5
    """First retry delay after a failed API call; doubles up to ``retry_max_s``."""
    retry_max_s: float = 4.0
    """Longest retry delay while the API is unreachable. It bounds how far the status
    lags behind a link that comes back (a WiFi drop: with the 2 s connect timeout the
    status shows what happened during the drop within about 6 s); a retry costs one
    connection attempt."""
    rediscover_s: float = 5.0
    """How often to look again for a Vehicle/RedundantAutopilot that does not exist yet."""
    watch_timeout_s: int = 60
    """Server-side timeout of one watch; the follower then simply watches again."""
    max_pending_events: int = 256
    """Events kept while the API is away; older ones are dropped (and counted)."""


@dataclass(frozen=True)
class Target:
    """The objects this agent reports on."""

    vehicle: str
    autopilot: Obj
    vehicle_annotations: Mapping[str, str] = field(default_factory=dict)
    """The Vehicle's annotations as read at discovery (the telemetry announcement)."""

    @property
    def name(self) -> str:
        """The RedundantAutopilot's name."""
        return str(self.autopilot["metadata"]["name"])

    @property
    def uid(self) -> str:
        """The RedundantAutopilot's uid (changes if it is deleted and created again)."""
        return str(self.autopilot["metadata"].get("uid", ""))

    def spec(self) -> RedundantAutopilotSpec:
        """Its spec, validated."""
        return RedundantAutopilotSpec.from_api(self.autopilot["spec"])

    @property
    def generation(self) -> int | None:
        """Its ``metadata.generation``."""
        value = self.autopilot["metadata"].get("generation")
        return int(value) if value is not None else None

    def status(self) -> RedundantAutopilotStatus | None:
        """The status as last stored in the API, if it parses."""
        raw = self.autopilot.get("status")
        if not raw:
            return None
        try:
            return RedundantAutopilotStatus.from_api(raw)
        except PlainValidationError:
            return None


def discover(kube: AgentKube, node_name: str) -> Target | None:
    """This node's Vehicle and RedundantAutopilot, or None while either is missing."""
    vehicle = kube.find_vehicle(node_name)
    if vehicle is None:
        return None
    name = str(vehicle["metadata"]["name"])
    autopilot = kube.find_autopilot(name, node_name)
    annotations = dict(vehicle["metadata"].get("annotations") or {})
    return Target(name, autopilot, annotations) if autopilot is not None else None


def announcement(current: Mapping[str, str], wanted: Mapping[str, str]) -> dict[str, str]:
    """The annotations to write on the Vehicle so that it carries ``wanted`` (empty: it
    already does)."""
    return {key: value for key, value in wanted.items() if current.get(key) != value}


def startup_spec(
    kube: AgentKube,
    node_name: str,
    state_file: StateFile,
    *,
    retry_s: float = 2.0,
    stop: threading.Event | None = None,
) -> tuple[RedundantAutopilotSpec, int | None, Target | None]:
    """The spec to start flying with in a cluster, and the target when the API answered.

    The API's RedundantAutopilot when it can be read; else the spec saved on disk by the
    last run (an agent restarted during a partition flies on with it, and the publisher
    keeps looking for the API); with neither, wait and try again — without a spec there
    is nothing to supervise.
    """
    stop = stop or threading.Event()
    while True:
        try:
            target = discover(kube, node_name)
            if target is not None:
                return target.spec(), target.generation, target
            why = f"no Vehicle with spec.nodeName={node_name} and a RedundantAutopilot for it"
        except (ApiUnavailableError, PlainValidationError) as exc:
            why = f"cannot read the RedundantAutopilot: {exc}"
        saved = state_file.load()
        if saved is not None:
            log.warning("%s; flying on with the spec saved in %s", why, state_file.path)
            return saved.spec, saved.generation, None
        log.warning("%s; nothing saved in %s either, waiting", why, state_file.path)
        if stop.wait(retry_s):
            raise SystemExit("stopped before a spec was found")


def carry_transitions(
    written: Sequence[Condition], current: Iterable[Condition]
) -> list[Condition]:
    """``current`` with each transition time kept from ``written`` where status is unchanged.

    The agent computes conditions in memory, so after a restart its transition times start
    afresh; merging against what the API already holds keeps them true.
    """
    result = list(written)
    for cond in current:
        result = set_condition(
            result,
            type=cond.type,
            status=cond.status,
            reason=cond.reason,
            message=cond.message,
            observed_generation=cond.observed_generation,
            at=cond.last_transition_time,
        )
    kept = {c.type for c in current}
    return [c for c in result if c.type in kept]


def merge_patch_body(status: RedundantAutopilotStatus) -> dict[str, Any]:
    """The whole status as a JSON merge patch that leaves nothing stale behind.

    A missing key means "keep" in a merge patch, so emptied fields go as explicit nulls,
    and so do emptied members of object fields (``lastFailover.safetyRoutine``); lists
    are replaced whole and go without nulls (:func:`roost_kube.patches.merge_patch_fields`,
    the rule of every Roost status write).
    """
    return merge_patch_fields(status)


class Publisher:
    """Reports one agent's status and Events, and follows its RedundantAutopilot."""

    def __init__(
        self,
        agent: ReportingAgent,
        kube: AgentKube,
        *,
        node_name: str,
        target: Target | None = None,
        settings: PublisherSettings | None = None,
        clock: Callable[[], float] = time.monotonic,
        announce: Mapping[str, str] | None = None,
    ) -> None:
        self._agent = agent
        self._announce = dict(announce or {})
        self._announced: str | None = None  # the Vehicle that carries the announcement
        self._kube = kube
        self._node_name = node_name
        self._settings = settings or PublisherSettings()
        self._clock = clock
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._target = target
        self._target_ready = threading.Event()
        self._events: deque[AgentEvent] = deque()
        self._kick = False
        self._last_written: RedundantAutopilotStatus | None = None
        self._last_write_at = float("-inf")
        self._retry_at = float("-inf")
        self._backoff = 0.0
        self.api_errors = 0  # failed API calls (a metrics counter)
        self._followed: tuple[str, int | None] | None = None
        self._seen_command: str | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self._threads: list[threading.Thread] = []
        if target is not None:
            self._adopt(target, applied=True)

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Subscribe to the agent and start the publisher and spec-follower threads."""
        self._unsubscribe = self._agent.subscribe(self._on_event)
        for run, name in (
            (self._publish_forever, "publisher"),
            (self._follow_forever, "spec-follower"),
        ):
            thread = threading.Thread(target=run, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        """Stop both threads (a watch in progress ends at its next event or timeout)."""
        self._stop.set()
        self._target_ready.set()
        if self._unsubscribe is not None:
            self._unsubscribe()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            thread.join(timeout=2)

    @property
    def pending_events(self) -> int:
        """Events queued for the API server (the newest ``max_pending_events``)."""
        return len(self._events)

    @property
    def target(self) -> Target | None:
        """The objects reported on, once discovered."""
        return self._target

    # -- agent events (on the agent's notifier thread: queue and wake only) -------------

    def _on_event(self, event: AgentEvent) -> None:
        post = posted(event)
        with self._cond:
            if post:
                if len(self._events) >= self._settings.max_pending_events:
                    dropped = self._events.popleft()
                    log.warning("API away too long: dropping Event %s", dropped.reason)
                self._events.append(event)
            self._kick = True
            self._cond.notify()

    # -- status out --------------------------------------------------------------------

    def _publish_forever(self) -> None:
        while not self._stop.is_set():
            try:
                wait = self._publish_step()
            except Exception:  # never let a bug end reporting; log and slow down
                log.exception("publisher step failed")
                wait = self._settings.retry_max_s
            with self._cond:
                if not self._kick and not self._stop.is_set():
                    self._cond.wait(max(wait, 0.0))
                self._kick = False

    def _failed(self, what: str, exc: Exception) -> float:
        self.api_errors += 1
        settings = self._settings
        self._backoff = min(max(self._backoff * 2, settings.retry_min_s), settings.retry_max_s)
        self._retry_at = self._clock() + self._backoff
        log.warning("%s failed (%s); retrying in %.1f s", what, exc, self._backoff)
        return self._backoff

    def _adopt(self, target: Target, *, applied: bool) -> None:
        """Take ``target`` as the object to report on; ``applied``: its spec already runs."""
        self._target = target
        written = target.status()
        if written is not None and written.node_name in (None, "", self._node_name):
            self._last_written = written
        if applied:
            self._followed = (target.uid, target.generation)
        self._target_ready.set()

    def _publish_step(self) -> float:
        """Do whatever is due; return how long to sleep at most."""
        settings = self._settings
        now = self._clock()
        if now < self._retry_at:
            return self._retry_at - now
        if self._target is None:
            try:
                target = discover(self._kube, self._node_name)
            except ApiUnavailableError as exc:
                return self._failed("discovery", exc)
            if target is None:
                log.info("no Vehicle/RedundantAutopilot for node %s yet", self._node_name)
                return settings.rediscover_s
            self._adopt(target, applied=False)
        target = self._target
        assert target is not None
        if self._announced != target.vehicle:
            wait = self._announce_step(target)
            if wait is not None:
                return wait
        status = self._agent.status()
        if self._last_written is not None:
            status = replace(
                status,
                conditions=carry_transitions(self._last_written.conditions, status.conditions),
            )
        delay = write_delay(
            change_class(self._last_written, status),
            now - self._last_write_at,
            min_interval_s=settings.min_interval_s,
            refresh_s=settings.refresh_s,
        )
        if delay <= 0:
            try:
                self._kube.patch_autopilot_status(target.name, merge_patch_body(status))
            except ApiUnavailableError as exc:
                return self._failed("status write", exc)
            except ApiError as exc:
                if exc.status == 404:
                    log.warning("RedundantAutopilot %s is gone; looking again", target.name)
                    self._target = None
                    self._announced = None  # its Vehicle may be a new one too
                    self._target_ready.clear()
                    return 0.0
                return self._failed("status write", exc)
            self._last_written = status
            self._last_write_at = self._clock()
            self._backoff = 0.0
            delay = settings.refresh_s
        if not self._post_events(target):
            return self._backoff
        return delay

    def _announce_step(self, target: Target) -> float | None:
        """Write the telemetry announcement on the Vehicle when it lacks it; a wait when
        the API is away (retried), None otherwise. A refusal (an installation without
        the RBAC for it) is logged once and not retried: the stream is only for eyes."""
        patch = announcement(target.vehicle_annotations, self._announce)
        if patch:
            try:
                self._kube.annotate_vehicle(target.vehicle, patch)
            except ApiUnavailableError as exc:
                return self._failed("telemetry announcement", exc)
            except ApiError as exc:
                log.warning(
                    "cannot announce the telemetry stream on Vehicle %s (%s); "
                    "annotate it by hand for the dashboard",
                    target.vehicle,
                    exc,
                )
            else:
                log.info("telemetry announced on Vehicle %s: %s", target.vehicle, patch)
        self._announced = target.vehicle
        return None

    def _post_events(self, target: Target) -> bool:
        """Post queued Events in order; False when the API failed (they stay queued)."""
        while True:
            with self._cond:
                if not self._events:
                    return True
                event = self._events[0]
            try:
                self._kube.post_event(
                    target.autopilot,
                    reason=event.reason,
                    message=event.message,
                    warning=event.warning,
                    at=event.time,
                    node_name=self._node_name,
                )
            except ApiError as exc:
                self._failed(f"event {event.reason}", exc)
                return False
            with self._cond:
                if self._events and self._events[0] is event:
                    self._events.popleft()

    # -- spec and commands in ------------------------------------------------------------

    def _follow_forever(self) -> None:
        backoff = 0.0
        settings = self._settings
        while not self._stop.is_set():
            self._target_ready.wait()
            target = self._target
            if self._stop.is_set() or target is None:
                continue
            try:
                for kind, obj in self._kube.watch_autopilot(target.name, settings.watch_timeout_s):
                    if self._stop.is_set():
                        return
                    backoff = 0.0
                    if kind == "DELETED":
                        log.warning("RedundantAutopilot %s was deleted", target.name)
                        break
                    if kind in ("ADDED", "MODIFIED"):
                        self._follow(obj)
                    if self._target is None:
                        break
            except ApiError as exc:
                self.api_errors += 1
                backoff = min(max(backoff * 2, settings.retry_min_s), settings.retry_max_s)
                log.warning("watch of %s failed (%s); again in %.1f s", target.name, exc, backoff)
                self._stop.wait(backoff)

    def _follow(self, obj: Obj) -> None:
        """Hand a new spec or a new command from the API to the agent.

        When the operator has labelled the RedundantAutopilot with another node (its
        Vehicle moved: a hot swap), this agent stops reporting on it and looks for a
        Vehicle on its own node again, so two agents never write one status.
        """
        node = (obj["metadata"].get("labels") or {}).get(LABEL_NODE)
        if node and node != self._node_name:
            log.warning(
                "RedundantAutopilot %s now belongs to node %s: no longer reporting on it",
                obj["metadata"]["name"],
                node,
            )
            self._target_ready.clear()
            self._target = None
            return
        target = replace(self._target, autopilot=obj) if self._target else Target("", obj)
        try:
            spec = target.spec()
        except PlainValidationError as exc:
            log.error("ignoring an invalid spec of %s: %s", target.name, exc)
            return
        key = (target.uid, target.generation)
        if key != self._followed:
            self._followed = key
            self._agent.apply_spec(spec, target.generation)  # also submits its command
        elif spec.command is not None and spec.command.id != self._seen_command:
            self._agent.submit(spec.command)
        self._seen_command = spec.command.id if spec.command is not None else None
        self._target = target
