"""Turn one autopilot's MAVLink messages into a health judgement (OK/WARN/ERROR/STALE).

Why a tracker plus a pure assessment: the link's reader thread feeds every message into
:meth:`HealthTracker.observe` (cheap, a few attribute writes under a lock), and the
decision loop calls :meth:`HealthTracker.assess` with the current time. Time is always a
parameter (a monotonic clock reading in seconds), never read inside, so every threshold
is unit-testable without sleeping and the same code serves the live agent and replays.

The rules follow the health model in ``docs/health-model.md`` (with its sources):

- liveness: age of any message (only where the link streams fast enough for that to mean
  something, see :data:`FAST_STREAM_FACTOR`) against a threshold learnt from the stream
  itself (below), and age of the heartbeat;
- frozen telemetry: messages keep coming but ``time_boot_ms`` stops advancing;
- reboot: ``time_boot_ms`` going backwards, or MAV_STATE BOOT after the autopilot was up;
- MAV_STATE: EMERGENCY / POWEROFF / FLIGHT_TERMINATION are errors, BOOT-like states in the
  air are errors, CRITICAL is a warning unless another finding corroborates it;
- SYS_STATUS sensor bits, classified by :func:`roost_mavlink.classify_sensors` (gyro,
  accel, AHRS are failover-critical once they persist; navigation sensors only warn);
- estimator flags (PX4 ESTIMATOR_STATUS, ArduPilot EKF_STATUS_REPORT): attitude lost or
  accelerometer error persisting is an error, position lost a warning;
- disarmed while in the air; attitude beyond the tilt envelope.

Corroboration: a reboot (``time_boot_ms`` back-step, MAV_STATE BOOT after it was up) or a
fatal MAV_STATE claimed by one message is a *claim*, acted on only once the following
message(s) of the autopilot corroborate it, so one forged, replayed or corrupted frame
that passed its CRC cannot trigger a switch. The next message settles the claim:

- it contradicts the claim (``time_boot_ms`` back on the old timeline; a heartbeat with a
  non-fatal, non-BOOT state): refuted, counted in :attr:`HealthTracker.refuted`;
- its MAVLink sequence number continues from the claim's (1..:data:`SEQ_WINDOW` ahead, so
  a few lost frames do not matter): confirmed, with the claim's time as the onset;
- it continues the sequence from before the claim instead: refuted (the claim did not
  come from the stream the autopilot is sending);
- it repeats the claim (a second fatal heartbeat, a second sample on the new timeline):
  confirmed. Otherwise the claim waits for the next message.

At 50 Hz telemetry that costs one message interval (20 ms) of the real-reboot and
EMERGENCY detection; with heartbeats only, one message of whatever streams.

No health without evidence: an autopilot not heard yet is STALE, one heard but without a
heartbeat yet is STARTING, and so is one on the ground and disarmed that is still
starting up — MAV_STATE UNINIT/BOOT (PX4 reports UNINIT for ~4 s, ArduPilot BOOT), an
estimator that has not yet produced an attitude since boot (PX4 ESTIMATOR_STATUS flags
0x480, ArduCopter EKF_STATUS_REPORT 0x400), or no absolute position yet (the GPS wait,
~35 s on ArduCopter). Start-up is neither lost nor failed: STARTING never triggers a
failover, and it is never a healthy standby either. Once an estimator has worked, losing
it again is the error it always was.

The tracker also keeps what the stream keeper (:mod:`roost_agent.streams`) and the
safety routine need: messages counted per type (to verify requested rates arrive) and
the last altitude and vertical speed (GLOBAL_POSITION_INT) to confirm that a hold holds.

The silence threshold adapts to each autopilot's stream. A fixed 200 ms fits a 50 Hz
stream with margin, but a PX4 onboard link delivers ~400 messages a second and never
leaves a gap much over 12 ms (the recordings under docs/health-model.md), so 200 ms of
silence is ~15 gaps longer than any healthy one. The tracker keeps the worst gap between
consecutive arrivals (kernel receive stamps, so the agent's own lateness is never a
gap) in each of the last :data:`LEARN_WINDOWS` one-second windows, and calls the stream
silent after ``silence_margin`` times the worst of them, held between
``message_error_min_ms`` and ``message_error_ms`` (the operator's bounds). Why the worst
gap rather than a fitted distribution (φ-accrual's normal or exponential): the gaps of
a multiplexed stream are a mix of near-zero gaps inside bursts and the periods of a dozen
rates, nothing like either distribution, and a mean/variance fit is pulled down by every
burst; the largest gap is distribution-free, a burst after a stall cannot lower it, and
a link that degrades slowly raises it as it goes. A gap of ``message_error_ms`` or more
is an outage, not the stream's rhythm, and is not learnt: an autopilot back from a
silence is judged by the rhythm it had. Until :data:`LEARN_MIN_WINDOWS` windows
are learnt (start-up, after a reboot, after the agent requested other stream rates) the
ceiling applies: a requested rate change never meets a threshold learnt on the old rates.
The warning for a late stream scales with it (``message_warn_ms / message_error_ms`` of
the threshold).

Only findings marked ``triggers_failover`` can make the arbiter switch; warnings never
do. The arbiter adds the hysteresis (confirm/clear times); here a finding is reported as
soon as its own definition holds.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

from roost_api.core import HealthLevel, Stack
from roost_api.plain import AutopilotHealth, Thresholds
from roost_mavlink import (
    MAV_MODE_FLAG_SAFETY_ARMED,
    MavLandedState,
    MavState,
    SensorReport,
    api_landed_state,
    classify_sensors,
    is_manual_mode,
    mav_state_name,
    mode_name,
    stack_from_heartbeat,
)
from roost_mavlink.codec import Fields, Frame, fields
from roost_mavlink.status import MAV_AUTOPILOT_INVALID, is_airborne, sensor_name

# The any-message age only means "silent" on a link that normally streams several
# messages inside the warn window; on a link with only 1 Hz telemetry it would fire every
# second. The check applies while the message rate measured over the last completed
# window brings at least FACTOR messages per warn interval. Counting per window, not
# averaging gaps, keeps bursts (heartbeat, status and landed state sent together) from
# looking like a fast stream.
FAST_STREAM_FACTOR: Final = 4.0
RATE_WINDOW_S: Final = 1.0
# The silence threshold is learnt from the worst gap of each of the last LEARN_WINDOWS
# rate windows, and applies once LEARN_MIN_WINDOWS are complete (module docstring).
LEARN_WINDOWS: Final = 8
LEARN_MIN_WINDOWS: Final = 2

# time_boot_ms may step back a little when UDP reorders packets (jitter); a reboot
# restarts it near zero. Only a step back larger than this counts as a reboot.
REBOOT_BACKSTEP_MS: Final = 1000
# A reboot stays an error this long: an autopilot that restarted mid-flight is not a
# failover target again until it has proven itself for a while.
REBOOT_REMEMBERED_S: Final = 10.0

# How far ahead of a claim's sequence number the corroborating message may be (lost frames).
SEQ_WINDOW: Final = 8

TILT_WARN_DEG: Final = 35.0
TILT_PERSIST_S: Final = 0.3

# Estimator status flags shared by PX4 ESTIMATOR_STATUS and ArduPilot EKF_STATUS_REPORT
# (common.xml ESTIMATOR_STATUS_FLAGS / ardupilotmega.xml EKF_STATUS_FLAGS).
ESTIMATOR_ATTITUDE: Final = 0x1
ESTIMATOR_POS_HORIZ_ABS: Final = 0x10
ESTIMATOR_ACCEL_ERROR: Final = 0x800  # ESTIMATOR_STATUS only
EKF_UNINITIALIZED: Final = 0x400  # EKF_STATUS_REPORT only
UNKNOWN_HEADING: Final = 65535  # GLOBAL_POSITION_INT.hdg when the autopilot has none

_FATAL_STATES: Final = {MavState.EMERGENCY, MavState.POWEROFF, MavState.FLIGHT_TERMINATION}
_NOT_FLYING_STATES: Final = {MavState.UNINIT, MavState.BOOT, MavState.CALIBRATING}
_UP_STATES: Final = {MavState.STANDBY, MavState.ACTIVE, MavState.CRITICAL}


@dataclass(frozen=True)
class Finding:
    """One reason an autopilot is not OK."""

    level: HealthLevel
    code: str  # stable identifier (e.g. "silent", "sensor:gyro"); reason has the numbers
    reason: str
    triggers_failover: bool = False
    onset: float | None = None  # monotonic time the condition began, when known
    varies: bool = False  # its reason reads the clock ("silent for 230 ms"): judged every tick


@dataclass(frozen=True)
class Assessment:
    """One autopilot's health at one instant: what the arbiter and the status read."""

    name: str
    stack: Stack
    at: float
    level: HealthLevel
    findings: tuple[Finding, ...]
    message_age_s: float | None
    heartbeat_age_s: float | None
    custom_mode: int | None
    armed: bool | None
    landed_state: int | None
    system_status: int | None
    unhealthy_sensors: tuple[str, ...]
    version: int = -1  # the tracker's judgement version it was made from (HealthTracker.holds)

    @property
    def failing(self) -> bool:
        """At least one finding that justifies a failover."""
        return any(f.triggers_failover for f in self.findings)

    @property
    def signature(self) -> tuple[HealthLevel, frozenset[str]]:
        """Level and finding codes: changes only when the judgement does, not its numbers."""
        return self.level, frozenset(f.code for f in self.findings)

    @property
    def reasons(self) -> tuple[str, ...]:
        """Human-readable reasons, worst first."""
        return tuple(f.reason for f in self.findings)

    @property
    def failure_reason(self) -> str:
        """The failover-triggering reasons joined, or the plain reasons when none trigger."""
        triggering = [f.reason for f in self.findings if f.triggers_failover]
        return "; ".join(triggering or list(self.reasons)) or "healthy"

    @property
    def onset(self) -> float | None:
        """Earliest known start of a failover-triggering condition."""
        onsets = [f.onset for f in self.findings if f.triggers_failover and f.onset is not None]
        return min(onsets) if onsets else None

    @property
    def in_air(self) -> bool | None:
        """From EXTENDED_SYS_STATE: True in air/takeoff/landing, None when unknown."""
        if self.landed_state is None or self.landed_state == MavLandedState.UNDEFINED:
            return None
        return is_airborne(self.landed_state)

    @property
    def mode(self) -> str | None:
        """Flight mode name decoded with the configured stack's encoding."""
        return None if self.custom_mode is None else mode_name(self.stack, self.custom_mode)

    @property
    def pilot_in_control(self) -> bool:
        """True when the autopilot flies a pilot-steered mode (MANUAL, POSCTL, ALT_HOLD...)."""
        mode = self.mode
        return mode is not None and is_manual_mode(self.stack, mode)

    def to_api(self) -> AutopilotHealth:
        """The status entry the publisher writes (roost_api.autopilot.AutopilotHealth)."""
        return AutopilotHealth(
            name=self.name,
            level=self.level,
            reasons=list(self.reasons),
            heartbeat_age_ms=_ms(self.heartbeat_age_s),
            message_age_ms=_ms(self.message_age_s),
            mode=self.mode,
            armed=self.armed,
            landed_state=None if self.landed_state is None else api_landed_state(self.landed_state),
            system_status=None
            if self.system_status is None
            else mav_state_name(self.system_status),
            unhealthy_sensors=list(self.unhealthy_sensors),
        )


