"""The agent's cheap MAVLink 2 framing (roost_agent.frames) agrees with pymavlink.

Every message type of the dialect is encoded by pymavlink (with random field values,
trailing zero fields that MAVLink 2 truncates, signed and unsigned) and read both ways:
the frame must give the same type, header and field values as pymavlink's own parser.
Whatever pymavlink would not decode cleanly must be refused, so the link falls back to
pymavlink for it. The messages added to the dialect (PX4's CURRENT_MODE and others
pymavlink's dialect lacks) are checked against pymavlink's own CRC_EXTRA computation and
against another implementation's frames; ``test_capture_replay`` checks them against the
recorded PX4 flights.
"""

from __future__ import annotations

import inspect
import random
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent.frames import Frame, known, layout, split
from roost_mavlink.definitions import EXTRA_MESSAGES, FieldDef, MessageDef

INT_RANGES = {
    "int8_t": (-128, 127),
    "uint8_t": (0, 255),
    "int16_t": (-32768, 32767),
    "uint16_t": (0, 65535),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1),
    "uint64_t": (0, 2**64 - 1),
}


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def _value(kind: str, rng: random.Random, zero: bool) -> Any:
    if kind == "char":
        return b"" if zero else bytes(rng.choice(b"abcxyz") for _ in range(3))
    if kind in ("float", "double"):
        return 0.0 if zero else rng.uniform(-1000, 1000)
    low, high = INT_RANGES[kind.replace("_mavlink_version", "")]
    return 0 if zero else rng.randint(low, high)


def _message(cls: Any, rng: random.Random, zero_tail: bool) -> Any:
    args = []
    names = list(cls.fieldnames)
    tail = set(names[len(names) // 2 :]) if zero_tail else set()
    counts = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    for name, kind in zip(names, cls.fieldtypes, strict=True):
        zero, count = name in tail, counts[name]
        if count and kind != "char":
            args.append([_value(kind, rng, zero) for _ in range(count)])
        else:
            args.append(_value(kind, rng, zero))
    return cls(*args)


def _encoded(signed: bool) -> list[bytes]:
    rng = random.Random(7)
    sink = _Sink()
    packer = mavlink.MAVLink(sink, srcSystem=3, srcComponent=1)
    if signed:
        packer.signing.secret_key = bytes(range(32))
        packer.signing.link_id = 2
        packer.signing.sign_outgoing = True
    for cls in mavlink.mavlink_map.values():
        for zero_tail in (False, True):
            packer.send(_message(cls, rng, zero_tail))
    return sink.frames


def _pymavlink(data: bytes) -> list[Any]:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    out = []
    msg = parser.parse_char(data)
    while msg is not None:
        out.append(msg)
        msg = parser.parse_char(b"")
    return out


def _same(frame: Frame, msg: Any) -> None:
    assert frame.get_type() == msg.get_type()
    assert frame.get_msgId() == msg.get_msgId()
    assert frame.get_srcSystem() == msg.get_srcSystem()
    assert frame.get_srcComponent() == msg.get_srcComponent()
    assert frame.get_seq() == msg.get_seq()
    assert frame.get_msgbuf() == msg.get_msgbuf()
    for name in msg.fieldnames:
        assert getattr(frame, name) == getattr(msg, name), (msg.get_type(), name)


@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
def test_every_message_type_reads_as_pymavlink_reads_it(signed: bool) -> None:
    frames = _encoded(signed)
    assert len(frames) == 2 * len(mavlink.mavlink_map)
    for data in frames:
        got = split(data)
        assert got is not None, data[:12].hex()
        (expected,) = _pymavlink(data)
        _same(got[0], expected)


def test_a_datagram_of_several_frames_gives_them_in_order() -> None:
    frames = _encoded(signed=False)[:40]
    data = b"".join(frames)
    got = split(data)
    assert got is not None
    expected = _pymavlink(data)
    assert len(got) == len(expected) == 40
    for frame, msg in zip(got, expected, strict=True):
        _same(frame, msg)


def test_a_field_of_another_type_is_refused_without_decoding() -> None:
    heartbeat = next(d for d in _encoded(signed=False) if d[7] == 0 and d[8] == 0)
    (frame,) = split(heartbeat) or []
    assert frame.get_type() == "HEARTBEAT"
    assert getattr(frame, "time_boot_ms", None) is None
    assert frame._full is None
    assert frame.to_dict()["mavpackettype"] == "HEARTBEAT"  # decoded on demand


def _corrupt(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0x55]) + data[at + 1 :]


def test_what_pymavlink_would_not_decode_cleanly_is_left_to_it() -> None:
    good = _encoded(signed=False)[0]
    signed_frame = _encoded(signed=True)[0]
    sink = _Sink()
    mavlink.MAVLink(sink, srcSystem=1, srcComponent=1).send(
        mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3), force_mavlink1=True
    )
    unknown = bytearray(good)
    unknown[7:10] = (0xFFFFFF).to_bytes(3, "little")
    flagged = bytearray(good)
    flagged[2] = 0x02
    refused = {
        "bad CRC": _corrupt(good, len(good) - 1),
        "corrupt payload": _corrupt(good, 12),
        "MAVLink 1": sink.frames[0],
        "truncated": good[:-1],
        "truncated signature": signed_frame[:-3],
        "garbage before": b"\x00" + good,
        "garbage after": good + b"\x00",
        "unknown message id": bytes(unknown),
        "unknown incompatibility flag": bytes(flagged),
    }
    for why, data in refused.items():
        assert split(data) is None, why
    assert split(b"") == []
    assert all(layout(msg_id) is not None for msg_id in mavlink.mavlink_map)
    assert layout(0xFFFFFF) is None


