"""One MAVLink link per autopilot: a transport, read by the shared reader, locked writes.

Why one link per autopilot (not one shared socket): two autopilots behind one socket are
merged by a MAVLink router and a command can reach both. The link is what the agent,
the hub and the keepers hold of an autopilot: it opens its transport
(:mod:`roost_agent.transport`), applies the trust rules (:mod:`roost_agent.trust`) to
every datagram the reader (:mod:`roost_agent.reader`) hands it, feeds the health
tracker and hands COMMAND_ACKs to whoever waits for them. Every frame is checked by
header and CRC and decoded field by field on demand by the agent's own codec
(:mod:`roost_mavlink.codec`, which judges bad data as pymavlink's parser does); the
agent's own frames are encoded by it too. Writes (the agent's heartbeat, safety
commands) take a lock, which also keeps the MAVLink sequence numbers in order.

A link never dies: any exception is counted, reported (``error``, shown in the status,
and a warning Event) and the link reopened with exponential backoff
(:data:`REOPEN_DELAY_S` doubling to :data:`REOPEN_MAX_S`). Opening (which can block: a
TCP connect) happens beside the reader, so one unreachable autopilot never delays
reading the others.

The agent talks as component 191 (onboard computer) with the autopilot's own system id,
as a companion computer does, and addresses commands to the autopilot's component
(never the broadcast component 0).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Generic, TypeVar, cast

from roost_agent.fastpath import RUN_FIELDS, Routed, Run, kind_names
from roost_agent.health import Fix, HealthTracker, Motion, ObservedRun, RunState
from roost_agent.reader import LinkReader, Session
from roost_agent.signing import LinkSigning
from roost_agent.transport import (
    Address,
    Transport,
    configured_peer,
    open_transport,
    recent_realtime_offset,
)
from roost_agent.trust import FOREIGN_ALERT_PER_S, RateAlarm, SourceLock, address_text
from roost_api.core import Stack
from roost_api.plain import AutopilotSpec
from roost_mavlink import AGENT_COMPONENT_ID, MavResult
from roost_mavlink.codec import MAVLINK_VERSION, BadData, Encoder, Frame, Value, scan
from roost_mavlink.signing import Signer, Verdict, Verifier
from roost_mavlink.status import MAV_AUTOPILOT_INVALID, MAV_TYPE_ONBOARD_CONTROLLER, MavState

log = logging.getLogger(__name__)

Params = tuple[float, float, float, float, float, float, float]
EventSink = Callable[[str, str, bool], None]  # (reason, message, warning)

DRAIN_MAX: Final = 256  # datagrams read from one transport per wake-up
# A kernel arrival stamp older than the read by more is taken as only this old. Stamps
# are CLOCK_REALTIME: a step of the wall clock between two offset readings shifts them,
# and a shift backwards makes every message look older than it is. This bounds that to
# 0.1 s (a silence is 0.2 s). A datagram really older than this (the bulk of a steered
# link waits up to a 0.1 s read interval, a loaded machine oversleeps) is judged a few
# milliseconds younger than it is, never a whole interval: taking the read time instead
# would delay a silence by the interval.
STAMP_SLACK_S = 0.1
REOPEN_DELAY_S: Final = 0.5
REOPEN_MAX_S: Final = 30.0


@dataclass
class LinkCounters:
    """What the reader saw; exposed for diagnostics, the status line and the benchmarks."""

    bytes: int = 0  # every datagram or read, dropped or not
    accepted: int = 0  # from the locked address, this autopilot's sysid/component
    foreign: int = 0  # datagrams from another address while locked (not parsed)
    unlocked: int = 0  # parsed before any address proved itself (not used)
    other: int = 0  # from the locked address but another sysid or component
    bad: int = 0  # bytes that did not parse or failed their CRC (BAD_DATA)
    unknown: int = 0  # framed, but a message id nobody declared: its CRC cannot be checked
    truncated: int = 0  # datagrams that ended inside a frame
    unsigned: int = 0  # dropped while signing is required: no signature
    bad_signature: int = 0  # dropped while signing is required: wrong or replayed
    errors: int = 0  # exceptions from the parser or the transport
    reopened: int = 0
    relocked: int = 0


LOG_REPLIES = frozenset({"LOG_ENTRY", "LOG_DATA"})
"""The log protocol's answers: no target field, so routed by who holds the session."""


