"""The simulated autopilot's geofence: the fence part of the mission protocol, served as
PX4 and ArduPilot serve it, and the breach check of its 3D flight.

Served (https://mavlink.io/en/services/mission.html, ``mission_type`` FENCE only; other
types keep the autopilot's "nothing stored" answer):

- upload: MISSION_COUNT starts it (a repeated MISSION_COUNT starts it again, as the
  firmware does); each item is asked for with MISSION_REQUEST_INT; an item repeated by
  the client (its request was lost) is asked for again; after the last, MISSION_ACK
  (accepted, or an error for an item that is not a fence item or a polygon whose
  ``param1`` vertex count does not match; the stored fence is then unchanged);
- download: MISSION_REQUEST_LIST → MISSION_COUNT, MISSION_REQUEST_INT → MISSION_ITEM_INT.

Enforcement follows the parameters the real stacks read: PX4 checks a stored fence and
``GF_MAX_VER_DIST`` (0: no altitude limit) with the action ``GF_ACTION``; ArduCopter
only with ``FENCE_ENABLE`` 1, the polygon and altitude types of ``FENCE_TYPE`` and the
action ``FENCE_ACTION``. A breach is acted on once when it begins, while armed and in the
air, as the firmware's fence check does (it latches until the vehicle is back inside).
"""

from __future__ import annotations

from typing import Any

from roost_api.core import Stack
from roost_api.fence import FenceAction, LatLon
from roost_mavlink.fence import (
    FENCE_COMMANDS,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_MISSION_TYPE_FENCE,
    Item,
    action_from_params,
    area_of,
    max_altitude_from_params,
    stack_param_names,
)
from roost_sim.kinematics import global_from_ned

MAV_MISSION_ACCEPTED = 0
MAV_MISSION_ERROR = 1
MAV_MISSION_UNSUPPORTED = 3
MAV_MISSION_INVALID_PARAM1 = 5


def upload_problem(items: list[Item]) -> int | None:
    """The MISSION_ACK error an autopilot gives for these fence items (None: stored)."""
    if any(i.command not in FENCE_COMMANDS for i in items):
        return MAV_MISSION_UNSUPPORTED
    vertices = [i for i in items if i.command == MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION]
    if vertices and (len(vertices) < 3 or any(int(v.param1) != len(vertices) for v in vertices)):
        return MAV_MISSION_INVALID_PARAM1
    return None


class SimFence:
    """The fence store of one simulated autopilot (its caller holds the autopilot's lock)."""

    def __init__(self, stack: Stack) -> None:
        self.stack = Stack(stack)
        self.items: list[Item] = []
        self.refuse_uploads = False  # a fault: every upload is answered with an error
        self.uploads = 0
        self._incoming: list[Item] | None = None
        self._expected = 0
        self._breached = False
        self.breaches: list[str] = []

    def handle(self, msg: Any, mav: Any, sysid: int, component_id: int) -> list[Any]:
        """A mission protocol message of ``mission_type`` FENCE; the replies."""
        kind = msg.get_type()
        to = (msg.get_srcSystem(), msg.get_srcComponent())
        fence = MAV_MISSION_TYPE_FENCE
        if kind == "MISSION_REQUEST_LIST":
            return [mav.mission_count_encode(*to, len(self.items), fence)]
        if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            if 0 <= msg.seq < len(self.items):
                return [self._item(mav, to, msg.seq)]
            return []
        if kind == "MISSION_COUNT":
            self._incoming, self._expected = [], int(msg.count)
            if self._expected == 0:
                return self._finish(mav, to)
            return [mav.mission_request_int_encode(*to, 0, fence)]
        if kind == "MISSION_ITEM_INT" and self._incoming is not None:
            got = len(self._incoming)
            if msg.seq == got:
                self._incoming.append(Item(msg.command, msg.param1, msg.x, msg.y))
                if len(self._incoming) == self._expected:
                    return self._finish(mav, to)
                return [mav.mission_request_int_encode(*to, got + 1, fence)]
            if msg.seq == got - 1:  # our request was lost: ask again
                return [mav.mission_request_int_encode(*to, got, fence)]
        return []

    def _finish(self, mav: Any, to: tuple[int, int]) -> list[Any]:
        items, self._incoming = self._incoming or [], None
        problem = MAV_MISSION_ERROR if self.refuse_uploads else upload_problem(items)
        if problem is None:
            self.items = items
            self.uploads += 1
            self._breached = False
        result = MAV_MISSION_ACCEPTED if problem is None else problem
        return [mav.mission_ack_encode(*to, result, MAV_MISSION_TYPE_FENCE)]

    def _item(self, mav: Any, to: tuple[int, int], seq: int) -> Any:
        item = self.items[seq]
        return mav.mission_item_int_encode(
            *to,
            seq,
            0,
            item.command,
            0,
            0,
            item.param1,
            0,
            0,
            0,
            item.x,
            item.y,
            0.0,
            MAV_MISSION_TYPE_FENCE,
        )

    def check(
        self,
        *,
        north_m: float,
        east_m: float,
        altitude_m: float,
        home: LatLon,
        params: dict[str, float],
        flying: bool,
    ) -> FenceAction | None:
        """The action to take now: set when a breach begins (None otherwise)."""
        action = action_from_params(self.stack, params)
        if not flying or action is None:
            self._breached = False
            return None
        area = (
            area_of(self.items) if (self.stack is Stack.PX4 or _ardupilot_polygon(params)) else None
        )
        lat, lon = global_from_ned(north_m, east_m, home.latitude, home.longitude)
        limit = max_altitude_from_params(self.stack, params)
        why = None
        if area is not None and not area.contains(LatLon(lat, lon)):
            why = f"outside the fence at {lat:.6f},{lon:.6f}"
        elif limit is not None and altitude_m > limit:
            why = f"above the fence's {limit:g} m at {altitude_m:.1f} m"
        if why is None:
            self._breached = False
            return None
        if self._breached:
            return None
        self._breached = True
        self.breaches.append(why)
        return action


def _ardupilot_polygon(params: dict[str, float]) -> bool:
    return bool(params.get("FENCE_ENABLE")) and bool(int(params.get("FENCE_TYPE", 0)) & 4)


def fence_params(stack: Stack, get: Any) -> dict[str, float]:
    """The stack's fence parameters as the autopilot holds them (``get``: by name)."""
    return {name: float(get(name)) for name in stack_param_names(stack)}


__all__ = ["SimFence", "fence_params", "upload_problem"]
