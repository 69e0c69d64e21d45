"""The fence part of the MAVLink mission protocol, and each stack's fence parameters.

A fence travels as mission items of ``mission_type`` MAV_MISSION_TYPE_FENCE (1) with the
mission protocol's handshakes (https://mavlink.io/en/services/mission.html):

- upload: MISSION_COUNT → the autopilot asks for each item with MISSION_REQUEST_INT
  (ArduPilot may still ask with MISSION_REQUEST) → MISSION_ITEM_INT → after the last, the
  autopilot answers MISSION_ACK (type 0 accepted, else the error);
- download: MISSION_REQUEST_LIST → MISSION_COUNT → MISSION_REQUEST_INT per item →
  MISSION_ITEM_INT → the client ends it with MISSION_ACK.

An inclusion polygon is one MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION (5001) item per
vertex with ``param1`` the vertex count; an inclusion circle is one
MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION (5003) with ``param1`` the radius in metres;
latitude/longitude in ``x``/``y`` as degrees * 1e7. The altitude limit and breach action
are parameters, named and typed per stack (PX4's geofence parameters, ArduPilot's
AC_Fence): see :func:`stack_params`.

:class:`Transfer` is the client side of one upload or download as a pure state machine
(messages in, messages out, the caller's clock), so the agent's keeper and the tests
drive the same code; the simulator serves the other side with pymavlink.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from roost_api.core import Stack
from roost_api.fence import Area, FenceAction, LatLon
from roost_mavlink.params import ParamType, float32

MAV_MISSION_TYPE_FENCE = 1
MAV_MISSION_ACCEPTED = 0
MAV_MISSION_ERROR = 1
MAV_MISSION_OPERATION_CANCELLED = 15
MAV_FRAME_GLOBAL = 0
MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION = 5001
MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION = 5003
FENCE_COMMANDS = (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION)

RETRY_S = 0.5
"""A transfer step without an answer for this long is sent again."""
MAX_RETRIES = 5
"""Unanswered repeats of one step before the transfer fails (NoAnswer)."""


@dataclass(frozen=True)
class Item:
    """One fence item as MISSION_ITEM_INT carries it (what a read-back is compared on)."""

    command: int
    param1: float
    x: int
    y: int

    def same(self, other: Item) -> bool:
        """Equal as the autopilot stores it (param1 as a 32-bit float)."""
        return (
            self.command == other.command
            and self.x == other.x
            and self.y == other.y
            and float32(self.param1) == float32(other.param1)
        )


def _e7(degrees: float) -> int:
    return round(degrees * 1e7)


def items_for(area: Area) -> list[Item]:
    """The fence items of an inclusion polygon or circle."""
    if area.centre is not None:
        c = area.centre
        return [
            Item(
                MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, area.radius_m, _e7(c.latitude), _e7(c.longitude)
            )
        ]
    points = list(area.polygon)
    if len(points) > 1 and points[0] == points[-1]:
        points = points[:-1]  # a GeoJSON-style closed ring: MAVLink closes it implicitly
    count = float(len(points))
    return [
        Item(MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, count, _e7(p.latitude), _e7(p.longitude))
        for p in points
    ]


def area_of(items: Sequence[Item]) -> Area | None:
    """The inclusion area the items describe (None: none the simulator can enforce)."""
    circles = [i for i in items if i.command == MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION]
    if circles:
        c = circles[0]
        return Area(centre=LatLon(c.x / 1e7, c.y / 1e7), radius_m=c.param1)
    vertices = [i for i in items if i.command == MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION]
    if len(vertices) < 3:
        return None
    return Area(polygon=tuple(LatLon(v.x / 1e7, v.y / 1e7) for v in vertices))


def mismatch(uploaded: Sequence[Item], read: Sequence[Item]) -> str | None:
    """How the read-back differs from the upload (None: it holds the fence)."""
    if len(read) != len(uploaded):
        return f"read back {len(read)} item(s), uploaded {len(uploaded)}"
    for n, (mine, theirs) in enumerate(zip(uploaded, read, strict=True)):
        if not mine.same(theirs):
            return f"item {n} reads back as {theirs}, uploaded {mine}"
    return None


@dataclass(frozen=True)
class StackParam:
    """A fence parameter of one stack: its name, type and the value to hold."""

    name: str
    ptype: ParamType
    value: float


# GF_ACTION (PX4 geofence, INT32): 1 warning, 2 hold (loiter), 3 return, 5 land.
_PX4_ACTION = {
    FenceAction.REPORT: 1.0,
    FenceAction.HOLD: 2.0,
    FenceAction.RETURN: 3.0,
    FenceAction.LAND: 5.0,
}
# FENCE_ACTION (ArduCopter AC_Fence, INT8): 0 report only, 1 RTL or land, 2 always land,
# 4 brake or land.
_ARDUPILOT_ACTION = {
    FenceAction.REPORT: 0.0,
    FenceAction.RETURN: 1.0,
    FenceAction.LAND: 2.0,
    FenceAction.HOLD: 4.0,
}
ARDUPILOT_FENCE_TYPE_ALT_MAX = 1
ARDUPILOT_FENCE_TYPE_POLYGON = 4  # every inclusion/exclusion polygon and circle item


def stack_params(stack: Stack, max_altitude_m: float, action: FenceAction) -> list[StackParam]:
    """The fence parameters ``stack`` needs for an uploaded fence with this altitude
    limit and breach action (PX4 checks a stored fence whenever one is uploaded; ArduPilot
    needs FENCE_ENABLE and the polygon and altitude types in FENCE_TYPE)."""
    if Stack(stack) is Stack.PX4:
        return [
            StackParam("GF_ACTION", ParamType.INT32, _PX4_ACTION[FenceAction(action)]),
            StackParam("GF_MAX_VER_DIST", ParamType.REAL32, float(max_altitude_m)),
        ]
    kinds = ARDUPILOT_FENCE_TYPE_ALT_MAX | ARDUPILOT_FENCE_TYPE_POLYGON
    return [
        StackParam("FENCE_ENABLE", ParamType.INT8, 1.0),
        StackParam("FENCE_TYPE", ParamType.INT8, float(kinds)),
        StackParam("FENCE_ALT_MAX", ParamType.REAL32, float(max_altitude_m)),
        StackParam("FENCE_ACTION", ParamType.INT8, _ARDUPILOT_ACTION[FenceAction(action)]),
    ]


def stack_param_names(stack: Stack) -> list[str]:
    """The fence parameters of ``stack`` (read before an upload, restored after)."""
    return [p.name for p in stack_params(stack, 1.0, FenceAction.RETURN)]


def action_from_params(stack: Stack, values: dict[str, float]) -> FenceAction | None:
    """The breach action the stack's parameters select (None: none, or not fenced)."""
    if Stack(stack) is Stack.PX4:
        table, name = _PX4_ACTION, "GF_ACTION"
    else:
        if not values.get("FENCE_ENABLE"):
            return None
        table, name = _ARDUPILOT_ACTION, "FENCE_ACTION"
    value = values.get(name)
    return next((action for action, v in table.items() if v == value), None)


