"""The simulated autopilot's SD card: one log per armed interval, served over MAVLink.

Like the real flight stacks, the sim logs from arming to disarming and keeps its logs
across reboots, and a ground station or the agent downloads them with the MAVLink log
protocol: ``LOG_REQUEST_LIST`` is answered with one ``LOG_ENTRY`` per log (one entry
with ``id 0, num_logs 0`` when there is none), ``LOG_REQUEST_DATA(id, ofs, count)``
with ``LOG_DATA`` messages of up to 90 bytes (``count 0`` at or past the end of the
file), ``LOG_REQUEST_END`` stops a transfer, ``LOG_ERASE`` empties the card. While
armed both stacks ignore log requests (they are writing the log), and so does the sim.
The data is paced (:attr:`SimLogs.rate_bytes_per_s`) as an autopilot's MAVLink
bandwidth budget does.

The formats are the real ones, small but complete:

- PX4: a ULog (``.ulg``): the 16-byte header, flag bits, info (``sys_name``,
  ``ver_sw``), parameters, formats of ``vehicle_local_position`` and
  ``vehicle_status``, their data at 10 Hz, logged messages (arming, disarming).
- ArduPilot: a DataFlash binary log (``.bin``): ``FMT`` records first (the one that
  describes ``FMT`` itself, then ``PARM``, ``MSG``, ``MODE``, ``GPS``, ``BARO``), the
  parameters, and the samples; pymavlink's ``DFReader`` (MAVExplorer, Mission Planner's
  reader) reads it.

Tests damage a log (:attr:`SimLogs.damage_next`, :meth:`SimLogs.truncate`,
:meth:`SimLogs.corrupt`) as a worn SD card or a stack killed while writing would.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from roost_api.core import Stack

LOG_DATA_BYTES = 90
DEFAULT_RATE_BYTES_PER_S = 150_000.0
SAMPLE_PERIOD_S = 0.1
MAX_BURST = 24  # LOG_DATA messages per tick at most (a burst is spread, not dumped)
ULOG_MAGIC = b"ULog\x01\x12\x35"
ULOG_SYNC = bytes((0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12))
DATAFLASH_HEAD = b"\xa3\x95"
GPS_EPOCH_UNIX_S = 315964800
GPS_LEAP_S = 18
EARTH_RADIUS_M = 6_378_137.0


@dataclass(frozen=True)
class Sample:
    boot_us: int
    unix_us: int
    north_m: float
    east_m: float
    altitude_m: float
    climb_mps: float
    armed: bool
    mode: int
    mode_name: str


@dataclass
class StoredLog:
    id: int
    time_utc: int
    data: bytes
    listed_size: int  # what LOG_ENTRY says (a truncated file says more than it has)


@dataclass
class _Transfer:
    log_id: int
    ofs: int
    end: int
    channel: tuple[int, int]  # (system, component) of the requester


@dataclass
class SimLogs:
    """One autopilot's logs (kept across reboots) and its current transfer."""

    stack: Stack
    params: Callable[[], dict[str, float]]
    home: tuple[float, float] = (47.397742, 8.545594)
    rate_bytes_per_s: float = DEFAULT_RATE_BYTES_PER_S
    logs: list[StoredLog] = field(default_factory=list)
    _samples: list[Sample] | None = None
    _next_sample: float = 0.0
    _transfer: _Transfer | None = None
    _credit: float = 0.0
    _last: float | None = None
    served_bytes: int = 0
    # What happens to the next log written: "truncate" (the stack died while writing:
    # the file ends early, the listing says the full size) or "corrupt" (its header
    # is overwritten). Tests set it; cleared once used.
    damage_next: str | None = None

    # -- logging while armed -----------------------------------------------------------

    def note(self, view: Any, now: float) -> None:
        """Called every tick with the autopilot's view: logs from arming to disarming."""
        if view.armed and self._samples is None:
            self._samples = []
            self._next_sample = now
        if self._samples is not None and now >= self._next_sample:
            self._next_sample = now + SAMPLE_PERIOD_S
            self._samples.append(
                Sample(
                    int(view.time_boot_ms) * 1000,
                    int(view.unix_usec),
                    float(view.north_m),
                    float(view.east_m),
                    float(view.altitude_m),
                    float(view.climb_mps),
                    bool(view.armed),
                    int(view.custom_mode),
                    str(view.mode),
                )
            )
        if not view.armed and self._samples is not None:
            samples, self._samples = self._samples, None
            self._store(samples)

    @property
    def samples_logging(self) -> int:
        """Samples in the log being written (0 while disarmed)."""
        return 0 if self._samples is None else len(self._samples)

    def _store(self, samples: list[Sample]) -> None:
        if not samples:
            return
        params = self.params()
        if self.stack is Stack.PX4:
            data = ulog_bytes(samples, params)
        else:
            data = dataflash_bytes(samples, params, self.home)
        log_id = (self.logs[-1].id if self.logs else 0) + 1
        self.logs.append(StoredLog(log_id, samples[0].unix_us // 1_000_000, data, len(data)))
        damage, self.damage_next = self.damage_next, None
        if damage == "truncate":
            self.truncate(log_id, len(data) * 2 // 3)
        elif damage == "corrupt":
            self.corrupt(log_id)

    # -- damage (tests) ----------------------------------------------------------------

    def truncate(self, log_id: int, keep: int) -> None:
        """The file ends after ``keep`` bytes; the listing still says the full size."""
        stored = self._find(log_id)
        if stored is not None:
            stored.data = stored.data[:keep]

    def corrupt(self, log_id: int) -> None:
        """The file's first bytes are overwritten (its header no longer says what it is)."""
        stored = self._find(log_id)
        if stored is not None:
            stored.data = b"\xff" * 16 + stored.data[16:]

    def _find(self, log_id: int) -> StoredLog | None:
        return next((s for s in self.logs if s.id == log_id), None)

    # -- the log protocol --------------------------------------------------------------

    def handle(self, msg: Any, mav: Any, armed: bool) -> list[Any]:
        """Answers to one LOG_* request (none while armed)."""
        kind = msg.get_type()
        if armed:
            self._transfer = None
            return []
        if kind == "LOG_REQUEST_LIST":
            if not self.logs:
                return [mav.log_entry_encode(0, 0, 0, 0, 0)]
            last = self.logs[-1].id
            return [
                mav.log_entry_encode(s.id, len(self.logs), last, s.time_utc, s.listed_size)
                for s in self.logs
                if msg.start <= s.id <= msg.end
            ]
        if kind == "LOG_REQUEST_DATA":
            stored = self._find(int(msg.id))
            if stored is None:
                return []
            end = min(int(msg.ofs) + int(msg.count), 1 << 32)
            channel = (msg.get_srcSystem(), msg.get_srcComponent())
            self._transfer = _Transfer(stored.id, int(msg.ofs), end, channel)
            return []
        if kind == "LOG_REQUEST_END":
            self._transfer = None
        elif kind == "LOG_ERASE":
            self.logs.clear()
            self._transfer = None
        return []

    def forget_transfer(self) -> None:
        """A reboot forgets the transfer in progress (the card keeps the logs)."""
        self._transfer = None

    def pending(self, now: float, mav: Any) -> list[Any]:
        """The LOG_DATA due by ``now`` (paced at :attr:`rate_bytes_per_s`)."""
        transfer = self._transfer
        last, self._last = self._last, now
        if transfer is None:
            self._credit = 0.0
            return []
        if last is not None:
            self._credit = min(
                self._credit + (now - last) * self.rate_bytes_per_s,
                MAX_BURST * LOG_DATA_BYTES,
            )
        stored = self._find(transfer.log_id)
        out: list[Any] = []
        while transfer.ofs < transfer.end and self._credit >= LOG_DATA_BYTES:
            data = b"" if stored is None else stored.data[transfer.ofs : transfer.ofs + 90]
            count = min(len(data), transfer.end - transfer.ofs)
            payload = list(data[:count].ljust(LOG_DATA_BYTES, b"\0"))
            out.append(mav.log_data_encode(transfer.log_id, transfer.ofs, count, payload))
            self._credit -= LOG_DATA_BYTES
            self.served_bytes += count
            if count == 0:  # past the end of the file: said once, then the transfer is over
                transfer.end = transfer.ofs
                break
            transfer.ofs += count
        if transfer.ofs >= transfer.end:
            self._transfer = None
        return out


# -- ULog (PX4) -----------------------------------------------------------------------


def _ulog_message(kind: bytes, body: bytes) -> bytes:
    return struct.pack("<HB", len(body), kind[0]) + body


def _ulog_info(key: str, value: bytes) -> bytes:
    k = key.encode()
    return _ulog_message(b"I", bytes([len(k)]) + k + value)


def ulog_bytes(samples: list[Sample], params: dict[str, float]) -> bytes:
    """A ULog file (version 1) of ``samples`` with ``params`` as its parameters."""
    start = samples[0].boot_us
    out = bytearray(ULOG_MAGIC + b"\x01" + struct.pack("<Q", start))
    out += _ulog_message(b"B", bytes(8) + bytes(8) + bytes(24))  # flag bits: nothing special
    sys_name = b"PX4"
    out += _ulog_info(f"char[{len(sys_name)}] sys_name", sys_name)
    out += _ulog_info("uint32_t ver_sw_release", struct.pack("<I", 0x010F0000))
    out += _ulog_info("uint64_t time_ref_utc", struct.pack("<Q", 0))
    for name, value in sorted(params.items()):
        if float(value).is_integer() and abs(value) < 2**31:
            k = f"int32_t {name}".encode()
            out += _ulog_message(b"P", bytes([len(k)]) + k + struct.pack("<i", int(value)))
        else:
            k = f"float {name}".encode()
            out += _ulog_message(b"P", bytes([len(k)]) + k + struct.pack("<f", value))
    formats = {
        "vehicle_local_position": "uint64_t timestamp;float x;float y;float z;float vz;",
        # No trailing padding: a ULog writer leaves it out of the data messages.
        "vehicle_status": "uint64_t timestamp;uint8_t arming_state;uint8_t nav_state;",
    }
    for name, fields in formats.items():
        out += _ulog_message(b"F", f"{name}:{fields}".encode())
    out += _ulog_message(b"A", struct.pack("<BH", 0, 0) + b"vehicle_local_position")
    out += _ulog_message(b"A", struct.pack("<BH", 0, 1) + b"vehicle_status")
    out += _ulog_message(b"S", ULOG_SYNC)
    out += _ulog_message(b"L", struct.pack("<BQ", ord("6"), start) + b"Armed by the agent")
    mode = None
    for s in samples:
        position = struct.pack(
            "<Qffff", s.boot_us, s.north_m, s.east_m, -s.altitude_m, -s.climb_mps
        )
        out += _ulog_message(b"D", struct.pack("<H", 0) + position)
        if s.mode != mode:
            mode = s.mode
            status = struct.pack("<QBB", s.boot_us, 2 if s.armed else 1, (s.mode >> 24) & 0xFF)
            out += _ulog_message(b"D", struct.pack("<H", 1) + status)
    end = samples[-1].boot_us
    out += _ulog_message(b"L", struct.pack("<BQ", ord("6"), end) + b"Disarmed")
    return bytes(out)


# -- DataFlash (ArduPilot) ------------------------------------------------------------

_FMT_TYPE = 128
_DF_TYPES: dict[str, tuple[int, str, str]] = {
    # name: (type id, format, columns)
    "PARM": (64, "QNf", "TimeUS,Name,Value"),
    "MSG": (65, "QZ", "TimeUS,Message"),
    "MODE": (66, "QMBB", "TimeUS,Mode,ModeNum,Rsn"),
    "GPS": (67, "QBIHBLLf", "TimeUS,Status,GMS,GWk,NSats,Lat,Lng,Alt"),
    "BARO": (68, "Qff", "TimeUS,Alt,CRt"),
}
_DF_SIZES = {"Q": 8, "N": 16, "f": 4, "Z": 64, "M": 1, "B": 1, "I": 4, "H": 2, "L": 4}
_DF_STRUCT = {
    "Q": "Q",
    "N": "16s",
    "f": "f",
    "Z": "64s",
    "M": "B",
    "B": "B",
    "I": "I",
    "H": "H",
    "L": "i",
}


def _df_length(fmt: str) -> int:
    return 3 + sum(_DF_SIZES[c] for c in fmt)


def _df_fmt(type_id: int, name: str, fmt: str, columns: str) -> bytes:
    length = 89 if type_id == _FMT_TYPE else _df_length(fmt)
    return DATAFLASH_HEAD + struct.pack(
        "<BBB4s16s64s",
        _FMT_TYPE,
        type_id,
        length,
        name.encode(),
        fmt.encode(),
        columns.encode(),
    )


def _df_record(name: str, *values: Any) -> bytes:
    type_id, fmt, _ = _DF_TYPES[name]
    layout = "<" + "".join(_DF_STRUCT[c] for c in fmt)
    return DATAFLASH_HEAD + bytes([type_id]) + struct.pack(layout, *values)


def _gps_time(unix_us: int) -> tuple[int, int]:
    """(GPS week, milliseconds of the week) of a UNIX time."""
    gps_s = unix_us / 1e6 - GPS_EPOCH_UNIX_S + GPS_LEAP_S
    week = int(gps_s // 604800)
    return week, int((gps_s - week * 604800) * 1000)


def dataflash_bytes(
    samples: list[Sample], params: dict[str, float], home: tuple[float, float]
) -> bytes:
    """A DataFlash binary log of ``samples`` with ``params``."""
    out = bytearray(_df_fmt(_FMT_TYPE, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    for name, (type_id, fmt, columns) in _DF_TYPES.items():
        out += _df_fmt(type_id, name, fmt, columns)
    first = samples[0].boot_us
    for name, value in sorted(params.items()):
        out += _df_record("PARM", first, name.encode()[:16], float(value))
    out += _df_record("MSG", first, b"ArduCopter V4.5.7 (simulated)")
    lat0, lon0 = home
    mode = None
    for s in samples:
        if s.mode != mode:
            mode = s.mode
            out += _df_record("MODE", s.boot_us, s.mode & 0xFF, s.mode & 0xFF, 0)
        lat = lat0 + math.degrees(s.north_m / EARTH_RADIUS_M)
        lon = lon0 + math.degrees(s.east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        week, ms = _gps_time(s.unix_us)
        out += _df_record(
            "GPS", s.boot_us, 3, ms, week, 12, int(lat * 1e7), int(lon * 1e7), s.altitude_m
        )
        out += _df_record("BARO", s.boot_us, s.altitude_m, s.climb_mps)
    out += _df_record("MSG", samples[-1].boot_us, b"Disarmed")
    return bytes(out)
