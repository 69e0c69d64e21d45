"""Check a datagram's MAVLink 2 frames cheaply; decode a message's fields only when read.

Why: the agent hears several hundred messages a second per autopilot and reads a few
fields of a few of them (heartbeats, status, attitude, position, acks); the rest it only
counts and checks ``time_boot_ms`` of. pymavlink's parser builds a full message object
for every frame, which was most of the agent's per-message cost on a companion computer.

:func:`split` accepts a datagram only when it is nothing but well-formed MAVLink 2 frames
that pymavlink would decode without complaint: the v2 magic, no incompatibility flag but
signing, whole frames back to back, a message id of the dialect and a good CRC (with its
CRC_EXTRA, computed by ``fastcrc`` as pymavlink does). Anything else — MAVLink 1, garbage,
a bad CRC, a truncated or unknown frame — returns None and the caller parses the datagram
with pymavlink exactly as before, so hostile traffic meets the same judgement either way.

A :class:`Frame` answers what pymavlink's message does: ``get_type``, ``get_srcSystem``,
``get_srcComponent``, ``get_seq``, ``get_msgId``, ``get_msgbuf``; a scalar field is read
straight from the payload (zero-padded, as MAVLink 2 truncates trailing zeros) and
anything else (arrays, strings, ``pack``, ``to_dict``...) from the pymavlink message,
decoded once on first use. A field another message type has and this one lacks raises
AttributeError without decoding (``getattr(msg, "time_boot_ms", None)`` stays cheap).

The dialect is pymavlink's ``ardupilotmega`` plus the messages real autopilots send that
it lacks (:data:`roost_mavlink.definitions.EXTRA_MESSAGES`: PX4's CURRENT_MODE, EVENT...):
their frames are checked and counted like any other and answer their scalar fields; they
have no pymavlink message behind them. :func:`known` checks such a frame where pymavlink's
parser returned it as an unknown message (links whose bytes go through that parser:
TCP, serial, datagrams the fast path refuses).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any

import fastcrc
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_mavlink.definitions import EXTRA_MESSAGES, MessageDef

V2_MAGIC = 0xFD
V2_HEADER = 10
CRC_BYTES = 2
SIGNATURE_BYTES = 13
IFLAG_SIGNED = 0x01

_crc16 = fastcrc.crc16.mcrf4xx
_HEADER = struct.Struct("<BBBBBBBHB")  # magic len incompat compat seq sys comp id_lo id_hi
_CRC = struct.Struct("<H")
_TOKEN = re.compile(r"(\d*)([a-zA-Z?])")


@dataclass(frozen=True)
class Layout:
    """What reading one message type needs: its name, CRC_EXTRA, full payload size, and
    where each scalar field sits (payload offset, struct)."""

    name: str
    crc_extra: bytes
    size: int
    scalars: dict[str, tuple[int, struct.Struct]]
    fields: frozenset[str]
    decodable: bool = True  # pymavlink can decode it (False: one of EXTRA_MESSAGES)


def _layout(cls: Any) -> Layout:
    fmt = cls.unpacker.format
    tokens = _TOKEN.findall(fmt[1:])
    scalars: dict[str, tuple[int, struct.Struct]] = {}
    if len(tokens) == len(cls.ordered_fieldnames):
        offset = 0
        for name, (count, code) in zip(cls.ordered_fieldnames, tokens, strict=True):
            unit = struct.Struct("<" + count + code)
            if not count and code != "s":
                scalars[name] = (offset, unit)
            offset += unit.size
    return Layout(
        name=cls.msgname,
        crc_extra=bytes([cls.crc_extra]),
        size=cls.unpacker.size,
        scalars=scalars,
        fields=frozenset(cls.fieldnames),
    )


def _extra_layout(message: MessageDef) -> Layout:
    scalars: dict[str, tuple[int, struct.Struct]] = {}
    offset = 0
    for f in message.wire_order:
        unit = struct.Struct("<" + f.code)
        if not f.array:
            scalars[f.name] = (offset, unit)
        offset += unit.size
    return Layout(
        name=message.name,
        crc_extra=bytes([message.crc_extra]),
        size=offset,
        scalars=scalars,
        fields=frozenset(f.name for f in message.fields),
        decodable=False,
    )


_LAYOUTS: dict[int, Layout] = {}  # built on first sight: an autopilot sends a few dozen types
_ANY_FIELD = frozenset().union(
    *(cls.fieldnames for cls in mavlink.mavlink_map.values()),
    *({f.name for f in m.fields} for m in EXTRA_MESSAGES.values()),
)


def layout(msg_id: int) -> Layout | None:
    """The layout of a message id of the dialect (None: not one of its messages)."""
    known = _LAYOUTS.get(msg_id)
    if known is None:
        cls = mavlink.mavlink_map.get(msg_id)
        extra = EXTRA_MESSAGES.get(msg_id)
        if cls is not None:
            known = _layout(cls)
        elif extra is not None:
            known = _extra_layout(extra)
        else:
            return None
        _LAYOUTS[msg_id] = known
    return known


_DECODER = mavlink.MAVLink(None)  # decode() keeps no state without a signing key


class Frame:
    """One checked MAVLink 2 frame (see the module docstring)."""

    __slots__ = ("_data", "_end", "_full", "_header", "_layout", "_mlen", "_start")

    def __init__(
        self,
        data: bytes,
        start: int,
        end: int,
        header: tuple[int, ...],
        layout: Layout,
    ) -> None:
        self._data = data
        self._start = start
        self._end = end
        self._mlen = header[1]
        self._header = header
        self._layout = layout
        self._full: Any = None

    def get_type(self) -> str:
        return self._layout.name

    def get_msgId(self) -> int:  # noqa: N802 - pymavlink's name
        header = self._header
        return header[7] | (header[8] << 16)

    def get_srcSystem(self) -> int:  # noqa: N802 - pymavlink's name
        return self._header[5]

    def get_srcComponent(self) -> int:  # noqa: N802 - pymavlink's name
        return self._header[6]

    def get_seq(self) -> int:
        return self._header[4]

    def get_msgbuf(self) -> bytearray:
        return bytearray(self._data[self._start : self._end])

    def decoded(self) -> Any:
        """The pymavlink message (decoded on first use)."""
        full = self._full
        if full is None:
            full = self._full = _DECODER.decode(self.get_msgbuf())
        return full

    def __getattr__(self, name: str) -> Any:
        layout = self._layout
        scalar = layout.scalars.get(name)
        if scalar is not None:
            offset, unit = scalar
            at = self._start + V2_HEADER + offset
            if offset + unit.size <= self._mlen:
                return unit.unpack_from(self._data, at)[0]
            payload = self._data[self._start + V2_HEADER : self._start + V2_HEADER + self._mlen]
            return unit.unpack_from(payload + bytes(layout.size - self._mlen), offset)[0]
        if (name in _ANY_FIELD and name not in layout.fields) or not layout.decodable:
            raise AttributeError(name)
        return getattr(self.decoded(), name)

    def __repr__(self) -> str:
        return f"Frame({self._layout.name}, seq {self.get_seq()})"


def split(data: bytes) -> list[Frame] | None:
    """The frames of a datagram made only of good MAVLink 2 frames; None otherwise."""
    frames: list[Frame] = []
    start, total = 0, len(data)
    while start < total:
        if total - start < V2_HEADER + CRC_BYTES or data[start] != V2_MAGIC:
            return None
        header = _HEADER.unpack_from(data, start)
        mlen, incompat = header[1], header[2]
        if incompat & ~IFLAG_SIGNED:
            return None
        crc_at = start + V2_HEADER + mlen
        end = crc_at + CRC_BYTES + (SIGNATURE_BYTES if incompat else 0)
        if end > total:
            return None
        msg_id = header[7] | (header[8] << 16)
        kind = _LAYOUTS.get(msg_id) or layout(msg_id)
        if kind is None:
            return None
        if _crc16(data[start + 1 : crc_at] + kind.crc_extra) != _CRC.unpack_from(data, crc_at)[0]:
            return None
        frames.append(Frame(data, start, end, header, kind))
        start = end
    return frames


def known(unknown: Any) -> Frame | None:
    """The frame behind pymavlink's ``MAVLink_unknown`` (a message id its dialect lacks,
    which pymavlink returns without checking its CRC) when it is a good frame of one of
    :data:`EXTRA_MESSAGES`; None otherwise (still unknown, or a bad CRC)."""
    data = bytes(getattr(unknown, "data", b""))
    if len(data) < V2_HEADER or data[0] != V2_MAGIC:
        return None
    if (data[7] | (data[8] << 8) | (data[9] << 16)) not in EXTRA_MESSAGES:
        return None
    frames = split(data)
    return frames[0] if frames is not None and len(frames) == 1 else None
