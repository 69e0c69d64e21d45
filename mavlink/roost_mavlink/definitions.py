"""MAVLink messages declared field by field: what the agent reads and sends, and what PX4
sends that pymavlink's dialect lacks.

Why declarations (the agent's codec, :mod:`roost_mavlink.codec`, reads them): the agent
decodes a few fields of a few messages (:data:`AGENT_MESSAGES`: HEARTBEAT, SYS_STATUS,
ATTITUDE, GLOBAL_POSITION_INT, the estimator reports, EXTENDED_SYS_STATE, COMMAND_ACK,
the hub's COMMAND_LONG/INT, PARAM_VALUE, AUTOPILOT_VERSION, LOG_ENTRY, LOG_DATA) and
encodes a few (HEARTBEAT, COMMAND_LONG, REQUEST_DATA_STREAM, PARAM_REQUEST_READ,
PARAM_REQUEST_LIST, PARAM_SET, the LOG_REQUEST_* of the log protocol);
pymavlink's generated dialect, which has them all, costs several MB to import. Every other
message id is only checked and counted, from the generated table
:mod:`roost_mavlink.checked_messages`.

:data:`EXTRA_MESSAGES`: PX4 v1.16 streams five messages, unasked, that pymavlink's
generated ``ardupilotmega`` dialect (2.4.x) does not define: CURRENT_MODE (436, 0.5 Hz),
LINK_NODE_STATUS (8), TIME_ESTIMATE_TO_TARGET (380), EVENT (410) and
CURRENT_EVENT_SEQUENCE (411). A frame of an id nobody declared cannot have its CRC
checked, so it would be counted as unknown: real autopilot frames lost from the link's
accounting, indistinguishable from corruption. The agent reads none of their fields.

Each definition is what MAVLink's message XML says (``common.xml``; the four beside
CURRENT_MODE were in ``development.xml`` when they were introduced): the fields in
declaration order with their C types, then the extension fields. From that the wire
order (base fields sorted by type size, largest first, stable; extension fields after
them in declared order) and CRC_EXTRA (the CRC-16/MCRF4XX of ``"NAME "`` and
``"type name "`` of every base field in wire order, plus the array length byte for
arrays, folded to one byte) are computed, the way MAVLink's generators compute them, so
a definition cannot drift from its checksum. ``tests/unit/test_mavlink_codec.py`` checks
the computation against every message of pymavlink's dialect, each of
:data:`AGENT_MESSAGES` against pymavlink's, and ``tests/unit/test_agent_health_replay.py``
every definition against the frames of the recorded PX4 flights.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import fastcrc

# C type -> (struct code, size in bytes)
TYPES: dict[str, tuple[str, int]] = {
    "uint64_t": ("Q", 8),
    "int64_t": ("q", 8),
    "double": ("d", 8),
    "uint32_t": ("I", 4),
    "int32_t": ("i", 4),
    "float": ("f", 4),
    "uint16_t": ("H", 2),
    "int16_t": ("h", 2),
    "uint8_t": ("B", 1),
    "int8_t": ("b", 1),
    "char": ("s", 1),
}


@dataclass(frozen=True)
class FieldDef:
    """One field: its C base type, name and array length (0: a scalar)."""

    type: str
    name: str
    array: int = 0

    @property
    def size(self) -> int:
        return TYPES[self.type][1] * max(1, self.array)

    @property
    def code(self) -> str:
        """The struct format of the field (a scalar's code, ``Ns`` for char arrays)."""
        code = TYPES[self.type][0]
        if self.type == "char":
            return f"{max(1, self.array)}s"
        return f"{self.array}{code}" if self.array else code


@dataclass(frozen=True)
class MessageDef:
    """One message as its XML declares it: base fields in declaration order, then the
    extension fields (after ``<extensions/>``) in declaration order."""

    id: int
    name: str
    fields: tuple[FieldDef, ...]
    extensions: tuple[FieldDef, ...] = ()

    @property
    def base_order(self) -> tuple[FieldDef, ...]:
        """The base fields as they sit in the payload: largest type first, stable."""
        return tuple(sorted(self.fields, key=lambda f: -TYPES[f.type][1]))

    @property
    def wire_order(self) -> tuple[FieldDef, ...]:
        """Every field as it sits in the payload: the sorted base, then the extensions."""
        return self.base_order + self.extensions

    @property
    def min_length(self) -> int:
        """Payload bytes of the base fields (a MAVLink 1 payload)."""
        return sum(f.size for f in self.fields)

    @property
    def max_length(self) -> int:
        """Payload bytes with every extension field (MAVLink 2 before zero truncation)."""
        return self.min_length + sum(f.size for f in self.extensions)

    @property
    def crc_extra(self) -> int:
        return crc_extra(self.name, self.base_order)

    @property
    def unpacker(self) -> struct.Struct:
        return struct.Struct("<" + "".join(f.code for f in self.wire_order))


def crc_extra(name: str, wire_order: tuple[FieldDef, ...]) -> int:
    """MAVLink's CRC_EXTRA of a message from its name and wire-ordered base fields."""
    seed = bytearray(f"{name} ".encode())
    for f in wire_order:
        seed += f"{f.type} {f.name} ".encode()
        if f.array:
            seed.append(f.array)
    crc = fastcrc.crc16.mcrf4xx(bytes(seed))
    return (crc & 0xFF) ^ (crc >> 8)


Declared = tuple[str, str] | tuple[str, str, int]


def _message(
    msg_id: int, name: str, *fields: Declared, extensions: tuple[Declared, ...] = ()
) -> MessageDef:
    return MessageDef(
        msg_id,
        name,
        tuple(FieldDef(*f) for f in fields),
        tuple(FieldDef(*f) for f in extensions),
    )


_PARAMS = tuple(("float", f"param{i}") for i in range(1, 8))
_TARGET: tuple[Declared, ...] = (("uint8_t", "target_system"), ("uint8_t", "target_component"))

# The messages whose fields the agent reads (health, hub, command acks, parameters,
# firmware, the fence part of the mission protocol) or writes (its heartbeat, commands,
# ArduPilot stream requests, parameter reads and writes, fence uploads and read-backs),
# as common.xml / ardupilotmega.xml declare them.
AGENT_MESSAGES: dict[int, MessageDef] = {
    m.id: m
    for m in (
        _message(
            0,
            "HEARTBEAT",
            ("uint8_t", "type"),
            ("uint8_t", "autopilot"),
            ("uint8_t", "base_mode"),
            ("uint32_t", "custom_mode"),
            ("uint8_t", "system_status"),
            ("uint8_t", "mavlink_version"),
        ),
        _message(
            1,
            "SYS_STATUS",
            ("uint32_t", "onboard_control_sensors_present"),
            ("uint32_t", "onboard_control_sensors_enabled"),
            ("uint32_t", "onboard_control_sensors_health"),
            ("uint16_t", "load"),
            ("uint16_t", "voltage_battery"),
            ("int16_t", "current_battery"),
            ("int8_t", "battery_remaining"),
            ("uint16_t", "drop_rate_comm"),
            ("uint16_t", "errors_comm"),
            ("uint16_t", "errors_count1"),
            ("uint16_t", "errors_count2"),
            ("uint16_t", "errors_count3"),
            ("uint16_t", "errors_count4"),
            extensions=(
                ("uint32_t", "onboard_control_sensors_present_extended"),
                ("uint32_t", "onboard_control_sensors_enabled_extended"),
                ("uint32_t", "onboard_control_sensors_health_extended"),
            ),
        ),
        _message(
            20,
            "PARAM_REQUEST_READ",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("char", "param_id", 16),
            ("int16_t", "param_index"),
        ),
        _message(
            21, "PARAM_REQUEST_LIST", ("uint8_t", "target_system"), ("uint8_t", "target_component")
        ),
        _message(
            22,
            "PARAM_VALUE",
            ("char", "param_id", 16),
            ("float", "param_value"),
            ("uint8_t", "param_type"),
            ("uint16_t", "param_count"),
            ("uint16_t", "param_index"),
        ),
        _message(
            23,
            "PARAM_SET",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("char", "param_id", 16),
            ("float", "param_value"),
            ("uint8_t", "param_type"),
        ),
        _message(
            30,
            "ATTITUDE",
            ("uint32_t", "time_boot_ms"),
            ("float", "roll"),
            ("float", "pitch"),
            ("float", "yaw"),
            ("float", "rollspeed"),
            ("float", "pitchspeed"),
            ("float", "yawspeed"),
        ),
        _message(
            33,
            "GLOBAL_POSITION_INT",
            ("uint32_t", "time_boot_ms"),
            ("int32_t", "lat"),
            ("int32_t", "lon"),
            ("int32_t", "alt"),
            ("int32_t", "relative_alt"),
            ("int16_t", "vx"),
            ("int16_t", "vy"),
            ("int16_t", "vz"),
            ("uint16_t", "hdg"),
        ),
        _message(
            40,
            "MISSION_REQUEST",
            *_TARGET,
            ("uint16_t", "seq"),
            extensions=(("uint8_t", "mission_type"),),
        ),
        _message(43, "MISSION_REQUEST_LIST", *_TARGET, extensions=(("uint8_t", "mission_type"),)),
        _message(
            44,
            "MISSION_COUNT",
            *_TARGET,
            ("uint16_t", "count"),
            extensions=(("uint8_t", "mission_type"),),
        ),
        _message(
            47,
            "MISSION_ACK",
            *_TARGET,
            ("uint8_t", "type"),
            extensions=(("uint8_t", "mission_type"),),
        ),
        _message(
            51,
            "MISSION_REQUEST_INT",
            *_TARGET,
            ("uint16_t", "seq"),
            extensions=(("uint8_t", "mission_type"),),
        ),
        _message(
            66,
            "REQUEST_DATA_STREAM",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("uint8_t", "req_stream_id"),
            ("uint16_t", "req_message_rate"),
            ("uint8_t", "start_stop"),
        ),
        _message(
            73,
            "MISSION_ITEM_INT",
            *_TARGET,
            ("uint16_t", "seq"),
            ("uint8_t", "frame"),
            ("uint16_t", "command"),
            ("uint8_t", "current"),
            ("uint8_t", "autocontinue"),
            *_PARAMS[:4],
            ("int32_t", "x"),
            ("int32_t", "y"),
            ("float", "z"),
            extensions=(("uint8_t", "mission_type"),),
        ),
        _message(
            75,
            "COMMAND_INT",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("uint8_t", "frame"),
            ("uint16_t", "command"),
            ("uint8_t", "current"),
            ("uint8_t", "autocontinue"),
            *_PARAMS[:4],
            ("int32_t", "x"),
            ("int32_t", "y"),
            ("float", "z"),
        ),
        _message(
            76,
            "COMMAND_LONG",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("uint16_t", "command"),
            ("uint8_t", "confirmation"),
            *_PARAMS,
        ),
        _message(
            77,
            "COMMAND_ACK",
            ("uint16_t", "command"),
            ("uint8_t", "result"),
            extensions=(
                ("uint8_t", "progress"),
                ("int32_t", "result_param2"),
                ("uint8_t", "target_system"),
                ("uint8_t", "target_component"),
            ),
        ),
        # the log protocol: the flight recorder fetches the autopilots' logs after landing
        _message(
            117,
            "LOG_REQUEST_LIST",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("uint16_t", "start"),
            ("uint16_t", "end"),
        ),
        _message(
            118,
            "LOG_ENTRY",
            ("uint16_t", "id"),
            ("uint16_t", "num_logs"),
            ("uint16_t", "last_log_num"),
            ("uint32_t", "time_utc"),
            ("uint32_t", "size"),
        ),
        _message(
            119,
            "LOG_REQUEST_DATA",
            ("uint8_t", "target_system"),
            ("uint8_t", "target_component"),
            ("uint16_t", "id"),
            ("uint32_t", "ofs"),
            ("uint32_t", "count"),
        ),
        _message(
            120,
            "LOG_DATA",
            ("uint16_t", "id"),
            ("uint32_t", "ofs"),
            ("uint8_t", "count"),
            ("uint8_t", "data", 90),
        ),
        _message(
            122, "LOG_REQUEST_END", ("uint8_t", "target_system"), ("uint8_t", "target_component")
        ),
        _message(
            148,
            "AUTOPILOT_VERSION",
            ("uint64_t", "capabilities"),
            ("uint32_t", "flight_sw_version"),
            ("uint32_t", "middleware_sw_version"),
            ("uint32_t", "os_sw_version"),
            ("uint32_t", "board_version"),
            ("uint8_t", "flight_custom_version", 8),
            ("uint8_t", "middleware_custom_version", 8),
            ("uint8_t", "os_custom_version", 8),
            ("uint16_t", "vendor_id"),
            ("uint16_t", "product_id"),
            ("uint64_t", "uid"),
            extensions=(("uint8_t", "uid2", 18),),
        ),
        _message(
            193,
            "EKF_STATUS_REPORT",
            ("uint16_t", "flags"),
            ("float", "velocity_variance"),
            ("float", "pos_horiz_variance"),
            ("float", "pos_vert_variance"),
            ("float", "compass_variance"),
            ("float", "terrain_alt_variance"),
            extensions=(("float", "airspeed_variance"),),
        ),
        _message(
            230,
            "ESTIMATOR_STATUS",
            ("uint64_t", "time_usec"),
            ("uint16_t", "flags"),
            ("float", "vel_ratio"),
            ("float", "pos_horiz_ratio"),
            ("float", "pos_vert_ratio"),
            ("float", "mag_ratio"),
            ("float", "hagl_ratio"),
            ("float", "tas_ratio"),
            ("float", "pos_horiz_accuracy"),
            ("float", "pos_vert_accuracy"),
        ),
        _message(
            245,
            "EXTENDED_SYS_STATE",
            ("uint8_t", "vtol_state"),
            ("uint8_t", "landed_state"),
        ),
    )
}


EXTRA_MESSAGES: dict[int, MessageDef] = {
    m.id: m
    for m in (
        _message(
            8,
            "LINK_NODE_STATUS",
            ("uint64_t", "timestamp"),
            ("uint8_t", "tx_buf"),
            ("uint8_t", "rx_buf"),
            ("uint32_t", "tx_rate"),
            ("uint32_t", "rx_rate"),
            ("uint16_t", "rx_parse_err"),
            ("uint16_t", "tx_overflows"),
            ("uint16_t", "rx_overflows"),
            ("uint32_t", "messages_sent"),
            ("uint32_t", "messages_received"),
            ("uint32_t", "messages_lost"),
        ),
        _message(
            380,
            "TIME_ESTIMATE_TO_TARGET",
            ("int32_t", "safe_return"),
            ("int32_t", "land"),
            ("int32_t", "mission_next_item"),
            ("int32_t", "mission_end"),
            ("int32_t", "commanded_action"),
        ),
        _message(
            410,
            "EVENT",
            ("uint8_t", "destination_component"),
            ("uint8_t", "destination_system"),
            ("uint32_t", "id"),
            ("uint32_t", "event_time_boot_ms"),
            ("uint16_t", "sequence"),
            ("uint8_t", "log_levels"),
            ("uint8_t", "arguments", 40),
        ),
        _message(411, "CURRENT_EVENT_SEQUENCE", ("uint16_t", "sequence"), ("uint8_t", "flags")),
        _message(
            436,
            "CURRENT_MODE",
            ("uint8_t", "standard_mode"),
            ("uint32_t", "custom_mode"),
            ("uint32_t", "intended_custom_mode"),
        ),
    )
}
