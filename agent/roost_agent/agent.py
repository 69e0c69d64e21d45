"""The node agent: links, health, arbiter, bridge and safety routine wired together.

This module is the wiring and the decision loop. What the arbiter's actions do (the
bridge switch, the safety routine, landing, the emergency stop, command results) is
:mod:`roost_agent.actions`; adopting a new spec while running is
:mod:`roost_agent.spec_changes`; the events subscribers get are :mod:`roost_agent.events`;
the state and outlets those parts share are declared in :mod:`roost_agent.parts`.

Threads and why:

- one reader thread (:class:`roost_agent.reader.LinkReader`) reads every autopilot link,
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
  beat (faster, every :data:`STREAM_CHECK_S`, while a keeper waits for an answer), lets
  each link's stream keeper (:mod:`roost_agent.streams`) request the telemetry the
  health model needs, and the firmware, parameter and fence keepers do their work;
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
from dataclasses import replace
from datetime import UTC, datetime

from roost_agent import firmware
from roost_agent.actions import Actions, SafetyWorker
from roost_agent.arbiter import AutopilotView, Policy, handle_command, next_due, settled, step
from roost_agent.bridge import Bridge
from roost_agent.events import AgentEvent, EventKind, FailoverEvent, Listener
from roost_agent.fence import Fences
from roost_agent.fence import Verdict as FenceVerdict
from roost_agent.health import Assessment
from roost_agent.hub import Hub, hub_for
from roost_agent.instep import InStep
from roost_agent.link import AutopilotLink
from roost_agent.params import ParamKeeper, Read, Verdict, nothing_declared
from roost_agent.parts import Running
from roost_agent.reader import LinkReader
from roost_agent.report import report, set_condition
from roost_agent.safety import DEFAULT_TIMING, Timing
from roost_agent.signing import LinkSigning
from roost_agent.spec_changes import SpecChanges, restore_state
from roost_agent.state import SafetyProgress, StateFile
from roost_agent.streams import StreamKeeper, Why, send_requests
from roost_api.autopilot_enums import AutopilotEntryConditionType, DriftPolicy
from roost_api.core import ConditionStatus, HealthLevel, Stack
from roost_api.fence import LatLon
from roost_api.plain import (
    AutopilotCommand,
    AutopilotHealth,
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
ROUTED_TICK_S = 0.5
"""The read interval while the hub's fast path takes the active autopilot's stream in
runs (:mod:`roost_agent.fastpath`) and every link is steered: the C loop returns at once
with anything Python reads whole (a state that changed, a tilt class that changed, a
heartbeat, an answer, the rate window's close) and at every health deadline, so the
interval bounds nothing but how often the bulk is taken; each return costs the agent
more than a hundred routed frames (docs/performance.md)."""
JUDGE_LATE_S = 1e-4
"""A tick meant for a health threshold comes this much after it: the judgement there
compares a difference of float times with the threshold and must see it crossed."""
HEARTBEAT_PERIOD_S = 1.0
STREAM_CHECK_S = 0.25
"""The heartbeat thread's round while a conversation runs: stream keepers, firmware
questions, parameter and fence keepers step this often after a round that sent them a
request or brought them an answer, and while an autopilot's streams are not settled
(just heard, rebooted, a stream missing: ``Agent._settled``). A
round that did neither once all are settled is followed by the next heartbeat's: the
keepers' own clocks run in seconds (a stream's measuring window is
:data:`roost_agent.streams.CHECK_S`, a parameter is read again after
:data:`roost_agent.params.RETRY_S`), a fence transfer steps faster
(:data:`FENCE_POLL_S`), and a new spec starts a round at once. Each round is a wake-up,
and on these machines a wake-up from idle costs ten times the round's work: at 0.1 s the
round was a third of an idle agent's CPU time, at 0.25 s still a fifteenth of one
routing 400 messages a second."""
FENCE_POLL_S = 0.005
FAILOVER_HISTORY = 100


def _utc_now() -> datetime:
    return datetime.now(UTC)


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


def _with_link_error(health: AutopilotHealth, error: str | None) -> AutopilotHealth:
    """The health entry with a failing link's last error first among its reasons."""
    if error is None:
        return health
    return replace(health, reasons=[f"link error: {error}", *health.reasons])


