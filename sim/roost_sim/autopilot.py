"""One simulated autopilot on a real link: streams, command handling and fault injection.

Threads: the process's tick scheduler (:mod:`roost_sim.scheduler`, one thread for every
autopilot in the process, rounds on a 2.5 ms grid) calls :meth:`SimulatedAutopilot.tick`,
which advances the :class:`~roost_sim.model.AutopilotModel` and sends each stream when
due; a receive thread per autopilot parses MAVLink 2 and answers commands; the link owns
a delay line for jitter. State is guarded by one lock; frames are encoded and sent
under a second so the MAVLink sequence number stays consistent.

What goes on the wire follows the real firmware (:mod:`roost_sim.streams`): the PX4
flavour streams PX4's onboard-link set at its rates from boot, with HEARTBEAT at 1 Hz
only; the ArduPilot flavour sends HEARTBEAT (at once on a mode change, too) and streams
the rest only once asked (SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM), sends STATUSTEXT
only after it has heard MAVLink on the link, and routes a ground station's heartbeat
onto the link (``SimConfig.gcs_heartbeat``, :meth:`SimulatedAutopilot.route`).
Everything a client may ask for is answered honestly: commands the sim does not
implement get MAV_RESULT_UNSUPPORTED, messages it cannot produce DENIED (PX4) or FAILED
(ArduPilot), parameters it does not have no PARAM_VALUE (as real stacks do).
"""

from __future__ import annotations

import logging
import math
import os
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from types import TracebackType
from typing import Any, Self

from pymavlink.dialects.v20 import all as mavlink

from roost_api.fence import FenceAction, LatLon
from roost_api.meta import Stack
from roost_mavlink import (
    AUTOPILOT_COMPONENT_ID,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MavResult,
    api_landed_state,
    heartbeat_autopilot,
    mav_state_name,
)
from roost_mavlink.fence import MAV_MISSION_TYPE_FENCE
from roost_mavlink.modes import ModeIntent, custom_mode, custom_mode_from_set_mode, intent_mode
from roost_mavlink.status import (
    MAV_AUTOPILOT_INVALID,
    MAV_TYPE_QUADROTOR,
    MavState,
    SensorBit,
    sensor_bits,
    sensor_name,
)
from roost_sim.battery import Battery
from roost_sim.faults import (
    DEFAULT_GARBAGE_BYTES_PER_S,
    SPOOF_SYSID_OFFSET,
    FaultKind,
    check_value,
    parse_number,
    parse_sensor,
    parse_state,
)
from roost_sim.fence import SimFence, fence_params
from roost_sim.kinematics import ned_from_global
from roost_sim.link import Link, PtyLink, UdpLink
from roost_sim.logs import SimLogs
from roost_sim.model import SEVERITY_CRITICAL, AutopilotModel, ModeChange, SimConfig, Touchdown
from roost_sim.params import ParamStore
from roost_sim.scheduler import TickScheduler, shared_scheduler
from roost_sim.streams import (
    ARDUPILOT_STREAM_GROUPS,
    ARDUPILOT_TIMESYNC_START_S,
    Gate,
    default_rates,
    gate_of,
    streamable,
)
from roost_sim.telemetry import Telemetry, View

_log = logging.getLogger(__name__)

MAV_CMD_GET_MESSAGE_INTERVAL = 510
MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
MAV_CMD_GET_HOME_POSITION = 410
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246
MAV_CMD_DO_AUX_FUNCTION = 218
AUX_FUNCTION_STANDBY = 76  # ArduPilot's "Standby" auxiliary function (RCx_OPTION 76)
AUX_SWITCH_HIGH = 2
MAV_COMP_ID_GIMBAL = 154
MAV_TYPE_GIMBAL = 26
GCS_SYSID = 255
GCS_COMPONENT_ID = 190

_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
_NOISE_PERIOD_S = 0.05
_SPOOF_PERIOD_S = 0.1
_GCS_PERIOD_S = 1.0
_RX_POLL_S = 5.0  # stop() interrupts the wait: this only bounds a lost wake-up
_MAX_SLEEP_S = 0.01
# SET_POSITION_TARGET_* type_mask bits: x/y/z ignored, yaw ignored.
_IGNORE_POSITION = 0b111
_IGNORE_YAW = 1 << 10
DEFAULT_LAG_PERCENT = 50.0
_RC_RELEASE = (0, 65535)  # RC_CHANNELS_OVERRIDE: hand the channel back / ignore it

# Version each flavour claims in AUTOPILOT_VERSION: (major, minor, patch), official build.
_FIRMWARE: dict[Stack, tuple[int, int, int]] = {Stack.PX4: (1, 16, 0), Stack.ARDUPILOT: (4, 7, 0)}
_FIRMWARE_VERSION_TYPE_OFFICIAL = 255
# The build's git hash, 8 bytes in flight_custom_version: ArduPilot writes the hash's
# first 8 characters, PX4 its first 8 bytes as a little-endian number.
_BUILD: dict[Stack, str] = {Stack.PX4: "d4a3b3c2e1f00abc", Stack.ARDUPILOT: "90700977"}
_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
)
_PARAM_ENCODING: dict[Stack, int] = {
    Stack.PX4: mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
    Stack.ARDUPILOT: mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
}


