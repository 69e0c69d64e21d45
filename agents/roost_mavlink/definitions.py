"""MAVLink messages real autopilots send that the agent's pymavlink dialect lacks.

Why: PX4 v1.16 streams five messages, unasked, that pymavlink's generated
``ardupilotmega`` dialect (2.4.x) does not define: CURRENT_MODE (436, 0.5 Hz),
LINK_NODE_STATUS (8), TIME_ESTIMATE_TO_TARGET (380), EVENT (410) and
CURRENT_EVENT_SEQUENCE (411). A frame of an id the dialect does not know cannot have its
CRC checked, so it was counted as bad data: real autopilot frames lost from the link's
accounting, indistinguishable from corruption. The agent reads none of their fields; it
needs to know them only to check them and count them as the autopilot's own traffic.

Each definition is what MAVLink's message XML says (``common.xml``; the four beside
CURRENT_MODE were in ``development.xml`` when they were introduced): the fields in
declaration order with their C types. From that the wire order (fields sorted by type
size, largest first, stable; extension fields, none here, would stay last) and
CRC_EXTRA (the CRC-16/MCRF4XX of ``"NAME "`` and ``"type name "`` of every wire-order
field, plus the array length byte for arrays, folded to one byte) are computed, the
way MAVLink's generators compute them, so a definition cannot drift from its checksum.
``tests/unit/test_agent_frames.py`` checks the computation against pymavlink's dialect
and every definition against the frames of the recorded PX4 flights.
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
    """One message as its XML declares it (fields in declaration order)."""

    id: int
    name: str
    fields: tuple[FieldDef, ...]

    @property
    def wire_order(self) -> tuple[FieldDef, ...]:
        """The fields as they sit in the payload: largest type first, stable."""
        return tuple(sorted(self.fields, key=lambda f: -TYPES[f.type][1]))

    @property
    def crc_extra(self) -> int:
        return crc_extra(self.name, self.wire_order)

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


def _message(msg_id: int, name: str, *fields: tuple[str, str] | tuple[str, str, int]) -> MessageDef:
    return MessageDef(msg_id, name, tuple(FieldDef(*f) for f in fields))


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
