"""The node agent: links, health, arbiter, bridge and safety routine wired together.

Threads and why:

- one reader thread (:class:`roost_agent.links.LinkReader`) reads every autopilot link,
  feeds the health trackers and runs the decision loop: every ``tick_s``, at once when a
  link saw something the arbiter acts on change or a command came, and exactly when the
  last tick said a judgement turns with nothing arriving (a silence threshold, the end
  of a confirm window), right after reading whatever arrived, it assesses every
  autopilot, steps the pure arbiter and executes its actions. One thread, one wake-up
  per tick: on a companion computer the wake-ups and GIL hand-offs of a thread per link
  and a separate loop cost more than the parsing. Messages keep their kernel arrival
  times, so reading once per tick does not age them; while a hub client is connected the
  reader wakes for every datagram (routed frames are not held back). The switch path is
  local and immediate: assessment, arbiter and the bridge write, with no logging, no
  network and no disk in between. Everything slower happens after the bridge switched;
- a worker runs the safety routine, landing orders and the emergency stop one at a time
  (a newer job supersedes an older one, nothing supersedes an emergency stop), so the
  decision loop never waits for an autopilot to answer;
- a heartbeat thread sends the agent's 1 Hz heartbeat on every link and, on the same
  beat (faster: every :data:`STREAM_CHECK_S`), lets each link's stream keeper
  (:mod:`roost_agent.streams`) request the telemetry the health model needs;
- a notifier delivers :class:`AgentEvent` objects to subscribers (the standalone JSON
  printer now, the Kubernetes publisher later) so a slow subscriber cannot stall a switch.

Every switch records its reason and the measured latency from detection (the start of
the decision tick that saw the confirmed failure) to the bridge write returning, plus
onset-to-switch when the health findings know the onset. Durable state goes to disk
(:mod:`roost_agent.state`) right after the switch, so a restarted agent keeps the
autopilot it chose and its latch; so does every step of the safety routine, which a
restarted agent resumes where it was (:meth:`roost_agent.safety.SafetyRunner.resume`).

For the publisher (:mod:`roost_agent.publisher`) the public surface is:
:meth:`Agent.status` (a complete ``RedundantAutopilotStatus``, conditions from
:mod:`roost_agent.report`),
:meth:`Agent.subscribe` (events: failovers, health changes, safety-routine progress,
command results), :meth:`Agent.submit` (execute an ``AutopilotCommand`` at most once per
id, also across restarts) and :meth:`Agent.apply_spec` (a new spec from the cluster).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from roost_agent import firmware
from roost_agent.arbiter import (
    Action,
    ArbiterState,
    AutopilotView,
    CommandDone,
    Decision,
    ForceDisarm,
    LandInPlace,
    NoHealthyStandby,
    Policy,
    RunSafetyRoutine,
    SafetyPlan,
    SwitchBridge,
    Trigger,
    handle_command,
    next_due,
    settled,
    step,
)
from roost_agent.bridge import Bridge, BridgeError
from roost_agent.fence import Fences
from roost_agent.fence import Verdict as FenceVerdict
from roost_agent.health import Assessment, HealthTracker
from roost_agent.hub import Hub, InStep, hub_for, hub_identity
from roost_agent.links import AutopilotLink, LinkReader
from roost_agent.params import ParamKeeper, Read, Verdict
from roost_agent.report import report, set_condition
from roost_agent.safety import (
    DEFAULT_TIMING,
    TERMINAL_PHASES,
    WARNING_PHASES,
    Phase,
    Progress,
    SafetyRunner,
    Timing,
)
from roost_agent.signing import LinkSigning
from roost_agent.state import (
    MAX_REMEMBERED_COMMANDS,
    PersistedState,
    SafetyProgress,
    StateFile,
)
from roost_agent.streams import StreamKeeper, Why, send_requests
from roost_api.autopilot_enums import (
    AutopilotEntryConditionType,
    CommandResultKind,
    DriftPolicy,
    FinalAction,
    SafetyRoutinePhase,
)
from roost_api.core import ConditionStatus, HealthLevel, Stack
from roost_api.fence import LatLon
from roost_api.plain import (
    AutopilotCommand,
    AutopilotHealth,
    AutopilotSpec,
    CommandResult,
    FailoverRecord,
    FirmwareInfo,
    ParametersSpec,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.plain_check import ApiDocument
from roost_mavlink import (
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_MODE_FLAG_SAFETY_ARMED,
    pymavlink_device,
)

log = logging.getLogger(__name__)

DEFAULT_TICK_S = 0.02
"""How long a datagram may wait to be read while no hub client hurries the reader: the
decision loop reads and ticks this often. Judgements that turn with nothing arriving
(a silence crossing its threshold, the confirm window of a failure ending) are not
held to it: :meth:`Agent.tick` says when the next one is due and the loop ticks then.
Each wake-up costs the agent more than the messages it reads (docs/performance.md)."""
STEERED_TICK_S = 0.1
"""The read interval while every link is steered (:mod:`roost_agent.steering`): the
kernel wakes the reader at once for a heartbeat or a command's answer, so only the bulk
of the stream waits this long, and it is judged by its arrival stamps. While a claim
waits for the message that settles it, the loop reads again after ``DEFAULT_TICK_S``."""
JUDGE_LATE_S = 1e-4
"""A tick meant for a health threshold comes this much after it: the judgement there
compares a difference of float times with the threshold and must see it crossed."""
HEARTBEAT_PERIOD_S = 1.0
STREAM_CHECK_S = 0.1
FENCE_POLL_S = 0.005
FAILOVER_HISTORY = 100


def _utc_now() -> datetime:
    return datetime.now(UTC)


class EventKind(StrEnum):
    """What an :class:`AgentEvent` is about."""

    STARTED = "Started"
    FAILOVER = "Failover"
    HEALTH = "HealthChanged"
    SAFETY = "SafetyRoutine"
    COMMAND = "Command"
    LAND_ORDERED = "LandOrdered"
    NO_HEALTHY_STANDBY = "NoHealthyStandby"
    EMERGENCY_STOP = "EmergencyStop"
    SPEC = "Spec"
    BRIDGE_ERROR = "BridgeError"
    LINK = "Link"
    PARAMETERS = "Parameters"
    FENCE = "Fence"


@dataclass(frozen=True)
class FailoverEvent:
    """One bridge switch with its timing (monotonic seconds)."""

    record: FailoverRecord
    detected_at: float
    switched_at: float
    onset_at: float | None

    @property
    def latency_ms(self) -> float:
        """Detection to bridge switched."""
        return (self.switched_at - self.detected_at) * 1000

    @property
    def onset_to_switch_ms(self) -> float | None:
        """Start of the failure (as the findings know it) to bridge switched."""
        return None if self.onset_at is None else (self.switched_at - self.onset_at) * 1000


@dataclass(frozen=True)
class AgentEvent:
    """Something a publisher reports; ``reason``/``message``/``warning`` map onto a
    Kubernetes Event, the optional payloads onto status fields."""

    kind: EventKind
    reason: str
    message: str
    warning: bool
    time: datetime
    autopilot: str | None = None
    failover: FailoverEvent | None = None
    health: AutopilotHealth | None = None
    command: CommandResult | None = None

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (the standalone agent prints these, one per line)."""
        doc: dict[str, Any] = {
            "event": self.kind.value,
            "reason": self.reason,
            "message": self.message,
            "warning": self.warning,
            "time": self.time.isoformat(),
        }
        if self.autopilot is not None:
            doc["autopilot"] = self.autopilot
        if self.failover is not None:
            doc["failover"] = self.failover.record.to_api()
            doc["latencyMs"] = self.failover.latency_ms
            doc["onsetToSwitchMs"] = self.failover.onset_to_switch_ms
            # CLOCK_MONOTONIC seconds, comparable with time.monotonic() in any process
            # on the same host (benchmarks measure fault onset -> switch with them).
            doc["monotonic"] = {
                "detectedAt": self.failover.detected_at,
                "switchedAt": self.failover.switched_at,
                "onsetAt": self.failover.onset_at,
            }
        if self.health is not None:
            doc["health"] = self.health.to_api()
        if self.command is not None:
            doc["command"] = self.command.to_api()
        return doc


