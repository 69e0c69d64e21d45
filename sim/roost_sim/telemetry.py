"""Telemetry messages of a simulated autopilot, built from one frozen view of its state.

Why a view: the ``freeze`` fault repeats the values of one instant verbatim, so every
builder reads a :class:`View` (taken under the autopilot's lock) and nothing else. The
values follow the recordings of the real firmware where the agent reads them (base_mode
per stack, SYS_STATUS battery fields, ESTIMATOR_STATUS / EKF_STATUS_REPORT flags, landed
state) and are plausible elsewhere (a gentle attitude wobble, fixed home position).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import all as mavlink

from roost_api.meta import Stack
from roost_mavlink import (
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    heartbeat_autopilot,
)
from roost_mavlink.status import MAV_TYPE_QUADROTOR, MavLandedState, MavState
from roost_sim.battery import BatteryReading
from roost_sim.kinematics import global_from_ned
from roost_sim.model import Sensors, SimConfig

_STABILIZE = mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
_GUIDED = mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
_AUTO = mavlink.MAV_MODE_FLAG_AUTO_ENABLED
_MANUAL = mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
# ArduCopter sets GUIDED_ENABLED in these modes (base_mode 89 vs 81 in STABILIZE).
_ARDUPILOT_GUIDED_FLAG_MODES = frozenset(
    {"AUTO", "RTL", "LOITER", "AVOID_ADSB", "FOLLOW", "GUIDED", "CIRCLE", "POSHOLD", "BRAKE",
     "SMART_RTL"}
)  # fmt: skip


@dataclass(frozen=True)
class View:
    """The values that go into telemetry at one instant (repeated verbatim when frozen)."""

    time_boot_ms: int
    unix_usec: int
    armed: bool
    custom_mode: int
    mode: str
    system_status: int
    landed_state: int
    altitude_m: float
    climb_mps: float
    north_m: float
    east_m: float
    vn_mps: float
    ve_mps: float
    yaw_rad: float
    sensors: Sensors
    gps_ok: bool
    estimator_flags: int
    battery: BatteryReading
    has_position: bool


class Telemetry:
    """Encodes each message the sim can send, for one stack and system."""

    def __init__(self, mav: Any, stack: Stack, sysid: int, config: SimConfig) -> None:
        self._mav = mav
        self.stack = stack
        self.sysid = sysid
        self.config = config
        names: dict[str, Callable[[View], Any]] = {
            "HEARTBEAT": self.heartbeat,
            "SYS_STATUS": self.sys_status,
            "EXTENDED_SYS_STATE": self.extended_sys_state,
            "ATTITUDE": self.attitude,
            "ATTITUDE_QUATERNION": self.attitude_quaternion,
            "GLOBAL_POSITION_INT": self.global_position,
            "LOCAL_POSITION_NED": self.local_position,
            "ODOMETRY": self.odometry,
            "HIGHRES_IMU": self.highres_imu,
            "ALTITUDE": self.altitude,
            "ATTITUDE_TARGET": self.attitude_target,
            "DISTANCE_SENSOR": self.distance_sensor,
            "POSITION_TARGET_LOCAL_NED": self.position_target_local,
            "POSITION_TARGET_GLOBAL_INT": self.position_target_global,
            "SERVO_OUTPUT_RAW": self.servo_output_raw,
            "TIMESYNC": self.timesync,
            "VFR_HUD": self.vfr_hud,
            "GPS_RAW_INT": self.gps_raw,
            "ESTIMATOR_STATUS": self.estimator_status,
            "EKF_STATUS_REPORT": self.ekf_status_report,
            "MISSION_CURRENT": self.mission_current,
            "OPEN_DRONE_ID_LOCATION": self.open_drone_id_location,
            "OPEN_DRONE_ID_SYSTEM": self.open_drone_id_system,
            "PING": self.ping,
            "SCALED_PRESSURE": self.scaled_pressure,
            "SYSTEM_TIME": self.system_time,
            "BATTERY_STATUS": self.battery_status,
            "CURRENT_MODE": self.current_mode,
            "HOME_POSITION": self.home_position,
            "GPS_GLOBAL_ORIGIN": self.gps_global_origin,
            "VIBRATION": self.vibration,
        }
        self.builders: dict[int, Callable[[View], Any]] = {
            int(getattr(mavlink, f"MAVLINK_MSG_ID_{name}")): build for name, build in names.items()
        }
        self._ping_seq = 0

    # ---- helpers ---------------------------------------------------------------------

    def _lat_lon(self, v: View) -> tuple[int, int]:
        lat, lon = global_from_ned(
            v.north_m, v.east_m, self.config.home_lat_deg, self.config.home_lon_deg
        )
        return round(lat * 1e7), round(lon * 1e7)

    def _home_lat_lon(self) -> tuple[int, int]:
        return int(self.config.home_lat_deg * 1e7), int(self.config.home_lon_deg * 1e7)

    def _amsl_mm(self, v: View) -> int:
        return int((self.config.home_amsl_m + v.altitude_m) * 1000)

    @staticmethod
    def angles(v: View) -> tuple[float, float, float, float, float, float]:
        """Roll, pitch, yaw and their rates: the heading with a gentle wobble that changes
        every sample (yaw in -pi..pi, as the stacks send it)."""
        t = v.time_boot_ms / 1000.0
        amp = 0.03 if v.landed_state != MavLandedState.ON_GROUND else 0.002
        roll, pitch = amp * math.sin(1.3 * t), amp * math.sin(0.9 * t + 1.0)
        yaw = math.remainder(v.yaw_rad + 0.01 * math.sin(0.2 * t), math.tau)
        return (
            roll,
            pitch,
            yaw,
            amp * 1.3 * math.cos(1.3 * t),
            amp * 0.9 * math.cos(0.9 * t + 1.0),
            0.002 * math.cos(0.2 * t),
        )

    def _quaternion(self, v: View) -> list[float]:
        roll, pitch, yaw = self.angles(v)[:3]
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        return [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]

    def _flying(self, v: View) -> bool:
        return v.landed_state != MavLandedState.ON_GROUND

    # ---- messages --------------------------------------------------------------------

    def base_mode(self, v: View) -> int:
        """The heartbeat's base_mode as each stack fills it (PX4 29/157, ArduCopter 81/89/217)."""
        armed = MAV_MODE_FLAG_SAFETY_ARMED if v.armed else 0
        if self.stack is Stack.PX4:
            return int(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | _STABILIZE | _GUIDED | _AUTO | armed)
        guided = v.mode in _ARDUPILOT_GUIDED_FLAG_MODES or v.system_status == MavState.BOOT
        flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | _STABILIZE | _MANUAL
        return int(flags | (_GUIDED if guided else 0) | armed)

    def heartbeat(self, v: View) -> Any:
        return self._mav.heartbeat_encode(
            MAV_TYPE_QUADROTOR,
            heartbeat_autopilot(self.stack),
            self.base_mode(v),
            v.custom_mode,
            v.system_status,
        )

    def sys_status(self, v: View) -> Any:
        b = v.battery
        return self._mav.sys_status_encode(
            v.sensors.present,
            v.sensors.enabled,
            v.sensors.health,
            250,  # load 25.0 %
            b.voltage_mv,
            b.current_ca,
            b.remaining_percent,
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def extended_sys_state(self, v: View) -> Any:
        vtol = mavlink.MAV_VTOL_STATE_MC if self.stack is Stack.ARDUPILOT else 0
        return self._mav.extended_sys_state_encode(vtol, v.landed_state)

    def attitude(self, v: View) -> Any:
        return self._mav.attitude_encode(v.time_boot_ms, *self.angles(v))

    def attitude_quaternion(self, v: View) -> Any:
        rates = self.angles(v)[3:]
        return self._mav.attitude_quaternion_encode(
            v.time_boot_ms, *self._quaternion(v), *rates, [0.0, 0.0, 0.0, 0.0]
        )

    def global_position(self, v: View) -> Any:
        lat, lon = self._lat_lon(v)
        yaw_cdeg = int(math.degrees(self.angles(v)[2]) * 100) % 36000
        return self._mav.global_position_int_encode(
            v.time_boot_ms,
            lat,
            lon,
            self._amsl_mm(v),
            int(v.altitude_m * 1000),
            int(v.vn_mps * 100),
            int(v.ve_mps * 100),
            int(-v.climb_mps * 100),
            yaw_cdeg,
        )

    def local_position(self, v: View) -> Any:
        return self._mav.local_position_ned_encode(
            v.time_boot_ms, v.north_m, v.east_m, -v.altitude_m, v.vn_mps, v.ve_mps, -v.climb_mps
        )

    def odometry(self, v: View) -> Any:
        nan = math.nan
        covariance = [0.26, *([nan] * 5), 0.26, *([nan] * 4), 0.5, *([nan] * 9)]
        return self._mav.odometry_encode(
            v.time_boot_ms * 1000,
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_BODY_FRD,
            v.north_m,
            v.east_m,
            -v.altitude_m,
            self._quaternion(v),
            v.vn_mps,
            v.ve_mps,
            -v.climb_mps,
            *self.angles(v)[3:],
            covariance,
            covariance,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT,
            0,
        )

    def highres_imu(self, v: View) -> Any:
        rates = self.angles(v)[3:]
        return self._mav.highres_imu_encode(
            v.time_boot_ms * 1000,
            0.05,
            -0.05,
            -9.73,
            *rates,
            0.0,
            0.0,
            0.0,
            95578.0,
            0.0,
            self.config.home_amsl_m + v.altitude_m,
            15.0,
            6719,
            0,
        )

    def altitude(self, v: View) -> Any:
        amsl = self.config.home_amsl_m + v.altitude_m
        return self._mav.altitude_encode(
            v.time_boot_ms * 1000, amsl, amsl, -v.altitude_m, v.altitude_m, math.nan, v.altitude_m
        )

    def attitude_target(self, v: View) -> Any:
        return self._mav.attitude_target_encode(
            v.time_boot_ms, 0, self._quaternion(v), 0.0, 0.0, 0.0, 0.5 if v.armed else 0.0
        )

    def distance_sensor(self, v: View) -> Any:
        return self._mav.distance_sensor_encode(
            v.time_boot_ms,
            10,
            4000,
            max(10, int(v.altitude_m * 100)),
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            0,
            mavlink.MAV_SENSOR_ROTATION_PITCH_270,
            0,
        )

    def position_target_local(self, v: View) -> Any:
        return self._mav.position_target_local_ned_encode(
            v.time_boot_ms, mavlink.MAV_FRAME_LOCAL_NED, 0, v.north_m, v.east_m, -v.altitude_m,
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        )  # fmt: skip

    def position_target_global(self, v: View) -> Any:
        lat, lon = self._lat_lon(v)
        return self._mav.position_target_global_int_encode(
            v.time_boot_ms, mavlink.MAV_FRAME_GLOBAL_INT, 0, lat, lon,
            self.config.home_amsl_m + v.altitude_m, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        )  # fmt: skip

    def servo_output_raw(self, v: View) -> Any:
        pwm = 1500 if self._flying(v) else (1100 if v.armed else 900)
        return self._mav.servo_output_raw_encode(
            v.time_boot_ms * 1000, 0, pwm, pwm, pwm, pwm, 0, 0, 0, 0
        )

    def timesync(self, v: View) -> Any:
        return self._mav.timesync_encode(0, v.time_boot_ms * 1_000_000)

    def vfr_hud(self, v: View) -> Any:
        heading = int(math.degrees(self.angles(v)[2])) % 360
        throttle = 50 if self._flying(v) else 0
        amsl = self.config.home_amsl_m + v.altitude_m
        ground = math.hypot(v.vn_mps, v.ve_mps)
        return self._mav.vfr_hud_encode(ground, ground, heading, throttle, amsl, v.climb_mps)

    def gps_raw(self, v: View) -> Any:
        lat, lon = self._lat_lon(v)
        fix = mavlink.GPS_FIX_TYPE_3D_FIX if v.gps_ok else mavlink.GPS_FIX_TYPE_NO_FIX
        return self._mav.gps_raw_int_encode(
            v.time_boot_ms * 1000, fix, lat, lon, self._amsl_mm(v), 80, 120, 0, 65535,
            10 if v.gps_ok else 0,
        )  # fmt: skip

    def estimator_status(self, v: View) -> Any:
        return self._mav.estimator_status_encode(
            v.time_boot_ms * 1000, v.estimator_flags, 0.1, 0.1, 0.1, 0.05, 0.0, 0.0, 0.5, 0.8
        )

    def ekf_status_report(self, v: View) -> Any:
        return self._mav.ekf_status_report_encode(v.estimator_flags, 0.02, 0.01, 0.01, 0.03, 0.0)

    def mission_current(self, _v: View) -> Any:
        return self._mav.mission_current_encode(0, 0, 0, 0)

    def open_drone_id_location(self, v: View) -> Any:
        lat, lon = self._lat_lon(v)
        amsl = self.config.home_amsl_m + v.altitude_m
        return self._mav.open_drone_id_location_encode(
            0, 0, [0] * 20, 2 if self._flying(v) else 1, 0, 0, int(v.climb_mps * 100), lat,
            lon, amsl, amsl, 0, v.altitude_m, 10, 4, 3, 1, (v.time_boot_ms % 3600000) / 1000, 0,
        )  # fmt: skip

    def open_drone_id_system(self, v: View) -> Any:
        lat, lon = self._home_lat_lon()
        return self._mav.open_drone_id_system_encode(
            0, 0, [0] * 20, 0, 0, lat, lon, 1, 0, -1000.0, -1000.0, 0, 0,
            self.config.home_amsl_m, v.unix_usec // 1_000_000 - 1546300800,
        )  # fmt: skip

    def ping(self, v: View) -> Any:
        self._ping_seq = (self._ping_seq + 1) % 2**32
        return self._mav.ping_encode(v.time_boot_ms * 1000, self._ping_seq, 0, 0)

    def scaled_pressure(self, v: View) -> Any:
        return self._mav.scaled_pressure_encode(v.time_boot_ms, 955.8, 0.0, 1500, 0)

    def system_time(self, v: View) -> Any:
        return self._mav.system_time_encode(v.unix_usec, v.time_boot_ms)

    def battery_status(self, v: View) -> Any:
        b = v.battery
        return self._mav.battery_status_encode(
            0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767,
            [b.voltage_mv, *([65535] * 9)], b.current_ca, -1, -1, b.remaining_percent, 0,
            int(b.charge_state), [0, 0, 0, 0], 0, 0,
        )  # fmt: skip

    def current_mode(self, v: View) -> Any:
        return self._mav.current_mode_encode(0, v.custom_mode, v.custom_mode)

    def home_position(self, v: View) -> Any:
        lat, lon = self._home_lat_lon()
        return self._mav.home_position_encode(
            lat, lon, int(self.config.home_amsl_m * 1000), 0.0, 0.0, 0.0,
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, v.time_boot_ms * 1000,
        )  # fmt: skip

    def gps_global_origin(self, v: View) -> Any:
        lat, lon = self._home_lat_lon()
        return self._mav.gps_global_origin_encode(
            lat, lon, int(self.config.home_amsl_m * 1000), v.time_boot_ms * 1000
        )

    def vibration(self, v: View) -> Any:
        return self._mav.vibration_encode(v.time_boot_ms * 1000, 0.01, 0.01, 0.01, 0, 0, 0)