def _whole(value: float) -> int:
    """A command param as an integer; NaN (MAVLink's "unset") reads as 0."""
    return int(value) if math.isfinite(value) else 0


def command_name(command: int) -> str:
    """MAV_CMD name of a command number (``MAV_CMD_NAV_LAND``), or its number."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    return str(entry.name) if entry is not None else str(command)


@dataclass(frozen=True)
class CommandRecord:
    """A command the sim received and what it answered."""

    at: float  # time.monotonic()
    command: int
    name: str
    params: tuple[float, ...]
    result: int
    source: tuple[int, int]  # (sysid, component) of the sender; (0, 0) for the local API


@dataclass(frozen=True)
class SimSnapshot:
    """Observable state of a simulated autopilot at one instant (JSON-friendly)."""

    name: str
    stack: str
    sysid: int
    connection: str
    armed: bool
    mode: str
    landed_state: str
    altitude_m: float
    climb_mps: float
    system_status: str
    ready: bool  # start-up done: it would arm now (booted, position estimate)
    time_boot_ms: int
    last_mode_change_at: float
    battery_percent: int
    last_touchdown_mps: float | None
    faults: dict[str, str]
    unhealthy_sensors: list[str]
    driving: bool | None = None  # on the motors per the bridge (None: no bridge told it)
    standby_aux: bool | None = None  # ArduPilot STANDBY aux function (None: never set)
    north_m: float = 0.0  # local NED position from home
    east_m: float = 0.0
    speed_mps: float = 0.0  # horizontal
    heading_deg: float = 90.0

    def to_json(self) -> dict[str, Any]:
        """Plain dict for the control socket and the CLI."""
        return asdict(self)


class _LinkWriter:
    """The file object pymavlink's encoder writes finished frames to."""

    def __init__(self, link: Link) -> None:
        self._link = link

    def write(self, data: bytes) -> None:
        self._link.send(bytes(data))


@dataclass
class _Streams:
    rates: dict[int, float]
    due: dict[int, float] = field(default_factory=dict)

    def reset(self, now: float) -> None:
        self.due = {msg_id: now for msg_id, rate in self.rates.items() if rate > 0}

    def set(self, msg_id: int, hz: float, now: float) -> None:
        self.rates[msg_id] = hz
        if hz > 0:
            self.due.setdefault(msg_id, now)
        else:
            self.due.pop(msg_id, None)


