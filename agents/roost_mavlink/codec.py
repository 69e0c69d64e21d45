"""The agent's MAVLink codec: frames from bytes, checked, decoded field by field on demand.

Why our own: pymavlink's generated dialect costs the agent ~7 MB of memory to import
(and its signing pulls in OpenSSL), on a companion computer where the agent should stay
small, and its parser builds a full message object for every frame, which was most of
the agent's per-message cost. The agent reads a few fields of a few message types
(heartbeats, status, attitude, position, acks) and only checks and counts the rest.

What a message id is known by (:func:`layout`):

- the messages the agent decodes or encodes, and those PX4 sends that pymavlink's
  dialect lacks, are declared field by field (:mod:`roost_mavlink.definitions`); every
  field reads;
- every other message of the ``ardupilotmega`` dialect is a row of
  :data:`roost_mavlink.checked_messages.CHECKED_MESSAGES` (name, CRC_EXTRA, lengths, and
  where ``time_boot_ms`` / ``target_system`` / ``target_component`` / ``target`` sit); only
  those fields read, any other raises AttributeError.

Judgement of bytes (:func:`scan`), the rules pymavlink's parser applies with robust
parsing, so hostile traffic meets the same judgement as before:

- bytes before a frame start (0xFD MAVLink 2, 0xFE MAVLink 1) are one :class:`BadData`;
- a frame's length comes from its header (plus the 13-byte signature when the signed
  flag is set); bytes that end inside a frame are left unconsumed (a datagram reader
  counts them truncated, a stream parser keeps them for the next read);
- a MAVLink 2 frame with an incompatibility flag other than signing is :class:`BadData`;
- a frame of an id nobody declared is an :class:`UnknownFrame` (its CRC cannot be
  checked); a known id with a bad CRC is :class:`BadData`, consuming the whole frame;
- a payload shorter than the message's is zero-padded (MAVLink 2 drops trailing zeros),
  a longer one's extra bytes are ignored; a signature is not judged here (see
  :mod:`roost_mavlink.signing`).

A :class:`Frame` answers what the agent asked of pymavlink's messages: ``get_type``,
``get_srcSystem``, ``get_srcComponent``, ``get_seq``, ``get_msgId``, ``get_msgbuf`` and
field attributes. :func:`encode` writes the MAVLink 2 frames the agent sends (trailing
zero bytes truncated, as MAVLink 2 senders do).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import fastcrc

from roost_mavlink.checked_messages import CHECKED_MESSAGES
from roost_mavlink.definitions import AGENT_MESSAGES, EXTRA_MESSAGES, MessageDef

V2_MAGIC = 0xFD
V1_MAGIC = 0xFE
V2_HEADER = 10
V1_HEADER = 6
CRC_BYTES = 2
SIGNATURE_BYTES = 13
IFLAG_SIGNED = 0x01
MAVLINK_VERSION = 3  # HEARTBEAT.mavlink_version of every MAVLink 2 sender

# Every message declared field by field (definitions.py), by id.
DECLARED: dict[int, MessageDef] = {**EXTRA_MESSAGES, **AGENT_MESSAGES}
_BY_NAME = {m.name: m for m in DECLARED.values()}

_crc16 = fastcrc.crc16.mcrf4xx
_V2_HEADER = struct.Struct("<BBBBBBBHB")  # magic len incompat compat seq sys comp id_lo id_hi
_V1_HEADER = struct.Struct("<BBBBBB")  # magic len seq sys comp id
_CRC = struct.Struct("<H")
_FRAME_START = re.compile(b"[\xfd\xfe]")


def message(name: str) -> MessageDef:
    """The declaration of a message the agent decodes or encodes (KeyError otherwise)."""
    return _BY_NAME[name]


def frame_crc(body: bytes | bytearray, crc_extra: int) -> int:
    """The CRC of a frame: X.25 over the header after the magic and the payload, then the
    message's CRC_EXTRA byte."""
    return int(_crc16(bytes(body) + bytes((crc_extra,))))


def crc_extra_of(msg_id: int) -> int | None:
    """CRC_EXTRA of a known message id; None for an id nobody declared."""
    known = layout(msg_id)
    return None if known is None else known.crc_extra


