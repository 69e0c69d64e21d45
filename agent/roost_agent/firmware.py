"""Firmware as a fact and a constraint: each autopilot's AUTOPILOT_VERSION, judged.

The agent asks every autopilot for AUTOPILOT_VERSION (MAV_CMD_REQUEST_MESSAGE, param1
148, every :data:`REQUEST_EVERY_S` until it comes, at most :data:`MAX_REQUESTS` times per
boot: PX4 and ArduPilot both answer it, and neither sends it unasked) and reports what it
says per autopilot (``status.autopilots[].firmware``): the flight software version, its
build (git hash), the board and the MAV_PROTOCOL_CAPABILITY flags. A RedundantAutopilot's
``spec.firmware`` can require a minimum version per stack and identical builds on every
autopilot of a stack; :func:`judge` gives the ``FirmwareAcceptable`` condition that
names the autopilot that breaks it (a Mission's preflight reads it).

``flight_sw_version`` packs MAJOR.MINOR.PATCH and FIRMWARE_VERSION_TYPE one byte each
(``major << 24 | minor << 16 | patch << 8 | type``). The build's git hash is the 8 bytes
of ``flight_custom_version``: ArduPilot writes the first 8 characters of the hash as
text, PX4 the hash's first 8 bytes as a little-endian number; both are shown as 16 or 8
hex digits as the firmware's own tools show them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from roost_api.autopilot_enums import AutopilotConditionReason as R
from roost_api.core import ConditionStatus, Stack
from roost_api.plain import AutopilotHealth, FirmwareInfo, FirmwareRequirement

MAVLINK_MSG_ID_AUTOPILOT_VERSION = 148
REQUEST_EVERY_S = 2.0
MAX_REQUESTS = 5
"""Unanswered requests before the agent stops asking (until the autopilot reboots)."""

_VERSION_TYPES = {0: "dev", 64: "alpha", 128: "beta", 192: "rc", 255: "official"}

# MAV_PROTOCOL_CAPABILITY bits, by name without the prefix (common.xml).
CAPABILITIES: tuple[tuple[int, str], ...] = (
    (1 << 0, "MISSION_FLOAT"),
    (1 << 1, "PARAM_FLOAT"),
    (1 << 2, "MISSION_INT"),
    (1 << 3, "COMMAND_INT"),
    (1 << 4, "PARAM_ENCODE_BYTEWISE"),
    (1 << 5, "FTP"),
    (1 << 6, "SET_ATTITUDE_TARGET"),
    (1 << 7, "SET_POSITION_TARGET_LOCAL_NED"),
    (1 << 8, "SET_POSITION_TARGET_GLOBAL_INT"),
    (1 << 9, "TERRAIN"),
    (1 << 10, "RESERVED3"),
    (1 << 11, "FLIGHT_TERMINATION"),
    (1 << 12, "COMPASS_CALIBRATION"),
    (1 << 13, "MAVLINK2"),
    (1 << 14, "MISSION_FENCE"),
    (1 << 15, "MISSION_RALLY"),
    (1 << 16, "RESERVED2"),
    (1 << 17, "PARAM_ENCODE_C_CAST"),
    (1 << 18, "COMPONENT_IMPLEMENTS_GIMBAL_MANAGER"),
    (1 << 19, "COMPONENT_ACCEPTS_GCS_CONTROL"),
    (1 << 20, "GRIPPER"),
)


def capability_names(bits: int) -> list[str]:
    """The names of the MAV_PROTOCOL_CAPABILITY flags set in ``bits``."""
    return [name for bit, name in CAPABILITIES if bits & bit]


def _git_hash(raw: Sequence[int]) -> str:
    data = bytes(raw)
    if data and all(chr(b) in "0123456789abcdefABCDEF" for b in data.rstrip(b"\0")):
        return data.rstrip(b"\0").decode().lower()  # ArduPilot: the hash's characters
    return int.from_bytes(data, "little").to_bytes(8, "big").hex() if any(data) else ""


def info(frame: Any) -> FirmwareInfo:
    """What an AUTOPILOT_VERSION message says (a codec frame or pymavlink's message)."""
    packed = int(frame.flight_sw_version)
    major, minor, patch = (packed >> 24) & 0xFF, (packed >> 16) & 0xFF, (packed >> 8) & 0xFF
    kind = packed & 0xFF
    return FirmwareInfo(
        version=f"{major}.{minor}.{patch}",
        version_type=_VERSION_TYPES.get(kind, f"type {kind}"),
        git_hash=_git_hash(frame.flight_custom_version),
        board_version=int(frame.board_version),
        vendor_id=int(frame.vendor_id),
        product_id=int(frame.product_id),
        capabilities=capability_names(int(frame.capabilities)),
    )


def capabilities_of(frame: Any) -> int:
    """The capability bits of an AUTOPILOT_VERSION message."""
    return int(frame.capabilities)


def parse_version(text: str) -> tuple[int, int, int]:
    """``"1.16.0"`` as a comparable tuple."""
    major, minor, patch = (int(part) for part in text.split("."))
    return major, minor, patch


def judge(
    requirement: FirmwareRequirement,
    stacks: Mapping[str, Stack],
    autopilots: Sequence[AutopilotHealth],
) -> tuple[ConditionStatus, R, str]:
    """The ``FirmwareAcceptable`` condition (status, reason, message).

    Rules, first that applies: an autopilot whose AUTOPILOT_VERSION has not come →
    Unknown ``NoFirmwareData``; one below its stack's minimum → False
    ``FirmwareBelowMinimum``; with ``identical``, autopilots of one stack on different
    versions or builds → False ``FirmwareVersionsDiffer``; otherwise True.
    """
    reported = {h.name: h.firmware for h in autopilots}
    missing = [name for name in stacks if reported.get(name) is None]
    if missing:
        return "Unknown", R.NO_FIRMWARE_DATA, f"no AUTOPILOT_VERSION yet from {', '.join(missing)}"
    firmware = {name: fw for name, fw in reported.items() if fw is not None and name in stacks}
    minimum = {Stack.PX4: requirement.px4_minimum, Stack.ARDUPILOT: requirement.ardupilot_minimum}
    below = [
        f"{name} runs {stacks[name].value} {fw.version}, below the required {low}"
        for name, fw in firmware.items()
        if (low := minimum[stacks[name]]) is not None
        and parse_version(fw.version) < parse_version(low)
    ]
    if below:
        return "False", R.FIRMWARE_BELOW_MINIMUM, "; ".join(below)
    if requirement.identical:
        differ = []
        for stack in Stack:
            builds = {
                n: (fw.version, fw.git_hash) for n, fw in firmware.items() if stacks[n] is stack
            }
            if len(set(builds.values())) > 1:
                differ.append(
                    ", ".join(f"{n} {v}" + (f" ({h})" if h else "") for n, (v, h) in builds.items())
                )
        if differ:
            return "False", R.FIRMWARE_VERSIONS_DIFFER, "not identical: " + "; ".join(differ)
    versions = ", ".join(f"{n} {fw.version}" for n, fw in firmware.items())
    return "True", R.FIRMWARE_ACCEPTABLE, f"meets the requirement: {versions}"
