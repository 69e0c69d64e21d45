"""roost_agent.firmware: AUTOPILOT_VERSION read as each firmware writes it, and the
``FirmwareAcceptable`` decision table."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent.firmware import CAPABILITIES, capability_names, info, judge
from roost_api.autopilot_enums import AutopilotConditionReason as R
from roost_api.core import HealthLevel, Stack
from roost_api.plain import AutopilotHealth, FirmwareInfo, FirmwareRequirement
from roost_mavlink.codec import encode, scan
from roost_mavlink.definitions import AGENT_MESSAGES


def version_message(packed: int, custom: bytes, capabilities: int) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_autopilot_version_message(
        capabilities, packed, 0, 0, 50, list(custom), [0] * 8, [0] * 8, 0x26AC, 0x11, 7
    )


def test_capability_names_are_mavlinks() -> None:
    for bit, name in CAPABILITIES:
        assert getattr(mavlink, f"MAV_PROTOCOL_CAPABILITY_{name}") == bit


def test_px4_and_ardupilot_builds_read_as_their_tools_show_them() -> None:
    px4 = version_message(
        (1 << 24) | (16 << 16) | (0 << 8) | 255,
        bytes.fromhex("d4a3b3c2e1f00abc")[::-1],  # the hash's bytes as a little-endian number
        mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
    )
    fw = info(px4)
    assert (fw.version, fw.version_type, fw.git_hash) == ("1.16.0", "official", "d4a3b3c2e1f00abc")
    assert (fw.board_version, fw.vendor_id, fw.product_id) == (50, 0x26AC, 0x11)
    assert fw.capabilities == ["PARAM_ENCODE_BYTEWISE", "MAVLINK2"]
    ardupilot = version_message((4 << 24) | (5 << 16) | (7 << 8) | 192, b"90700977", 1 << 17)
    fw = info(ardupilot)
    assert (fw.version, fw.version_type, fw.git_hash) == ("4.5.7", "rc", "90700977")
    assert capability_names(1 << 17) == ["PARAM_ENCODE_C_CAST"]


def test_the_agents_codec_reads_it_as_pymavlink_does() -> None:
    msg = version_message((4 << 24) | (7 << 16) | 255, b"90700977", 1 << 17)
    values = {name: getattr(msg, name) for name in msg.fieldnames}
    frame = scan(encode(AGENT_MESSAGES[148], values, seq=0, system=1, component=1))[0][0]
    assert info(frame) == info(msg)


def health(name: str, version: str | None, build: str = "") -> AutopilotHealth:
    fw = (
        None
        if version is None
        else FirmwareInfo(version=version, version_type="official", git_hash=build)
    )
    return AutopilotHealth(name=name, level=HealthLevel.OK, firmware=fw)


STACKS = {"fc1": Stack.PX4, "fc2": Stack.PX4, "fc3": Stack.ARDUPILOT}
CASES = [
    # (requirement, versions (fc1, fc2, fc3) with builds) -> (status, reason, in message)
    (FirmwareRequirement(), [("1.16.0", ""), None, ("4.5.7", "")],
     "Unknown", R.NO_FIRMWARE_DATA, "fc2"),
    (FirmwareRequirement(), [("1.14.0", ""), ("1.16.0", ""), ("4.5.7", "")],
     "True", R.FIRMWARE_ACCEPTABLE, "fc1 1.14.0"),
    (FirmwareRequirement(px4_minimum="1.15.0"), [("1.14.3", ""), ("1.16.0", ""), ("4.5.7", "")],
     "False", R.FIRMWARE_BELOW_MINIMUM, "fc1 runs px4 1.14.3, below the required 1.15.0"),
    (FirmwareRequirement(px4_minimum="1.15.0", ardupilot_minimum="4.5.0"),
     [("1.16.0", ""), ("1.15.0", ""), ("4.4.4", "")],
     "False", R.FIRMWARE_BELOW_MINIMUM, "fc3 runs ardupilot 4.4.4"),
    (FirmwareRequirement(ardupilot_minimum="4.10.0"),
     [("1.16.0", ""), ("1.16.0", ""), ("4.9.0", "")],
     "False", R.FIRMWARE_BELOW_MINIMUM, "fc3"),  # compared as numbers, not text
    (FirmwareRequirement(identical=True), [("1.16.0", "aa"), ("1.16.0", "bb"), ("4.5.7", "")],
     "False", R.FIRMWARE_VERSIONS_DIFFER, "fc1 1.16.0 (aa), fc2 1.16.0 (bb)"),
    (FirmwareRequirement(identical=True), [("1.16.0", "aa"), ("1.16.0", "aa"), ("4.5.7", "")],
     "True", R.FIRMWARE_ACCEPTABLE, ""),  # one of each stack: nothing to differ from
    (FirmwareRequirement(px4_minimum="1.17.0", identical=True),
     [("1.16.0", "aa"), ("1.16.1", "bb"), ("4.5.7", "")],
     "False", R.FIRMWARE_BELOW_MINIMUM, "fc2 runs px4 1.16.1"),  # below first
]  # fmt: skip


@pytest.mark.parametrize(("requirement", "versions", "status", "reason", "text"), CASES)
def test_firmware_acceptable_decision_table(
    requirement: FirmwareRequirement,
    versions: list[tuple[str, str] | None],
    status: str,
    reason: R,
    text: str,
) -> None:
    autopilots = [
        health(name, None if v is None else v[0], "" if v is None else v[1])
        for name, v in zip(STACKS, versions, strict=True)
    ]
    got = judge(requirement, STACKS, autopilots)
    assert got[:2] == (status, reason)
    assert text in got[2]