Listener = Callable[[AgentEvent], None]


@dataclass(frozen=True)
class _Running:
    """The configuration the decision loop works with; swapped as one object."""

    spec: RedundantAutopilotSpec
    generation: int | None
    policy: Policy
    links: Mapping[str, AutopilotLink]
    channels: Mapping[str, int]


@dataclass
class _Job:
    """One unit of work for the safety worker."""

    title: str
    run: Callable[[threading.Event], None]
    emergency: bool = False
    cancel: threading.Event = field(default_factory=threading.Event)


class _SafetyWorker:
    """Runs one job at a time. A new job cancels the running one and replaces a pending
    one, except that nothing but another emergency stop cancels or replaces an emergency
    stop."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._pending: _Job | None = None
        self._current: _Job | None = None
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="safety-worker", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, job: _Job) -> None:
        with self._cond:
            current, pending = self._current, self._pending
            if current is not None and (job.emergency or not current.emergency):
                current.cancel.set()
            if pending is not None and pending.emergency and not job.emergency:
                log.warning("dropping %s: an emergency stop is pending", job.title)
                return
            self._pending = job
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stopping = True
            if self._current is not None:
                self._current.cancel.set()
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                job, self._pending = self._pending, None
                assert job is not None
                self._current = job
            try:
                job.run(job.cancel)
            except Exception:
                log.exception("%s failed", job.title)
            finally:
                with self._cond:
                    self._current = None


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


def _rates(keeper: StreamKeeper) -> str:
    return ", ".join(f"{name} {hz:.0f} Hz" for name, hz in keeper.rates.items())


def _view(a: Assessment, in_step: InStep | None = None) -> AutopilotView:
    return AutopilotView(
        name=a.name,
        level=a.level,
        failing=a.failing,
        reason=a.failure_reason,
        armed=a.armed,
        in_air=a.in_air,
        pilot_in_control=a.pilot_in_control,
        onset=a.onset,
        in_step=None if in_step is None else in_step.status,
    )


def _in_step_status(verdict: InStep) -> ConditionStatus:
    if verdict.status is None:
        return "Unknown"
    return "True" if verdict.status else "False"


def _armed(link: AutopilotLink) -> bool:
    """Whether the autopilot's last heartbeat said armed."""
    beat = link.heartbeat()
    return beat is not None and bool(beat[1] & MAV_MODE_FLAG_SAFETY_ARMED)


def _positions(links: Iterable[AutopilotLink]) -> dict[str, LatLon]:
    """Where each autopilot last said the vehicle is (none before a GPS fix: lat/lon 0)."""
    out = {}
    for link in links:
        fix = link.tracker.fix()
        if fix is not None and (fix.lat_deg, fix.lon_deg) != (0.0, 0.0):
            out[link.name] = LatLon(fix.lat_deg, fix.lon_deg)
    return out


def _declared_for(declared: ParametersSpec, stack: Stack) -> dict[str, float]:
    """The parameters declared for the autopilots of ``stack``."""
    entries = declared.px4 if stack is Stack.PX4 else declared.ardupilot
    return {p.name: p.value for p in entries}