@dataclass(frozen=True)
class Layout:
    """What reading one message type needs: its name, CRC_EXTRA, full payload size, and
    where each readable field sits (payload offset, struct; ``text`` for char arrays)."""

    name: str
    crc_extra: int
    size: int
    scalars: dict[str, tuple[int, struct.Struct]]
    arrays: dict[str, tuple[int, struct.Struct, bool]]
    crc_byte: bytes  # CRC_EXTRA as the byte appended to what the CRC covers

    @property
    def fields(self) -> tuple[str, ...]:
        return (*self.scalars, *self.arrays)


def _declared_layout(message: MessageDef) -> Layout:
    scalars: dict[str, tuple[int, struct.Struct]] = {}
    arrays: dict[str, tuple[int, struct.Struct, bool]] = {}
    offset = 0
    for f in message.wire_order:
        unit = struct.Struct("<" + f.code)
        if f.array or f.type == "char":
            arrays[f.name] = (offset, unit, f.type == "char")
        else:
            scalars[f.name] = (offset, unit)
        offset += unit.size
    crc = message.crc_extra
    return Layout(message.name, crc, offset, scalars, arrays, bytes((crc,)))


def _checked_layout(msg_id: int) -> Layout | None:
    entry = CHECKED_MESSAGES.get(msg_id)
    if entry is None:
        return None
    name, crc_extra, _, max_length, common = entry
    scalars = {field: (offset, struct.Struct("<" + code)) for field, offset, code in common}
    return Layout(name, crc_extra, max_length, scalars, {}, bytes((crc_extra,)))


_LAYOUTS: dict[int, Layout] = {}  # built on first sight: an autopilot sends a few dozen types


def layout(msg_id: int) -> Layout | None:
    """The layout of a known message id (None: nobody declared it)."""
    known = _LAYOUTS.get(msg_id)
    if known is None:
        declared = DECLARED.get(msg_id)
        known = _declared_layout(declared) if declared is not None else _checked_layout(msg_id)
        if known is None:
            return None
        _LAYOUTS[msg_id] = known
    return known


class Frame:
    """One CRC-checked frame of a known message (see the module docstring)."""

    __slots__ = ("_at", "_data", "_end", "_header", "_layout", "_start")

    def __init__(  # noqa: PLR0917 - built for every frame received: positional is cheaper
        self,
        data: bytes,
        start: int,
        end: int,
        header: tuple[int, ...],  # as a MAVLink 2 header unpacks (see _V2_HEADER)
        layout: Layout,
        at: int,  # where the payload begins
    ) -> None:
        self._data = data
        self._start = start
        self._end = end
        self._header = header
        self._layout = layout
        self._at = at

    def get_type(self) -> str:
        return self._layout.name

    def get_msgId(self) -> int:  # noqa: N802 - the name MAVLink tools use
        header = self._header
        return header[7] | (header[8] << 16)

    def get_srcSystem(self) -> int:  # noqa: N802 - the name MAVLink tools use
        return self._header[5]

    def get_srcComponent(self) -> int:  # noqa: N802 - the name MAVLink tools use
        return self._header[6]

    def get_seq(self) -> int:
        return self._header[4]

    def get_source(self) -> tuple[int, int]:
        """(system id, component id) of the sender, in one call for the reader's check."""
        header = self._header
        return header[5], header[6]

    def get_msgbuf(self) -> bytes:
        """The whole frame as received (signature included)."""
        return self._data[self._start : self._end]

    def _padded(self) -> bytes:
        """The payload zero-padded to the message's full size (longer: as received)."""
        at, mlen = self._at, self._header[1]
        raw = self._data[at : at + mlen]
        missing = self._layout.size - mlen
        return raw + bytes(missing) if missing > 0 else raw

    def __getattr__(self, name: str) -> Any:
        layout = self._layout
        scalar = layout.scalars.get(name)
        if scalar is not None:
            offset, unit = scalar
            if offset + unit.size <= self._header[1]:
                return unit.unpack_from(self._data, self._at + offset)[0]
            return unit.unpack_from(self._padded(), offset)[0]
        array = layout.arrays.get(name)
        if array is None:
            raise AttributeError(name)
        offset, unit, text = array
        values = unit.unpack_from(self._padded(), offset)
        return values[0].rstrip(b"\0") if text else list(values)

    def to_dict(self) -> dict[str, Any]:
        """Every readable field by name, and the type as ``mavpackettype``."""
        out: dict[str, Any] = {"mavpackettype": self.get_type()}
        for name in self._layout.fields:
            out[name] = getattr(self, name)
        return out

    def with_field(self, name: str, value: int) -> bytes:
        """This frame with one scalar field set to ``value``: same sender, sequence and
        MAVLink version, unsigned (a signature covers what changed), CRC recomputed."""
        offset, unit = self._layout.scalars[name]
        _, mlen, _, compat, seq, sys, comp, _, _ = self._header
        msg_id = self.get_msgId()
        payload = bytearray(self._data[self._at : self._at + mlen])
        if len(payload) < offset + unit.size:
            payload += bytes(offset + unit.size - len(payload))
        unit.pack_into(payload, offset, value)
        if self._data[self._start] == V1_MAGIC:
            body = _V1_HEADER.pack(V1_MAGIC, len(payload), seq, sys, comp, msg_id)[1:]
        else:
            payload = _truncated(payload)
            body = _v2_header(
                mlen=len(payload), compat=compat, seq=seq, sys=sys, comp=comp, msg_id=msg_id
            )
        body += payload
        magic = self._data[self._start]
        return bytes((magic,)) + body + _CRC.pack(frame_crc(body, self._layout.crc_extra))

    def __repr__(self) -> str:
        return f"Frame({self._layout.name}, seq {self.get_seq()})"


