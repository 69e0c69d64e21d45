"""Real MAVLink frames for tests: pymavlink's encoder and parser, and a ground client's
message as the hub reads it (the agent's codec).

The hub's pure parts (``tests/unit``) and its routing through a bound endpoint
(``tests/integration``) build and read frames the same way.
"""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_mavlink.codec import scan

VEHICLE = 42
"""The hub's system id in these tests (the vehicle as ground clients see it)."""


def encode(msg: Any, sysid: int = 1, component: int = 1) -> bytes:
    return bytes(msg.pack(mavlink.MAVLink(None, sysid, component)))


def parse(frame: bytes) -> Any:
    parser = mavlink.MAVLink(None)
    return parser.parse_char(frame)


def heartbeat() -> Any:
    return mavlink.MAVLink_heartbeat_message(2, 12, 128 | 1, 4, 4, 3)


def client_msg(msg: Any) -> Any:
    """A client's message as the hub reads it (the agent's codec)."""
    ((frame,), _) = scan(encode(msg, sysid=255, component=190))
    return frame