class Agent(Actions, SpecChanges):
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
        # Wakes the heartbeat thread's rest for a round now (a new spec; stop).
        self._round_now = threading.Event()
        self._rounds = 0  # the heartbeat thread's rounds so far (keeper_rounds)
        self._worker = SafetyWorker()
        self._threads: list[threading.Thread] = []
        self._reader = LinkReader()
        self._reader.drive(self._tick_while_running, tick_s, steered_tick_s, ROUTED_TICK_S)
        self._cfg = Running(
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
            self._reader.fast_route = self._hub.fast_route
            self._hub.on_sinks_changed = self._reader.look_again
            self._reader.postponable = self.postponable
        self._in_step: dict[str, InStep] = {}
        self._views: dict[str, tuple[tuple[object, ...], AutopilotView]] = {}
        # The configuration the arbiter was settled under after the last full tick
        # (None: it was not, or no tick yet): see _nothing_new.
        self._settled_with: Running | None = None
        # What the last tick's due came from (Agent.postponable): the configuration, the
        # judgements, whether it was when they stop holding; None: the arbiter's due.
        self._due_from: tuple[Running, Mapping[str, Assessment], bool] | None = None
        self._postpone_before = math.inf  # a claim waits: read again by then at the latest

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
        self._round_now.set()
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
    def keeper_rounds(self) -> int:
        """Rounds the stream, firmware, parameter and fence keepers were stepped in so far
        (:data:`STREAM_CHECK_S`)."""
        return self._rounds

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
            self._round_now.set()  # declared parameters or a fence may have changed
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
        self._postpone_before = math.inf
        due = self.tick()
        if any(link.tracker.claim_pending for link in self._cfg.links.values()):
            soon = self._clock() + self._tick_s  # read the message that settles it soon
            due = soon if due is None else min(due, soon)
            self._postpone_before = soon
        return due

    def postponable(self) -> tuple[AutopilotLink, float, float, float, float] | None:
        """After a tick that returned a due from health thresholds: the active
        autopilot's link, the first of those thresholds a new message of it would not
        postpone, the age of its last message at which the first one it would falls
        (the late or silent stream), and frozen telemetry's threshold with the age of
        its last ``time_boot_ms`` advance at which it falls; of a standby, every
        threshold but its late stream's warning (``HealthTracker.next_threshold``: the
        arbiter acts on a standby's failures, and judges it afresh when it is to become
        the target), which would otherwise bring the reader back every few tens of
        milliseconds while two autopilots stream. The reader's fast path
        waits for those ages past the active autopilot's latest frames instead of waking
        at the due while frames come (roost_agent.fastpath). None: the due is the
        arbiter's, not a threshold's.
        Worked out when asked (on the reader thread, before it waits), not at every tick:
        only the fast path asks."""
        judged = self._due_from
        if judged is None:
            return None
        cfg, assessments, holding = judged
        active = cfg.links.get(self._state.active)
        if active is None:
            return None
        fixed, age, frozen, frozen_age = self._postpone_before, math.inf, math.inf, math.inf
        for name, link in cfg.links.items():
            last = assessments.get(name)
            if last is None:
                return None
            tracker = link.tracker
            if link is active:
                own, age, frozen, frozen_age = tracker.postponed_by_messages(last)
                fixed = min(fixed, own + JUDGE_LATE_S)
            else:
                later = (  # not its late warning (the docstring says why)
                    tracker.holds_until(last, late_warning=False)
                    if holding
                    else tracker.next_threshold(last, late_warning=False)
                )
                fixed = min(fixed, later + JUDGE_LATE_S)
        return active, fixed, age + JUDGE_LATE_S, frozen + JUDGE_LATE_S, frozen_age + JUDGE_LATE_S

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
            self._due_from = (cfg, self._assessments, True)
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
            self._due_from = (cfg, assessments, False)
            return due + JUDGE_LATE_S
        self._settled_with = None
        self._due_from = None
        return next_due(self._state, cfg.policy, now)

    def _nothing_new(self, cfg: Running, now: float, in_step: Mapping[str, InStep]) -> float | None:
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
    def _judgements_hold_until(cfg: Running, judged: Mapping[str, Assessment]) -> float:
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

    # -- health events, conditions -----------------------------------------------------

    def _note_health_changes(self, assessments: Mapping[str, Assessment]) -> None:
        for name, a in assessments.items():
            signature = a.signature
            previous = self._signatures.get(name)
            if signature == previous:
                continue
            self._signatures[name] = signature
            self._round_now.set()  # heard first or again, rebooted: the keepers look now
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

    # -- persistence, heartbeats, events -------------------------------------------------

    def _heartbeat_forever(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            links = self._cfg.links
            if self._clock() >= next_beat:
                next_beat = self._clock() + HEARTBEAT_PERIOD_S
                for link in links.values():
                    link.send_heartbeat()
            self._rounds += 1
            asked = False
            for link in links.values():
                try:
                    asked = self._keep_streams(link) or asked
                except Exception:  # a stream request must never stop the heartbeats
                    log.exception("%s: stream keeping failed", link.name)
            for link in links.values():
                try:
                    asked = self._keep_firmware(link) or asked
                except Exception:  # nor a firmware question
                    log.exception("%s: asking for the firmware version failed", link.name)
            cfg = self._cfg
            received = {name: link.params.take() for name, link in cfg.links.items()}
            try:
                asked = self._keep_params(cfg, received) or asked
            except Exception:  # nor a parameter read or write
                log.exception("parameter keeping failed")
            try:
                self._keep_fence(cfg, received)
            except Exception:  # nor a fence transfer
                log.exception("fence keeping failed")
            talking = (
                asked
                or any(received.values())
                or self._fences.transferring()
                or not all(self._settled(link) for link in links.values())
            )
            self._rest(cfg, STREAM_CHECK_S if talking else next_beat - self._clock())

    def _settled(self, link: AutopilotLink) -> bool:
        """Whether this link's stream keeper expects nothing soon: nobody to ask (not
        heard yet, the link lost) or its streams arrive as requested. Until then (just
        heard, rebooted, a stream missing) rounds come every :data:`STREAM_CHECK_S`; an
        autopilot heard again changes its health, which starts a round at once
        (:meth:`_note_health_changes`). Firmware questions keep their own clock
        (:data:`roost_agent.firmware.REQUEST_EVERY_S`), which the heartbeat's pace
        serves."""
        keeper = self._keepers.get(link.name)
        return keeper is not None and keeper[0] is link and keeper[1].settled

    def _rest(self, cfg: Running, period_s: float) -> None:
        """Wait ``period_s`` between heartbeat rounds, or until a round is wanted now;
        while a fence transfer runs, step the fence keepers every :data:`FENCE_POLL_S`
        meanwhile (a transfer is one round trip per item: at the round's pace a
        20-vertex upload and its read-back would take over 4 s)."""
        until = self._clock() + period_s
        while not self._stop.is_set():
            left = until - self._clock()
            if left <= 0 or self._round_now.is_set():
                self._round_now.clear()
                return
            if not self._fences.transferring():
                self._round_now.wait(left)
                continue
            self._round_now.wait(min(left, FENCE_POLL_S))
            try:
                self._keep_fence(cfg, {})
            except Exception:
                log.exception("fence keeping failed")

    def _keep_firmware(self, link: AutopilotLink) -> bool:
        """Ask a heard autopilot for AUTOPILOT_VERSION until it answers, and again after
        it rebooted (a firmware update reboots it); take each answer. Whether it asked."""
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
            return False
        if (known is not None and known[3] == reboots) or link.heartbeat() is None:
            return False
        now = self._clock()
        asked = self._version_asked.get(link.name)
        if asked is None or asked[0] is not link or asked[3] != reboots:
            tries = 1  # a new link, or the autopilot rebooted
        elif now - asked[1] < firmware.REQUEST_EVERY_S or asked[2] >= firmware.MAX_REQUESTS:
            return False  # asked recently, or often enough until the next reboot
        else:
            tries = asked[2] + 1
        self._version_asked[link.name] = (link, now, tries, reboots)
        request = float(firmware.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        link.send_command(MAV_CMD_REQUEST_MESSAGE, (request, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        return True

    def _keep_fence(
        self, cfg: Running, received: dict[str, list[tuple[str, float, int, float]]]
    ) -> None:
        """Step every autopilot's fence keeper (roost_agent.fence) with what its link
        received."""

        def emit(reason: str, message: str, warning: bool, autopilot: str) -> None:
            self._emit(EventKind.FENCE, reason, message, warning=warning, autopilot=autopilot)
            self._reader.poke()

        messages = {name: link.mission.take() for name, link in cfg.links.items()}
        if (
            cfg.spec.fence is None
            and not any(messages.values())
            and not any(received.values())
            and self._fences.at_rest(cfg.links)
        ):
            return  # no fence, none to restore, nothing arrived: the step would do nothing
        self._fences.step(
            cfg.links,
            cfg.spec.fence,
            messages=messages,
            params=received,
            capabilities={name: fw[2] for name, fw in self._firmware.items()},
            positions=_positions(cfg.links.values()),
            armed=any(_armed(link) for link in cfg.links.values()),
            now=self._clock(),
            emit=emit,
        )

    def _keep_params(
        self, cfg: Running, received: dict[str, list[tuple[str, float, int, float]]]
    ) -> bool:
        """Step every autopilot's parameter keeper: take the PARAM_VALUEs its link
        received, send the reads and writes it asks for, report what changed. Whether it
        sent any."""
        declared = cfg.spec.parameters
        keepers = (keeper for _, keeper in self._param_keepers.values())
        if declared is None and nothing_declared(keepers, self._param_verdicts):
            return False  # every keeper would stay empty, no verdict to withdraw
        restore = declared is not None and declared.on_drift == DriftPolicy.RESTORE
        armed = any(_armed(link) for link in cfg.links.values())
        now = self._clock()
        sent = False
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
                    sent = True
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
        return sent

    def _keep_streams(self, link: AutopilotLink) -> bool:
        """Step this link's stream keeper and send what it asks for; whether it asked."""
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
        return bool(requests)

    def _hub_event(self, reason: str, message: str, warning: bool) -> None:
        self._emit(EventKind.LINK, reason, message, warning=warning)

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