class SimulatedAutopilot:
    """A PX4 or ArduPilot flavoured autopilot on one link (UDP or pseudo-terminal)."""

    def __init__(
        self,
        stack: Stack | str,
        sysid: int = 1,
        *,
        link: Link,
        name: str | None = None,
        component_id: int = AUTOPILOT_COMPONENT_ID,
        config: SimConfig | None = None,
        rates: dict[int, float] | None = None,
        battery: Battery | None = None,
        scheduler: TickScheduler | None = None,
    ) -> None:
        self.stack = Stack(stack)
        self.sysid = sysid
        self.component_id = component_id
        self.name = name or f"{self.stack.value}-{sysid}"
        # What logs, errors and thread names call it: ``vehicle/autopilot`` where one
        # process hosts several vehicles (their autopilot names repeat).
        self.label = self.name
        self.link = link
        self.config = config or SimConfig()
        self.battery = battery or Battery()
        self._lock = threading.RLock()
        self._tx_lock = threading.Lock()
        self._model = AutopilotModel(self.stack, self.config, battery=self.battery)
        self.params = ParamStore(self.stack, sysid=sysid, config=self.config)
        # The SD card: one log per armed interval, served over the MAVLink log protocol.
        self.logs = SimLogs(
            self.stack, lambda: {n: self.params.get(n) for n in self.params.names()}
        )
        self.fence = SimFence(self.stack)
        # What AUTOPILOT_VERSION says (tests set other versions and builds).
        self.firmware_version: tuple[int, int, int] = _FIRMWARE[self.stack]
        self.firmware_build = _BUILD[self.stack]
        self._rate_overrides = dict(rates or {})
        self._streams = _Streams(rates=self._initial_rates())
        self._mav = mavlink.MAVLink(_LinkWriter(link), srcSystem=sysid, srcComponent=component_id)
        self._telemetry = Telemetry(self._mav, self.stack, sysid, self.config)
        self._commands: list[CommandRecord] = []
        self._unhandled: Counter[str] = Counter()
        self._heartbeats_heard: Counter[tuple[int, int]] = Counter()
        self._silent = False
        self._frozen: View | None = None
        self._reboot_at: float | None = None
        self._garbage_bytes_per_s = 0.0
        self._spoof_sysid: int | None = None
        self._next_noise = 0.0
        self._next_spoof = 0.0
        self._next_gcs = 0.0
        self._heard = False  # ArduPilot sends STATUSTEXT only on a link it has heard on
        self._heartbeat_mode: int | None = None
        self._origin_sent = False
        self._driving: bool | None = None
        self._setpoints = 0  # position setpoints received (any mode)
        self._standby_aux: bool | None = None
        self._scheduler = scheduler or shared_scheduler()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def _initial_rates(self) -> dict[int, float]:
        rates = default_rates(self.stack, preset=self.config.preset_streams)
        return {**rates, **self._rate_overrides}

    # ---- construction helpers --------------------------------------------------------

    @classmethod
    def udp(
        cls,
        stack: Stack | str,
        sysid: int = 1,
        *,
        target_port: int | None = None,
        bind_port: int = 0,
        host: str = "127.0.0.1",
        **kwargs: Any,
    ) -> SimulatedAutopilot:
        """A sim on UDP that streams to ``host:target_port`` (when given)."""
        target = (host, target_port) if target_port is not None else None
        return cls(stack, sysid, link=UdpLink(target, bind=(host, bind_port)), **kwargs)

    @classmethod
    def pty(cls, stack: Stack | str, sysid: int = 1, **kwargs: Any) -> SimulatedAutopilot:
        """A sim on a fresh pseudo-terminal; open :attr:`device` after :meth:`start`."""
        return cls(stack, sysid, link=PtyLink(), **kwargs)

    # ---- lifecycle -------------------------------------------------------------------

    def start(self) -> Self:
        """Open the link and start streaming (the autopilot boots now)."""
        if self._threads:
            return self
        self._stop.clear()
        self.link.open()
        with self._lock:
            self._reboot(time.monotonic())
        self._threads = [
            threading.Thread(target=self._run_rx, name=f"sim-{self.label}-rx", daemon=True)
        ]
        for thread in self._threads:
            thread.start()
        self._scheduler.register(self)
        return self

    def stop(self) -> None:
        """Stop ticking and receiving and close the link; safe to call twice."""
        self._stop.set()
        self._scheduler.unregister(self)
        self.link.interrupt()
        for thread in self._threads:
            thread.join(timeout=2)
        if self._threads:
            self.link.close()
        self._threads = []

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def connection(self) -> str:
        """``AutopilotSpec.connection`` for an agent on this host (valid after start)."""
        return self.link.connection

    @property
    def device(self) -> str:
        """Serial device path of a pty sim (empty for UDP)."""
        return self.link.device if isinstance(self.link, PtyLink) else ""

    # ---- observation -----------------------------------------------------------------

    def snapshot(self) -> SimSnapshot:
        """Current observable state."""
        with self._lock:
            model = self._model
            touchdown = model.touchdowns[-1].speed_mps if model.touchdowns else None
            return SimSnapshot(
                name=self.name,
                stack=self.stack.value,
                sysid=self.sysid,
                connection=self.connection if self._threads else "",
                armed=model.armed,
                mode=model.mode,
                landed_state=api_landed_state(model.landed_state).value,
                altitude_m=round(model.altitude_m, 3),
                climb_mps=round(model.climb_mps, 3),
                system_status=mav_state_name(model.system_status()),
                ready=model.ready_to_arm,
                time_boot_ms=model.time_boot_ms(),
                last_mode_change_at=model.mode_history[-1].at,
                battery_percent=model.battery_reading().remaining_percent,
                last_touchdown_mps=touchdown,
                faults=self._fault_values(),
                unhealthy_sensors=[sensor_name(b) for b in sensor_bits(model.sensor_faults)],
                driving=self._driving,
                standby_aux=self._standby_aux,
                north_m=round(model.horizontal.north_m, 3),
                east_m=round(model.horizontal.east_m, 3),
                speed_mps=round(model.horizontal.speed_mps, 3),
                heading_deg=round(math.degrees(model.horizontal.yaw_rad) % 360.0, 1),
            )

    @property
    def commands(self) -> list[CommandRecord]:
        """Every command received, oldest first."""
        with self._lock:
            return list(self._commands)

    @property
    def mode_history(self) -> list[ModeChange]:
        """Every mode entered since start, oldest first (reboots included)."""
        with self._lock:
            return list(self._model.mode_history)

    @property
    def touchdowns(self) -> list[Touchdown]:
        """Every ground contact since start with its vertical speed (a crash is a fast one)."""
        with self._lock:
            return list(self._model.touchdowns)

    @property
    def stream_rates(self) -> dict[int, float]:
        """Current stream rates in Hz by message id (requested or the flavour's default)."""
        with self._lock:
            return {k: v for k, v in self._streams.rates.items() if v > 0}

    @property
    def heartbeats_heard(self) -> dict[tuple[int, int], int]:
        """HEARTBEATs received, by sender (system, component): a real autopilot watches
        these for its companion-computer and ground-station failsafes."""
        with self._lock:
            return dict(self._heartbeats_heard)

    @property
    def unhandled_messages(self) -> dict[str, int]:
        """Counts of received message types the sim ignores (to see what clients ask)."""
        with self._lock:
            return dict(self._unhandled)

    def wait_until(
        self, predicate: Callable[[SimSnapshot], bool], timeout: float = 10.0
    ) -> SimSnapshot:
        """Poll :meth:`snapshot` until ``predicate`` holds; raise TimeoutError otherwise."""
        deadline = time.monotonic() + timeout
        while True:
            snap = self.snapshot()
            if predicate(snap):
                return snap
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{self.label}: condition not met within {timeout}s: {snap}")
            time.sleep(0.02)

    def wait_ready(self, timeout: float = 10.0) -> SimSnapshot:
        """Wait until start-up is done and the autopilot would arm (see ``SimConfig``)."""
        return self.wait_until(lambda snap: snap.ready, timeout=timeout)

    # ---- local control (tests, benchmarks) -------------------------------------------

    def fly(self, altitude_m: float | None = None) -> None:
        """Arm and take off through the same rules as commands (logged with source 0/0).

        Raises RuntimeError when a step is refused, e.g. before start-up is done: wait
        with :meth:`wait_ready` first. ArduPilot is put in GUIDED first.
        """
        alt = altitude_m if altitude_m is not None else self.config.takeoff_alt_m
        with self._lock:
            if self.stack is Stack.ARDUPILOT:
                guided = float(custom_mode(self.stack, "GUIDED"))
                self._local(MAV_CMD_DO_SET_MODE, (1.0, guided, 0, 0, 0, 0, 0))
            self._local(MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, 0, 0, 0, 0, 0))
            param7 = alt + self.config.home_amsl_m if self.stack is Stack.PX4 else alt
            self._local(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, math.nan, math.nan, param7))

    def local_command(self, command: int, params: tuple[float, ...]) -> int:
        """Run one command through the same rules as a received COMMAND_LONG (logged
        with source 0/0), as a ground station on another link would send it.

        Raises RuntimeError when it is refused (an arming refusal names its reasons).
        """
        with self._lock:
            return self._local(command, params)

    def _local(self, command: int, params: tuple[float, ...]) -> int:
        reasons = self._model.arming_refusals() if command == MAV_CMD_COMPONENT_ARM_DISARM else []
        result, _ = self._execute(command, params, (0, 0))
        if result != MavResult.ACCEPTED:
            why = f": {', '.join(reasons)}" if reasons else ""
            raise RuntimeError(f"{self.label}: {command_name(command)} refused ({result}){why}")
        return result

    def set_driving(self, driving: bool) -> None:
        """The bridge connected this autopilot's outputs to the motors, or not."""
        with self._lock:
            self._driving = driving

    @property
    def setpoints_received(self) -> int:
        """SET_POSITION_TARGET_* messages addressed to this autopilot so far."""
        return self._setpoints

    @property
    def driving(self) -> bool | None:
        """Whether the bridge says this autopilot drives the motors (None: no bridge)."""
        return self._driving

    def set_rate(self, message_id: int, hz: float) -> None:
        """Stream ``message_id`` at ``hz`` (0 stops it), whatever the flavour would do."""
        with self._lock:
            self._rate_overrides[message_id] = hz
            self._streams.set(message_id, hz, time.monotonic())

    def set_throttle(self, stick: float | None) -> None:
        """The pilot's throttle stick, 0 (low) to 1 (high); None: no RC (reads low)."""
        if stick is not None and not (math.isfinite(stick) and 0.0 <= stick <= 1.0):
            raise ValueError(f"throttle must be between 0 and 1, not {stick!r}")
        with self._lock:
            self.config.throttle = stick

    def route(self, frame: bytes) -> None:
        """Put a frame from another system/component on this link, as ArduPilot routes it.

        Only the ArduPilot flavour routes; PX4's onboard link (without forwarding to it)
        does not, so the frame is dropped there.
        """
        if self.stack is Stack.ARDUPILOT:
            with self._lock:
                sending = self._sending()
            if sending:
                self.link.write_noise(bytes(frame))  # as received: not re-signed

    # ---- fault injection -------------------------------------------------------------

    def inject(self, kind: FaultKind | str, value: str | float | None = None) -> None:
        """Start a fault (see :mod:`roost_sim.faults` for kinds and values).

        An unknown kind or an invalid value raises ValueError before anything changes.
        """
        kind = FaultKind(kind)
        check_value(kind, value)
        now = time.monotonic()
        with self._lock:
            if kind is FaultKind.SILENCE:
                self._silent = True
            elif kind is FaultKind.FREEZE:
                self._frozen = self._frozen or self._view()
            elif kind is FaultKind.SENSOR:
                self._model.sensor_faults |= parse_sensor(value)
            elif kind is FaultKind.STATE:
                self._model.state_override = parse_state(value)
            elif kind is FaultKind.REBOOT:
                self._reboot_at = now + parse_number(kind, value, 0.0)
            elif kind is FaultKind.GARBAGE:
                self._garbage_bytes_per_s = parse_number(kind, value, DEFAULT_GARBAGE_BYTES_PER_S)
            elif kind is FaultKind.LOSS:
                self.link.impairment.loss_percent = parse_number(kind, value, 10.0)
            elif kind is FaultKind.JITTER:
                self.link.impairment.jitter_ms = parse_number(kind, value, 50.0)
            elif kind is FaultKind.SPOOF:
                default = (self.sysid + SPOOF_SYSID_OFFSET - 1) % 255 + 1
                self._spoof_sysid = int(parse_number(kind, value, default))
            elif kind is FaultKind.BATTERY:
                self.battery.fail()
            elif kind is FaultKind.LAG:
                self._model.speed_scale = parse_number(kind, value, DEFAULT_LAG_PERCENT) / 100.0

    def clear(self, kind: FaultKind | str | None = None) -> None:
        """End one fault kind, or every fault when ``kind`` is None."""
        kinds = list(FaultKind) if kind is None else [FaultKind(kind)]
        with self._lock:
            for k in kinds:
                if k is FaultKind.SILENCE:
                    self._silent = False
                elif k is FaultKind.FREEZE:
                    self._frozen = None
                elif k is FaultKind.SENSOR:
                    self._model.sensor_faults = SensorBit(0)
                elif k is FaultKind.STATE:
                    self._model.state_override = None
                elif k is FaultKind.GARBAGE:
                    self._garbage_bytes_per_s = 0.0
                elif k is FaultKind.LOSS:
                    self.link.impairment.loss_percent = 0.0
                elif k is FaultKind.JITTER:
                    self.link.impairment.jitter_ms = 0.0
                    self.link.flush_delayed()
                elif k is FaultKind.SPOOF:
                    self._spoof_sysid = None
                elif k is FaultKind.BATTERY and self.battery.failed:
                    self.battery.replace()
                elif k is FaultKind.LAG:
                    self._model.speed_scale = 1.0

    def _fault_values(self) -> dict[str, str]:
        model, imp = self._model, self.link.impairment
        active: dict[FaultKind, object] = {
            FaultKind.SILENCE: self._silent or None,
            FaultKind.FREEZE: self._frozen is not None or None,
            FaultKind.SENSOR: ",".join(sensor_name(b) for b in sensor_bits(model.sensor_faults))
            or None,
            FaultKind.STATE: model.state_override.name if model.state_override else None,
            FaultKind.REBOOT: self._reboot_at,
            FaultKind.GARBAGE: self._garbage_bytes_per_s or None,
            FaultKind.LOSS: imp.loss_percent or None,
            FaultKind.JITTER: imp.jitter_ms or None,
            FaultKind.SPOOF: self._spoof_sysid,
            FaultKind.BATTERY: self.battery.failed or None,
            FaultKind.LAG: round(model.speed_scale * 100, 1) if model.speed_scale != 1.0 else None,
        }
        return {k.value: str(v) for k, v in active.items() if v is not None}

    def _sending(self) -> bool:
        return not self._silent and self._reboot_at is None

    # ---- main loop (run by the scheduler): kinematics and streams ---------------------

    def tick(self, now: float) -> float:
        """One round of the main loop at ``now``: step the model, send what is due; the
        time the next round is wanted (at most :data:`_MAX_SLEEP_S` away: the model steps
        and reboots, noise and events are seen at least that often).

        The scheduler logs an exception and retries later, so a bug in one message
        cannot silence the autopilot nor its neighbours.
        """
        messages, noise, next_due = self._tick(now)
        for message in messages:
            self._send(message)
        for frame in noise:
            self.link.write_noise(frame)
        return min(next_due, now + _MAX_SLEEP_S)

    def _tick(self, now: float) -> tuple[list[Any], list[bytes], float]:
        with self._lock:
            if self._reboot_at is not None and now >= self._reboot_at:
                self._reboot(now)
            if self._frozen is None:
                self._model.step()
                self._enforce_fence()
            view = self._frozen or self._view()
            # A stream whose start-up step is not reached stays due: it starts on time.
            due = [m for m, t in self._streams.due.items() if t <= now and self._gate_open(m)]
            for msg_id in due:
                self._streams.due[msg_id] = self._next_due(msg_id, now)
            texts, self._model.texts = self._model.texts, []
            messages: list[Any] = []
            self.logs.note(view, now)
            if self._sending():
                messages = [self._telemetry.builders[m](view) for m in due]
                messages += self._events(view, texts)
                messages += self.logs.pending(now, self._mav)
            noise = self._noise(now) if self._sending() else []
            next_due = min(
                (t for t in self._streams.due.values() if t > now), default=now + _MAX_SLEEP_S
            )
        return messages, noise, next_due

    def _enforce_fence(self) -> None:
        """Act on a fence breach as the firmware does (roost_sim.fence)."""
        model = self._model
        action = self.fence.check(
            north_m=model.horizontal.north_m,
            east_m=model.horizontal.east_m,
            altitude_m=model.altitude_m,
            home=LatLon(self.config.home_lat_deg, self.config.home_lon_deg),
            params=fence_params(self.stack, self.params.get),
            flying=model.armed and not model.on_ground,
        )
        if action is None:
            return
        model.texts.append((SEVERITY_CRITICAL, f"Geofence breached: {self.fence.breaches[-1]}"))
        if action is FenceAction.RETURN:
            model.return_to_launch()
        elif action is FenceAction.LAND:
            model.land()
        elif action is FenceAction.HOLD:
            model.set_mode(custom_mode(self.stack, intent_mode(self.stack, ModeIntent.HOLD)))

    def _gate_open(self, msg_id: int) -> bool:
        model = self._model
        gate = gate_of(self.stack, msg_id)
        if self._frozen is not None:
            return True  # a hung main loop repeats whatever it was sending
        if gate is Gate.POWER_ON:
            return True
        if gate is Gate.POSITION:
            # PX4 publishes a global position shortly before its estimator reports one.
            lead = 0.82 if self.stack is Stack.PX4 else 1.0
            return model.uptime() >= model.boot_times.position_s * lead
        if gate is Gate.SETPOINT:
            return model.armed or not model.on_ground
        times = model.boot_times
        if self.stack is Stack.ARDUPILOT:  # only its unrequested TIMESYNC is gated
            return model.uptime() >= min(ARDUPILOT_TIMESYNC_START_S, times.position_s)
        start = {
            Gate.HEARTBEAT: times.first_heartbeat_s,
            Gate.ATTITUDE: times.standby_s * 0.35,
            Gate.ESTIMATOR: times.attitude_s,
        }[gate]
        return model.uptime() >= start

    def _events(self, view: View, texts: list[tuple[int, str]]) -> list[Any]:
        """Messages sent on an event rather than a schedule."""
        out: list[Any] = []
        model = self._model
        if self.stack is Stack.ARDUPILOT and self._heartbeat_mode != view.custom_mode:
            # ArduPilot sends a heartbeat at once on a mode change; PX4 waits for its 1 Hz.
            if self._heartbeat_mode is not None and self._streams.rates.get(_HEARTBEAT, 0) > 0:
                out.append(self._telemetry.heartbeat(view))
            self._heartbeat_mode = view.custom_mode
        if not self._origin_sent and model.uptime() >= model.boot_times.origin_s:
            self._origin_sent = True
            out.append(self._telemetry.gps_global_origin(view))
            if self.stack is Stack.ARDUPILOT:
                out.append(self._telemetry.home_position(view))
        if self.stack is Stack.ARDUPILOT and self._heard:
            for severity, text in texts:
                out.append(self._mav.statustext_encode(severity, text.encode()[:50], 0, 0))
        return out

    def _next_due(self, msg_id: int, now: float) -> float:
        period = 1.0 / self._streams.rates[msg_id]
        due = self._streams.due[msg_id] + period
        return due if due > now else now + period  # fell behind: do not burst

    def _reboot(self, now: float) -> None:
        self._reboot_at = None
        self._frozen = None
        self._model.reboot()
        self.logs.forget_transfer()
        self._model.texts.clear()
        self._heard = False
        self._heartbeat_mode = None
        self._origin_sent = False
        self._streams = _Streams(rates=self._initial_rates())  # requests do not survive
        self._streams.reset(now)

    def _view(self) -> View:
        model = self._model
        return View(
            time_boot_ms=model.time_boot_ms(),
            unix_usec=time.time_ns() // 1000,
            armed=model.armed,
            custom_mode=model.custom_mode,
            mode=model.mode,
            system_status=int(model.system_status()),
            landed_state=int(model.landed_state),
            altitude_m=model.altitude_m,
            climb_mps=model.climb_mps,
            north_m=model.horizontal.north_m,
            east_m=model.horizontal.east_m,
            vn_mps=model.horizontal.vn_mps,
            ve_mps=model.horizontal.ve_mps,
            yaw_rad=model.horizontal.yaw_rad,
            sensors=model.sensors(),
            gps_ok=not model.sensor_faults & SensorBit.GPS,
            estimator_flags=model.estimator_flags(),
            battery=model.battery_reading(),
            has_position=model.has_position,
        )

    def _noise(self, now: float) -> list[bytes]:
        frames: list[bytes] = []
        if self._garbage_bytes_per_s > 0 and now >= self._next_noise:
            self._next_noise = now + _NOISE_PERIOD_S
            size = max(1, int(self._garbage_bytes_per_s * _NOISE_PERIOD_S))
            heartbeat = self._telemetry.heartbeat(self._view())
            corrupted = bytearray(heartbeat.pack(mavlink.MAVLink(None)))
            corrupted[len(corrupted) // 2] ^= 0xFF  # a real-looking frame failing its CRC
            frames.append(os.urandom(size) + bytes(corrupted))
        if self._spoof_sysid is not None and now >= self._next_spoof:
            self._next_spoof = now + _SPOOF_PERIOD_S
            frames.extend(self._spoof_frames())
        if self.config.gcs_heartbeat and self.stack is Stack.ARDUPILOT and now >= self._next_gcs:
            self._next_gcs = now + _GCS_PERIOD_S
            gcs = mavlink.MAVLink(None, srcSystem=GCS_SYSID, srcComponent=GCS_COMPONENT_ID)
            frames.append(
                gcs.heartbeat_encode(
                    mavlink.MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, int(MavState.ACTIVE)
                ).pack(gcs)
            )
        return frames

    def _spoof_frames(self) -> list[bytes]:
        assert self._spoof_sysid is not None
        foreign = mavlink.MAVLink(None, srcSystem=self._spoof_sysid, srcComponent=1)
        gimbal = mavlink.MAVLink(None, srcSystem=self.sysid, srcComponent=MAV_COMP_ID_GIMBAL)
        emergency = int(MavState.EMERGENCY)
        return [
            foreign.heartbeat_encode(
                MAV_TYPE_QUADROTOR, heartbeat_autopilot(self.stack), 0, 0, emergency
            ).pack(foreign),
            foreign.attitude_encode(self._model.time_boot_ms(), 2.5, -1.2, 0, 9, 9, 9).pack(
                foreign
            ),
            gimbal.heartbeat_encode(MAV_TYPE_GIMBAL, MAV_AUTOPILOT_INVALID, 0, 0, emergency).pack(
                gimbal
            ),
        ]

    def _send(self, message: Any) -> None:
        with self._tx_lock:
            try:
                self._mav.send(message)
            except (struct.error, TypeError, ValueError):  # a bad field must not stop the link
                _log.exception("%s: cannot encode %s", self.label, message.get_type())

    # ---- receive thread: commands and protocol handshakes ----------------------------

    def _run_rx(self) -> None:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        while not self._stop.is_set():
            data = self.link.receive(_RX_POLL_S)
            if not data:
                continue
            with self._lock:
                if not self._sending():
                    continue  # a silent or rebooting autopilot hears nothing either
            try:
                messages = parser.parse_buffer(data) or []
            except mavlink.MAVError:
                continue
            for message in messages:
                try:
                    self._handle(message)
                except Exception:  # one odd message must not kill the autopilot
                    _log.exception("%s: failed to handle %s", self.label, message)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        replies: list[Any] = []
        with self._lock:
            self._heard = True
            if self._frozen is not None:
                return  # a hung main loop answers nothing
            if kind in ("COMMAND_LONG", "COMMAND_INT"):
                replies = self._command_message(msg)
            elif kind.startswith("PARAM_"):
                replies = self.params.handle(msg, self._mav, self.sysid, self.component_id)
            elif kind == "PING" and msg.target_system == 0:
                # A ping request: answer it addressed to the sender, as PX4 does.
                replies = [
                    self._mav.ping_encode(
                        msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
                    )
                ]
            elif kind == "TIMESYNC":
                if msg.tc1 == 0:
                    replies = [self._mav.timesync_encode(time.monotonic_ns(), msg.ts1)]
            elif (
                kind.startswith("MISSION_")
                and getattr(msg, "mission_type", 0) == MAV_MISSION_TYPE_FENCE
                and self._for_us(msg)
            ):
                replies = self.fence.handle(msg, self._mav, self.sysid, self.component_id)
            elif kind == "MISSION_REQUEST_LIST" and self._for_us(msg):
                # No mission, fence or rally points are stored: say so.
                replies = [
                    self._mav.mission_count_encode(
                        msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type
                    )
                ]
            elif kind == "REQUEST_DATA_STREAM" and self._for_us(msg):
                self._request_data_stream(msg.req_stream_id, msg.req_message_rate, msg.start_stop)
            elif kind == "SET_POSITION_TARGET_LOCAL_NED" and self._for_us(msg):
                self._local_setpoint(msg)
            elif kind == "SET_POSITION_TARGET_GLOBAL_INT" and self._for_us(msg):
                self._global_setpoint(msg)
            elif kind == "RC_CHANNELS_OVERRIDE" and self._for_us(msg):
                raw = msg.chan3_raw
                if raw not in _RC_RELEASE:
                    self.config.throttle = min(1.0, max(0.0, (raw - 1000) / 1000.0))
                elif raw == 0:
                    self.config.throttle = None
            elif kind.startswith("LOG_") and self._for_us(msg):
                replies = self.logs.handle(msg, self._mav, self._model.armed)
            elif kind == "HEARTBEAT":
                # what a real autopilot's companion / ground-station failsafe watches
                self._heartbeats_heard[msg.get_srcSystem(), msg.get_srcComponent()] += 1
            else:
                self._unhandled[kind] += 1
        for reply in replies:
            self._send(reply)

    def _local_setpoint(self, msg: Any) -> None:
        """SET_POSITION_TARGET_LOCAL_NED in the local NED frame: position and yaw."""
        self._setpoints += 1
        if msg.type_mask & _IGNORE_POSITION or msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
            self._unhandled["SET_POSITION_TARGET_LOCAL_NED (no local position)"] += 1
            return
        yaw = None if msg.type_mask & _IGNORE_YAW else msg.yaw
        self._model.position_setpoint(msg.x, msg.y, -msg.z, yaw)

    def _global_setpoint(self, msg: Any) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT: latitude/longitude and an AMSL or relative
        altitude, converted to the local frame around home."""
        self._setpoints += 1
        frames = {
            mavlink.MAV_FRAME_GLOBAL_INT: self.config.home_amsl_m,
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: 0.0,
            mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: 0.0,  # flat ground at home
        }
        if msg.type_mask & _IGNORE_POSITION or msg.coordinate_frame not in frames:
            self._unhandled["SET_POSITION_TARGET_GLOBAL_INT (no global position)"] += 1
            return
        north, east = ned_from_global(
            msg.lat_int / 1e7, msg.lon_int / 1e7, self.config.home_lat_deg, self.config.home_lon_deg
        )
        yaw = None if msg.type_mask & _IGNORE_YAW else msg.yaw
        self._model.position_setpoint(north, east, msg.alt - frames[msg.coordinate_frame], yaw)

    def _for_us(self, msg: Any) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (
            0,
            self.component_id,
        )

    def _command_message(self, msg: Any) -> list[Any]:
        if not self._for_us(msg):
            return []
        params: tuple[float, ...]
        if msg.get_type() == "COMMAND_LONG":
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
            params += (msg.param7,)
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z)
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        result, after = self._execute(msg.command, params, source)
        ack = self._mav.command_ack_encode(msg.command, result, 0, 0, source[0], source[1])
        return [ack, *after]

    def _execute(
        self, command: int, p: tuple[float, ...], source: tuple[int, int]
    ) -> tuple[int, list[Any]]:
        after: list[Any] = []
        model = self._model
        if command == MAV_CMD_COMPONENT_ARM_DISARM:
            result = model.arm(arm=p[0] >= 0.5, magic=p[1])
        elif command == MAV_CMD_NAV_TAKEOFF:
            result = model.takeoff(p[6])
        elif command == MAV_CMD_DO_SET_MODE:
            try:
                result = model.set_mode(custom_mode_from_set_mode(self.stack, p[0], p[1], p[2]))
            except ValueError:
                result = model.invalid_result()
        elif command == MAV_CMD_NAV_LAND:
            result = model.land()
        elif command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            result = model.return_to_launch()
        elif command == MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(_whole(p[0]), p[1])
        elif command == MAV_CMD_GET_MESSAGE_INTERVAL:
            result, after = self._get_interval(_whole(p[0]))
        elif command == MAV_CMD_REQUEST_MESSAGE:
            result, after = self._request(_whole(p[0]))
        elif command == MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result, after = self._request(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        elif command == MAV_CMD_GET_HOME_POSITION:
            result, after = self._request(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
        elif command == MAV_CMD_DO_AUX_FUNCTION and self.stack is Stack.ARDUPILOT:
            result = self._aux_function(_whole(p[0]), _whole(p[1]))
        elif command == MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and _whole(p[0]) == 1:
            if model.armed:
                result = model.refused_result()
            else:
                result = MavResult.ACCEPTED
                self._reboot_at = time.monotonic() + 0.2  # after the ACK has left
        else:
            result = MavResult.UNSUPPORTED
        self._commands.append(
            CommandRecord(
                at=time.monotonic(),
                command=command,
                name=command_name(command),
                params=tuple(float(x) for x in p),
                result=result,
                source=source,
            )
        )
        return result, after

    def _aux_function(self, function: int, switch: int) -> int:
        """ArduPilot's DO_AUX_FUNCTION; only STANDBY is modelled (its switch position is
        recorded: high while another controller flies the vehicle)."""
        if function != AUX_FUNCTION_STANDBY:
            return MavResult.UNSUPPORTED
        self._standby_aux = switch == AUX_SWITCH_HIGH
        return MavResult.ACCEPTED

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        if msg_id == _HEARTBEAT and self.stack is Stack.PX4:
            return MavResult.DENIED  # PX4 keeps HEARTBEAT at 1 Hz
        if not math.isfinite(interval_us) or not streamable(self.stack, msg_id):
            return self._model.invalid_result()
        if interval_us < 0:
            hz = 0.0
        elif interval_us == 0:
            hz = default_rates(self.stack).get(msg_id, 0.0)
        else:
            hz = 1e6 / interval_us
        self._streams.set(msg_id, hz, time.monotonic())
        return MavResult.ACCEPTED

    def _request_data_stream(self, stream_id: int, rate_hz: int, start: int) -> None:
        """REQUEST_DATA_STREAM: ArduPilot sets a whole group's rate (PX4 ignores it)."""
        if self.stack is not Stack.ARDUPILOT:
            self._unhandled["REQUEST_DATA_STREAM"] += 1
            return
        groups = (
            list(ARDUPILOT_STREAM_GROUPS)
            if stream_id == mavlink.MAV_DATA_STREAM_ALL
            else [stream_id]
            if stream_id in ARDUPILOT_STREAM_GROUPS
            else []
        )
        hz = float(rate_hz) if start else 0.0
        now = time.monotonic()
        for group in groups:
            for msg_id in ARDUPILOT_STREAM_GROUPS[group]:
                self._streams.set(msg_id, hz, now)

    def _get_interval(self, msg_id: int) -> tuple[int, list[Any]]:
        if msg_id not in self._telemetry.builders:
            return self._model.invalid_result(), []
        hz = self._streams.rates.get(msg_id, 0.0)
        interval = int(1e6 / hz) if hz > 0 else -1
        return MavResult.ACCEPTED, [self._mav.message_interval_encode(msg_id, interval)]

    def _request(self, msg_id: int) -> tuple[int, list[Any]]:
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return MavResult.ACCEPTED, [self._autopilot_version()]
        if msg_id not in self._telemetry.builders:
            return self._model.invalid_result(), []
        return MavResult.ACCEPTED, [self._telemetry.builders[msg_id](self._frozen or self._view())]

    def _autopilot_version(self) -> Any:
        major, minor, patch = self.firmware_version
        version = (major << 24) | (minor << 16) | (patch << 8) | _FIRMWARE_VERSION_TYPE_OFFICIAL
        build = self.firmware_build
        custom = (
            int(build, 16).to_bytes(8, "big")[::-1]
            if self.stack is Stack.PX4
            else build.encode()[:8].ljust(8, b"\0")
        )
        return self._mav.autopilot_version_encode(
            _CAPABILITIES | _PARAM_ENCODING[self.stack],
            version,
            0,
            0,
            0,
            list(custom),
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x524F4F5354000000 | self.sysid,  # "ROOST" + sysid: unique per sim
        )


def message_id(message_name: str) -> int:
    """Message id for a name such as ``ATTITUDE`` (for :meth:`SimulatedAutopilot.set_rate`)."""
    value = getattr(mavlink, f"MAVLINK_MSG_ID_{message_name.upper()}", None)
    if not isinstance(value, int):
        raise KeyError(f"unknown MAVLink message {message_name!r}")
    return value
