"""A PX4-like autopilot's messages fed straight into a health tracker at chosen times.

For tests of the health model and the decision loop that need real MAVLink messages
(encoded and decoded by pymavlink, so each carries the stream's next sequence number)
but no sockets and no clock; :func:`two_px4_spec` is the vehicle such an agent (never
started: its links never open) flies.
"""

from __future__ import annotations

import os
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mav

from roost_agent.health import (
    LATEST_ONLY_KINDS,
    READ_KINDS,
    STATE_FIELDS,
    TILT_WARN_DEG,
    Assessment,
    HealthTracker,
    ObservedRun,
    tilt_degrees,
)
from roost_api.autopilot import (
    AutopilotSpec,
    FailoverPolicy,
    RedundantAutopilotSpec,
    Thresholds,
)
from roost_api.meta import Stack
from roost_mavlink import MavLandedState, MavState, SensorBit, custom_mode
from roost_mavlink.codec import scan
from roost_mavlink.status import MAV_AUTOPILOT_PX4, stack_sensors

ARMED = 128 | 1
SENSORS = int(stack_sensors(Stack.PX4)) & ~int(SensorBit.RC_RECEIVER | SensorBit.PREARM_CHECK)
LOITER = custom_mode(Stack.PX4, "AUTO.LOITER")


class Feed:
    """Feeds one tracker the messages of a PX4-like autopilot at chosen times.

    Every message goes through a real encode and decode, so it carries the next MAVLink
    sequence number of the autopilot's stream (the corroboration rules read it). Decoded
    by pymavlink, or with ``codec`` by the agent's own codec, as the link reader decodes.
    """

    def __init__(
        self,
        tracker: HealthTracker,
        *,
        codec: bool = False,
        summarise: bool = False,
        runs: bool = False,
    ) -> None:
        self.tracker = tracker
        self.codec = codec or summarise or runs
        self.summarise = summarise
        # Frames handed over as the hub's fast path does with runs (_udpbatch.c): a
        # model of its rules, between flush() calls as between two of its calls.
        self.runs = RunModel(tracker) if runs else None
        self.boot_ms = 100_000
        self.t = 0.0
        self.sensors_health = SENSORS
        self.sensors_enabled = SENSORS
        self.encoder = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.decoder = mav.MAVLink(None)

    def observe(self, msg: Any, *, seq: int | None = None) -> bool:
        """Deliver ``msg`` as the stream's next frame (or with a forged ``seq``)."""
        if seq is not None:
            saved, self.encoder.seq = self.encoder.seq, seq
        frame = msg.pack(self.encoder)
        if seq is None:
            self.encoder.seq = (self.encoder.seq + 1) % 256
        else:
            self.encoder.seq = saved
        if self.codec:
            (msg,), _ = scan(bytes(frame))
            kind = msg.get_type()
            if self.runs is not None:
                return self.runs.take(msg, self.t)
            if self.summarise and kind not in READ_KINDS:
                # as the hub's fast path hands such a frame over: by its summary
                return self.tracker.observe_routine(kind, msg.boot_time(), msg.get_seq(), self.t)
            return self.tracker.observe(msg, self.t)
        return self.tracker.observe(self.decoder.decode(bytearray(frame)), self.t)

    def heartbeat(
        self,
        *,
        state: int = MavState.ACTIVE,
        base_mode: int = ARMED,
        mode: int = LOITER,
        autopilot: int = MAV_AUTOPILOT_PX4,
    ) -> bool:
        msg = mav.MAVLink_heartbeat_message(2, autopilot, base_mode, mode, state, 3)
        return self.observe(msg)

    def landed(self, state: int = MavLandedState.IN_AIR) -> bool:
        return self.observe(mav.MAVLink_extended_sys_state_message(0, state))

    def sys_status(self, health: int | None = None, enabled: int | None = None) -> bool:
        if health is not None:
            self.sensors_health = health
        if enabled is not None:
            self.sensors_enabled = enabled
        enabled, health = self.sensors_enabled, self.sensors_health
        msg = mav.MAVLink_sys_status_message(
            enabled, enabled, health, 100, 12000, -1, -1, 0, 0, 0, 0, 0, 0
        )
        return self.observe(msg)

    def attitude(self, roll: float = 0.0, pitch: float = 0.0, *, advance: bool = True) -> None:
        if advance:
            self.boot_ms = 100_000 + round(self.t * 1000)
        msg = mav.MAVLink_attitude_message(self.boot_ms, roll, pitch, 0.0, 0.0, 0.0, 0.0)
        self.observe(msg)

    def attitude_changes(self) -> bool:
        """One ATTITUDE on the current timeline; whether the tracker reported a change."""
        self.boot_ms = 100_000 + round(self.t * 1000)
        return self.observe(mav.MAVLink_attitude_message(self.boot_ms, 0, 0, 0, 0, 0, 0))

    def fly(
        self, seconds: float, *, rate_hz: float = 50.0, roll: float = 0.0, pitch: float = 0.0
    ) -> None:
        """Stream ATTITUDE at ``rate_hz`` plus 1 Hz heartbeats and 5 Hz status for ``seconds``."""
        end = self.t + seconds
        n = 0
        while self.t < end:
            if n % round(rate_hz) == 0:
                self.heartbeat()
                self.landed()
            if n % max(1, round(rate_hz / 5)) == 0:
                self.sys_status()
            self.attitude(roll, pitch)
            self.t += 1 / rate_hz
            n += 1

    def at(self, dt: float) -> Assessment:
        self.flush()
        return self.tracker.assess(self.t + dt)

    def flush(self) -> bool:
        """Hand over the run being gathered, as the fast path does when it returns;
        what the tracker said of it."""
        return self.runs.flush() if self.runs is not None else False


