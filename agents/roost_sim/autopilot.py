"""One simulated autopilot on a real link: streams, command handling and fault injection.

Threads: a tick thread advances the :class:`~roost_sim.model.AutopilotModel` and sends
each stream when due; a receive thread parses MAVLink 2 and answers commands; the link
owns a delay line for jitter. State is guarded by one lock; frames are encoded and sent
under a second so the MAVLink sequence number stays consistent.

Besides the streams every autopilot sends (HEARTBEAT 1 Hz, SYS_STATUS and EXTENDED_SYS_STATE 5 Hz,
ATTITUDE 50 Hz, GLOBAL_POSITION_INT 10 Hz, SYSTEM_TIME 1 Hz) it sends GPS_RAW_INT and
HOME_POSITION at 1 Hz: a ground station (MAVSDK) judges "global position ok" and "home
position ok" from them. Everything a client may ask for is answered honestly: commands
the sim does not implement get MAV_RESULT_UNSUPPORTED, messages it cannot produce
MAV_RESULT_DENIED, parameters it does not have no PARAM_VALUE (as real stacks do).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from types import TracebackType
from typing import Any, Self

from pymavlink.dialects.v20 import common as mavlink

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
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MavResult,
    heartbeat_autopilot,
    landed_state_name,
    mav_state_name,
)
from roost_mavlink.modes import custom_mode_from_set_mode
from roost_mavlink.status import (
    MAV_AUTOPILOT_INVALID,
    MAV_TYPE_QUADROTOR,
    LandedState,
    MavState,
    SensorBit,
    sensor_bits,
    sensor_name,
)
from roost_sim.faults import (
    DEFAULT_GARBAGE_BYTES_PER_S,
    SPOOF_SYSID_OFFSET,
    FaultKind,
    parse_number,
    parse_sensor,
    parse_state,
)
from roost_sim.link import Link, PtyLink, UdpLink
from roost_sim.model import AutopilotModel, ModeChange, Sensors, SimConfig
from roost_sim.params import ParamStore

_log = logging.getLogger(__name__)

MAV_CMD_GET_MESSAGE_INTERVAL = 510
MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
MAV_CMD_GET_HOME_POSITION = 410
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246
MAV_COMP_ID_GIMBAL = 154
MAV_TYPE_GIMBAL = 26

# Message id -> default rate in Hz (0 = only on request).
DEFAULT_RATES: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 1.0,
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: 0.0,
}
_NOISE_PERIOD_S = 0.05
_SPOOF_PERIOD_S = 0.1
_RX_POLL_S = 0.2
_MAX_SLEEP_S = 0.01

# Version each flavour claims in AUTOPILOT_VERSION: (major, minor, patch), official build.
_FIRMWARE: dict[Stack, tuple[int, int, int]] = {Stack.PX4: (1, 15, 0), Stack.ARDUPILOT: (4, 5, 0)}
_FIRMWARE_VERSION_TYPE_OFFICIAL = 255
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
    system_status: str
    time_boot_ms: int
    last_mode_change_at: float
    faults: dict[str, str]
    unhealthy_sensors: list[str]

    def to_json(self) -> dict[str, Any]:
        """Plain dict for the control socket and the CLI."""
        return asdict(self)


@dataclass(frozen=True)
class _View:
    """The values that go into telemetry at one instant (repeated verbatim when frozen)."""

    time_boot_ms: int
    unix_usec: int
    armed: bool
    custom_mode: int
    system_status: int
    landed_state: int
    altitude_m: float
    climb_mps: float
    sensors: Sensors
    gps_ok: bool


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
    ) -> None:
        self.stack = Stack(stack)
        self.sysid = sysid
        self.component_id = component_id
        self.name = name or f"{self.stack.value}-{sysid}"
        self.link = link
        self.config = config or SimConfig()
        self._lock = threading.RLock()
        self._tx_lock = threading.Lock()
        self._model = AutopilotModel(self.stack, self.config)
        self.params = ParamStore(self.stack, sysid=sysid, config=self.config)
        self._streams = _Streams(rates={**DEFAULT_RATES, **(rates or {})})
        self._mav = mavlink.MAVLink(_LinkWriter(link), srcSystem=sysid, srcComponent=component_id)
        self._commands: list[CommandRecord] = []
        self._unhandled: Counter[str] = Counter()
        self._silent = False
        self._frozen: _View | None = None
        self._reboot_at: float | None = None
        self._garbage_bytes_per_s = 0.0
        self._spoof_sysid: int | None = None
        self._next_noise = 0.0
        self._next_spoof = 0.0
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._builders: dict[int, Callable[[_View], Any]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: self._gps_raw,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
        }

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
            self._model.reboot()
            self._streams.reset(time.monotonic())
        self._threads = [
            threading.Thread(target=self._run_tick, name=f"sim-{self.name}-tick", daemon=True),
            threading.Thread(target=self._run_rx, name=f"sim-{self.name}-rx", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        return self

    def stop(self) -> None:
        """Stop the threads and close the link; safe to call twice."""
        self._stop.set()
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
            return SimSnapshot(
                name=self.name,
                stack=self.stack.value,
                sysid=self.sysid,
                connection=self.connection if self._threads else "",
                armed=model.armed,
                mode=model.mode,
                landed_state=landed_state_name(model.landed_state),
                altitude_m=round(model.altitude_m, 3),
                system_status=mav_state_name(model.system_status()),
                time_boot_ms=model.time_boot_ms(),
                last_mode_change_at=model.mode_history[-1].at,
                faults=self._fault_values(),
                unhealthy_sensors=[sensor_name(b) for b in sensor_bits(model.sensor_faults)],
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
                raise TimeoutError(f"{self.name}: condition not met within {timeout}s: {snap}")
            time.sleep(0.02)

    # ---- local control (tests, benchmarks) -------------------------------------------

    def fly(self, altitude_m: float | None = None) -> None:
        """Arm and take off through the same rules as commands (logged with source 0/0).

        Raises RuntimeError when a step is refused, e.g. during the BOOT phase right after
        start: wait with ``wait_until(lambda s: s.system_status != "BOOT")`` first.
        """
        alt = altitude_m if altitude_m is not None else self.config.takeoff_alt_m
        with self._lock:
            if self.stack is Stack.ARDUPILOT:
                self._local(MAV_CMD_DO_SET_MODE, (1.0, 4.0, 0, 0, 0, 0, 0))  # GUIDED
            self._local(MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, 0, 0, 0, 0, 0))
            param7 = alt + self.config.home_amsl_m if self.stack is Stack.PX4 else alt
            self._local(MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, math.nan, math.nan, param7))

    def _local(self, command: int, params: tuple[float, ...]) -> int:
        result, _ = self._execute(command, params, (0, 0))
        if result != MavResult.ACCEPTED:
            raise RuntimeError(f"{self.name}: {command_name(command)} refused ({result})")
        return result

    def set_rate(self, message_id: int, hz: float) -> None:
        """Stream ``message_id`` at ``hz`` (0 stops it)."""
        with self._lock:
            self._streams.rates[message_id] = hz
            if hz > 0:
                self._streams.due.setdefault(message_id, time.monotonic())
            else:
                self._streams.due.pop(message_id, None)

    # ---- fault injection -------------------------------------------------------------

    def inject(self, kind: FaultKind | str, value: str | float | None = None) -> None:
        """Start a fault (see :mod:`roost_sim.faults` for kinds and values)."""
        kind = FaultKind(kind)
        now = time.monotonic()
        with self._lock:
            if kind is FaultKind.SILENCE:
                self._silent = True
            elif kind is FaultKind.FREEZE:
                self._frozen = self._frozen or self._view()
            elif kind is FaultKind.SENSOR:
                self._model.sensor_faults |= parse_sensor(
                    value if not isinstance(value, float) else int(value)
                )
            elif kind is FaultKind.STATE:
                self._model.state_override = parse_state(
                    value if not isinstance(value, float) else int(value)
                )
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
                self._spoof_sysid = int(parse_number(kind, value, default)) or default

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
                elif k is FaultKind.SPOOF:
                    self._spoof_sysid = None

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
        }
        return {k.value: str(v) for k, v in active.items() if v is not None}

    def _sending(self) -> bool:
        return not self._silent and self._reboot_at is None

    # ---- tick thread: kinematics and streams -----------------------------------------

    def _run_tick(self) -> None:
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                if self._reboot_at is not None and now >= self._reboot_at:
                    self._reboot(now)
                if self._frozen is None:
                    self._model.step()
                due = [m for m, t in self._streams.due.items() if t <= now]
                for msg_id in due:
                    self._streams.due[msg_id] = self._next_due(msg_id, now)
                messages = []
                if due and self._sending():
                    view = self._frozen or self._view()
                    messages = [self._builders[m](view) for m in due]
                noise = self._noise(now) if self._sending() else []
                next_due = min(self._streams.due.values(), default=now + _MAX_SLEEP_S)
            for message in messages:
                self._send(message)
            for frame in noise:
                self.link.write_noise(frame)
            self._stop.wait(min(max(next_due - time.monotonic(), 0.0), _MAX_SLEEP_S))

    def _next_due(self, msg_id: int, now: float) -> float:
        period = 1.0 / self._streams.rates[msg_id]
        due = self._streams.due[msg_id] + period
        return due if due > now else now + period  # fell behind: do not burst

    def _reboot(self, now: float) -> None:
        self._reboot_at = None
        self._frozen = None
        self._model.reboot()
        self._streams.reset(now)

    def _view(self) -> _View:
        model = self._model
        return _View(
            time_boot_ms=model.time_boot_ms(),
            unix_usec=time.time_ns() // 1000,
            armed=model.armed,
            custom_mode=model.custom_mode,
            system_status=int(model.system_status()),
            landed_state=int(model.landed_state),
            altitude_m=model.altitude_m,
            climb_mps=model.climb_mps,
            sensors=model.sensors(),
            gps_ok=not model.sensor_faults & SensorBit.GPS,
        )

    def _build(self, msg_id: int) -> Any:
        return self._builders[msg_id](self._frozen or self._view())

    def _extended_sys_state(self, v: _View) -> Any:
        return self._mav.extended_sys_state_encode(0, v.landed_state)

    def _system_time(self, v: _View) -> Any:
        return self._mav.system_time_encode(v.unix_usec, v.time_boot_ms)

    def _heartbeat(self, v: _View) -> Any:
        base_mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            MAV_MODE_FLAG_SAFETY_ARMED if v.armed else 0
        )
        return self._mav.heartbeat_encode(
            MAV_TYPE_QUADROTOR,
            heartbeat_autopilot(self.stack),
            base_mode,
            v.custom_mode,
            v.system_status,
        )

    def _sys_status(self, v: _View) -> Any:
        flying = v.landed_state != LandedState.ON_GROUND
        return self._mav.sys_status_encode(
            v.sensors.present,
            v.sensors.enabled,
            v.sensors.health,
            250,  # load 25.0 %
            16200,  # mV
            1500 if flying else 50,  # cA
            80,  # %
            0,
            0,
            0,
            0,
            0,
            0,
        )

    @staticmethod
    def _angles(v: _View) -> tuple[float, float, float, float, float, float]:
        # A gentle deterministic wobble: values change every sample unless frozen.
        t = v.time_boot_ms / 1000.0
        amp = 0.03 if v.landed_state != LandedState.ON_GROUND else 0.002
        roll, pitch = amp * math.sin(1.3 * t), amp * math.sin(0.9 * t + 1.0)
        yaw = 1.5708 + 0.01 * math.sin(0.2 * t)
        return (
            roll,
            pitch,
            yaw,
            amp * 1.3 * math.cos(1.3 * t),
            amp * 0.9 * math.cos(0.9 * t + 1.0),
            0.002 * math.cos(0.2 * t),
        )

    def _attitude(self, v: _View) -> Any:
        return self._mav.attitude_encode(v.time_boot_ms, *self._angles(v))

    def _global_position(self, v: _View) -> Any:
        cfg = self.config
        yaw_cdeg = int(math.degrees(self._angles(v)[2]) * 100) % 36000
        return self._mav.global_position_int_encode(
            v.time_boot_ms,
            int(cfg.home_lat_deg * 1e7),
            int(cfg.home_lon_deg * 1e7),
            int((cfg.home_amsl_m + v.altitude_m) * 1000),
            int(v.altitude_m * 1000),
            0,
            0,
            int(-v.climb_mps * 100),
            yaw_cdeg,
        )

    def _gps_raw(self, v: _View) -> Any:
        cfg = self.config
        fix = mavlink.GPS_FIX_TYPE_3D_FIX if v.gps_ok else mavlink.GPS_FIX_TYPE_NO_FIX
        return self._mav.gps_raw_int_encode(
            v.time_boot_ms * 1000,
            fix,
            int(cfg.home_lat_deg * 1e7),
            int(cfg.home_lon_deg * 1e7),
            int((cfg.home_amsl_m + v.altitude_m) * 1000),
            80,
            120,
            0,
            65535,
            12 if v.gps_ok else 0,
        )

    def _home_position(self, v: _View) -> Any:
        cfg = self.config
        return self._mav.home_position_encode(
            int(cfg.home_lat_deg * 1e7),
            int(cfg.home_lon_deg * 1e7),
            int(cfg.home_amsl_m * 1000),
            0.0,
            0.0,
            0.0,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            v.time_boot_ms * 1000,
        )

    def _autopilot_version(self, _v: _View) -> Any:
        major, minor, patch = _FIRMWARE[self.stack]
        version = (major << 24) | (minor << 16) | (patch << 8) | _FIRMWARE_VERSION_TYPE_OFFICIAL
        return self._mav.autopilot_version_encode(
            _CAPABILITIES | _PARAM_ENCODING[self.stack],
            version,
            0,
            0,
            0,
            list(b"roostsim"),
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x524F4F5354000000 | self.sysid,  # "ROOST" + sysid: unique per sim
        )

    def _noise(self, now: float) -> list[bytes]:
        frames: list[bytes] = []
        if self._garbage_bytes_per_s > 0 and now >= self._next_noise:
            self._next_noise = now + _NOISE_PERIOD_S
            size = max(1, int(self._garbage_bytes_per_s * _NOISE_PERIOD_S))
            corrupted = bytearray(self._heartbeat(self._view()).pack(mavlink.MAVLink(None)))
            corrupted[len(corrupted) // 2] ^= 0xFF  # a real-looking frame failing its CRC
            frames.append(os.urandom(size) + bytes(corrupted))
        if self._spoof_sysid is not None and now >= self._next_spoof:
            self._next_spoof = now + _SPOOF_PERIOD_S
            frames.extend(self._spoof_frames())
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
            self._mav.send(message)

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
                    _log.exception("%s: failed to handle %s", self.name, message)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        replies: list[Any] = []
        with self._lock:
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
            elif kind == "MISSION_REQUEST_LIST" and self._for_us(msg):
                # No mission, fence or rally points are stored: say so.
                replies = [
                    self._mav.mission_count_encode(
                        msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type
                    )
                ]
            elif kind != "HEARTBEAT":
                self._unhandled[kind] += 1
        for reply in replies:
            self._send(reply)

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

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return MavResult.DENIED  # HEARTBEAT stays at 1 Hz on both stacks
        if not math.isfinite(interval_us) or msg_id not in DEFAULT_RATES:
            return MavResult.DENIED
        if interval_us < 0:
            hz = 0.0
        elif interval_us == 0:
            hz = DEFAULT_RATES[msg_id]
        else:
            hz = 1e6 / interval_us
        self.set_rate(msg_id, hz)
        return MavResult.ACCEPTED

    def _get_interval(self, msg_id: int) -> tuple[int, list[Any]]:
        if msg_id not in DEFAULT_RATES:
            return MavResult.DENIED, []
        hz = self._streams.rates.get(msg_id, 0.0)
        interval = int(1e6 / hz) if hz > 0 else -1
        return MavResult.ACCEPTED, [self._mav.message_interval_encode(msg_id, interval)]

    def _request(self, msg_id: int) -> tuple[int, list[Any]]:
        if msg_id not in DEFAULT_RATES:
            return MavResult.DENIED, []
        return MavResult.ACCEPTED, [self._build(msg_id)]


def message_id(message_name: str) -> int:
    """Message id for a name such as ``ATTITUDE`` (for :meth:`SimulatedAutopilot.set_rate`)."""
    value = getattr(mavlink, f"MAVLINK_MSG_ID_{message_name.upper()}", None)
    if not isinstance(value, int):
        raise KeyError(f"unknown MAVLink message {message_name!r}")
    return value