# -- messages the dialect lacks (roost_mavlink.definitions) ---------------------------------


def _declared(cls: Any) -> tuple[MessageDef, bool]:
    """A pymavlink message class as a definition of its base fields (declaration order,
    base types; extension fields, the constructor's defaulted arguments, left out) and
    whether it has extension fields."""
    counts = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    parameters = inspect.signature(cls.__init__).parameters
    base = [n for n in cls.fieldnames if parameters[n].default is inspect.Parameter.empty]
    kinds = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
    fields = tuple(
        FieldDef(kinds[name].replace("_mavlink_version", ""), name, counts[name]) for name in base
    )
    return MessageDef(cls.id, cls.msgname, fields), len(base) < len(cls.fieldnames)


def test_wire_order_and_crc_extra_are_computed_as_the_generators_compute_them() -> None:
    """Against every message of pymavlink's dialect (extension fields are not in CRC_EXTRA
    and keep their declared place after the base fields)."""
    for cls in mavlink.mavlink_map.values():
        message, extended = _declared(cls)
        assert message.crc_extra == cls.crc_extra, cls.msgname
        wire = [f.name for f in message.wire_order]
        assert wire == list(cls.ordered_fieldnames[: len(wire)]), cls.msgname
        if not extended:
            assert message.unpacker.size == cls.unpacker.size, cls.msgname


def test_the_added_messages_are_ones_the_dialect_lacks() -> None:
    assert EXTRA_MESSAGES
    assert not set(EXTRA_MESSAGES) & set(mavlink.mavlink_map)
    assert all(m.id == msg_id for msg_id, m in EXTRA_MESSAGES.items())


def _current_mode_frame(custom_mode: int, *, corrupt: bool = False) -> bytes:
    """CURRENT_MODE as pymavlink's ``all`` dialect (which defines it) encodes it."""
    from pymavlink.dialects.v20 import all as everything  # noqa: PLC0415 - this test only

    sink = _Sink()
    packer = everything.MAVLink(sink, srcSystem=1, srcComponent=1)
    packer.send(everything.MAVLink_current_mode_message(4, custom_mode, custom_mode + 1))
    data = sink.frames[0]
    return _corrupt(data, len(data) - 1) if corrupt else data


def test_current_mode_reads_as_another_implementation_writes_it() -> None:
    (frame,) = split(_current_mode_frame(0x04030000)) or []
    assert frame.get_type() == "CURRENT_MODE" and frame.get_msgId() == 436
    assert (frame.standard_mode, frame.custom_mode, frame.intended_custom_mode) == (
        4,
        0x04030000,
        0x04030001,
    )
    assert getattr(frame, "time_boot_ms", None) is None
    assert split(_current_mode_frame(1, corrupt=True)) is None


def test_an_added_message_is_recognised_behind_pymavlinks_unknown_message() -> None:
    """pymavlink returns an id its dialect lacks as ``UNKNOWN_<id>`` without checking the
    CRC; :func:`known` checks it against the added definition."""
    good, bad = _current_mode_frame(7), _current_mode_frame(7, corrupt=True)
    (unknown,) = _pymavlink(good)
    assert unknown.get_type() == "UNKNOWN_436"
    frame = known(unknown)
    assert frame is not None and frame.custom_mode == 7
    (corrupt,) = _pymavlink(bad)
    assert corrupt.get_type() == "UNKNOWN_436" and known(corrupt) is None
    other = bytearray(good)
    other[7:10] = (0xFFFF00).to_bytes(3, "little")
    (undefined,) = _pymavlink(bytes(other))
    assert known(undefined) is None
