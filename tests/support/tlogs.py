"""Flights written as a MAVLink telemetry log (``.tlog``) with pymavlink's own encoder,
plus the agent's decisions beside them, for the records plotting tests and benchmark.

A tlog is what the agent's recorder writes: each frame after an 8-byte big-endian
microsecond UNIX time. Two autopilots (system ids 1 and 2, ArduCopter) fly a climb,
a leg east and a descent; the active one fails over to the standby halfway (a health
change, then the failover and the safety routine in ``decisions.jsonl``).
"""

from __future__ import annotations

import json
import math
import struct
from datetime import UTC, datetime
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

GUIDED, LAND = 4, 9
HOME = (47.3977, 8.5456)


def _frame(
    out: bytearray, when: float, message: mavlink.MAVLink_message, sender: mavlink.MAVLink
) -> None:
    out += struct.pack(">Q", int(when * 1e6)) + message.pack(sender)


def write_flight(
    directory: Path, start: float, duration_s: float = 60.0, rate_hz: float = 10.0
) -> dict[str, bytes]:
    """``hub.tlog``, ``decisions.jsonl`` and both autopilots' params under ``directory``;
    returns them by path (relative to the flight)."""
    senders = {sysid: mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1) for sysid in (1, 2)}
    out = bytearray()
    steps = int(duration_s * rate_hz)
    switch = duration_s / 2
    for step in range(steps):
        t = step / rate_hz
        climb = min(t / 10, 1.0) * 20 if t < duration_s - 10 else (duration_s - t) / 10 * 20
        east = max(0.0, t - 10) * 0.8
        north = 5 * math.sin(t / 10)
        lat = HOME[0] + north / 6_371_000 * 180 / math.pi
        lon = HOME[1] + east / (6_371_000 * math.cos(math.radians(HOME[0]))) * 180 / math.pi
        for sysid, sender in senders.items():
            if step % int(rate_hz) == 0:
                mode = LAND if (sysid == 2 and t >= switch + 1) else GUIDED
                heartbeat = sender.heartbeat_encode(2, 3, 1 | 128, mode, 4)
                _frame(out, start + t, heartbeat, sender)
            position = sender.global_position_int_encode(
                int(t * 1000), int(lat * 1e7), int(lon * 1e7), int((400 + climb) * 1000),
                int(climb * 1000), 80, 0, 0, 9000,
            )  # fmt: skip
            _frame(out, start + t, position, sender)

    def at(offset: float) -> str:
        return datetime.fromtimestamp(start + offset, UTC).isoformat()

    events = [
        {"event": "HealthChanged", "autopilot": "ap-a", "reason": "Unhealthy",
         "message": "GPS lost", "time": at(switch - 1),
         "health": {"name": "ap-a", "level": "ERROR"}},
        {"event": "Failover", "autopilot": "ap-b", "reason": "FailedOver",
         "message": "ap-a -> ap-b: GPS lost", "time": at(switch), "latencyMs": 42.0},
        {"event": "SafetyRoutine", "autopilot": "ap-b", "reason": "SafetyRoutine",
         "message": "hold, then land", "time": at(switch + 1)},
        {"event": "HealthChanged", "autopilot": "ap-b", "reason": "Healthy", "message": "",
         "time": at(1), "health": {"name": "ap-b", "level": "OK"}},
    ]  # fmt: skip
    files = {
        "hub.tlog": bytes(out),
        "decisions.jsonl": "".join(json.dumps(e) + "\n" for e in events).encode(),
        "params/ap-a.json": json.dumps({"SYSID_THISMAV": 1}).encode(),
        "params/ap-b.json": json.dumps({"SYSID_THISMAV": 2}).encode(),
    }
    for path, data in files.items():
        (directory / path).parent.mkdir(parents=True, exist_ok=True)
        (directory / path).write_bytes(data)
    return files