def _ms(seconds: float | None) -> int | None:
    return None if seconds is None else round(seconds * 1000)


def tilt_degrees(roll: float, pitch: float) -> float:
    """Angle between the body z axis and the vertical, from roll and pitch in radians."""
    cos_tilt = math.cos(roll) * math.cos(pitch)
    return math.degrees(math.acos(max(-1.0, min(1.0, cos_tilt))))


StateHeld = dict[str, tuple[int, ...]]
"""Per kind of :data:`STATE_FIELDS`, what a frame of it must say in the fields the
tracker reads, in order, to change nothing when read (-1: any value may change
something)."""

RunState = tuple[float, float, int, float, float, int, int, StateHeld]
""":meth:`HealthTracker.run_state`: the tilt warn and envelope angles and the class of
the last tilt (-1: none yet; 0 level, 1 past warn, 2 past the envelope), the silence
threshold, when the rate window ends (its closing may learn another silence threshold:
runs stop there until the state is asked again), the highest ``time_boot_ms`` (-1:
none), the step back in it that claims a reboot (ms), and the states held
(:data:`StateHeld`: a frame of a state kind that repeats them may join a run)."""

Postponable = tuple[float, float, float, float]
""":meth:`HealthTracker.postponed_by_messages`: the first threshold no new message
postpones, the age of the last message at which the first one a new message postpones
falls, frozen telemetry's first threshold, and the age of the last advance of
``time_boot_ms`` at which it falls."""

STATE_FIELDS: Final[dict[str, tuple[str, ...]]] = {
    "SYS_STATUS": ("onboard_control_sensors_enabled", "onboard_control_sensors_health"),
    "EXTENDED_SYS_STATE": ("landed_state",),
    "ESTIMATOR_STATUS": ("flags",),
    "EKF_STATUS_REPORT": ("flags",),
}
"""The kinds the tracker reads a state from (:data:`StateHeld`), with the fields it
reads. Only a change matters: a frame whose fields repeat the state held changes nothing
when read, so it may join a run (:meth:`HealthTracker.observe_run`) as a routine frame
does."""


@dataclass(frozen=True)
class ObservedRun:
    """Consecutive messages of one autopilot taken together (:meth:`HealthTracker.observe_run`)."""

    first_at: float
    last_at: float
    max_gap: float  # the longest time between two of them
    frames: int
    counts: tuple[tuple[str, int], ...]  # (message type, messages)
    boot_max: int  # the highest time_boot_ms (-1: none carried one)
    boot_max_at: float  # when the message that carried it arrived
    last_seq: int
    latest: tuple[tuple[str, Any, float], ...]  # (type, message, arrival): the last of a kind


@dataclass(frozen=True)
class _Claim:
    """A reboot or fatal state one message asserted, waiting for corroboration."""

    at: float
    seq: int | None
    prev_seq: int | None
    reason: str  # the reboot reason; "" for a fatal state
    status: int | None = None  # the claimed MAV_STATE (heartbeat claims)
    boot_ms: int | None = None  # the new time_boot_ms (back-step claims)


def _follows(seq: int | None, after: int | None) -> bool:
    return seq is not None and after is not None and 1 <= (seq - after) % 256 <= SEQ_WINDOW


