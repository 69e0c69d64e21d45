"""The agent's MAVLink codec: frames from bytes, checked, decoded field by field on demand.

Why our own: pymavlink's generated dialect costs the agent several times this codec's
memory to import (and its signing pulls in OpenSSL; docs/performance.md#memory), on a
companion computer where the agent should stay small, and its parser builds a full
message object for every frame, which would be most of the agent's per-message cost.
The agent reads a few fields of a few message types (heartbeats, status, attitude,
position, acks) and only checks and counts the rest.

What a message id is known by (:func:`layout`):

- the messages the agent decodes or encodes, and those PX4 sends that pymavlink's
  dialect lacks, are declared field by field (:mod:`roost_mavlink.definitions`); every
  field reads;
- every other message of the ``ardupilotmega`` dialect is a row of
  :data:`roost_mavlink.checked_messages.CHECKED_MESSAGES` (name, CRC_EXTRA, lengths, and
  where ``time_boot_ms`` / ``target_system`` / ``target_component`` / ``target`` sit); only
  those fields read, any other raises AttributeError.

Judgement of bytes (:func:`scan`), the rules pymavlink's parser applies with robust
parsing, so hostile traffic meets the same judgement as it would there:

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import fastcrc

from roost_mavlink.checked_messages import CHECKED_MESSAGES
from roost_mavlink.definitions import AGENT_MESSAGES, EXTRA_MESSAGES, MessageDef

V2_MAGIC: Final = 0xFD
V1_MAGIC: Final = 0xFE
V2_HEADER: Final = 10
V1_HEADER: Final = 6
CRC_BYTES: Final = 2
SIGNATURE_BYTES: Final = 13
IFLAG_SIGNED: Final = 0x01
MAVLINK_VERSION = 3  # HEARTBEAT.mavlink_version of every MAVLink 2 sender

# Every message declared field by field (definitions.py), by id.
DECLARED: dict[int, MessageDef] = {**EXTRA_MESSAGES, **AGENT_MESSAGES}
_BY_NAME = {m.name: m for m in DECLARED.values()}

# Final: the compiled build reads them as native globals, not from the module's dict.
_crc16: Final = fastcrc.crc16.mcrf4xx
_V2_HEADER: Final = struct.Struct(
    "<BBBBBBBHB"
)  # magic len incompat compat seq sys comp id_lo id_hi
_V1_HEADER: Final = struct.Struct("<BBBBBB")  # magic len seq sys comp id
_CRC: Final = struct.Struct("<H")
_FRAME_START: Final = re.compile(b"[\xfd\xfe]")
_BOOT_TIME: Final = "<I"  # time_boot_ms, wherever a message carries it
_U32: Final = struct.Struct(_BOOT_TIME)


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
    msg_id: int
    crc_extra: int
    size: int
    scalars: dict[str, tuple[int, struct.Struct]]
    arrays: dict[str, tuple[int, struct.Struct, bool]]
    boot_at: int = -1  # payload offset of ``time_boot_ms`` (uint32); -1: the message has none

    @property
    def fields(self) -> tuple[str, ...]:
        return (*self.scalars, *self.arrays)


def _boot_at(scalars: dict[str, tuple[int, struct.Struct]]) -> int:
    found = scalars.get("time_boot_ms")
    return found[0] if found is not None and found[1].format == _BOOT_TIME else -1


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
    return Layout(message.name, message.id, crc, offset, scalars, arrays, _boot_at(scalars))


def _checked_layout(msg_id: int) -> Layout | None:
    entry = CHECKED_MESSAGES.get(msg_id)
    if entry is None:
        return None
    name, crc_extra, _, max_length, common = entry
    scalars = {field: (offset, struct.Struct("<" + code)) for field, offset, code in common}
    return Layout(name, msg_id, crc_extra, max_length, scalars, {}, _boot_at(scalars))


# Built on first sight: an autopilot sends a few dozen types.
_LAYOUTS: Final[dict[int, Layout]] = {}


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


@dataclass(frozen=True)
class Fields:
    """Scalar fields of one message type read together (:meth:`Frame.read_fields`): one
    unpack at an offset worked out once, instead of a lookup by name for each."""

    layout: Layout
    names: tuple[str, ...]
    offset: int  # of the first field in the payload
    end: int  # payload offset after the last field
    unit: struct.Struct  # the fields, and pad bytes for what lies between them


def fields(name: str, *names: str) -> Fields:
    """Scalar fields ``names`` of the declared message ``name``, in wire order."""
    known = layout(message(name).id)
    assert known is not None
    places = [known.scalars[n] for n in names]  # KeyError: not a scalar field of it
    code, at = "<", places[0][0]
    for offset, unit in places:
        if offset < at:
            raise ValueError(f"{name}: {', '.join(names)} are not in wire order")
        code += (f"{offset - at}x" if offset > at else "") + unit.format.lstrip("<")
        at = offset + unit.size
    return Fields(known, tuple(names), places[0][0], at, struct.Struct(code))


class Frame:
    """One CRC-checked frame of a known message (see the module docstring)."""

    __slots__ = (
        "_at",
        "_comp",
        "_compat",
        "_data",
        "_end",
        "_layout",
        "_mlen",
        "_seq",
        "_start",
        "_sys",
    )

    def __init__(  # noqa: PLR0917 - built for every frame received: positional is cheaper
        self,
        data: bytes,
        start: int,
        end: int,
        layout: Layout,
        at: int,  # where the payload begins
        mlen: int,  # the payload's length as received
        seq: int,
        sys: int,
        comp: int,
        compat: int,  # MAVLink 2 compatibility flags (MAVLink 1: 0)
    ) -> None:
        self._data = data
        self._start = start
        self._end = end
        self._layout = layout
        self._at = at
        self._mlen = mlen
        self._seq = seq
        self._sys = sys
        self._comp = comp
        self._compat = compat

    def get_type(self) -> str:
        return self._layout.name

    def get_msgId(self) -> int:  # noqa: N802 - the name MAVLink tools use
        return self._layout.msg_id

    def get_srcSystem(self) -> int:  # noqa: N802 - the name MAVLink tools use
        return self._sys

    def get_srcComponent(self) -> int:  # noqa: N802 - the name MAVLink tools use
        return self._comp

    def get_seq(self) -> int:
        return self._seq

    def get_source(self) -> tuple[int, int]:
        """(system id, component id) of the sender."""
        return self._sys, self._comp

    def get_msgbuf(self) -> bytes:
        """The whole frame as received (signature included)."""
        return self._data[self._start : self._end]

    def has_field(self, name: str) -> bool:
        """Whether this frame's message type has a field ``name``: a dictionary lookup,
        where ``getattr(frame, name, None)`` raises and catches AttributeError for a
        type without it (the hub asks every routed frame whether it targets the agent)."""
        layout = self._layout
        return name in layout.scalars or name in layout.arrays

    def boot_time(self) -> int | None:
        """``time_boot_ms``, or None for a message without one: the field every frame is
        asked for, read from its offset without a lookup by name."""
        at = self._layout.boot_at
        if at < 0:
            return None
        if at + 4 > self._mlen:  # MAVLink 2 dropped trailing zeros: from the padding
            return int(_U32.unpack_from(self._padded(), at)[0])
        data, at = self._data, self._at + at
        return data[at] | (data[at + 1] << 8) | (data[at + 2] << 16) | (data[at + 3] << 24)

    def read_fields(self, fields: Fields) -> tuple[Any, ...]:
        """The values of ``fields`` (a :func:`fields` of this frame's type), as the
        attributes of the same names read them."""
        if fields.layout is not self._layout:
            raise ValueError(f"{fields.layout.name} fields asked of a {self._layout.name}")
        if fields.end <= self._mlen:
            return fields.unit.unpack_from(self._data, self._at + fields.offset)
        return fields.unit.unpack_from(self._padded(), fields.offset)

    def _padded(self) -> bytes:
        """The payload zero-padded to the message's full size (longer: as received)."""
        at, mlen = self._at, self._mlen
        raw = self._data[at : at + mlen]
        missing = self._layout.size - mlen
        return raw + bytes(missing) if missing > 0 else raw

    def __getattr__(self, name: str) -> Any:
        layout = self._layout
        scalar = layout.scalars.get(name)
        if scalar is not None:
            offset, unit = scalar
            if offset + unit.size <= self._mlen:
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
        mlen, compat, seq, sys, comp = self._mlen, self._compat, self._seq, self._sys, self._comp
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
    if not _crc_ok(data, start, start + V1_HEADER + mlen, kind.crc_extra):
        return BadData(data[start:end], f"bad CRC ({kind.name})")
    return Frame(data, start, end, kind, start + V1_HEADER, mlen, seq, sys, comp, 0)


def _crc_ok(data: bytes, start: int, crc_at: int, crc_extra: int) -> bool:
    """Whether the frame at ``start`` carries the right CRC at ``crc_at``: X.25 over the
    header after the magic and the payload, then CRC_EXTRA (MAVLink's crc_accumulate of
    one byte, worked out here rather than appended to a copy of the frame)."""
    crc: int = _crc16(data[start + 1 : crc_at])
    tmp = (crc_extra ^ crc) & 0xFF
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc == data[crc_at] | (data[crc_at + 1] << 8)


def scan(data: bytes) -> tuple[list[Parsed], int]:
    """Everything ``data`` holds, in order, and how many bytes of it that used: less than
    ``len(data)`` when it ends inside a frame (the rest is that frame's beginning).

    (The MAVLink 2 path is written out in the loop: it runs for every frame received.)"""
    out: list[Parsed] = []
    start, total = 0, len(data)
    while start < total:
        magic = data[start]
        if magic == V2_MAGIC:
            if total - start < V2_HEADER + CRC_BYTES:  # the shortest frame ends past it
                break
            # The header read byte by byte: magic len incompat compat seq sys comp id (3)
            mlen, incompat = data[start + 1], data[start + 2]
            end = start + V2_HEADER + mlen + CRC_BYTES
            if incompat & IFLAG_SIGNED:
                end += SIGNATURE_BYTES
            if end > total:
                break
            if incompat & ~IFLAG_SIGNED:
                out.append(BadData(data[start:end], f"incompatibility flags 0x{incompat:02x}"))
            else:
                msg_id = data[start + 7] | (data[start + 8] << 8) | (data[start + 9] << 16)
                kind = _LAYOUTS.get(msg_id) or layout(msg_id)
                crc_at = start + V2_HEADER + mlen
                if kind is None:
                    out.append(UnknownFrame(data[start:end], msg_id))
                elif not _crc_ok(data, start, crc_at, kind.crc_extra):
                    out.append(BadData(data[start:end], f"bad CRC ({kind.name})"))
                else:
                    seq, sys, comp = data[start + 4], data[start + 5], data[start + 6]
                    compat = data[start + 3]
                    at = start + V2_HEADER
                    out.append(Frame(data, start, end, kind, at, mlen, seq, sys, comp, compat))
        elif magic == V1_MAGIC:
            if total - start < V1_HEADER + CRC_BYTES:  # the shortest frame ends past it
                break
            end = start + V1_HEADER + data[start + 1] + CRC_BYTES
            if end > total:
                break
            out.append(_v1_frame(data, start, end))
        else:
            found = _FRAME_START.search(data, start + 1)
            end = total if found is None else found.start()
            out.append(BadData(data[start:end], "bad prefix"))
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


Value = int | float | str | bytes | Sequence[int] | Sequence[float]
"""A field's value to encode: a number, text for a char array, numbers for an array."""


def encode(
    message: MessageDef, values: Mapping[str, Value], *, seq: int, system: int, component: int
) -> bytes:
    """One unsigned MAVLink 2 frame of ``message``. Every base field must be given;
    extension fields not given are zero. A char array takes text (str or bytes, padded
    with zeros), any other array a sequence of its length."""
    args: list[Any] = []
    for f in message.wire_order:
        if f.name in values:
            value = values[f.name]
        elif f in message.extensions:
            value = bytes(0) if f.type == "char" else [0] * f.array if f.array else 0
        else:
            raise ValueError(f"{message.name}: no value for {f.name}")
        if f.type == "char":
            args.append(value.encode() if isinstance(value, str) else value)
        elif f.array:
            if isinstance(value, (int, float, str, bytes)) or len(value) != f.array:
                raise ValueError(f"{message.name}.{f.name}: {f.array} values expected")
            args.extend(value)
        else:
            args.append(value)
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

    def encode(self, name: str, **values: Value) -> bytes:
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
    "Fields",
    "Frame",
    "Layout",
    "Parsed",
    "StreamParser",
    "UnknownFrame",
    "Value",
    "crc_extra_of",
    "encode",
    "fields",
    "frame_crc",
    "layout",
    "message",
    "scan",
]
