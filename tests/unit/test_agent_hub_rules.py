"""The MAVLink hub's pure parts: frame rewriting, retargeting, what is mirrored, the
StandbyInStep decision table and the arbiter's preference for standbys in step.

Frames are real MAVLink bytes (pymavlink's encoder). Routing through a real hub (its UDP
endpoint bound) is in ``tests/integration/test_agent_hub_routing.py``.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent.arbiter import ArbiterState, AutopilotView, Policy, SwitchBridge, step
from roost_agent.hub import MAV_CMD_DO_AUX_FUNCTION, retarget, rewrite_source
from roost_agent.instep import (
    MIRRORED_COMMANDS,
    InStepTracker,
    Snapshot,
    horizontal_m,
    judge_standby,
)
from roost_api.autopilot import (
    Failback,
    StandbyInStepReason,
    StandbyLimits,
)
from roost_api.meta import HealthLevel, Stack
from roost_mavlink import mav_result_name
from tests.support.mavframes import VEHICLE, client_msg, encode, heartbeat, parse

R = StandbyInStepReason


# -- frames ------------------------------------------------------------------------------


def test_rewrite_source_gives_a_valid_frame_from_the_vehicle() -> None:
    frame = encode(heartbeat(), sysid=7)
    out = rewrite_source(frame, VEHICLE)
    assert out is not None
    msg = parse(out)
    assert msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == VEHICLE
    assert msg.get_srcComponent() == 1 and msg.custom_mode == 4


def test_rewrite_source_keeps_a_frame_already_from_the_vehicle() -> None:
    frame = encode(heartbeat(), sysid=VEHICLE)
    assert rewrite_source(frame, VEHICLE) is frame


def test_rewrite_source_handles_mavlink1_and_drops_signatures() -> None:
    v1 = bytes(heartbeat().pack(mavlink.MAVLink(None, 7, 1), force_mavlink1=True))
    out = rewrite_source(v1, VEHICLE)
    assert out is not None and out[0] == 0xFE and parse(out).get_srcSystem() == VEHICLE
    signer = mavlink.MAVLink(None, 7, 1)
    signer.signing.secret_key = bytes(32)
    signer.signing.sign_outgoing = True
    signed = bytes(heartbeat().pack(signer))
    assert signed[2] & 1
    out = rewrite_source(signed, VEHICLE)
    assert out is not None and not out[2] & 1 and len(out) == len(signed) - 13
    assert parse(out).get_srcSystem() == VEHICLE


@pytest.mark.parametrize(
    "frame", [b"", b"\xfd\x09", b"garbage-garbage", b"\xfd" + bytes(6) + b"\xff\xff\xff\x00\x00"]
)
def test_rewrite_source_refuses_what_is_not_a_known_frame(frame: bytes) -> None:
    assert rewrite_source(frame, VEHICLE) is None


def test_retarget_addresses_the_autopilot_and_keeps_the_sender() -> None:
    msg = client_msg(mavlink.MAVLink_command_long_message(VEHICLE, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    for sysid in (1, 2):
        out = parse(retarget(msg, VEHICLE, sysid))
        assert out.target_system == sysid and out.command == 400
        assert (out.get_srcSystem(), out.get_srcComponent()) == (255, 190)
        assert out.get_seq() == msg.get_seq()
    assert msg.target_system == VEHICLE  # the parsed message is left as it was


def test_retarget_leaves_broadcasts_and_other_systems_alone() -> None:
    for target in (0, 9):
        msg = client_msg(
            mavlink.MAVLink_command_long_message(target, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        )
        assert retarget(msg, VEHICLE, 1) == bytes(msg.get_msgbuf())
    hb = client_msg(heartbeat())
    assert retarget(hb, VEHICLE, 1) == bytes(hb.get_msgbuf())
    manual = client_msg(mavlink.MAVLink_manual_control_message(VEHICLE, 0, 0, 500, 0, 0))
    assert parse(retarget(manual, VEHICLE, 3)).target == 3


# -- StandbyInStep decision table ----------------------------------------------------------

LIMITS = StandbyLimits(position_m=3.0, altitude_m=1.5, confirm_ms=500)
NOW = 100.0
LAT, LON = 47.0, 8.0


def snap(stack: Stack = Stack.PX4, **changes: Any) -> Snapshot:
    base: dict[str, Any] = {
        "heartbeat_at": NOW - 0.2,
        "armed": True,
        "mode": "AUTO.LOITER" if stack is Stack.PX4 else "GUIDED",
        "position_at": NOW - 0.1,
        "lat_deg": LAT,
        "lon_deg": LON,
        "relative_alt_m": 10.0,
    }
    base.update(changes)
    return Snapshot(stack, **base)


METRE_LAT = 1 / 111_195  # degrees of latitude per metre


@pytest.mark.parametrize(
    ("standby", "status", "reason"),
    [
        (snap(), True, R.IN_STEP),
        (snap(heartbeat_at=None), None, R.NO_DATA),
        (snap(heartbeat_at=NOW - 3.5), False, R.SILENT),
        (snap(rejected={176: ("answered DENIED", NOW - 1)}), False, R.REJECTED_MIRRORED),
        (snap(rejected={176: ("answered DENIED", NOW - 40)}), True, R.IN_STEP),
        (snap(awaiting={400: NOW - 2.0}), False, R.SILENT),
        (snap(awaiting={400: NOW - 0.5}), True, R.IN_STEP),
        (snap(armed=False), False, R.ARMED_DIFFERS),
        (snap(mode="AUTO.RTL"), False, R.MODE_DIFFERS),
        (snap(Stack.ARDUPILOT), True, R.IN_STEP),  # modes not compared across stacks
        (snap(lat_deg=LAT + 2.9 * METRE_LAT), True, R.IN_STEP),
        (snap(lat_deg=LAT + 3.5 * METRE_LAT), False, R.POSITION_DIFFERS),
        (snap(relative_alt_m=11.4), True, R.IN_STEP),
        (snap(relative_alt_m=11.6), False, R.ALTITUDE_DIFFERS),
        (snap(lat_deg=None, lon_deg=None), None, R.NO_DATA),
    ],
)
def test_standby_in_step_decision_table(
    standby: Snapshot, status: bool | None, reason: StandbyInStepReason
) -> None:
    verdict = judge_standby(snap(), standby, LIMITS, stale_s=3.0, now=NOW)
    assert (verdict.status, verdict.reason) == (status, reason), verdict.message


def test_standby_is_unknown_while_the_active_has_no_heartbeat() -> None:
    verdict = judge_standby(snap(heartbeat_at=None, armed=None), snap(), LIMITS, stale_s=3, now=NOW)
    assert verdict.status is None and verdict.reason == R.NO_DATA


def test_in_step_changes_only_after_the_confirm_time() -> None:
    tracker = InStepTracker(0.5)
    good = judge_standby(snap(), snap(), LIMITS, stale_s=3, now=NOW)
    bad = judge_standby(snap(), snap(armed=False), LIMITS, stale_s=3, now=NOW)
    assert tracker.update("fc2", good, 0.0).status is True
    assert tracker.update("fc2", bad, 0.1).status is True  # not confirmed yet
    assert tracker.update("fc2", good, 0.3).status is True  # the blip ended
    assert tracker.update("fc2", bad, 0.4).status is True  # a new difference starts over
    assert tracker.update("fc2", bad, 0.8).status is True
    assert tracker.update("fc2", bad, 0.9).status is False  # 0.5 s of difference


def test_horizontal_distance_is_in_metres() -> None:
    assert math.isclose(horizontal_m(LAT, LON, LAT + 10 * METRE_LAT, LON), 10.0, rel_tol=0.01)


# -- the arbiter prefers standbys in step ----------------------------------------------------

POLICY = Policy(
    priority=("fc1", "fc2", "fc3"),
    automatic=True,
    confirm_s=0.1,
    clear_s=1.0,
    failback=Failback.MANUAL,
    skip_safety_in_manual_mode=True,
)


def view(name: str, *, failing: bool = False, in_step: bool | None = None) -> AutopilotView:
    return AutopilotView(
        name=name,
        level=HealthLevel.ERROR if failing else HealthLevel.OK,
        failing=failing,
        reason="heartbeat lost" if failing else "",
        armed=True,
        in_air=True,
        in_step=in_step,
    )


def switch_target(fc2: bool | None, fc3: bool | None) -> tuple[str, bool | None] | None:
    views = {"fc1": view("fc1", failing=True), "fc2": view("fc2", in_step=fc2)}
    views["fc3"] = view("fc3", in_step=fc3)
    state = ArbiterState(active="fc1", in_flight=True, ok_since={"fc2": 0.0, "fc3": 0.0})
    decision = step(state, views, POLICY, 5.0)
    decision = step(decision.state, views, POLICY, 5.2)
    switches = [a for a in decision.actions if isinstance(a, SwitchBridge)]
    return (switches[0].to_autopilot, switches[0].in_step) if switches else None


@pytest.mark.parametrize(
    ("fc2", "fc3", "expected"),
    [
        (True, True, ("fc2", True)),  # both in step: priority order
        (False, True, ("fc3", True)),  # the in-step standby first
        (None, True, ("fc3", True)),  # not known to be in step counts as not in step
        (False, False, ("fc2", False)),  # none in step: still the best available
        (None, None, ("fc2", None)),  # no hub: priority order, in step unknown
    ],
)
def test_arbiter_prefers_standbys_in_step(
    fc2: bool | None, fc3: bool | None, expected: tuple[str, bool | None]
) -> None:
    assert switch_target(fc2, fc3) == expected


# -- routing and mirroring -------------------------------------------------------------------


def test_the_hubs_command_and_result_names_are_mavlinks() -> None:
    """The hub names mirrored commands and ack results itself (no pymavlink in the agent):
    the same numbers and names as pymavlink's dialect."""
    for number, name in MIRRORED_COMMANDS.items():
        assert getattr(mavlink, name) == number
    assert mavlink.MAV_CMD_DO_AUX_FUNCTION == MAV_CMD_DO_AUX_FUNCTION
    for number, entry in mavlink.enums["MAV_RESULT"].items():
        if not entry.name.endswith("ENUM_END"):
            assert mav_result_name(number) == entry.name