@dataclass
class _Observed:
    """Everything the tracker remembers; mutated only under the tracker's lock."""

    first_at: float | None = None
    last_at: float | None = None
    window_start: float = 0.0
    window_count: int = 0
    stream_rate: float | None = None  # messages/s over the last completed window
    expected_rate: float | None = None  # messages/s of the streams requested and verified
    window_gap: float = 0.0  # the longest gap between two arrivals in this rate window
    gaps: list[float] = field(default_factory=list)  # ... in the last LEARN_WINDOWS windows
    silence_s: float | None = None  # the learnt silence threshold (None: the ceiling)
    heartbeat_at: float | None = None
    heartbeat_autopilot: int | None = None
    base_mode: int | None = None
    custom_mode: int | None = None
    system_status: int | None = None
    system_status_since: float | None = None
    was_up: bool = False
    landed_state: int | None = None
    sensors_enabled: int | None = None
    sensors_health: int | None = None
    sensors: SensorReport | None = None  # classified once per change, not per assessment
    unhealthy_names: tuple[str, ...] = ()
    critical_since: dict[int, float] = field(default_factory=dict)
    boot_ms_max: int | None = None
    boot_advanced_at: float | None = None
    reboot_at: float | None = None
    reboot_reason: str = ""
    tilt_deg: float | None = None
    tilt_over_since: float | None = None
    estimator_flags: int | None = None
    estimator_kind: str = ""
    estimator_bad_since: float | None = None
    estimator_ever_ok: bool = False  # attitude estimate seen working since (re)boot
    position_ever_ok: bool = False  # absolute horizontal position seen since (re)boot
    disarmed_in_air_at: float | None = None
    last_seq: int | None = None
    claim: _Claim | None = None
    refuted: int = 0
    counts: dict[str, int] = field(default_factory=dict)  # messages per type
    reboots: int = 0
    altitude_m: float | None = None  # GLOBAL_POSITION_INT relative_alt
    climb_mps: float | None = None  # up positive (GLOBAL_POSITION_INT vz is down positive)
    motion_at: float | None = None
    position_msg: Any = None  # the last GLOBAL_POSITION_INT, decoded only when sampled
    position_at: float | None = None
    # Bumped whenever something a judgement reads changed, other than the times of the
    # last message, heartbeat and time_boot_ms advance (which only ever move on):
    # HealthTracker.holds.
    version: int = 0


@dataclass(frozen=True)
class Fix:
    """The last position an autopilot reported (GLOBAL_POSITION_INT), decoded on demand."""

    lat_deg: float
    lon_deg: float
    altitude_m: float  # above home
    heading_deg: float | None  # None: the autopilot does not know (hdg 65535)
    at: float  # when it was received (monotonic)


@dataclass(frozen=True)
class Motion:
    """The last vertical state an autopilot reported (GLOBAL_POSITION_INT)."""

    altitude_m: float  # above home
    climb_mps: float  # up positive
    at: float  # when it was received (monotonic)


@dataclass(frozen=True)
class StreamFacts:
    """What the stream keeper judges requested rates and reconnects by."""

    counts: dict[str, int]
    heartbeat_at: float | None
    last_at: float | None
    reboots: int


