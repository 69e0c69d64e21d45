"""Whether each standby autopilot follows the active one: the hub's in-step judgement.

Why this module exists apart from the routing (:mod:`roost_agent.hub`): routing moves
frames; this judges what the frames said. The hub records what it reads of every
autopilot in a :class:`Snapshot` (heartbeat, armed state, mode, position, answers to
mirrored commands); :func:`judge_standby` compares a standby with the active (armed
state, mode, position and altitude within ``HubSpec.standby_limits``, and whether it
rejected or left unanswered a mirrored command) and :class:`InStepTracker` confirms a
difference over ``confirm_ms`` before it counts. The result is the ``StandbyInStep``
condition and the arbiter's preference for standbys in step. Pure functions of
snapshots and explicit times, so the rules are unit-tested without sockets
(tests/unit/test_agent_hub_rules.py).

Modes are compared only between autopilots of the same stack (a custom mode number
means something else on the other stack).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from roost_api.autopilot_enums import StandbyInStepReason
from roost_api.core import Stack
from roost_api.plain import StandbyLimits
from roost_mavlink import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MavResult,
    mav_result_name,
)

MIRROR_ACK_TIMEOUT_S = 1.5  # a standby that does not acknowledge a mirrored command by then
REJECTION_MEMORY_S = 30.0  # how long an unresolved rejection keeps a standby out of step

# Flight-state commands a client sends that every standby must follow (MAV_CMD numbers
# of common.xml, with their names for the in-step messages).
MIRRORED_COMMANDS: dict[int, str] = {
    MAV_CMD_COMPONENT_ARM_DISARM: "MAV_CMD_COMPONENT_ARM_DISARM",
    MAV_CMD_DO_SET_MODE: "MAV_CMD_DO_SET_MODE",
    MAV_CMD_NAV_TAKEOFF: "MAV_CMD_NAV_TAKEOFF",
    24: "MAV_CMD_NAV_TAKEOFF_LOCAL",
    MAV_CMD_NAV_LAND: "MAV_CMD_NAV_LAND",
    MAV_CMD_NAV_RETURN_TO_LAUNCH: "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    17: "MAV_CMD_NAV_LOITER_UNLIM",
    300: "MAV_CMD_MISSION_START",
    192: "MAV_CMD_DO_REPOSITION",
    178: "MAV_CMD_DO_CHANGE_SPEED",
    179: "MAV_CMD_DO_SET_HOME",
    193: "MAV_CMD_DO_PAUSE_CONTINUE",
    224: "MAV_CMD_DO_SET_MISSION_CURRENT",
    92: "MAV_CMD_NAV_GUIDED_ENABLE",
}


@dataclass
class Snapshot:
    """One autopilot's state as the hub last read it (monotonic seconds)."""

    stack: Stack
    heartbeat_at: float | None = None
    armed: bool | None = None
    mode: str | None = None
    position_at: float | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    relative_alt_m: float | None = None
    # mirrored command -> (what happened, when): a rejection until an accepting answer
    rejected: dict[int, tuple[str, float]] = field(default_factory=dict)
    # mirrored command -> when it was sent, until the standby answers it
    awaiting: dict[int, float] = field(default_factory=dict)


@dataclass(frozen=True)
class InStep:
    """Whether a standby follows the active autopilot; ``status`` None means not known."""

    status: bool | None
    reason: StandbyInStepReason
    message: str