class _Writer:
    """Where the link's frames go: its own (encoded and numbered as the agent) and hub
    clients' (as they are), signed when the link signs."""

    def __init__(self, transport: Transport, signer: Signer | None, encoder: Encoder) -> None:
        self.transport = transport
        self.signer = signer
        self.encoder = encoder
        self.record: Callable[[bytes], None] | None = None  # the flight recorder's tap

    def write(self, frame: bytes) -> None:
        if self.signer is not None:
            frame = self.signer.sign(frame)
        self.transport.send(frame)
        record = self.record  # after the send: recording never delays a frame
        if record is not None:
            record(frame)

    def send(self, name: str, **values: Value) -> None:
        """Encode one message from the agent and write it."""
        self.write(self.encoder.encode(name, **values))


def _nothing() -> None:
    pass


class AckMailbox:
    """COMMAND_ACKs by command number, so a sender can wait for the answer to its command."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._acks: dict[int, tuple[int, int]] = {}  # command -> (serial, result)

    def serial(self, command: int) -> int:
        """Number of acks seen so far for ``command`` (take it before sending)."""
        with self._cond:
            return self._acks.get(command, (0, 0))[0]

    def put(self, command: int, result: int) -> None:
        """Record an ack (called by the reader)."""
        with self._cond:
            serial = self._acks.get(command, (0, 0))[0] + 1
            self._acks[command] = (serial, result)
            self._cond.notify_all()

    def latest(self, command: int) -> int | None:
        """The last ack result for ``command``, None when none came yet."""
        with self._cond:
            entry = self._acks.get(command)
            return None if entry is None else entry[1]

    def wait(self, command: int, after_serial: int, timeout_s: float) -> int | None:
        """The first ack result for ``command`` newer than ``after_serial``, or None."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                serial, result = self._acks.get(command, (0, 0))
                if serial > after_serial:
                    return result
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._cond.wait(remaining):
                    serial, result = self._acks.get(command, (0, 0))
                    return result if serial > after_serial else None


PARAM_INBOX_MAX: Final = 4096  # a client's full parameter list is about 1,000 on PX4
T = TypeVar("T")
MISSION_INBOX_MAX: Final = 1024  # a fence download is one message per item
MISSION_MESSAGES: Final = frozenset(
    {"MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK"}
)
"""The mission protocol messages an autopilot sends the agent (roost_agent.fence)."""
READ_KINDS: Final = (
    frozenset({"COMMAND_ACK", "PARAM_VALUE", "AUTOPILOT_VERSION"}) | MISSION_MESSAGES | LOG_REPLIES
)
"""The message types whose content the link itself reads (:meth:`AutopilotLink._message`):
never summarised by the hub's fast path (:func:`roost_agent.fastpath.routine_bitmap`)."""
_KIND_NAMES: Final = kind_names()