def max_altitude_from_params(stack: Stack, values: dict[str, float]) -> float | None:
    """The altitude limit the stack's parameters set (None: none)."""
    if Stack(stack) is Stack.PX4:
        limit = values.get("GF_MAX_VER_DIST", 0.0)
        return limit if limit > 0 else None
    if not values.get("FENCE_ENABLE") or not int(values.get("FENCE_TYPE", 0)) & 1:
        return None
    return values.get("FENCE_ALT_MAX")


# -- the client side of one transfer ---------------------------------------------------

Message = tuple[str, dict[str, Any]]
"""A mission protocol message: its name and fields (targets are the caller's)."""


class Outcome(Enum):
    """Where a transfer stands."""

    RUNNING = "running"
    DONE = "done"
    REFUSED = "refused"  # the autopilot answered MISSION_ACK with an error
    NO_ANSWER = "no-answer"


@dataclass
class Transfer:
    """One upload (``items`` given) or download (``items`` None) of the fence."""

    items: list[Item] | None
    outcome: Outcome = Outcome.RUNNING
    detail: str = ""
    received: list[Item] = field(default_factory=list)
    _expected: int | None = None
    _last: Message | None = None
    _sent_at: float = -math.inf
    _retries: int = 0

    @classmethod
    def upload(cls, items: Sequence[Item]) -> Transfer:
        return cls(list(items))

    @classmethod
    def download(cls) -> Transfer:
        return cls(None)

    def _send(self, message: Message, now: float) -> list[Message]:
        self._last, self._sent_at, self._retries = message, now, 0
        return [message]

    def start(self, now: float) -> list[Message]:
        """The message that begins the transfer."""
        fence = {"mission_type": MAV_MISSION_TYPE_FENCE}
        if self.items is None:
            return self._send(("MISSION_REQUEST_LIST", fence), now)
        return self._send(("MISSION_COUNT", {"count": len(self.items), **fence}), now)

    def step(self, now: float) -> list[Message]:
        """The repeat due now (nothing answered the last message for :data:`RETRY_S`)."""
        if self.outcome is not Outcome.RUNNING or self._last is None:
            return []
        if now - self._sent_at < RETRY_S:
            return []
        if self._retries >= MAX_RETRIES:
            self.outcome = Outcome.NO_ANSWER
            self.detail = f"no answer to {self._last[0]} after {MAX_RETRIES + 1} tries"
            return []
        self._retries += 1
        self._sent_at = now
        return [self._last]

    def _item(self, seq: int) -> Message:
        assert self.items is not None
        item = self.items[seq]
        return (
            "MISSION_ITEM_INT",
            {
                "seq": seq,
                "frame": MAV_FRAME_GLOBAL,
                "command": item.command,
                "current": 0,
                "autocontinue": 0,
                "param1": item.param1,
                "param2": 0.0,
                "param3": 0.0,
                "param4": 0.0,
                "x": item.x,
                "y": item.y,
                "z": 0.0,
                "mission_type": MAV_MISSION_TYPE_FENCE,
            },
        )

    def _request(self, seq: int) -> Message:
        return ("MISSION_REQUEST_INT", {"seq": seq, "mission_type": MAV_MISSION_TYPE_FENCE})

    def _ack(self, result: int) -> Message:
        return ("MISSION_ACK", {"type": result, "mission_type": MAV_MISSION_TYPE_FENCE})

    def receive(self, name: str, fields: dict[str, Any], now: float) -> list[Message]:
        """One mission protocol message from the autopilot; returns what to send."""
        if self.outcome is not Outcome.RUNNING:
            return []
        if int(fields.get("mission_type", 0)) != MAV_MISSION_TYPE_FENCE:
            return []  # another transfer type (a ground station's mission upload)
        if self.items is not None:
            return self._upload_receive(name, fields, now)
        return self._download_receive(name, fields, now)

    def _upload_receive(self, name: str, fields: dict[str, Any], now: float) -> list[Message]:
        assert self.items is not None
        if name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            seq = int(fields["seq"])
            if 0 <= seq < len(self.items):
                return self._send(self._item(seq), now)
            return []
        if name == "MISSION_ACK":
            result = int(fields["type"])
            if result == MAV_MISSION_ACCEPTED:
                self.outcome = Outcome.DONE
            else:
                self.outcome = Outcome.REFUSED
                self.detail = f"MISSION_ACK result {result}"
        return []

    def _download_receive(self, name: str, fields: dict[str, Any], now: float) -> list[Message]:
        if name == "MISSION_COUNT" and self._expected is None:
            self._expected = int(fields["count"])
            if self._expected == 0:
                self.outcome = Outcome.DONE
                return [self._ack(MAV_MISSION_ACCEPTED)]
            return self._send(self._request(0), now)
        if name == "MISSION_ITEM_INT" and self._expected is not None:
            seq = int(fields["seq"])
            if seq != len(self.received):
                return []  # a repeat of an item already taken, or out of order
            self.received.append(
                Item(
                    int(fields["command"]),
                    float(fields["param1"]),
                    int(fields["x"]),
                    int(fields["y"]),
                )
            )
            if len(self.received) == self._expected:
                self.outcome = Outcome.DONE
                return [self._ack(MAV_MISSION_ACCEPTED)]
            return self._send(self._request(len(self.received)), now)
        if name == "MISSION_ACK" and int(fields["type"]) != MAV_MISSION_ACCEPTED:
            self.outcome = Outcome.REFUSED
            self.detail = f"MISSION_ACK result {int(fields['type'])}"
        return []


__all__ = [
    "FENCE_COMMANDS",
    "MAV_MISSION_TYPE_FENCE",
    "Item",
    "Message",
    "Outcome",
    "StackParam",
    "Transfer",
    "action_from_params",
    "area_of",
    "items_for",
    "max_altitude_from_params",
    "mismatch",
    "stack_param_names",
    "stack_params",
]