class HealthTracker:
    """Accumulates one autopilot's messages; :meth:`assess` judges them at a given time.

    ``observe`` is called by exactly one reader thread; ``assess`` by the decision loop.
    A lock makes every assessment see one consistent set of observations.
    """

    def __init__(self, name: str, stack: Stack, thresholds: Thresholds) -> None:
        self.name = name
        self.stack = Stack(stack)
        self.thresholds = thresholds
        self._lock = threading.Lock()
        self._o = _Observed()

    def set_thresholds(self, thresholds: Thresholds) -> None:
        """Apply new thresholds (a spec change); observations are kept."""
        with self._lock:
            self.thresholds = thresholds
            self._o.silence_s = _learnt_silence_s(self._o, thresholds)
            self._o.version += 1

    # -- observing -------------------------------------------------------------------

    def observe(self, msg: Any, now: float) -> bool:
        """Record one message from this autopilot received at ``now``.

        Returns True when a fact the arbiter acts on changed (MAV_STATE, arming, landed
        state, sensor health, a reboot) or a silence ended, so the caller can wake the
        decision loop at once instead of waiting for its next tick (a standby's time
        free of failures starts when it is heard again, not a read interval later).

        Runs for every message the autopilot sends (hundreds a second): the bulk of the
        stream only updates its arrival time, counts, ``time_boot_ms`` and sequence
        number here, with one lookup for the few types read further (:data:`_READERS`).
        """
        boot_ms: int | None
        if isinstance(msg, Frame):  # the agent's own codec: read natively
            kind, boot_ms, seq = msg.get_type(), msg.boot_time(), msg.get_seq()
        else:  # any message with pymavlink's surface (replays, tests)
            kind = msg.get_type()
            carries_boot_time = _BOOT_TIME_KINDS.get(kind)
            if carries_boot_time is None:
                carries_boot_time = _learn_boot_time(kind, msg)
            boot_ms = msg.time_boot_ms if carries_boot_time else None
            seq = msg.get_seq()
        return self._locked_record(msg, kind, boot_ms, seq, now)

    def observe_routine(self, kind: str, boot_ms: int | None, seq: int, now: float) -> bool:
        """:meth:`observe` for a message of a kind whose content the tracker does not read
        (not in :data:`READ_KINDS`), given by what it is judged by: its type,
        ``time_boot_ms`` (None: it has none) and sequence number. The hub's fast path hands
        the bulk of the stream over so (:mod:`roost_agent.fastpath`), and it is judged by
        the same code as a message observed whole."""
        return self._locked_record(None, kind, boot_ms, seq, now)

    def run_state(self) -> RunState | None:
        """What a run of messages taken together (:meth:`observe_run`) must respect, or
        None while messages must be judged one by one: a claim waits for the message that
        settles it, or no ``time_boot_ms`` has been seen yet (every message is then
        compared before and after, as :meth:`_record` does)."""
        with self._lock:
            o = self._o
            if o.claim is not None or o.boot_advanced_at is None:
                return None
            th = self.thresholds
            tilt = o.tilt_deg
            tilt_class = (
                -1
                if tilt is None
                else 2
                if tilt > th.max_tilt_deg
                else 1
                if _tilt_warned(o, th)
                else 0
            )
            return (
                TILT_WARN_DEG,
                th.max_tilt_deg,
                tilt_class,
                _silence_s(o, th),
                o.window_start + RATE_WINDOW_S,
                -1 if o.boot_ms_max is None else o.boot_ms_max,
                REBOOT_BACKSTEP_MS,
                _state_held(o),
            )

    def observe_run(self, run: ObservedRun) -> bool:
        """:meth:`observe` for consecutive messages taken together (the hub's fast path,
        :mod:`roost_agent.fastpath`), made while :meth:`run_state` held, of kinds the
        tracker does not read or reads only the latest of (:data:`LATEST_ONLY_KINDS`):
        the same arrival, gap, count, rate window, ``time_boot_ms`` and sequence
        bookkeeping as message by message, then the latest of each kind read. The run
        ends where a message would have changed more (``_udpbatch.c``): before a
        silence, at the message that closes the rate window, before a tilt class change
        or a step back in ``time_boot_ms``. Returns what :meth:`observe` returns."""
        lock = self._lock
        lock.acquire()
        try:
            return self._record_run(run)
        finally:
            lock.release()

    def _record_run(self, run: ObservedRun) -> bool:
        o = self._o
        th = self.thresholds
        silence_ended = False
        if o.last_at is None:
            o.first_at = o.window_start = run.first_at
        else:
            gap = run.first_at - o.last_at
            _learn_gap(o, th, gap)
            silence_ended = gap >= _silence_s(o, th)
            if silence_ended:
                o.version += 1
        _learn_gap(o, th, run.max_gap)
        o.last_at = run.last_at
        counts = o.counts
        for kind, count in run.counts:
            counts[kind] = counts.get(kind, 0) + count
        o.window_count += run.frames
        if run.last_at - o.window_start >= RATE_WINDOW_S:
            self._close_rate_window(run.last_at)
        if run.boot_max >= 0 and o.claim is None:
            high = o.boot_ms_max
            if high is None or run.boot_max > high:
                o.boot_ms_max, o.boot_advanced_at = run.boot_max, run.boot_max_at
        o.last_seq = run.last_seq
        changed = False
        for kind, msg, at in run.latest:
            read = _READERS.get(kind)
            if read is not None:
                changed = read(self, msg, at) or changed
        return changed or silence_ended

    def _locked_record(
        self, msg: Any, kind: str, boot_ms: int | None, seq: int, now: float
    ) -> bool:
        """:meth:`_record` under the tracker's lock."""
        # acquire/release rather than ``with``: compiled, ``with`` looks __enter__ and
        # __exit__ up on the lock's type and calls each with an argument tuple.
        lock = self._lock
        lock.acquire()
        try:
            return self._record(msg, kind, boot_ms, seq, now)
        finally:
            lock.release()

    def _record(self, msg: Any, kind: str, boot_ms: int | None, seq: int, now: float) -> bool:
        """Judge one message by its type, time and number (``msg`` itself is read only
        for a kind in :data:`READ_KINDS`; None for others observed by
        :meth:`observe_routine`)."""
        o = self._o
        th = self.thresholds
        # Messages that can change a judgement other than by their arrival time are
        # compared before and after (a few a second); the stream's bulk is not.
        judged = o.claim is not None or o.boot_advanced_at is None or kind in _JUDGED_KINDS
        before = _judged(o, th) if judged else None
        last_at = o.last_at
        silence_ended = False
        if last_at is None:
            o.first_at = o.window_start = now
        else:
            # between kernel arrival stamps: the agent's own lateness is not in it. A gap
            # of the ceiling or more is an outage (the autopilot was silent, the link
            # lost), not the stream's rhythm: it is not learnt.
            gap = now - last_at
            _learn_gap(o, th, gap)
            silence_ended = gap >= _silence_s(o, th)
            if silence_ended:
                # A silence ends: what is judged only while messages come (frozen
                # telemetry) may apply from this message on, and the decision loop
                # should see the autopilot back now (its time free of failures starts).
                o.version += 1
        o.last_at = now
        counts = o.counts
        counts[kind] = counts.get(kind, 0) + 1
        o.window_count += 1
        if now - o.window_start >= RATE_WINDOW_S:
            self._close_rate_window(now)
        changed = o.claim is not None and self._settle(msg, kind, boot_ms, seq)
        if boot_ms is not None and (o.claim is None or o.claim.status is not None):
            high = o.boot_ms_max
            if high is None or boot_ms > high:
                o.boot_ms_max, o.boot_advanced_at = boot_ms, now
            elif boot_ms < high - REBOOT_BACKSTEP_MS and o.claim is None:
                reason = f"rebooted: time_boot_ms went back from {high} to {boot_ms}"
                o.claim = _Claim(now, seq, o.last_seq, reason, boot_ms=boot_ms)
        o.last_seq = seq
        read = _READERS.get(kind)
        if read is not None:
            changed = read(self, msg, now) or changed
        if judged and not silence_ended and _judged(o, th) != before:
            # (a silence that ended has moved the version already: once is enough, and
            # a run, which compares nothing, moves it by that alone)
            o.version += 1
        return changed or silence_ended

    def _close_rate_window(self, now: float) -> None:
        """End the message-rate window at ``now`` (once a second), and learn its worst gap."""
        o = self._o
        th = self.thresholds
        fast, silence_s = _fast_stream(o, th), _silence_s(o, th)
        o.stream_rate = o.window_count / (now - o.window_start)
        o.window_start, o.window_count = now, 0
        gaps = o.gaps
        gaps.append(o.window_gap)
        if len(gaps) > LEARN_WINDOWS:
            del gaps[0]
        o.window_gap = 0.0
        o.silence_s = _learnt_silence_s(o, th)
        if _fast_stream(o, th) != fast or _silence_s(o, th) != silence_s:
            o.version += 1

    def _settle(self, msg: Any, kind: str, boot_ms: int | None, seq: int | None) -> bool:
        """Let the message after a claim confirm or refute it (module docstring)."""
        o = self._o
        claim = o.claim
        assert claim is not None
        status = int(msg.system_status) if kind == "HEARTBEAT" else None
        if claim.boot_ms is not None and boot_ms is not None:
            assert o.boot_ms_max is not None
            new_timeline = boot_ms < o.boot_ms_max - REBOOT_BACKSTEP_MS
            contradicts, repeats = not new_timeline, new_timeline
        elif status is not None and int(msg.autopilot) != MAV_AUTOPILOT_INVALID:
            contradicts = status not in _FATAL_STATES and status != MavState.BOOT
            repeats = status == claim.status or (
                claim.status in _FATAL_STATES and status in _FATAL_STATES
            )
        else:
            contradicts = repeats = False
        if contradicts:
            verdict: bool | None = False
        elif _follows(seq, claim.seq):
            verdict = True
        elif _follows(seq, claim.prev_seq):
            verdict = False
        else:
            verdict = True if repeats else None
        if verdict is None:
            return False
        o.claim = None
        if not verdict:
            o.refuted += 1
            return False
        if claim.status is not None:
            o.system_status, o.system_status_since = claim.status, claim.at
        if claim.reason:
            self._note_reboot(claim.at, claim.reason)
        if claim.boot_ms is not None:
            o.boot_ms_max, o.boot_advanced_at = claim.boot_ms, claim.at
        return True

    def _note_reboot(self, now: float, reason: str) -> None:
        o = self._o
        _forget_gaps(o)  # streams restart at the firmware's defaults
        o.reboot_at = now
        o.reboot_reason = reason
        o.reboots += 1
        o.was_up = False
        o.estimator_ever_ok = o.position_ever_ok = False
        o.sensors_enabled = o.sensors_health = o.sensors = None  # re-judged from the next one
        o.unhealthy_names = ()
        o.critical_since.clear()
        o.disarmed_in_air_at = None

    def _observe_heartbeat(self, msg: Any, now: float) -> bool:
        o = self._o
        if int(msg.autopilot) == MAV_AUTOPILOT_INVALID:
            return False  # a non-autopilot component sharing the id: not this autopilot
        previous = (o.base_mode, o.custom_mode, o.system_status)
        was_armed = o.base_mode is not None and bool(o.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        o.heartbeat_at = now
        o.heartbeat_autopilot = int(msg.autopilot)
        o.base_mode = int(msg.base_mode)
        o.custom_mode = int(msg.custom_mode)
        status = int(msg.system_status)
        # Only BOOT: PX4 v1.16 also reports UNINIT after a battery-failsafe landing and
        # disarm, without rebooting (its reboots show as time_boot_ms going back).
        rebooting = status == MavState.BOOT and o.was_up
        if o.claim is None and (rebooting or _newly_fatal(status, o.system_status)):
            reason = "rebooted: MAV_STATE BOOT after it was up" if rebooting else ""
            o.claim = _Claim(now, msg.get_seq(), o.last_seq, reason, status=status)
            if rebooting:  # a reboot disarms: not "disarmed in the air" (judged once settled)
                return (o.base_mode, o.custom_mode, o.system_status) != previous
        elif o.claim is None:
            if status != o.system_status:
                o.system_status_since = now
            o.system_status = status
            if status in _UP_STATES:
                o.was_up = True
        armed = bool(o.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        if was_armed and not armed and o.landed_state is not None and is_airborne(o.landed_state):
            o.disarmed_in_air_at = now
        elif armed:
            o.disarmed_in_air_at = None
        return (o.base_mode, o.custom_mode, o.system_status) != previous

    def _observe_sys_status(self, msg: Any, now: float) -> bool:
        o = self._o
        enabled = int(msg.onboard_control_sensors_enabled)
        health = int(msg.onboard_control_sensors_health)
        changed = (enabled, health) != (o.sensors_enabled, o.sensors_health)
        o.sensors_enabled, o.sensors_health = enabled, health
        if changed:
            o.sensors = classify_sensors(enabled, health)
            o.unhealthy_names = tuple(sensor_name(b) for b in o.sensors.unhealthy)
            o.critical_since = {
                int(b): o.critical_since.get(int(b), now) for b in o.sensors.critical
            }
        return changed

    def _observe_landed_state(self, landed: int, now: float) -> bool:
        o = self._o
        changed = landed != o.landed_state
        o.landed_state = landed
        if landed == MavLandedState.ON_GROUND:
            o.disarmed_in_air_at = None
        return changed

    def _observe_attitude(self, roll: float, pitch: float, now: float) -> None:
        o = self._o
        warned = _tilt_warned(o, self.thresholds)
        o.tilt_deg = tilt_degrees(roll, pitch)
        if o.tilt_deg > self.thresholds.max_tilt_deg:
            if o.tilt_over_since is None:
                o.tilt_over_since = now
                o.version += 1
        elif o.tilt_over_since is not None:
            o.tilt_over_since = None
            o.version += 1
        if _tilt_warned(o, self.thresholds) != warned:
            o.version += 1

    def _observe_estimator(self, kind: str, flags: int, now: float) -> None:
        o = self._o
        o.estimator_flags, o.estimator_kind = flags, kind
        if _estimator_attitude_bad(kind, flags):
            if o.estimator_bad_since is None:
                o.estimator_bad_since = now
        else:
            o.estimator_bad_since = None
            o.estimator_ever_ok = True
        if flags & ESTIMATOR_POS_HORIZ_ABS:
            o.position_ever_ok = True

    # -- judging ---------------------------------------------------------------------

    def assess(self, now: float) -> Assessment:
        """Judge the observations as of ``now`` (pure with respect to the tracker)."""
        with self._lock:
            o = self._o
            findings = _findings(o, self.stack, self.thresholds, now)
            level = max((f.level for f in findings), key=lambda lv: lv.rank, default=HealthLevel.OK)
            return Assessment(
                name=self.name,
                stack=self.stack,
                at=now,
                level=level,
                findings=tuple(sorted(findings, key=lambda f: -f.level.rank)),
                message_age_s=None if o.last_at is None else now - o.last_at,
                heartbeat_age_s=None if o.heartbeat_at is None else now - o.heartbeat_at,
                custom_mode=o.custom_mode,
                armed=None
                if o.base_mode is None
                else bool(o.base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
                landed_state=o.landed_state,
                system_status=o.system_status,
                unhealthy_sensors=o.unhealthy_names,
                version=o.version if not any(f.varies for f in findings) else -1,
            )

    def holds(self, judged: Assessment, now: float) -> bool:
        """Whether :meth:`assess` at ``now`` would find exactly what ``judged`` found (its
        findings, level and flight facts; not its ages), without judging again.

        True when nothing a judgement reads changed since (the version) and ``now`` is
        before the first threshold any finding could cross with nothing new arriving:
        the silence, heartbeat and frozen-telemetry thresholds from the times of the last
        message, heartbeat and ``time_boot_ms`` advance, which only ever move later, and
        the persistence times of sensor, estimator, tilt and reboot findings
        (:func:`_next_threshold`). An assessment with a finding whose text reads the
        clock never holds. This is what lets the decision loop skip a tick in which
        nothing can have changed; silence is still judged at the tick its threshold passes.
        """
        return now < self.holds_until(judged)

    def holds_until(self, judged: Assessment, *, late_warning: bool = True) -> float:
        """The time until which :meth:`holds` is true for ``judged`` with nothing new
        observed (minus infinity when something it read changed already): when the
        decision loop next has to judge this autopilot although no message came.
        ``late_warning=False``: leaving out the late stream's warning (see
        :meth:`next_threshold`)."""
        with self._lock:
            o = self._o
            if judged.version != o.version:
                return -math.inf
            return _next_threshold(o, self.thresholds, judged.at, late_warning=late_warning)

    def next_threshold(self, judged: Assessment, *, late_warning: bool = True) -> float:
        """The first time after ``judged`` a finding could appear, go or change level with
        nothing new observed — also for a judgement that never holds because a finding's
        text reads the clock: when to judge again at the latest.

        ``late_warning=False`` leaves out the threshold at which a fast stream turns late
        (a warning: the next message is overdue, the stream not yet silent), for a
        standby whose judgement is wanted only where the arbiter acts on it: a warning is
        not a failure (its time free of failures runs on through it), and whether a
        standby is OK when it is to become the target is judged afresh at that tick, from
        every message read by then. Its silence still counts: a failure restarts that
        time, and the arbiter must see it begin."""
        with self._lock:
            return _next_threshold(self._o, self.thresholds, judged.at, late_warning=late_warning)

    def postponed_by_messages(self, judged: Assessment) -> Postponable:
        """:meth:`next_threshold` split for a reader that watches arrivals itself (the
        hub's fast path, :mod:`roost_agent.fastpath`), infinity where there is none:
        :data:`Postponable`. Each message postpones the first threshold on the last
        message's age to its own arrival plus that age; each message whose
        ``time_boot_ms`` advances postpones frozen telemetry's likewise."""
        with self._lock:
            o = self._o
            ages, frozen, fixed = _threshold_times(o, self.thresholds, late_warning=True)
            first_age = _first_after(ages, judged.at)
            last_at = o.last_at
            age = math.inf if last_at is None else first_age - last_at
            first_frozen = _first_after(frozen, judged.at)
            advanced_at = o.boot_advanced_at
            frozen_age = math.inf if advanced_at is None else first_frozen - advanced_at
            return _first_after(fixed, judged.at), age, first_frozen, frozen_age

    @property
    def claim_pending(self) -> bool:
        """A claim (reboot, fatal state) waits for the message that settles it."""
        with self._lock:
            return self._o.claim is not None

    @property
    def refuted(self) -> int:
        """Claims (reboot, fatal state) the following messages contradicted."""
        with self._lock:
            return self._o.refuted

    def expect_streams(self, rate_hz: float | None) -> None:
        """Judge liveness on these verified requested streams (None: on what arrives,
        as other rates are being requested: the learnt silence threshold is relearnt)."""
        with self._lock:
            self._o.expected_rate = rate_hz
            if rate_hz is None:
                _forget_gaps(self._o)
            self._o.version += 1

    def silence_threshold_s(self) -> float:
        """The silence (any-message age ERROR) threshold now, learnt or the ceiling."""
        with self._lock:
            return _silence_s(self._o, self.thresholds)

    def heartbeat(self) -> tuple[int, int, float] | None:
        """(custom_mode, base_mode, received_at) of the last heartbeat, for confirmations."""
        with self._lock:
            o = self._o
            if o.heartbeat_at is None or o.custom_mode is None or o.base_mode is None:
                return None
            return o.custom_mode, o.base_mode, o.heartbeat_at

    def landed_state(self) -> int | None:
        """Last EXTENDED_SYS_STATE landed_state."""
        with self._lock:
            return self._o.landed_state

    def system_status(self) -> int | None:
        """Last heartbeat MAV_STATE."""
        with self._lock:
            return self._o.system_status

    def motion(self) -> Motion | None:
        """Last altitude and vertical speed, None before the first GLOBAL_POSITION_INT."""
        with self._lock:
            o = self._o
            if o.altitude_m is None or o.climb_mps is None or o.motion_at is None:
                return None
            return Motion(o.altitude_m, o.climb_mps, o.motion_at)

    def fix(self) -> Fix | None:
        """Last horizontal position and heading, None before the first GLOBAL_POSITION_INT.

        The message is kept as received and decoded here, at the reader's (the telemetry
        stream's) rate, so the link's reader does no work for it.
        """
        with self._lock:
            msg, at = self._o.position_msg, self._o.position_at
        if msg is None or at is None:
            return None
        hdg = int(msg.hdg)
        return Fix(
            lat_deg=int(msg.lat) / 1e7,
            lon_deg=int(msg.lon) / 1e7,
            altitude_m=int(msg.relative_alt) / 1000.0,
            heading_deg=None if hdg == UNKNOWN_HEADING else hdg / 100.0,
            at=at,
        )

    def reboots(self) -> int:
        """How many reboots of the autopilot were seen (re-read what a reboot may change)."""
        with self._lock:
            return self._o.reboots

    def stream_facts(self) -> StreamFacts:
        """Per-type counts, last heartbeat, last message and reboots (for the keeper)."""
        with self._lock:
            o = self._o
            return StreamFacts(dict(o.counts), o.heartbeat_at, o.last_at, o.reboots)


def _values(msg: Any, wanted: Fields) -> tuple[Any, ...]:
    """The fields ``wanted`` of ``msg``: read at their offsets from the agent's own frames,
    by name from any other message (replays, tests)."""
    if isinstance(msg, Frame):
        return msg.read_fields(wanted)
    return tuple(getattr(msg, name) for name in wanted.names)


# The fields read from the stream's fast messages (100 and 50 Hz), in wire order.
_TILT: Final = fields("ATTITUDE", "roll", "pitch")
_VERTICAL: Final = fields("GLOBAL_POSITION_INT", "relative_alt", "vz")


def _read_landed_state(tracker: HealthTracker, msg: Any, now: float) -> bool:
    return tracker._observe_landed_state(int(msg.landed_state), now)


def _read_attitude(tracker: HealthTracker, msg: Any, now: float) -> bool:
    roll, pitch = _values(msg, _TILT)
    tracker._observe_attitude(float(roll), float(pitch), now)
    return False


def _read_estimator(tracker: HealthTracker, msg: Any, now: float) -> bool:
    tracker._observe_estimator(msg.get_type(), int(msg.flags), now)
    return False


def _read_position(tracker: HealthTracker, msg: Any, now: float) -> bool:
    o = tracker._o
    relative_alt, vz = _values(msg, _VERTICAL)
    o.altitude_m = int(relative_alt) / 1000.0
    o.climb_mps = -int(vz) / 100.0
    o.motion_at = now
    o.position_msg, o.position_at = msg, now
    return False


# The message types whose fields the tracker reads, each with what reads them (under the
# tracker's lock; True: a fact the arbiter acts on changed). Every other type only counts.
_READERS: Final[dict[str, Callable[[HealthTracker, Any, float], bool]]] = {
    "HEARTBEAT": HealthTracker._observe_heartbeat,
    "SYS_STATUS": HealthTracker._observe_sys_status,
    "EXTENDED_SYS_STATE": _read_landed_state,
    "ATTITUDE": _read_attitude,
    "ESTIMATOR_STATUS": _read_estimator,
    "EKF_STATUS_REPORT": _read_estimator,
    "GLOBAL_POSITION_INT": _read_position,
}

LATEST_ONLY_KINDS: Final = frozenset({"ATTITUDE", "GLOBAL_POSITION_INT"})
"""Of :data:`READ_KINDS`, those whose reading leaves nothing but the latest value, for
ATTITUDE as long as the tilt stays in its class (level, past the warning angle, past the
envelope): a run (:meth:`HealthTracker.observe_run`) reads only its last one of each."""
READ_KINDS: Final = frozenset(_READERS)
"""The message types whose content the tracker reads (HEARTBEAT's also to settle a
claim); of every other type only the type, arrival time, sequence number and
``time_boot_ms`` (:meth:`HealthTracker.observe_routine`)."""

# Whether a message type carries ``time_boot_ms``, learnt from its first message (asking
# each message would cost a failed attribute lookup for every type without one).
_BOOT_TIME_KINDS: Final[dict[str, bool]] = {}


def _learn_boot_time(kind: str, msg: Any) -> bool:
    carries = isinstance(getattr(msg, "time_boot_ms", None), int)
    _BOOT_TIME_KINDS[kind] = carries
    return carries


# Messages whose content a judgement reads beyond their arrival time (tilt from ATTITUDE,
# at 100 Hz, is tracked by its own changes in HealthTracker._observe_attitude).
_JUDGED_KINDS: Final = frozenset(
    {"HEARTBEAT", "SYS_STATUS", "EXTENDED_SYS_STATE", "ESTIMATOR_STATUS", "EKF_STATUS_REPORT"}
)
# Thresholds are compared with ``>=`` on differences of floats; a recheck this much
# early costs one judgement, a recheck late would miss one.
_RECHECK_EARLY_S: Final = 1e-6


def _judged(o: _Observed, th: Thresholds) -> tuple[object, ...]:
    """Everything :func:`_findings` and the assessment read, except the times that only
    move on (last message, heartbeat, time_boot_ms advance) and tilt (its own changes)."""
    return (
        o.first_at is None,
        o.heartbeat_at is None,
        o.boot_advanced_at is None,
        _fast_stream(o, th),
        o.heartbeat_autopilot,
        o.base_mode,
        o.custom_mode,
        o.system_status,
        o.system_status_since,
        o.landed_state,
        o.sensors,
        tuple(o.critical_since.items()),
        o.unhealthy_names,
        o.reboot_at,
        o.reboot_reason,
        o.estimator_flags,
        o.estimator_kind,
        o.estimator_bad_since,
        o.estimator_ever_ok,
        o.position_ever_ok,
        o.disarmed_in_air_at,
    )


def _tilt_warned(o: _Observed, th: Thresholds) -> bool:
    return o.tilt_deg is not None and o.tilt_deg > min(TILT_WARN_DEG, th.max_tilt_deg)


def _next_threshold(o: _Observed, th: Thresholds, after: float, *, late_warning: bool) -> float:
    """The first time after ``after`` (when the last judgement was made) a finding could
    appear, go or change level with nothing new observed (see
    :meth:`HealthTracker.holds`): every threshold of :func:`_findings` (but the late
    stream's warning without ``late_warning``: :meth:`HealthTracker.next_threshold`).
    Thresholds passed by then were part of that judgement; one within float rounding of
    it still counts."""
    ages, frozen, fixed = _threshold_times(o, th, late_warning=late_warning)
    return _first_after([*ages, *frozen, *fixed], after)


def _first_after(times: list[float], after: float) -> float:
    upcoming = [t for t in times if t > after - _RECHECK_EARLY_S]
    return min(upcoming) - _RECHECK_EARLY_S if upcoming else math.inf


def _threshold_times(
    o: _Observed, th: Thresholds, *, late_warning: bool
) -> tuple[list[float], list[float], list[float]]:
    """The thresholds of :func:`_next_threshold`: those a new message postpones (the
    last message's age: late, unless ``late_warning`` is False, and silent), frozen
    telemetry's (a message whose ``time_boot_ms`` advances postpones it) and the others."""
    if o.last_at is None or o.first_at is None:
        return [], [], []  # "no data" lasts until a message comes (a new version)
    fast = _fast_stream(o, th)
    silence_s = _silence_s(o, th)
    if fast:
        silent = o.last_at + silence_s
        ages = [o.last_at + _late_s(silence_s, th), silent] if late_warning else [silent]
    else:
        ages = [o.last_at + th.heartbeat_error_ms / 1000]
    times: list[float] = []
    frozen: list[float] = []
    if o.heartbeat_at is not None:
        times.append(o.heartbeat_at + th.heartbeat_warn_ms / 1000)
    else:
        times.append(o.first_at + th.heartbeat_error_ms / 1000)
    if o.boot_advanced_at is not None:
        limit_ms = th.message_error_ms if fast else th.heartbeat_error_ms
        frozen.append(o.boot_advanced_at + limit_ms / 1000)
    if o.reboot_at is not None:
        times.append(o.reboot_at + REBOOT_REMEMBERED_S)
    persist_s = th.sensor_persist_ms / 1000
    times.extend(since + persist_s for since in o.critical_since.values())
    if o.estimator_bad_since is not None:
        times.append(o.estimator_bad_since + persist_s)
    if o.tilt_over_since is not None:
        times.append(o.tilt_over_since + TILT_PERSIST_S)
    return ages, frozen, times


def _state_held(o: _Observed) -> StateHeld:
    """:data:`StateHeld` (-1: nothing held yet, or something read from such a frame was
    forgotten since, as a reboot forgets that the estimator ever worked; the estimator's
    flags only for the kind they came from)."""
    landed = o.landed_state
    if landed is None or (landed == MavLandedState.ON_GROUND and o.disarmed_in_air_at is not None):
        landed = -1
    flags = o.estimator_flags
    if flags is not None:
        bad = _estimator_attitude_bad(o.estimator_kind, flags)
        if (
            (o.estimator_bad_since is None) == bad
            or (not bad and not o.estimator_ever_ok)
            or (flags & ESTIMATOR_POS_HORIZ_ABS and not o.position_ever_ok)
        ):
            flags = None
    held_flags = -1 if flags is None else flags
    return {
        "SYS_STATUS": (
            -1 if o.sensors_enabled is None else o.sensors_enabled,
            -1 if o.sensors_health is None else o.sensors_health,
        ),
        "EXTENDED_SYS_STATE": (landed,),
        "ESTIMATOR_STATUS": (held_flags if o.estimator_kind == "ESTIMATOR_STATUS" else -1,),
        "EKF_STATUS_REPORT": (held_flags if o.estimator_kind == "EKF_STATUS_REPORT" else -1,),
    }


def _newly_fatal(status: int, previous: int | None) -> bool:
    return status in _FATAL_STATES and previous not in _FATAL_STATES


def _estimator_attitude_bad(kind: str, flags: int) -> bool:
    if not flags & ESTIMATOR_ATTITUDE:
        return True
    if kind == "ESTIMATOR_STATUS":
        return bool(flags & ESTIMATOR_ACCEL_ERROR)
    return bool(flags & EKF_UNINITIALIZED)


def _findings(o: _Observed, stack: Stack, th: Thresholds, now: float) -> list[Finding]:
    """Every finding for the observations ``o`` at time ``now`` (see module docstring)."""
    if o.last_at is None:
        return [Finding(HealthLevel.STALE, "no-data", "no MAVLink message received yet", True)]
    found: list[Finding] = []
    found += _liveness(o, th, now)
    found += _reboot(o, now)
    found += _sensors(o, th, now)
    found += _estimator(o, th, now)
    found += _flight(o, th, now)
    found += _mav_state(o, found)
    found += _starting(o)
    if o.heartbeat_autopilot is not None:
        reported = stack_from_heartbeat(o.heartbeat_autopilot)
        if reported is not None and reported != stack:
            found.append(
                Finding(
                    HealthLevel.WARN,
                    "stack-mismatch",
                    f"heartbeat says {reported.value} but {stack.value} is configured: "
                    "mode commands would use the wrong encoding",
                )
            )
    return found


def _liveness(o: _Observed, th: Thresholds, now: float) -> list[Finding]:
    assert o.last_at is not None and o.first_at is not None
    found: list[Finding] = []
    silent_s = now - o.last_at
    if silent_s * 1000 >= th.heartbeat_error_ms:
        found.append(
            Finding(
                HealthLevel.STALE,
                "link-lost",
                f"link lost: no message for {silent_s:.1f} s",
                True,
                o.last_at,
                varies=True,
            )
        )
    elif _fast_stream(o, th):
        limit_s = _silence_s(o, th)
        if silent_s >= limit_s:
            found.append(
                Finding(
                    HealthLevel.ERROR,
                    "silent",
                    f"silent for {silent_s * 1000:.0f} ms (limit {limit_s * 1000:.0f} ms)",
                    True,
                    o.last_at,
                    varies=True,
                )
            )
        elif silent_s >= _late_s(limit_s, th):
            found.append(
                Finding(
                    HealthLevel.WARN,
                    "late",
                    f"no message for {silent_s * 1000:.0f} ms",
                    varies=True,
                )
            )
    since_beat = o.heartbeat_at if o.heartbeat_at is not None else o.first_at
    beat_age_ms = (now - since_beat) * 1000
    label = "no heartbeat" if o.heartbeat_at is None else "heartbeat"
    if beat_age_ms >= th.heartbeat_error_ms:
        found.append(
            Finding(
                HealthLevel.ERROR,
                "heartbeat-lost",
                f"{label} lost for {beat_age_ms:.0f} ms",
                True,
                since_beat,
                varies=True,
            )
        )
    elif o.heartbeat_at is not None and beat_age_ms >= th.heartbeat_warn_ms:
        found.append(
            Finding(
                HealthLevel.WARN,
                "heartbeat-late",
                f"heartbeat late: {beat_age_ms:.0f} ms",
                varies=True,
            )
        )
    if o.boot_advanced_at is not None and silent_s * 1000 < th.message_error_ms:
        stuck_ms = (now - o.boot_advanced_at) * 1000
        limit_ms = th.message_error_ms if _fast_stream(o, th) else th.heartbeat_error_ms
        if stuck_ms >= limit_ms:
            found.append(
                Finding(
                    HealthLevel.ERROR,
                    "frozen",
                    f"telemetry frozen: time_boot_ms stuck at {o.boot_ms_max} "
                    f"for {stuck_ms:.0f} ms",
                    True,
                    o.boot_advanced_at,
                    varies=True,
                )
            )
    return found


def _learn_gap(o: _Observed, th: Thresholds, gap: float) -> None:
    """A gap between messages joins the rate window's worst, unless it is an outage (the
    ceiling or more: the autopilot was silent, the link lost), not the stream's rhythm."""
    if gap > o.window_gap and gap * 1000 < th.message_error_ms:
        o.window_gap = gap


def _learnt_silence_s(o: _Observed, th: Thresholds) -> float | None:
    """The silence threshold the gaps learnt so far give (None: too few to trust yet)."""
    if len(o.gaps) < LEARN_MIN_WINDOWS:
        return None
    learnt = max(th.message_error_min_ms / 1000, th.silence_margin * max(o.gaps))
    return min(learnt, th.message_error_ms / 1000)


def _silence_s(o: _Observed, th: Thresholds) -> float:
    """Seconds without any message that make a fast stream silent (an ERROR)."""
    learnt = o.silence_s
    return th.message_error_ms / 1000 if learnt is None else learnt


def _late_s(silence_s: float, th: Thresholds) -> float:
    """Seconds without any message that make a fast stream late (a WARN)."""
    return silence_s * th.message_warn_ms / th.message_error_ms


def _forget_gaps(o: _Observed) -> None:
    """Relearn the silence threshold from the next windows (the ceiling until then)."""
    o.gaps.clear()
    o.window_gap = 0.0
    o.silence_s = None


def _fast_stream(o: _Observed, th: Thresholds) -> bool:
    rate = o.expected_rate if o.expected_rate is not None else o.stream_rate
    return rate is not None and rate * th.message_warn_ms / 1000 >= FAST_STREAM_FACTOR


def _reboot(o: _Observed, now: float) -> list[Finding]:
    if o.reboot_at is not None and now - o.reboot_at < REBOOT_REMEMBERED_S:
        return [Finding(HealthLevel.ERROR, "reboot", o.reboot_reason, True, o.reboot_at)]
    return []


def _sensors(o: _Observed, th: Thresholds, now: float) -> list[Finding]:
    report = o.sensors
    if report is None:
        return []
    found: list[Finding] = []
    for bit in report.critical:
        since = o.critical_since.get(int(bit), now)
        lasted_ms = (now - since) * 1000
        if lasted_ms >= th.sensor_persist_ms:
            found.append(
                Finding(
                    HealthLevel.ERROR,
                    f"sensor:{sensor_name(bit)}",
                    f"{sensor_name(bit)} unhealthy for {lasted_ms:.0f} ms",
                    True,
                    since,
                    varies=True,
                )
            )
        else:
            found.append(
                Finding(
                    HealthLevel.WARN, f"sensor:{sensor_name(bit)}", f"{sensor_name(bit)} unhealthy"
                )
            )
    for bit in report.warn:
        found.append(
            Finding(HealthLevel.WARN, f"sensor:{sensor_name(bit)}", f"{sensor_name(bit)} unhealthy")
        )
    return found


def _may_be_starting(o: _Observed) -> bool:
    """Disarmed and not known to be flying: start-up findings are STARTING, not errors."""
    armed = o.base_mode is not None and bool(o.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
    airborne = o.landed_state is not None and is_airborne(o.landed_state)
    return not armed and not airborne


def _starting(o: _Observed) -> list[Finding]:
    """Start-up that has not finished: no heartbeat yet, booting (not in the air)."""
    if o.heartbeat_at is None:
        return [Finding(HealthLevel.STARTING, "starting", "no heartbeat yet")]
    if o.system_status in (MavState.UNINIT, MavState.BOOT) and _may_be_starting(o):
        name = mav_state_name(o.system_status)
        return [Finding(HealthLevel.STARTING, "starting", f"booting (MAV_STATE {name})")]
    return []


def _estimator(o: _Observed, th: Thresholds, now: float) -> list[Finding]:
    if o.estimator_flags is None:
        return []
    found: list[Finding] = []
    if not o.estimator_ever_ok and o.estimator_bad_since is not None and _may_be_starting(o):
        found.append(
            Finding(
                HealthLevel.STARTING,
                "estimator-starting",
                f"estimator starting ({o.estimator_kind} flags {o.estimator_flags:#x})",
            )
        )
    elif o.estimator_bad_since is not None:
        lasted_ms = (now - o.estimator_bad_since) * 1000
        bad = Finding(
            HealthLevel.ERROR if lasted_ms >= th.sensor_persist_ms else HealthLevel.WARN,
            "estimator",
            f"estimator attitude lost or accelerometer error ({o.estimator_kind} "
            f"flags {o.estimator_flags:#x})",
            lasted_ms >= th.sensor_persist_ms,
            o.estimator_bad_since,
        )
        found.append(bad)
    if not o.estimator_flags & ESTIMATOR_POS_HORIZ_ABS:
        if not o.position_ever_ok and _may_be_starting(o):
            found.append(
                Finding(
                    HealthLevel.STARTING,
                    "position-starting",
                    "waiting for an absolute position estimate (GPS)",
                )
            )
        else:
            found.append(
                Finding(HealthLevel.WARN, "position", "no absolute horizontal position estimate")
            )
    return found


def _flight(o: _Observed, th: Thresholds, now: float) -> list[Finding]:
    found: list[Finding] = []
    if o.disarmed_in_air_at is not None:
        found.append(
            Finding(
                HealthLevel.ERROR,
                "disarmed-in-air",
                "disarmed while in the air",
                True,
                o.disarmed_in_air_at,
            )
        )
    if o.tilt_deg is not None:
        if o.tilt_over_since is not None and now - o.tilt_over_since >= TILT_PERSIST_S:
            found.append(
                Finding(
                    HealthLevel.ERROR,
                    "tilt",
                    f"attitude {o.tilt_deg:.0f} deg beyond the {th.max_tilt_deg:.0f} deg envelope",
                    True,
                    o.tilt_over_since,
                    varies=True,
                )
            )
        elif o.tilt_deg > min(TILT_WARN_DEG, th.max_tilt_deg):
            found.append(
                Finding(HealthLevel.WARN, "tilt", f"attitude {o.tilt_deg:.0f} deg", varies=True)
            )
    return found


def _mav_state(o: _Observed, others: list[Finding]) -> list[Finding]:
    if o.system_status is None:
        return []
    status = o.system_status
    name = mav_state_name(status)
    onset = o.system_status_since
    if status in _FATAL_STATES:
        return [Finding(HealthLevel.ERROR, "mav-state", f"MAV_STATE {name}", True, onset)]
    airborne = o.landed_state is not None and is_airborne(o.landed_state)
    if status in _NOT_FLYING_STATES and airborne:
        return [
            Finding(
                HealthLevel.ERROR, "mav-state", f"MAV_STATE {name} while in the air", True, onset
            )
        ]
    if status == MavState.CRITICAL:
        corroboration = [f.reason for f in others if f.level.rank >= HealthLevel.WARN.rank]
        if corroboration:
            why = "MAV_STATE CRITICAL, corroborated by " + ", ".join(corroboration)
            return [Finding(HealthLevel.ERROR, "mav-state", why, True, onset)]
        return [Finding(HealthLevel.WARN, "mav-state", "MAV_STATE CRITICAL (failsafe active)")]
    return []
