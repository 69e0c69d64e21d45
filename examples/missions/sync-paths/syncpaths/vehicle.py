"""The follower's one way to its vehicle: :class:`Vehicle`, over MAVLink with pymavlink.

The follower needs five things of a vehicle: where it is, take off, fly position
setpoints, and land. On a Roost vehicle the agent's MAVLink hub is the endpoint (the
vehicle's sysid, routed to whichever autopilot is active; ``MAVLINK_URL``, default
``udpout:127.0.0.1:14550``). A mavros-based implementation would subscribe to
``/mavros/local_position/pose`` and publish ``/mavros/setpoint_position/local`` behind
the same methods; nothing else in the package changes.

Modes by stack: PX4 flies setpoints in OFFBOARD (main mode 6) and needs a setpoint stream
before it accepts the switch; ArduCopter flies them in GUIDED (4) and takes off there.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Protocol

from pymavlink import mavutil

from syncpaths.trajectory import Point

PX4_OFFBOARD = (6, 0)  # main mode, sub mode
PX4_LAND = (4, 6)  # AUTO.LAND
ARDUPILOT_GUIDED = 4
ARDUPILOT_LAND = 9
POSITION_ONLY = 0b0000_1111_1111_1000  # SET_POSITION_TARGET type_mask: x, y, z only
COMMAND_TRIES = 3  # a command and two resends ...
COMMAND_TRY_S = 1.0  # ... each waited for this long for its answer


class Vehicle(Protocol):
    def position(self) -> Point | None: ...
    def take_off(self, altitude_m: float, timeout_s: float = 30.0) -> None: ...
    def fly_setpoints(self, first: Point) -> None: ...
    def send_setpoint(self, point: Point) -> None: ...
    def land(self) -> None: ...


class MavlinkVehicle:
    """A vehicle on a MAVLink endpoint (``udpout:host:port``, ``udpin:``, serial ...)."""

    def __init__(self, url: str, *, source_system: int = 245) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            url, source_system=source_system, source_component=191
        )
        self.target: tuple[int, int] | None = None
        self.px4 = False
        self._position: Point | None = None
        self._acks: dict[int, int] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, name="mavlink-read", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        last_beat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_beat >= 1.0:  # a companion computer's heartbeat
                self.conn.mav.heartbeat_send(
                    mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                    mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0,
                )  # fmt: skip
                last_beat = now
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is None:
                continue
            kind = msg.get_type()
            with self._lock:
                if kind == "HEARTBEAT" and msg.type != mavutil.mavlink.MAV_TYPE_GCS:
                    if msg.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                        self.target = (msg.get_srcSystem(), msg.get_srcComponent())
                        self.px4 = msg.autopilot == mavutil.mavlink.MAV_AUTOPILOT_PX4
                elif kind == "LOCAL_POSITION_NED":
                    self._position = (msg.x, msg.y, msg.z)
                elif kind == "COMMAND_ACK":
                    self._acks[msg.command] = msg.result

    def close(self) -> None:
        self._stop.set()
        self._reader.join(timeout=2)
        self.conn.close()

    def wait_connected(self, timeout_s: float = 15.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self.target is None or self._position is None:
            if time.monotonic() > deadline:
                raise TimeoutError("no autopilot heartbeat and position on the MAVLink endpoint")
            if self.target is not None:
                self._request_position()
            time.sleep(0.1)

    def _request_position(self) -> None:
        self._command(
            mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000, wait=False,
        )  # fmt: skip

    def position(self) -> Point | None:
        with self._lock:
            return self._position

    def _command(self, command: int, *params: float, wait: bool = True) -> int | None:
        """Send a COMMAND_LONG and return its COMMAND_ACK's result.

        A command or its answer lost on the link is sent again, as the MAVLink command
        protocol has it: the same command with its confirmation field counting the
        resends, which an autopilot answers whether or not it acted on an earlier copy.
        """
        assert self.target is not None
        full = (list(params) + [0.0] * 7)[:7]
        with self._lock:
            self._acks.pop(command, None)
        for confirmation in range(COMMAND_TRIES):
            self.conn.mav.command_long_send(*self.target, command, confirmation, *full)
            if not wait:
                return None
            deadline = time.monotonic() + COMMAND_TRY_S
            while time.monotonic() < deadline:
                with self._lock:
                    if command in self._acks:
                        return self._acks[command]
                time.sleep(0.02)
        raise TimeoutError(f"no answer to command {command} in {COMMAND_TRIES} tries")

    def _mode(self, px4: tuple[int, int], ardupilot: int) -> int | None:
        params = (1, *px4) if self.px4 else (1, ardupilot)
        return self._command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, *params)

    def take_off(self, altitude_m: float, timeout_s: float = 30.0) -> None:
        accepted = mavutil.mavlink.MAV_RESULT_ACCEPTED
        if not self.px4 and self._mode(PX4_OFFBOARD, ARDUPILOT_GUIDED) != accepted:
            raise RuntimeError("GUIDED refused")
        deadline = time.monotonic() + timeout_s
        # an autopilot still starting up refuses to arm for a while: ask again
        while self._command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) != accepted:
            if time.monotonic() > deadline:
                raise RuntimeError("arming refused")
            time.sleep(0.5)
        alt = math.nan if self.px4 else altitude_m  # PX4: its takeoff altitude (AMSL param)
        if (
            self._command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, alt)
            != accepted
        ):
            raise RuntimeError("takeoff refused")
        while (p := self.position()) is None or -p[2] < min(altitude_m, 2.0) * 0.8:
            if time.monotonic() > deadline:
                raise TimeoutError("did not climb")
            time.sleep(0.1)

    def fly_setpoints(self, first: Point) -> None:
        """Into the setpoint mode; PX4 needs setpoints flowing before the switch."""
        self.send_setpoint(first)
        if self._mode(PX4_OFFBOARD, ARDUPILOT_GUIDED) != mavutil.mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError("the setpoint mode was refused")

    def send_setpoint(self, point: Point) -> None:
        assert self.target is not None
        self.conn.mav.set_position_target_local_ned_send(
            0, *self.target, mavutil.mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY,
            *point, 0, 0, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip

    def land(self) -> None:
        self._mode(PX4_LAND, ARDUPILOT_LAND)