class Inbox(Generic[T]):
    """Messages from the autopilot for a keeper on another thread (parameters, the
    mission protocol); the oldest go first when nobody takes them."""

    def __init__(self, limit: int) -> None:
        self._lock = threading.Lock()
        self._items: deque[T] = deque(maxlen=limit)

    def put(self, item: T) -> None:
        with self._lock:
            self._items.append(item)

    def take(self) -> list[T]:
        """Everything received since the last take, oldest first."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


ParamInbox = Inbox[tuple[str, float, int, float]]
"""PARAM_VALUEs: name, wire value, type, arrival."""
MissionInbox = Inbox[tuple[str, dict[str, Any], float]]
"""Mission protocol messages addressed to the agent: name, fields, arrival."""


class AutopilotLink:
    """The agent's connection to one autopilot."""

    def __init__(
        self,
        spec: AutopilotSpec,
        tracker: HealthTracker,
        on_change: Callable[[], None] = lambda: None,
        clock: Callable[[], float] = time.monotonic,
        *,
        signing: LinkSigning | None = None,
        on_event: EventSink = lambda reason, message, warning: None,
        reader: LinkReader | None = None,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.stack = Stack(spec.stack)
        # Whose frames this link accepts.
        self._sysid: int = spec.sysid
        self._component: int = spec.component_id
        self.tracker = tracker
        self.counters = LinkCounters()
        self.acks = AckMailbox()
        self.signing = signing
        self.error: str | None = None  # the last failure while the link is down
        self._on_change = on_change
        self._on_event = on_event
        self._clock = clock
        self._write_lock = threading.Lock()
        self._transport: Transport | None = None
        self._writer: _Writer | None = None
        self._stop = threading.Event()
        # The reader this link is read by: shared by the agent's links, or its own.
        self._reader = reader
        self._own_reader: LinkReader | None = None
        self._session: Session | None = None
        self._delay = REOPEN_DELAY_S
        # Kernel arrival timestamps are CLOCK_REALTIME: usable where the clock is monotonic.
        self._stamps = clock is time.monotonic
        self._foreign_alarm = RateAlarm(FOREIGN_ALERT_PER_S)
        self._signature_alarm = RateAlarm(FOREIGN_ALERT_PER_S)
        self._locked: Address | None = None
        # Called by the reader with every accepted message (the hub routes them to clients).
        self.tap: Callable[[Any, float], None] | None = None
        # Whether the datagram being read was routed to the hub's plain UDP clients in C
        # already (roost_agent.fastpath): the hub's tap sends it to the others only.
        self.routed = False
        # Called by the reader with the number of routine frames of a datagram the hub's
        # fast path routed in C (roost_agent.fastpath): True when the hub has counted
        # them and has nothing else to do with them; False: they go to ``tap`` whole.
        self.tap_routed: Callable[[int], bool] | None = None
        # Called by the reader with a run of datagrams the hub's fast path routed in C
        # (roost_agent.fastpath): their frame count and the last frame of each kept kind.
        self.tap_run: Callable[[int, Sequence[tuple[str, Any, float]]], None] | None = None
        # The flight recorder's tap (roost_agent.records_recorder): every frame accepted
        # from the autopilot (after the hub routed it and the tracker judged it) and
        # every frame written to it (after the write).
        self._record: Callable[[bytes], None] | None = None
        # LOG_ENTRY and LOG_DATA go here while an autopilot log is being fetched
        # (roost_agent.records_logs); dropped otherwise.
        self._log_sink: Callable[[Frame], None] | None = None
        self.params = ParamInbox(PARAM_INBOX_MAX)
        self.mission = MissionInbox(MISSION_INBOX_MAX)
        # The autopilot's last AUTOPILOT_VERSION (roost_agent.firmware reads it).
        self.version: Frame | None = None

    @property
    def log_sink(self) -> Callable[[Frame], None] | None:
        """Where LOG_ENTRY and LOG_DATA go while the agent fetches the autopilot's logs."""
        return self._log_sink

    @log_sink.setter
    def log_sink(self, sink: Callable[[Frame], None] | None) -> None:
        self._log_sink = sink
        reader = self._own_reader or self._reader
        if reader is not None:
            # Once set, the hub's fast path must not route a log reply: the reader's wait
            # in C (roost_agent.fastpath) began before, so it is woken and this returns
            # once the reader is back in Python; its next route sees the sink.
            reader.call(_nothing)

    @property
    def record(self) -> Callable[[bytes], None] | None:
        return self._record

    @record.setter
    def record(self, record: Callable[[bytes], None] | None) -> None:
        with self._write_lock:
            self._record = record
            if self._writer is not None:
                self._writer.record = record

    def fast_source(self) -> tuple[Session, Address] | None:
        """The session the hub's fast path may read in C and the address its frames
        must come from (:mod:`roost_agent.fastpath`): a UDP link with kernel arrival
        stamps, holding its source lock, not requiring signatures. None otherwise."""
        session = self._session
        if session is None or not self._stamps or session.verifier is not None:
            return None
        locked = session.lock.locked
        if locked is None or session.transport.fast_fds() is None:
            return None
        return session, locked

    @property
    def locked_address(self) -> Address | None:
        """The address this link hears (None: not locked yet, or a serial/TCP link)."""
        return self._locked

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Start reading (on the shared reader, else on one of its own); the transport is
        opened (and reopened) in the background."""
        self._stop.clear()
        reader = self._reader
        if reader is None:
            reader = self._own_reader = LinkReader(name=f"link-{self.name}")
            reader.start()
        self._delay = REOPEN_DELAY_S
        reader.call(lambda: self._open_soon(reader, 0.0))

    def stop(self) -> None:
        """Stop reading and close the transport."""
        self._stop.set()
        reader = self._own_reader or self._reader
        if reader is not None:
            reader.call(self._forget)
        if self._own_reader is not None:
            self._own_reader.stop()
            self._own_reader = None
        self._close()

    def _forget(self) -> None:
        session, self._session = self._session, None
        reader = self._own_reader or self._reader
        if session is not None and reader is not None:
            reader.detach(session)

    def _close(self) -> None:
        with self._write_lock:
            transport, self._transport, self._writer = self._transport, None, None
        if transport is not None:
            try:
                transport.close()
            except OSError:
                log.debug("closing %s failed", self.name, exc_info=True)

    def _event(self, reason: str, message: str, warning: bool) -> None:
        try:
            self._on_event(reason, f"{self.name}: {message}", warning)
        except Exception:  # a reporting bug must not stop the reader
            log.exception("%s: reporting %s failed", self.name, reason)

    # -- opening, failing, reopening (on the reader thread; opening itself beside it) --

    def _open_soon(self, reader: LinkReader, delay_s: float) -> None:
        def begin() -> None:
            if not self._stop.is_set():
                threading.Thread(
                    target=self._open_beside, args=(reader,), name=f"open-{self.name}", daemon=True
                ).start()

        reader.after(delay_s, begin)

    def _open_beside(self, reader: LinkReader) -> None:
        """Open the transport (may block) and hand the session to the reader."""
        try:
            session = self._open()
        except Exception as exc:
            failure = exc
            reader.call(lambda: self.failed(failure, None))
            return
        session.link = self

        def adopt() -> None:
            if self._stop.is_set():
                self._close()
                return
            try:
                reader.attach(session)
            except Exception as exc:
                self.failed(exc, session)
                return
            self._session = session

        reader.call(adopt)

    def failed(self, exc: Exception, session: Session | None) -> None:
        """Report a failure, close, and reopen with backoff (on the reader thread)."""
        self._session = None
        self.counters.errors += 1
        text = " ".join(f"{type(exc).__name__}: {exc}".split())
        if text != self.error:
            log.warning("%s: link failed (%s); retrying", self.name, text)
            self._event("LinkError", f"link failed: {text}; retrying", True)
        self.error = text
        self._close()
        if self._stop.is_set():
            return
        if session is not None and self.counters.accepted > session.accepted_at_open:
            self._delay = REOPEN_DELAY_S  # it worked for a while: retry soon
        self.counters.reopened += 1
        reader = self._own_reader or self._reader
        if reader is not None:
            self._open_soon(reader, self._delay)
        self._delay = min(self._delay * 2, REOPEN_MAX_S)

    # -- reading ---------------------------------------------------------------------

    def _open(self) -> Session:
        transport = open_transport(self.spec.connection, steer=True)
        try:
            peer = configured_peer(self.spec.connection)
            relock_s = self.tracker.thresholds.heartbeat_error_ms / 1000
            if transport.fixed_peer is not None:
                lock = SourceLock(relock_after_s=relock_s, fixed=transport.fixed_peer)
            elif peer is not None and peer[1] is not None:
                lock = SourceLock(relock_after_s=relock_s, fixed=(peer[0], peer[1]))
            else:
                host = None if peer is None else peer[0]
                lock = SourceLock(relock_after_s=relock_s, host=host)
            if lock.locked is not None:
                transport.lock_to(lock.locked)
            self._locked = lock.locked
            signing = self.signing
            signer = signing.signer(self.spec.bridge_channel) if signing is not None else None
            verifier = signing.verifier() if signing is not None and signing.require else None
            writer = _Writer(transport, signer, Encoder(self.spec.sysid, AGENT_COMPONENT_ID))
            writer.record = self._record
        except BaseException:
            transport.close()
            raise
        with self._write_lock:
            self._transport, self._writer = transport, writer
        return Session(transport, lock, verifier, accepted_at_open=self.counters.accepted)

    def drain(self, session: Session) -> None:
        """Read what the transport has (up to :data:`DRAIN_MAX`), or take what the hub's
        fast path read of it (:mod:`roost_agent.fastpath`); failures propagate."""
        stamps = self._stamps
        offset = recent_realtime_offset() if stamps else 0.0
        pushed = session.pushed
        if pushed is not None:
            session.pushed = None
            try:
                for item in pushed:
                    if len(item) == RUN_FIELDS:
                        self._run(session, cast("Run", item))
                        continue
                    data, sender, stamp, routed, frames = cast("Routed", item)
                    self.routed = routed
                    now = self._arrival(session, stamp, offset)
                    if frames is None or not self._routine(session, data, sender, frames, now):
                        self._datagram(session, data, sender, now)
            finally:
                self.routed = False
            return
        for data, sender, stamp in session.transport.receive_batch(DRAIN_MAX):
            now = self._arrival(session, stamp, offset)
            self._datagram(session, data, sender, now)

    def _arrival(self, session: Session, stamp: float | None, offset: float) -> float:
        """The time a datagram is judged to have arrived: its kernel stamp on the
        agent's clock (``offset``: realtime minus monotonic), never before an earlier
        datagram's time, nor more than the slack before the read; a stamp after the
        read is not believed at all."""
        now = self._clock()
        if stamp is not None and self._stamps:
            arrived = stamp - offset
            if arrived < now:
                # compared one by one: max() would box the floats
                earliest = now - STAMP_SLACK_S
                now = arrived if arrived > earliest else earliest
                last = session.arrived
                now = last if last > now else now
        session.arrived = now
        return now

    def _datagram(self, session: Session, data: bytes, sender: Address | None, now: float) -> None:
        self.counters.bytes += len(data)
        lock = session.lock
        locked = sender is None or sender == lock.locked
        if not locked and sender is not None and not lock.hears(sender, now):
            self.counters.foreign += 1
            fired = self._foreign_alarm.note(now, address_text(sender))
            if fired is not None:
                self._event(
                    "ForeignMavlinkTraffic",
                    f"ignored datagrams ({fired}) from "
                    f"{self._foreign_alarm.describe()}; only the autopilot at "
                    f"{address_text(lock.locked)} is heard (a misconfigured second sender, "
                    "or MAVLink injection)",
                    True,
                )
            return
        if session.transport.datagrams:
            items, used = scan(data)
            if used < len(data):  # a frame never continues in the next datagram
                self.counters.truncated += 1
        else:
            items = session.parser.feed(data)
        try:
            for item in items:
                if isinstance(item, Frame):
                    # A frame of this datagram may have taken the lock for its sender.
                    locked = locked or sender == lock.locked
                    self._message(session, item, sender, now, locked)
                elif isinstance(item, BadData):
                    self.counters.bad += 1
                else:
                    self.counters.unknown += 1
        except Exception:  # a bug reading one message must not stop the reader
            self.counters.errors += 1

    def _routine(
        self,
        session: Session,
        data: bytes,
        sender: Address | None,
        frames: tuple[int, ...],
        now: float,
    ) -> bool:
        """A datagram the hub's fast path routed in C, of routine frames only, taken by
        their summary (id, sequence number, ``time_boot_ms`` or -1 each: the kinds no one
        reads the content of, :func:`roost_agent.fastpath.routine_bitmap`): accepted,
        counted by the hub and judged by the tracker as :meth:`_message` does with them
        whole. False, having done nothing, when it must be read whole instead: the
        recorder wants the frames, signatures are checked, the lock moved since C read
        it, or the hub has more to do (:attr:`tap_routed`)."""
        if self._record is not None or session.verifier is not None:
            return False
        if sender is None or sender != session.lock.locked:
            return False
        tap_routed = self.tap_routed
        if tap_routed is None or not tap_routed(len(frames) // 3):
            return False
        self.counters.bytes += len(data)
        tracker = self.tracker
        names = _KIND_NAMES
        try:
            for i in range(0, len(frames), 3):
                self._accepted(session.lock, now)
                boot_ms = frames[i + 2]
                kind = names[frames[i]]
                if tracker.observe_routine(
                    kind, None if boot_ms < 0 else boot_ms, frames[i + 1], now
                ):
                    self._on_change()
        except Exception:  # a bug reading one message must not stop the reader
            self.counters.errors += 1
        return True

    def run_state(self) -> RunState | None:
        """What the hub's fast path must respect to hand this link's stream over in runs
        (:data:`roost_agent.fastpath.Run`), or None: datagram by datagram (the recorder
        wants every frame, signatures are checked, the hub takes no runs, or the tracker
        judges message by message now: :meth:`HealthTracker.run_state`)."""
        session = self._session
        if self._record is not None or self.tap_run is None:
            return None
        if session is None or session.verifier is not None:
            return None
        return self.tracker.run_state()

    def _run(self, session: Session, run: Run) -> None:
        """A run of datagrams the hub's fast path routed in C, taken together: accepted,
        counted by the hub and judged by the tracker as their frames one by one would
        be (:meth:`HealthTracker.observe_run`). Only the last frame of each kept kind is
        read whole."""
        first_at, last_at, max_gap, frames, _, size, last_seq, boot_max, boot_at, ids, kept = run
        earliest = session.arrived
        first_at = first_at if first_at > earliest else earliest
        last_at = last_at if last_at > first_at else first_at
        session.arrived = last_at
        self.counters.bytes += size
        names = _KIND_NAMES
        latest: list[tuple[str, Any, float]] = []
        try:
            for i in range(0, len(kept), 2):
                data = kept[i]
                assert isinstance(data, bytes)
                at = kept[i + 1]
                assert isinstance(at, float)
                items, _ = scan(data)
                for frame in items:
                    if isinstance(frame, Frame):
                        latest.append((frame.get_type(), frame, at))
            self._accepted(session.lock, last_at)
            self.counters.accepted += frames - 1
            tap_run = self.tap_run
            if tap_run is not None:
                tap_run(frames, latest)
            observed = ObservedRun(
                first_at,
                last_at,
                max_gap,
                frames,
                tuple((names[ids[i]], ids[i + 1]) for i in range(0, len(ids), 2)),
                boot_max,
                boot_at,
                last_seq,
                tuple(latest),
            )
            if self.tracker.observe_run(observed):
                self._on_change()
        except Exception:  # a bug reading one run must not stop the reader
            self.counters.errors += 1

    def _accepted(self, lock: SourceLock, now: float) -> None:
        """A frame of this autopilot from the locked address is taken."""
        lock.seen(now)
        self.counters.accepted += 1
        if self.error is not None:
            self.error = None
            self._event("LinkRecovered", "receiving again", False)

    def _message(
        self, session: Session, msg: Frame, sender: Address | None, now: float, locked: bool
    ) -> None:
        """One frame of a datagram; ``locked``: from the address the link is locked to."""
        kind = msg.get_type()
        lock = session.lock
        if msg.get_srcSystem() != self._sysid or msg.get_srcComponent() != self._component:
            if locked:
                self.counters.other += 1
            else:
                self.counters.unlocked += 1
            return
        if session.verifier is not None and not self._signed(session.verifier, msg, sender, now):
            return
        if not locked:
            assert sender is not None
            proof = kind == "HEARTBEAT" and int(msg.autopilot) != MAV_AUTOPILOT_INVALID
            if not (proof and lock.prove(sender, now)):
                self.counters.unlocked += 1
                return
            self._took_lock(session, sender)
        self._accepted(lock, now)
        tap = self.tap
        if tap is not None:
            tap(msg, now)
        if kind == "COMMAND_ACK":
            target_system = getattr(msg, "target_system", 0)
            target_component = getattr(msg, "target_component", 0)
            if target_system in (0, self.spec.sysid) and target_component in (
                0,
                AGENT_COMPONENT_ID,
            ):
                self.acks.put(int(msg.command), int(msg.result))
        elif kind == "PARAM_VALUE":
            name = bytes(msg.param_id).decode("ascii", "replace")
            self.params.put((name, float(msg.param_value), int(msg.param_type), now))
        elif kind in MISSION_MESSAGES:
            if msg.target_system in (0, self.spec.sysid) and msg.target_component in (
                0,
                AGENT_COMPONENT_ID,
            ):
                self.mission.put((kind, msg.to_dict(), now))
        elif kind == "AUTOPILOT_VERSION":
            self.version = msg
        elif kind in LOG_REPLIES:
            sink = self._log_sink
            if sink is not None:
                sink(msg)
        if self.tracker.observe(msg, now):
            self._on_change()
        record = self._record  # last: routed and judged before it is recorded
        if record is not None:
            record(msg.get_msgbuf())

    def _signed(self, verifier: Verifier, msg: Frame, sender: Address | None, now: float) -> bool:
        verdict = verifier.check(msg.get_msgbuf())
        if verdict is Verdict.GOOD:
            writer = self._writer
            signer = writer.signer if writer is not None else None
            if signer is not None and signer.key is not verifier.used:
                signer.use(verifier.used)  # answer with the key the autopilot has
            return True
        if verdict is Verdict.UNSIGNED:
            self.counters.unsigned += 1
        else:
            self.counters.bad_signature += 1
        fired = self._signature_alarm.note(now, f"{address_text(sender)} ({verdict.value})")
        if fired is not None:
            self._event(
                "UnsignedMavlink",
                f"dropped frames ({fired}) that carry the autopilot's ids without a valid "
                f"signature, from {self._signature_alarm.describe()}",
                True,
            )
        return False

    def _took_lock(self, session: Session, sender: Address) -> None:
        previous, self._locked = self._locked, sender
        session.transport.lock_to(sender)
        if previous is None:
            self._event("AutopilotLocked", f"listening to {address_text(sender)} only", False)
        else:
            self.counters.relocked += 1
            self._event(
                "AutopilotAddressChanged",
                f"{address_text(previous)} fell silent and {address_text(sender)} proved "
                "itself with the autopilot's heartbeats: listening there now",
                True,
            )

    # -- writing ---------------------------------------------------------------------

    def _send(self, write: Callable[[_Writer], None]) -> bool:
        with self._write_lock:
            if self._writer is None:
                return False
            try:
                write(self._writer)
            except (OSError, ValueError) as exc:
                log.debug("%s: write failed: %s", self.name, exc)
                return False
            return True

    def rekey(self, signing: LinkSigning) -> None:
        """Adopt a rotated key at once: frames from now on are signed with it and, when
        signing is required, checked against it (the autopilot's streams start afresh)."""
        with self._write_lock:
            self.signing = signing
            writer = self._writer
            if writer is not None and writer.signer is not None:
                writer.signer = signing.signer(self.spec.bridge_channel)
            session = self._session
            if session is not None and session.verifier is not None:
                session.verifier = signing.verifier()

    def send_frame(self, frame: bytes) -> bool:
        """Forward a finished MAVLink frame (a hub client's), signed like the agent's own."""
        return self._send(lambda writer: writer.write(frame))

    def send_heartbeat(self) -> bool:
        """The agent's own 1 Hz heartbeat (onboard controller, not an autopilot).

        It tells the autopilot an onboard computer is present and lets a ``udpout``
        or TCP peer learn where to send.
        """
        return self._send(
            lambda writer: writer.send(
                "HEARTBEAT",
                type=MAV_TYPE_ONBOARD_CONTROLLER,
                autopilot=MAV_AUTOPILOT_INVALID,
                base_mode=0,
                custom_mode=0,
                system_status=MavState.ACTIVE,
                mavlink_version=MAVLINK_VERSION,
            )
        )

    def _send_to_autopilot(self, name: str, **values: Value) -> bool:
        """One message addressed to this autopilot's system and component."""
        target = {"target_system": self.spec.sysid, "target_component": self.spec.component_id}
        return self._send(lambda writer: writer.send(name, **target, **values))

    def send_message(self, name: str, **values: Value) -> bool:
        """One message (``name`` of common.xml) addressed to this autopilot."""
        return self._send_to_autopilot(name, **values)

    def send_command(self, command: int, params: Params, confirmation: int = 0) -> bool:
        """COMMAND_LONG addressed to this autopilot's system and component."""
        param = {f"param{i}": value for i, value in enumerate(params, start=1)}
        return self._send_to_autopilot(
            "COMMAND_LONG", command=command, confirmation=confirmation, **param
        )

    def read_param(self, name: str) -> bool:
        """PARAM_REQUEST_READ of one parameter by name (answered by a PARAM_VALUE)."""
        return self._send_to_autopilot("PARAM_REQUEST_READ", param_id=name, param_index=-1)

    def write_param(self, name: str, wire: float, ptype: int) -> bool:
        """PARAM_SET of one parameter (answered by a PARAM_VALUE with what it now holds);
        ``wire``: the value as the float field carries it (roost_agent.params.to_wire)."""
        return self._send_to_autopilot(
            "PARAM_SET", param_id=name, param_value=wire, param_type=ptype
        )

    def send_mission(self, name: str, fields: Mapping[str, Value]) -> bool:
        """One mission protocol message (roost_agent.fence) addressed to this autopilot."""
        return self._send_to_autopilot(name, **fields)

    def request_data_stream(self, stream_id: int, hz: int) -> bool:
        """REQUEST_DATA_STREAM (start) for one MAV_DATA_STREAM group (ArduPilot)."""
        return self._send_to_autopilot(
            "REQUEST_DATA_STREAM", req_stream_id=stream_id, req_message_rate=hz, start_stop=1
        )

    def command(
        self, command: int, params: Params, *, confirmation: int, timeout_s: float
    ) -> int | None:
        """Send a command and wait for its COMMAND_ACK result (None: no answer in time).

        MAV_RESULT_IN_PROGRESS is not an answer: the wait goes on (once more for
        ``timeout_s``) for the final result.
        """
        serial = self.acks.serial(command)
        if not self.send_command(command, params, confirmation):
            return None
        result = self.acks.wait(command, serial, timeout_s)
        if result == MavResult.IN_PROGRESS:
            final = self.acks.wait(command, serial + 1, timeout_s)
            return MavResult.IN_PROGRESS if final is None else final
        return result

    def heartbeat(self) -> tuple[int, int, float] | None:
        """(custom_mode, base_mode, received_at) of the autopilot's last heartbeat."""
        return self.tracker.heartbeat()

    def landed_state(self) -> int | None:
        """The autopilot's last reported landed state."""
        return self.tracker.landed_state()

    def system_status(self) -> int | None:
        """The autopilot's last reported MAV_STATE."""
        return self.tracker.system_status()

    def motion(self) -> Motion | None:
        """The autopilot's last altitude and vertical speed."""
        return self.tracker.motion()

    def fix(self) -> Fix | None:
        """The autopilot's last position and heading (decoded now, not by the reader)."""
        return self.tracker.fix()