class BadData:
    """Bytes that are no frame: a bad prefix, a bad CRC, unknown incompatibility flags."""

    __slots__ = ("data", "reason")

    def __init__(self, data: bytes, reason: str) -> None:
        self.data = data
        self.reason = reason

    def get_type(self) -> str:
        return "BAD_DATA"

    def get_msgbuf(self) -> bytes:
        return self.data

    def __repr__(self) -> str:
        return f"BadData({self.reason}, {len(self.data)} bytes)"


class UnknownFrame:
    """A well-framed frame of an id nobody declared: its CRC cannot be checked."""

    __slots__ = ("data", "msg_id")

    def __init__(self, data: bytes, msg_id: int) -> None:
        self.data = data
        self.msg_id = msg_id

    def get_type(self) -> str:
        return f"UNKNOWN_{self.msg_id}"

    def get_msgId(self) -> int:  # noqa: N802 - the name MAVLink tools use
        return self.msg_id

    def get_msgbuf(self) -> bytes:
        return self.data

    def __repr__(self) -> str:
        return f"UnknownFrame({self.msg_id})"


Parsed = Frame | UnknownFrame | BadData


def _v1_frame(data: bytes, start: int, end: int) -> Parsed:
    """Judge the MAVLink 1 frame ``data[start:end]``."""
    _, mlen, seq, sys, comp, msg_id = _V1_HEADER.unpack_from(data, start)
    kind = _LAYOUTS.get(msg_id) or layout(msg_id)
    if kind is None:
        return UnknownFrame(data[start:end], msg_id)
    crc_at = start + V1_HEADER + mlen
    if _crc16(data[start + 1 : crc_at] + kind.crc_byte) != _CRC.unpack_from(data, crc_at)[0]:
        return BadData(data[start:end], f"bad CRC ({kind.name})")
    header = (V1_MAGIC, mlen, 0, 0, seq, sys, comp, msg_id, 0)
    return Frame(data, start, end, header, kind, start + V1_HEADER)


def scan(data: bytes) -> tuple[list[Parsed], int]:
    """Everything ``data`` holds, in order, and how many bytes of it that used: less than
    ``len(data)`` when it ends inside a frame (the rest is that frame's beginning).

    (The MAVLink 2 path is written out in the loop: it runs for every frame received.)"""
    out: list[Parsed] = []
    append = out.append
    start, total = 0, len(data)
    while start < total:
        magic = data[start]
        if magic == V2_MAGIC:
            if total - start < V2_HEADER + CRC_BYTES:  # the shortest frame ends past it
                break
            header = _V2_HEADER.unpack_from(data, start)
            incompat = header[2]
            end = start + V2_HEADER + header[1] + CRC_BYTES
            if incompat & IFLAG_SIGNED:
                end += SIGNATURE_BYTES
            if end > total:
                break
            if incompat & ~IFLAG_SIGNED:
                append(BadData(data[start:end], f"incompatibility flags 0x{incompat:02x}"))
            else:
                msg_id = header[7] | (header[8] << 16)
                kind = _LAYOUTS.get(msg_id) or layout(msg_id)
                crc_at = start + V2_HEADER + header[1]
                if kind is None:
                    append(UnknownFrame(data[start:end], msg_id))
                elif (
                    _crc16(data[start + 1 : crc_at] + kind.crc_byte)
                    != _CRC.unpack_from(data, crc_at)[0]
                ):
                    append(BadData(data[start:end], f"bad CRC ({kind.name})"))
                else:
                    append(Frame(data, start, end, header, kind, start + V2_HEADER))
        elif magic == V1_MAGIC:
            if total - start < V1_HEADER + CRC_BYTES:  # the shortest frame ends past it
                break
            end = start + V1_HEADER + data[start + 1] + CRC_BYTES
            if end > total:
                break
            append(_v1_frame(data, start, end))
        else:
            found = _FRAME_START.search(data, start + 1)
            end = total if found is None else found.start()
            append(BadData(data[start:end], "bad prefix"))
        start = end
    return out, start