def connection_problems(spec: RedundantAutopilotSpec) -> list[str]:
    """One line per autopilot whose connection URL the agent could not open."""
    problems = []
    for autopilot in spec.autopilots:
        try:
            pymavlink_device(autopilot.connection)
        except ValueError as exc:
            problems.append(f"autopilot {autopilot.name}: {exc}")
    return problems


def _with_link_error(health: AutopilotHealth, error: str | None) -> AutopilotHealth:
    """The health entry with a failing link's last error first among its reasons."""
    if error is None:
        return health
    return replace(health, reasons=[f"link error: {error}", *health.reasons])


class Agent:
    """Watches the autopilots of one vehicle and keeps a healthy one on the motors."""

    def __init__(
        self,
        spec: RedundantAutopilotSpec | ApiDocument,
        bridge: Bridge,
        *,
        state_file: StateFile | None = None,
        generation: int | None = None,
        node_name: str = "",
        tick_s: float = DEFAULT_TICK_S,
        steered_tick_s: float = STEERED_TICK_S,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], datetime] = _utc_now,
        timing: Timing = DEFAULT_TIMING,
        signing: LinkSigning | None = None,
    ) -> None:
        self._bridge = bridge
        self._signing = signing
        self._state_file = state_file
        self._node_name = node_name
        self._tick_s = tick_s
        self._clock = clock
        self._wall_clock = wall_clock
        self._timing = timing
        spec = RedundantAutopilotSpec.from_api(spec)  # the API model is taken too
        saved = state_file.load() if state_file is not None else None
        self._state = restore_state(spec, saved)
        self._restored = saved is not None and saved.active == self._state.active
        self._lock = threading.RLock()
        self._persist_lock = threading.Lock()
        self._processed: OrderedDict[str, CommandResult] = OrderedDict(
            (c.id, c) for c in (saved.commands if saved else [])
        )
        self._pending: dict[str, Future[CommandResult]] = {}
        self._inbox: deque[AutopilotCommand] = deque()
        self._last_failover: FailoverRecord | None = saved.last_failover if saved else None
        self._safety: SafetyProgress | None = saved.safety if saved else None
        self._keepers: dict[str, tuple[AutopilotLink, StreamKeeper]] = {}
        # Declared parameters per autopilot (roost_agent.params), on the heartbeat thread;
        # their ParametersInSync verdicts are read by status() under the lock.
        self._param_keepers: dict[str, tuple[AutopilotLink, ParamKeeper]] = {}
        self._param_verdicts: dict[str, Verdict] = {}
        # The Mission's fence per autopilot (roost_agent.fence), on the heartbeat thread.
        self._fences = Fences()
        # Each autopilot's AUTOPILOT_VERSION as read (frame, what it says, its capability
        # bits, the reboots seen when it came) and when it was last asked for
        # (roost_agent.firmware).
        self._firmware: dict[str, tuple[object, FirmwareInfo, int, int]] = {}
        self._version_asked: dict[str, tuple[AutopilotLink, float, int, int]] = {}
        self._last_command: CommandResult | None = (
            next(reversed(self._processed.values())) if self._processed else None
        )
        self._failovers: deque[FailoverEvent] = deque(maxlen=FAILOVER_HISTORY)
        self._assessments: dict[str, Assessment] = {}
        self._signatures: dict[str, tuple[HealthLevel, frozenset[str]]] = {}
        self._last_status: RedundantAutopilotStatus | None = None
        self._listeners: list[Listener] = []
        self._events: queue.SimpleQueue[AgentEvent | None] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._worker = _SafetyWorker()
        self._threads: list[threading.Thread] = []
        self._reader = LinkReader()
        self._reader.drive(self._tick_while_running, tick_s, steered_tick_s)
        self._cfg = _Running(
            spec=spec,
            generation=generation,
            policy=Policy.from_spec(spec),
            links={a.name: self._new_link(a, spec) for a in spec.autopilots},
            channels={a.name: a.bridge_channel for a in spec.autopilots},
        )
        self._spec_lock = threading.Lock()
        # The vehicle's MAVLink endpoint (roost_agent.hub), when the spec asks for it.
        self._hub: Hub | None = hub_for(
            spec, self._state.active, self._cfg.links, signing=signing, on_event=self._hub_event
        )
        if self._hub is not None:  # routed frames are not held back while clients wait
            self._reader.hurry = self._hub.has_clients
        self._in_step: dict[str, InStep] = {}
        self._views: dict[str, tuple[tuple[object, ...], AutopilotView]] = {}
        # The configuration the arbiter was settled under after the last full tick
        # (None: it was not, or no tick yet): see _nothing_new.
        self._settled_with: _Running | None = None

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> None:
        """Assert the bridge, open the links and start deciding."""
        cfg = self._cfg
        channel = cfg.channels[self._state.active]
        if self._bridge.selected != channel:
            self._bridge.select(channel)
        self._reader.start()
        for link in cfg.links.values():
            link.start()
        if self._hub is not None:
            self._hub.start()
            self._hub.aux_standby(self._state.active)
        self._worker.start()
        self._resume_safety(cfg)
        for target, name in (
            (self._heartbeat_forever, "agent-heartbeat"),
            (self._notify_forever, "event-notifier"),
        ):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        how = "restored from the state file" if self._restored else "primary"
        latch = ", latched" if self._state.latched else ""
        self._emit(
            EventKind.STARTED,
            "AgentStarted",
            f"active autopilot {self._state.active} ({how}{latch}) on bridge channel {channel}",
        )
        self._persist()
        if cfg.spec.command is not None:
            self.submit(cfg.spec.command)

    def stop(self) -> None:
        """Stop every thread and link; the bridge keeps its selection."""
        self._stop.set()
        self._worker.stop()
        self._events.put(None)
        for thread in self._threads:
            thread.join(timeout=5)
        for link in self._cfg.links.values():
            link.stop()
        self._reader.stop()
        if self._hub is not None:
            self._hub.stop()

    def __enter__(self) -> Agent:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- public surface ------------------------------------------------------------------

    @property
    def active(self) -> str:
        """The autopilot on the motors."""
        return self._state.active

    @property
    def latched(self) -> bool:
        """Whether a failover latched the agent."""
        return self._state.latched

    @property
    def links(self) -> Mapping[str, AutopilotLink]:
        """The links by autopilot name (counters, trackers)."""
        return self._cfg.links

    def rekey(self, signing: LinkSigning) -> None:
        """Adopt a rotated signing key without a restart: every link and the hub sign
        with it and take it (and the previous key) from now on; links opened later too."""
        with self._spec_lock:
            self._signing = signing
            for link in self._cfg.links.values():
                link.rekey(signing)
            if self._hub is not None:
                self._hub.rekey(signing)

    @property
    def hub(self) -> Hub | None:
        """The vehicle's MAVLink endpoint (None when the spec has no hub)."""
        return self._hub

    @property
    def last_failover(self) -> FailoverRecord | None:
        """The last switch (restored from the state file after a restart)."""
        return self._last_failover

    @property
    def vehicle_name(self) -> str:
        """The vehicle the agent flies (its spec's ``vehicleName``)."""
        return self._cfg.spec.vehicle_name

    @property
    def read_interval_s(self) -> float:
        """How long the bulk of the autopilots' streams may wait to be read now: the
        steered interval while every link is steered, the short one otherwise."""
        return self._reader.tick_s

    def failovers(self) -> list[FailoverEvent]:
        """Switches since start, oldest first (the last ``FAILOVER_HISTORY``)."""
        with self._lock:
            return list(self._failovers)

    def assessments(self) -> dict[str, Assessment]:
        """Every autopilot's health as of now (of those the decision loop judged yet).

        Judged afresh: the decision loop keeps its last judgement while nothing can
        have changed it, but its message and heartbeat ages go on."""
        with self._lock:
            return self._current_assessments()

    def _current_assessments(self) -> dict[str, Assessment]:
        links, now = self._cfg.links, self._reader.as_of(self._clock())
        return {n: links[n].tracker.assess(now) for n in self._assessments if n in links}

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Call ``listener`` with every event (on the notifier thread); returns unsubscribe."""
        with self._lock:
            self._listeners.append(listener)

        def unsubscribe() -> None:
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return unsubscribe

    def submit(self, command: AutopilotCommand | ApiDocument) -> Future[CommandResult]:
        """Execute ``command`` at most once per id; the future resolves to its result.

        A command whose id was already executed (also before a restart: ids are kept on
        disk) resolves to the stored result without running again.
        """
        command = AutopilotCommand.from_api(command)  # the API model is taken too
        with self._lock:
            done = self._processed.get(command.id)
            if done is not None:
                future: Future[CommandResult] = Future()
                future.set_result(done)
                return future
            pending = self._pending.get(command.id)
            if pending is not None:
                return pending
            future = Future()
            self._pending[command.id] = future
            self._inbox.append(command)
        self._reader.poke()
        return future

    def apply_spec(
        self, spec: RedundantAutopilotSpec | ApiDocument, generation: int | None = None
    ) -> str | None:
        """Adopt a new spec (policy, thresholds, primary, command, connection details).

        Returns None when applied, else why it was refused: the set of autopilots and
        their bridge channels cannot change while running (the bridge hardware is
        claimed per channel; restart the agent), and connection details only change on
        the ground (a reopened link starts without data). A command in the spec is
        submitted either way.
        """
        spec = RedundantAutopilotSpec.from_api(spec)  # the API model is taken too
        refusal = self._apply_spec(spec, generation)
        if refusal is not None:
            self._emit(EventKind.SPEC, "SpecRejected", refusal, warning=True)
        else:
            self._emit(EventKind.SPEC, "SpecApplied", f"generation {generation}")
        if spec.command is not None:
            self.submit(spec.command)
        return refusal

    def status(self) -> RedundantAutopilotStatus:
        """The complete status the agent reports for its RedundantAutopilot.

        Conditions come from :func:`roost_agent.report.report`; their transition times
        carry over from the previous call.
        """
        with self._lock:
            cfg = self._cfg
            state = self._state
            assessments = self._current_assessments()
            healths = [
                self._with_entry_conditions(
                    self._with_firmware(
                        _with_link_error(assessments[a.name].to_api(), cfg.links[a.name].error)
                    )
                )
                for a in cfg.spec.autopilots
                if a.name in assessments
            ]
            observed = RedundantAutopilotStatus(
                hub_endpoints=self._hub.endpoint_status() if self._hub is not None else [],
                active_autopilot=state.active,
                autopilots=healths,
                last_failover=self._last_failover,
                failover_count=state.failover_count,
                latched=state.latched,
                last_command=self._last_command,
            )
            self._last_status = report(
                self._last_status,
                observed,
                spec=cfg.spec,
                left_behind=state.failed_from,
                generation=cfg.generation,
                node_name=self._node_name,
                now=self._wall_clock().replace(microsecond=0),
            )
            return self._last_status

    def _with_firmware(self, health: AutopilotHealth) -> AutopilotHealth:
        """The health entry with what the autopilot's AUTOPILOT_VERSION said."""
        known = self._firmware.get(health.name)
        return health if known is None else replace(health, firmware=known[1])

    def _with_entry_conditions(self, health: AutopilotHealth) -> AutopilotHealth:
        """The health entry with its StandbyInStep (with the hub only), ParametersInSync
        (with declared parameters only) and FenceInSync (with a Mission's fence, and
        while the previous one is restored) conditions."""
        previous = self._last_status
        conditions = next(
            (
                h.conditions
                for h in (previous.autopilots if previous else [])
                if h.name == health.name
            ),
            [],
        )
        at = self._wall_clock().replace(microsecond=0)
        verdict = self._in_step.get(health.name)
        if verdict is not None:
            conditions = set_condition(
                conditions,
                type=AutopilotEntryConditionType.STANDBY_IN_STEP.value,
                status=_in_step_status(verdict),
                reason=verdict.reason.value,
                message=verdict.message,
                at=at,
            )
        kept = {AutopilotEntryConditionType.STANDBY_IN_STEP.value} if verdict else set()
        own: tuple[tuple[AutopilotEntryConditionType, Verdict | FenceVerdict | None], ...] = (
            (AutopilotEntryConditionType.PARAMETERS_IN_SYNC, self._param_verdicts.get(health.name)),
            (AutopilotEntryConditionType.FENCE_IN_SYNC, self._fences.verdict(health.name)),
        )
        for kind, judged in own:
            if judged is not None:
                conditions = set_condition(
                    conditions,
                    type=kind.value,
                    status=judged.status,
                    reason=judged.reason.value,
                    message=judged.message,
                    at=at,
                )
                kept.add(kind.value)
        conditions = [c for c in conditions if c.type in kept]
        return replace(health, conditions=conditions) if conditions or health.conditions else health

    # -- decision loop -------------------------------------------------------------------

    def _tick_while_running(self) -> float | None:
        if self._stop.is_set():  # stopping: the links close, nothing is decided on that
            return None
        due = self.tick()
        if any(link.tracker.claim_pending for link in self._cfg.links.values()):
            soon = self._clock() + self._tick_s  # read the message that settles it soon
            due = soon if due is None else min(due, soon)
        return due

    def tick(self) -> float | None:
        """One decision: assess, step the arbiter, switch first, then everything else.

        A tick in which nothing can have changed returns at once (:meth:`_nothing_new`):
        most ticks of a healthy flight. Returns when, on this clock, the next decision is
        due even if no message arrives (None: nothing sooner than the next read): the
        first health threshold any autopilot crosses while the arbiter is settled, when
        the arbiter may act next otherwise (:func:`~roost_agent.arbiter.next_due`: the end
        of a confirm window, or of a standby's time free of failures).
        """
        cfg = self._cfg
        # Judged as of the start of the last read: what arrived since is not read yet, so
        # the reader running late (a starved CPU) never reads as an autopilot's silence.
        now = self._reader.as_of(self._clock())
        in_step = self._hub.in_step(now) if self._hub is not None else {}
        quiet_until = self._nothing_new(cfg, now, in_step)
        if quiet_until is not None:
            if in_step:
                with self._lock:
                    self._in_step = in_step
            return quiet_until + JUDGE_LATE_S
        assessments = {name: link.tracker.assess(now) for name, link in cfg.links.items()}
        views = {name: self._view(a, in_step.get(name)) for name, a in assessments.items()}
        if not settled(self._state, views, cfg.policy):
            self._execute(cfg, step(self._state, views, cfg.policy, now))
        with self._lock:
            commands = list(self._inbox)
            self._inbox.clear()
            self._assessments = assessments
            self._in_step = in_step
        for command in commands:
            decision = handle_command(
                self._state,
                views,
                cfg.policy,
                command,
                now=self._clock(),
                wall_now=self._wall_clock(),
            )
            self._execute(cfg, decision)
        self._note_health_changes(assessments)
        if settled(self._state, views, cfg.policy):
            self._settled_with = cfg
            due = min(link.tracker.next_threshold(assessments[n]) for n, link in cfg.links.items())
            return due + JUDGE_LATE_S
        self._settled_with = None
        return next_due(self._state, cfg.policy, now)

    def _nothing_new(
        self, cfg: _Running, now: float, in_step: Mapping[str, InStep]
    ) -> float | None:
        """Until when a full tick would decide exactly what the last one did (None: not
        now): the arbiter was settled after it (:func:`roost_agent.arbiter.settled`: no
        timer runs, nothing pending) under the same configuration, no command waits,
        every autopilot's judgement holds (:meth:`roost_agent.health.HealthTracker.holds`:
        nothing it reads changed, no threshold passed since) and the hub's in-step
        verdicts are the same. Then the views are the ones the arbiter settled on, so
        stepping it would change nothing, and no health event is due. A threshold
        passing is exactly what ends the skipping, and the loop ticks when it does."""
        if self._settled_with is not cfg or self._inbox:
            return None
        until = self._judgements_hold_until(cfg, self._assessments)
        if now >= until:
            return None
        if (in_step or self._in_step) and {n: v.status for n, v in in_step.items()} != {
            n: v.status for n, v in self._in_step.items()
        }:
            return None
        return until

    @staticmethod
    def _judgements_hold_until(cfg: _Running, judged: Mapping[str, Assessment]) -> float:
        """The first time an autopilot's last judgement stops holding (minus infinity:
        one has no judgement yet, or already changed)."""
        until = math.inf
        for name, link in cfg.links.items():
            last = judged.get(name)
            if last is None:
                return -math.inf
            until = min(until, link.tracker.holds_until(last))
        return until

    def _view(self, a: Assessment, in_step: InStep | None) -> AutopilotView:
        """:func:`_view`, reusing the last one while what it is made of is unchanged (a
        healthy autopilot's findings are empty tick after tick)."""
        status = None if in_step is None else in_step.status
        key = (a.stack, a.level, a.findings, a.armed, a.landed_state, a.custom_mode, status)
        cached = self._views.get(a.name)
        if cached is not None and cached[0] == key:
            return cached[1]
        view = _view(a, in_step)
        self._views[a.name] = (key, view)
        return view

    def _execute(self, cfg: _Running, decision: Decision) -> None:
        before = self._state
        self._state = decision.state
        for action in decision.actions:
            self._perform(cfg, before, action)
        after = self._state
        durable = (after.active, after.latched, after.failed_from, after.failover_count)
        if durable != (before.active, before.latched, before.failed_from, before.failover_count):
            self._persist()

    def _perform(self, cfg: _Running, before: ArbiterState, action: Action) -> None:
        if isinstance(action, SwitchBridge):
            self._switch(cfg, before, action)
        elif isinstance(action, RunSafetyRoutine):
            self._start_routine(cfg, action.autopilot)
        elif isinstance(action, LandInPlace):
            self._start_landing(cfg, action)
        elif isinstance(action, NoHealthyStandby):
            self._emit(
                EventKind.NO_HEALTHY_STANDBY,
                "NoHealthyStandby",
                f"{action.reason}; pilot flies manually, no landing ordered",
                warning=True,
                autopilot=action.autopilot,
            )
        elif isinstance(action, ForceDisarm):
            self._emergency_stop(cfg, action)
        else:
            self._command_done(action)

    def _switch(self, cfg: _Running, before: ArbiterState, action: SwitchBridge) -> None:
        hub = self._hub
        try:
            self._bridge.select(cfg.channels[action.to_autopilot])
            if hub is not None:  # the clients' route moves with the motors, same tick
                hub.set_active(action.to_autopilot)
        except BridgeError as exc:
            # The motors stay where they were: undo the decision, the next tick retries.
            self._state = replace(
                self._state,
                active=before.active,
                latched=before.latched,
                failed_from=before.failed_from,
                failover_count=before.failover_count,
            )
            self._emit(
                EventKind.BRIDGE_ERROR,
                "BridgeSwitchFailed",
                f"could not switch to {action.to_autopilot}: {exc}",
                warning=True,
                autopilot=action.to_autopilot,
            )
            return
        switched_at = self._clock()
        record = FailoverRecord(
            time=self._wall_clock().replace(microsecond=0),
            from_autopilot=action.from_autopilot,
            to_autopilot=action.to_autopilot,
            reason=action.reason,
            latency_ms=round((switched_at - action.detected_at) * 1000, 3),
            trigger=action.trigger,
            safety_routine=None
            if action.safety == SafetyPlan.NONE
            else SafetyRoutinePhase(action.safety.value),
            standby_in_step=action.in_step,
        )
        event = FailoverEvent(record, action.detected_at, switched_at, action.onset)
        with self._lock:
            self._last_failover = record
            self._failovers.append(event)
        if action.safety == SafetyPlan.RUN:
            self._start_routine(cfg, action.to_autopilot)
        if hub is not None:
            hub.aux_standby(action.to_autopilot)
        onset = event.onset_to_switch_ms
        timing = f"switched {event.latency_ms:.3f} ms after detection" + (
            f", {onset:.0f} ms after onset" if onset is not None else ""
        )
        reasons = {
            Trigger.AUTOMATIC: "FailedOver",
            Trigger.COMMAND: "SwitchedByCommand",
            Trigger.FAILBACK: "FailedBack",
        }
        self._emit(
            EventKind.FAILOVER,
            reasons[action.trigger],
            f"{action.from_autopilot} -> {action.to_autopilot}: {action.reason} ({timing})",
            warning=action.trigger == Trigger.AUTOMATIC,
            autopilot=action.to_autopilot,
            failover=event,
        )

    def _command_done(self, done: CommandDone) -> None:
        result = CommandResult(
            id=done.command_id,
            result=done.result,
            message=done.message,
            time=self._wall_clock().replace(microsecond=0),
        )
        with self._lock:
            self._processed[done.command_id] = result
            while len(self._processed) > MAX_REMEMBERED_COMMANDS:
                self._processed.popitem(last=False)
            self._last_command = result
            future = self._pending.pop(done.command_id, None)
        self._persist()
        if future is not None:
            future.set_result(result)
        self._emit(
            EventKind.COMMAND,
            f"Command{done.result.value}",
            f"{done.command_id}: {done.message}",
            warning=done.result != CommandResultKind.EXECUTED,
            command=result,
        )

    # -- safety jobs ---------------------------------------------------------------------

    def _reporter(self, autopilot: str) -> Callable[[Phase, str], None]:
        def report(phase: Phase, message: str) -> None:
            with self._lock:
                record = self._last_failover
                if record is not None and record.to_autopilot == autopilot:
                    self._last_failover = replace(record, safety_routine=phase)
            self._persist()
            self._emit(
                EventKind.SAFETY,
                f"SafetyRoutine{phase.value}",
                message,
                warning=phase in WARNING_PHASES,
                autopilot=autopilot,
            )

        return report

    def _runner(self, link: AutopilotLink, cancel: threading.Event) -> SafetyRunner:
        return SafetyRunner(
            link,
            cancel,
            self._reporter(link.name),
            self._timing,
            self._clock,
            progress=self._record_progress,
        )

    def _record_progress(self, progress: Progress) -> None:
        """Keep the routine's progress in the state file (written before it goes on)."""
        with self._lock:
            self._safety = SafetyProgress(
                autopilot=progress.autopilot,
                phase=progress.phase.value,
                final_action=progress.final_action,
                hold_seconds=progress.hold_seconds,
                hold_started=progress.hold_started,
                land_started=progress.land_started,
                holds=progress.holds,
            )

    def _start_routine(self, cfg: _Running, autopilot: str) -> None:
        link = cfg.links[autopilot]
        routine = cfg.spec.failover_policy.safety_routine
        # Durable before the worker starts: an agent killed right after the switch still
        # finds the routine to run in its state file.
        self._record_progress(
            Progress(autopilot, Phase.STARTED, routine.final_action, routine.hold_seconds)
        )
        self._persist()

        def run(cancel: threading.Event) -> None:
            self._runner(link, cancel).run(routine)

        self._worker.submit(_Job(f"safety routine on {autopilot}", run))

    def _resume_safety(self, cfg: _Running) -> None:
        """After a restart: continue a safety routine or landing the last run left open."""
        saved = self._safety
        if saved is None or Phase(saved.phase) in TERMINAL_PHASES:
            return
        link = cfg.links.get(saved.autopilot)
        if link is None:
            return
        progress = Progress(
            saved.autopilot,
            Phase(saved.phase),
            saved.final_action,
            saved.hold_seconds,
            saved.hold_started,
            saved.land_started,
            saved.holds,
        )
        self._emit(
            EventKind.SAFETY,
            "SafetyRoutineResumed",
            f"{saved.autopilot}: resuming the safety routine from {saved.phase} after a restart",
            warning=True,
            autopilot=saved.autopilot,
        )

        def run(cancel: threading.Event) -> None:
            self._runner(link, cancel).resume(progress)

        self._worker.submit(_Job(f"resumed safety routine on {saved.autopilot}", run))

    def _start_landing(self, cfg: _Running, action: LandInPlace) -> None:
        self._emit(
            EventKind.LAND_ORDERED,
            "LandOrdered",
            f"{action.autopilot}: {action.reason}",
            warning=True,
            autopilot=action.autopilot,
        )
        link = cfg.links[action.autopilot]
        self._record_progress(
            Progress(action.autopilot, Phase.STARTED, FinalAction.LAND, 0.0, holds=False)
        )
        self._persist()

        def run(cancel: threading.Event) -> None:
            self._runner(link, cancel).land_now()

        self._worker.submit(_Job(f"landing {action.autopilot}", run))

    def _emergency_stop(self, cfg: _Running, action: ForceDisarm) -> None:
        self._emit(EventKind.EMERGENCY_STOP, "EmergencyStop", action.reason, warning=True)
        active = self._state.active
        order = sorted(action.autopilots, key=lambda n: n != active)
        links = [cfg.links[n] for n in order]

        def run(cancel: threading.Event) -> None:
            threads = [
                threading.Thread(target=self._runner(link, cancel).force_disarm, daemon=True)
                for link in links
            ]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()

        self._worker.submit(_Job("emergency stop", run, emergency=True))

    # -- health events, conditions -----------------------------------------------------

    def _note_health_changes(self, assessments: Mapping[str, Assessment]) -> None:
        for name, a in assessments.items():
            signature = a.signature
            previous = self._signatures.get(name)
            if signature == previous:
                continue
            self._signatures[name] = signature
            was = previous[0].value if previous else "unknown"
            why = "; ".join(a.reasons) or "healthy"
            self._emit(
                EventKind.HEALTH,
                "AutopilotHealthChanged",
                f"{name}: {was} -> {a.level.value}: {why}",
                warning=a.level.rank >= HealthLevel.ERROR.rank,
                autopilot=name,
                health=a.to_api(),
            )

    # -- spec changes --------------------------------------------------------------------

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
            self._cfg = _Running(
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

    # -- persistence, heartbeats, events -------------------------------------------------

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

    def _heartbeat_forever(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            links = self._cfg.links
            if self._clock() >= next_beat:
                next_beat = self._clock() + HEARTBEAT_PERIOD_S
                for link in links.values():
                    link.send_heartbeat()
            for link in links.values():
                try:
                    self._keep_streams(link)
                except Exception:  # a stream request must never stop the heartbeats
                    log.exception("%s: stream keeping failed", link.name)
            for link in links.values():
                try:
                    self._keep_firmware(link)
                except Exception:  # nor a firmware question
                    log.exception("%s: asking for the firmware version failed", link.name)
            cfg = self._cfg
            received = {name: link.params.take() for name, link in cfg.links.items()}
            try:
                self._keep_params(cfg, received)
            except Exception:  # nor a parameter read or write
                log.exception("parameter keeping failed")
            try:
                self._keep_fence(cfg, received)
            except Exception:  # nor a fence transfer
                log.exception("fence keeping failed")
            self._rest(cfg, STREAM_CHECK_S)

    def _rest(self, cfg: _Running, period_s: float) -> None:
        """Wait ``period_s`` between heartbeat rounds; while a fence transfer runs, step
        the fence keepers every :data:`FENCE_POLL_S` meanwhile (a transfer is one round
        trip per item: at the round's pace a 20-vertex upload and its read-back would
        take over 4 s)."""
        until = self._clock() + period_s
        while not self._stop.is_set():
            left = until - self._clock()
            if left <= 0:
                return
            if not self._fences.transferring():
                self._stop.wait(left)
                return
            self._stop.wait(min(left, FENCE_POLL_S))
            try:
                self._keep_fence(cfg, {})
            except Exception:
                log.exception("fence keeping failed")

    def _keep_firmware(self, link: AutopilotLink) -> None:
        """Ask a heard autopilot for AUTOPILOT_VERSION until it answers, and again after
        it rebooted (a firmware update reboots it); take each answer."""
        frame = link.version
        reboots = link.tracker.reboots()
        known = self._firmware.get(link.name)
        if frame is not None and (known is None or known[0] is not frame):
            fw = firmware.info(frame)
            with self._lock:
                self._firmware[link.name] = (frame, fw, firmware.capabilities_of(frame), reboots)
            self._emit(
                EventKind.LINK,
                "FirmwareReported",
                f"{link.name}: {link.stack.value} {fw.version} ({fw.version_type}"
                + (f", build {fw.git_hash}" if fw.git_hash else "")
                + f"), board {fw.board_version}",
                autopilot=link.name,
            )
            return
        if (known is not None and known[3] == reboots) or link.heartbeat() is None:
            return
        now = self._clock()
        asked = self._version_asked.get(link.name)
        if asked is None or asked[0] is not link or asked[3] != reboots:
            tries = 1  # a new link, or the autopilot rebooted
        elif now - asked[1] < firmware.REQUEST_EVERY_S or asked[2] >= firmware.MAX_REQUESTS:
            return  # asked recently, or often enough until the next reboot
        else:
            tries = asked[2] + 1
        self._version_asked[link.name] = (link, now, tries, reboots)
        request = float(firmware.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        link.send_command(MAV_CMD_REQUEST_MESSAGE, (request, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))

    def _keep_fence(
        self, cfg: _Running, received: dict[str, list[tuple[str, float, int, float]]]
    ) -> None:
        """Step every autopilot's fence keeper (roost_agent.fence) with what its link
        received."""

        def emit(reason: str, message: str, warning: bool, autopilot: str) -> None:
            self._emit(EventKind.FENCE, reason, message, warning=warning, autopilot=autopilot)
            self._reader.poke()

        self._fences.step(
            cfg.links,
            cfg.spec.fence,
            messages={name: link.mission.take() for name, link in cfg.links.items()},
            params=received,
            capabilities={name: fw[2] for name, fw in self._firmware.items()},
            positions=_positions(cfg.links.values()),
            armed=any(_armed(link) for link in cfg.links.values()),
            now=self._clock(),
            emit=emit,
        )

    def _keep_params(
        self, cfg: _Running, received: dict[str, list[tuple[str, float, int, float]]]
    ) -> None:
        """Step every autopilot's parameter keeper: take the PARAM_VALUEs its link
        received, send the reads and writes it asks for, report what changed."""
        declared = cfg.spec.parameters
        restore = declared is not None and declared.on_drift == DriftPolicy.RESTORE
        armed = any(_armed(link) for link in cfg.links.values())
        now = self._clock()
        for link in cfg.links.values():
            values = received.get(link.name, [])
            want = {} if declared is None else _declared_for(declared, link.stack)
            known = self._param_keepers.get(link.name)
            if known is None or known[0] is not link:  # a new link: a new keeper
                known = self._param_keepers[link.name] = (link, ParamKeeper(link.stack))
            keeper = known[1]
            keeper.declare(want)
            fw = self._firmware.get(link.name)
            if fw is not None:  # the encoding the firmware announces
                keeper.set_capabilities(fw[2])
            if not keeper.declared:
                if self._param_verdicts.pop(link.name, None) is not None:
                    self._reader.poke()
                continue
            for name, wire, ptype, at in values:
                drift = keeper.observe(name, wire, ptype, at)
                if drift is not None:
                    self._emit(
                        EventKind.PARAMETERS,
                        "ParameterDrifted",
                        f"{link.name}: {drift.name} is {drift.observed:g}, declared "
                        f"{drift.desired:g}"
                        + ("; writing it back" if restore else "; reported only (onDrift Report)"),
                        warning=True,
                        autopilot=link.name,
                    )
            if link.heartbeat() is not None:  # nobody to ask before the autopilot is heard
                for op in keeper.step(now, armed=armed, restore=restore):
                    if isinstance(op, Read):
                        link.read_param(op.name)
                    else:
                        link.write_param(op.name, op.wire, int(op.ptype))
            verdict = keeper.verdict()
            with self._lock:
                before = self._param_verdicts.get(link.name)
                self._param_verdicts[link.name] = verdict
            if before is None or (before.status, before.reason) != (verdict.status, verdict.reason):
                self._emit(
                    EventKind.PARAMETERS,
                    f"Parameters{verdict.reason.value}",
                    f"{link.name}: {verdict.message}",
                    warning=verdict.status == "False",
                    autopilot=link.name,
                )

    def _keep_streams(self, link: AutopilotLink) -> None:
        """Step this link's stream keeper and send what it asks for."""
        known = self._keepers.get(link.name)
        if known is None or known[0] is not link:  # a new link (spec change): a new keeper
            known = self._keepers[link.name] = (link, StreamKeeper(link.stack))
        keeper = known[1]
        epoch, verified, checks = keeper.epoch, keeper.verified, keeper.checks
        requests = keeper.step(
            link.tracker.stream_facts(),
            self._clock(),
            link.acks.latest(MAV_CMD_SET_MESSAGE_INTERVAL),
        )
        if keeper.epoch is not epoch:
            link.tracker.expect_streams(None)  # new stream configuration: judge what arrives
        elif keeper.checks != checks:
            link.tracker.expect_streams(keeper.arriving_rate)
        if keeper.verified and not verified:
            log.info("%s: requested streams arrive (%s)", link.name, _rates(keeper))
        if requests:
            why = keeper.epoch.value if keeper.epoch is not None else Why.CONNECT.value
            # the first request of an epoch is news; the backed-off repeats are not
            (log.info if keeper.attempts == 1 else log.debug)(
                "%s: requesting %s (%s, attempt %d)",
                link.name,
                ", ".join(f"{r.message}@{r.hz:g}Hz/{r.method.value}" for r in requests),
                why,
                keeper.attempts,
            )
            send_requests(link, requests)

    def _hub_event(self, reason: str, message: str, warning: bool) -> None:
        self._emit(EventKind.LINK, reason, message, warning=warning)

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

    def _notify_forever(self) -> None:
        while True:
            event = self._events.get()
            if event is None:
                return
            (log.warning if event.warning else log.info)("%s: %s", event.reason, event.message)
            with self._lock:
                listeners = list(self._listeners)
            for listener in listeners:
                try:
                    listener(event)
                except Exception:
                    log.exception("event listener failed")