def horizontal_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Distance in metres between two nearby positions (equirectangular; metres apart)."""
    k = math.pi / 180
    x = (lon2 - lon1) * k * math.cos((lat1 + lat2) / 2 * k)
    y = (lat2 - lat1) * k
    return math.hypot(x, y) * 6_371_000.0


def command_text(command: int) -> str:
    return MIRRORED_COMMANDS.get(command, str(command))


def judge_standby(
    active: Snapshot,
    standby: Snapshot,
    limits: StandbyLimits,
    *,
    stale_s: float,
    now: float,
) -> InStep:
    """Whether ``standby`` is in step with ``active`` right now (no confirmation time)."""
    reason = StandbyInStepReason
    if standby.heartbeat_at is None:
        return InStep(None, reason.NO_DATA, "no heartbeat from this standby yet")
    if now - standby.heartbeat_at > stale_s:
        age = now - standby.heartbeat_at
        return InStep(False, reason.SILENT, f"no heartbeat for {age:.1f} s")
    for command, (text, at) in standby.rejected.items():
        if now - at <= REJECTION_MEMORY_S:
            return InStep(
                False, reason.REJECTED_MIRRORED, f"{command_text(command)} mirrored: {text}"
            )
    for command, sent in standby.awaiting.items():
        if now - sent > MIRROR_ACK_TIMEOUT_S:
            return InStep(
                False,
                reason.SILENT,
                f"no answer to mirrored {command_text(command)} for {now - sent:.1f} s",
            )
    if active.heartbeat_at is None or active.armed is None:
        return InStep(None, reason.NO_DATA, "no heartbeat from the active autopilot")
    if standby.armed != active.armed:
        state = "armed" if standby.armed else "disarmed"
        return InStep(False, reason.ARMED_DIFFERS, f"{state}, the active is not")
    if standby.stack == active.stack and standby.mode != active.mode:
        return InStep(
            False, reason.MODE_DIFFERS, f"mode {standby.mode}, the active flies {active.mode}"
        )
    if (
        active.lat_deg is not None
        and active.lon_deg is not None
        and standby.lat_deg is not None
        and standby.lon_deg is not None
    ):
        apart = horizontal_m(active.lat_deg, active.lon_deg, standby.lat_deg, standby.lon_deg)
        if apart > limits.position_m:
            return InStep(
                False,
                reason.POSITION_DIFFERS,
                f"position {apart:.1f} m from the active's (limit {limits.position_m:g} m)",
            )
    if active.relative_alt_m is not None and standby.relative_alt_m is not None:
        dz = abs(active.relative_alt_m - standby.relative_alt_m)
        if dz > limits.altitude_m:
            return InStep(
                False,
                reason.ALTITUDE_DIFFERS,
                f"altitude {dz:.1f} m from the active's (limit {limits.altitude_m:g} m)",
            )
    if active.lat_deg is None or standby.lat_deg is None:
        return InStep(None, reason.NO_DATA, "no position from both autopilots yet")
    modes = "" if standby.stack == active.stack else " (modes not compared across stacks)"
    return InStep(True, reason.IN_STEP, f"armed state, mode and position agree{modes}")


class InStepTracker:
    """Confirms a standby's verdict: a change counts after ``confirm_s`` (hysteresis)."""

    def __init__(self, confirm_s: float) -> None:
        self.confirm_s = confirm_s
        self._shown: dict[str, InStep] = {}
        self._since: dict[str, tuple[bool | None, float]] = {}

    def update(self, name: str, verdict: InStep, now: float) -> InStep:
        """The verdict to show for ``name`` after seeing ``verdict`` at ``now``."""
        shown = self._shown.get(name)
        if shown is None or shown.status == verdict.status:
            self._since.pop(name, None)
            self._shown[name] = verdict
            return verdict
        status, since = self._since.get(name, (verdict.status, now))
        if status != verdict.status:
            since = now
        self._since[name] = (verdict.status, since)
        if now - since >= self.confirm_s:
            self._since.pop(name, None)
            self._shown[name] = verdict
            return verdict
        return shown

    def forget(self, name: str) -> None:
        self._shown.pop(name, None)
        self._since.pop(name, None)


def note_answer(seen: Snapshot, command: int, result: int, now: float) -> None:
    """A standby answered a mirrored ``command``: it is no longer awaited, and a
    rejection is remembered (until an accepting answer) for :func:`judge_standby`."""
    if command not in MIRRORED_COMMANDS:
        return
    if result == MavResult.IN_PROGRESS:
        return
    seen.awaiting.pop(command, None)
    if result == MavResult.ACCEPTED:
        seen.rejected.pop(command, None)
    else:
        seen.rejected[command] = (f"answered {mav_result_name(result)}", now)