def two_px4_spec(first_port: int, thresholds: Thresholds | None = None) -> RedundantAutopilotSpec:
    """Vehicle ``v1``: PX4 autopilots fc1 (primary, sysid 1, channel 0) and fc2 on UDP
    ports ``first_port + 1`` and ``+ 2`` of 127.0.0.1 (nobody sends there)."""
    return RedundantAutopilotSpec(
        vehicle_name="v1",
        autopilots=[
            AutopilotSpec(
                name=f"fc{i}",
                stack="px4",
                connection=f"udp://127.0.0.1:{first_port + i}",
                sysid=i,
                bridge_channel=i - 1,
            )
            for i in (1, 2)
        ],
        primary="fc1",
        failover_policy=FailoverPolicy(thresholds=thresholds or Thresholds()),
    )


# what never joins a run (read whole); a state kind joins while it repeats the state held
_RUN_KINDS_READ = READ_KINDS - LATEST_ONLY_KINDS - frozenset(STATE_FIELDS)


class RunModel:
    """The hub fast path's rules for runs (``roost_agent/_udpbatch.c``) over frames
    decoded by the agent's codec, for the health model's tests: between two
    :meth:`flush` calls (two returns of the C call) frames join a run while
    :meth:`HealthTracker.run_state` allowed runs at the first of them, and go whole
    (:meth:`HealthTracker.observe`) otherwise, ending the run before them; a run also
    ends before a gap of the silence threshold. A HEARTBEAT, a step back in
    ``time_boot_ms``, an ATTITUDE whose tilt class changes and a frame of a state kind
    that does not repeat the state held go whole; whatever goes whole while runs are
    taken, and the frame that closes the rate window, end the C call (a flush)."""

    def __init__(self, tracker: HealthTracker) -> None:
        self.tracker = tracker
        self.state = tracker.run_state()
        self.running = self.state is not None
        self.frames: list[tuple[Any, float]] = []

    def _tilt_class(self, msg: Any) -> int:
        assert self.state is not None
        max_deg = self.state[1]
        tilt = tilt_degrees(float(msg.roll), float(msg.pitch))
        return 2 if tilt > max_deg else 1 if tilt > min(TILT_WARN_DEG, max_deg) else 0

    def take(self, msg: Any, at: float) -> bool:
        if self.state is None:
            return self.tracker.observe(msg, at)
        warn, max_deg, tilt_class, gap, window_end, boot_high, backstep, held = self.state
        kind, boot = msg.get_type(), msg.boot_time()
        running = self.running
        joins = running
        if self.running:
            if kind == "HEARTBEAT":
                self.running = joins = False
            if boot is not None and boot_high >= 0 and boot < boot_high - backstep:
                self.running = joins = False
            elif boot is not None:
                boot_high = max(boot_high, boot)
            if kind == "ATTITUDE":
                now_class = self._tilt_class(msg)
                if now_class != tilt_class:
                    self.running = joins = False
                tilt_class = now_class
            fields = STATE_FIELDS.get(kind)
            if fields is not None:
                said = tuple(int(getattr(msg, f)) for f in fields)
                if said != held[kind]:
                    self.running = joins = False
                elif at >= window_end:
                    joins = False  # whole: the window's close is judged before and after
            joins = joins and kind not in _RUN_KINDS_READ
        changed = False
        if joins:
            if self.frames and at - self.frames[-1][1] >= gap:
                changed = self._close()
            self.frames.append((msg, at))
        else:
            changed = self._close()
            changed = self.tracker.observe(msg, at) or changed
        self.state = (warn, max_deg, tilt_class, gap, window_end, boot_high, backstep, held)
        if running and (not joins or at >= window_end):
            # what goes whole is read at once, and the rate window closes at this frame
            # and may learn another silence threshold: the C call returns
            changed = self.flush() or changed
        return changed

    def flush(self) -> bool:
        """The gathered run to the tracker, and the rules start again from its state
        (the C call returns, and the next one is made)."""
        changed = self._close()
        self.state = self.tracker.run_state()
        self.running = self.state is not None
        return changed

    def _close(self) -> bool:
        frames, self.frames = self.frames, []
        changed = False
        if frames:
            counts: dict[str, int] = {}
            latest: dict[str, tuple[str, Any, float]] = {}
            boot_max, boot_at, max_gap = -1, 0.0, 0.0
            for i, (msg, at) in enumerate(frames):
                kind = msg.get_type()
                counts[kind] = counts.get(kind, 0) + 1
                if kind in LATEST_ONLY_KINDS:
                    latest[kind] = (kind, msg, at)
                boot = msg.boot_time()
                if boot is not None and boot > boot_max:
                    boot_max, boot_at = boot, at
                if i:
                    max_gap = max(max_gap, at - frames[i - 1][1])
            changed = self.tracker.observe_run(
                ObservedRun(
                    frames[0][1],
                    frames[-1][1],
                    max_gap,
                    len(frames),
                    tuple(counts.items()),
                    boot_max,
                    boot_at,
                    frames[-1][0].get_seq(),
                    tuple(latest.values()),
                )
            )
        return changed