class StreamParser:
    """Frames from a byte stream (TCP, serial) that may split them across reads; what a
    read leaves unfinished (at most one frame's beginning) waits for the next."""

    def __init__(self) -> None:
        self._pending = b""

    def feed(self, data: bytes) -> list[Parsed]:
        buffer = self._pending + data if self._pending else data
        items, used = scan(buffer)
        self._pending = buffer[used:]
        return items

    def pending(self) -> int:
        """Bytes of an unfinished frame held for the next read."""
        return len(self._pending)


def _truncated(payload: bytearray) -> bytearray:
    """MAVLink 2 drops a payload's trailing zero bytes (at least one byte stays)."""
    end = len(payload)
    while end > 1 and payload[end - 1] == 0:
        end -= 1
    return payload[:end]


def _v2_header(*, mlen: int, compat: int, seq: int, sys: int, comp: int, msg_id: int) -> bytes:
    """A MAVLink 2 header without its magic byte (what the CRC covers), unsigned."""
    return _V2_HEADER.pack(
        V2_MAGIC, mlen, 0, compat, seq, sys, comp, msg_id & 0xFFFF, msg_id >> 16
    )[1:]


def encode(
    message: MessageDef, values: Mapping[str, int | float], *, seq: int, system: int, component: int
) -> bytes:
    """One unsigned MAVLink 2 frame of ``message``. Every base field must be given;
    extension fields not given are zero. Arrays are not written (the agent sends none)."""
    args: list[int | float] = []
    for f in message.wire_order:
        if f.array or f.type == "char":
            raise ValueError(f"{message.name}.{f.name}: arrays are not encoded")
        if f.name in values:
            args.append(values[f.name])
        elif f in message.extensions:
            args.append(0)
        else:
            raise ValueError(f"{message.name}: no value for {f.name}")
    unknown = set(values) - {f.name for f in message.wire_order}
    if unknown:
        raise ValueError(f"{message.name} has no field {sorted(unknown)}")
    payload = _truncated(bytearray(message.unpacker.pack(*args)))
    header = _v2_header(
        mlen=len(payload), compat=0, seq=seq & 0xFF, sys=system, comp=component, msg_id=message.id
    )
    body = header + payload
    return bytes((V2_MAGIC,)) + body + _CRC.pack(frame_crc(body, message.crc_extra))


class Encoder:
    """Frames from one system and component, numbered in sending order (the caller keeps
    sends in order, e.g. under a write lock)."""

    def __init__(self, system: int, component: int) -> None:
        self.system = system
        self.component = component
        self.seq = 0

    def encode(self, name: str, **values: int | float) -> bytes:
        frame = encode(
            message(name), values, seq=self.seq, system=self.system, component=self.component
        )
        self.seq = (self.seq + 1) & 0xFF
        return frame


__all__ = [
    "CRC_BYTES",
    "DECLARED",
    "IFLAG_SIGNED",
    "MAVLINK_VERSION",
    "SIGNATURE_BYTES",
    "V1_HEADER",
    "V1_MAGIC",
    "V2_HEADER",
    "V2_MAGIC",
    "BadData",
    "Encoder",
    "Frame",
    "Layout",
    "Parsed",
    "StreamParser",
    "UnknownFrame",
    "crc_extra_of",
    "encode",
    "frame_crc",
    "layout",
    "message",
    "scan",
]
