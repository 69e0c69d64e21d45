"""The agent's MAVLink codec (roost_mavlink.codec) agrees with pymavlink byte for byte.

Every message type of pymavlink's dialect is encoded by pymavlink (random field values,
trailing zero fields that MAVLink 2 truncates, signed and unsigned, MAVLink 1 where the
id fits) and read by the codec: the same type, header and frame, and the same value of
every field the codec reads (all fields of the declared messages; the common addressing
and time fields of the rest). What the codec encodes, pymavlink encodes identically.
Damaged byte streams are judged as pymavlink's robust parser judges them (frame by frame:
bad data, unknown, good, and where a truncated frame begins). The generated table and
the declarations are checked against pymavlink's dialect so neither can drift; the
messages PX4 sends that the dialect lacks against pymavlink's ``all`` dialect, and
``test_agent_health_replay`` checks them against recorded PX4 flights.
"""

from __future__ import annotations

import random
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_mavlink.checked_messages import CHECKED_MESSAGES
from roost_mavlink.codec import (
    DECLARED,
    BadData,
    Encoder,
    Frame,
    StreamParser,
    UnknownFrame,
    crc_extra_of,
    encode,
    fields,
    layout,
    scan,
)
from roost_mavlink.definitions import AGENT_MESSAGES, EXTRA_MESSAGES
from roost_mavlink.table_gen import COMMON_FIELDS, build, declared

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


def _encoded(signed: bool = False, mavlink1: bool = False) -> list[bytes]:
    rng = random.Random(7)
    sink = _Sink()
    packer = mavlink.MAVLink(sink, srcSystem=3, srcComponent=1)
    if signed:
        packer.signing.secret_key = bytes(range(32))
        packer.signing.link_id = 2
        packer.signing.sign_outgoing = True
    for msg_id, cls in mavlink.mavlink_map.items():
        if mavlink1 and msg_id > 255:
            continue
        for zero_tail in (False, True):
            packer.send(_message(cls, rng, zero_tail), force_mavlink1=mavlink1)
    return sink.frames


def _pymavlink(data: bytes) -> tuple[list[Any], int]:
    """What pymavlink's robust parser makes of ``data``, and the bytes it keeps waiting."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    out = []
    msg = parser.parse_char(data)
    while msg is not None:
        out.append(msg)
        msg = parser.parse_char(b"")
    return out, parser.buf_len()


def _readable(msg_id: int) -> list[str]:
    if msg_id in DECLARED:
        return [f.name for f in DECLARED[msg_id].wire_order]
    return [name for name, _, _ in CHECKED_MESSAGES[msg_id][4]]


def _same(frame: Any, msg: Any) -> None:
    assert isinstance(frame, Frame), (frame, msg)
    assert frame.get_type() == msg.get_type()
    assert frame.get_msgId() == msg.get_msgId()
    assert frame.get_srcSystem() == msg.get_srcSystem()
    assert frame.get_srcComponent() == msg.get_srcComponent()
    assert frame.get_seq() == msg.get_seq()
    assert frame.get_msgbuf() == msg.get_msgbuf()
    names = _readable(msg.get_msgId())
    for name in names:
        got, want = getattr(frame, name), getattr(msg, name)
        if isinstance(want, str):
            want = want.encode()
        assert got == want, (msg.get_type(), name)
    for name in set(msg.fieldnames) - set(names):
        assert getattr(frame, name, None) is None, (msg.get_type(), name)
    _same_natively(frame, msg, names)


def _same_natively(frame: Frame, msg: Any, names: list[str]) -> None:
    """What the link, the health tracker and the hub read without a lookup by name
    (``Frame.boot_time``, ``Frame.read_fields``, ``Frame.has_field``) is what the
    attributes read."""
    boot_ms = msg.time_boot_ms if "time_boot_ms" in names else None
    assert frame.boot_time() == boot_ms, msg.get_type()
    # Frame.has_field: what the hub asks every routed frame instead of a getattr that raises
    assert all(frame.has_field(name) for name in names), msg.get_type()
    unreadable = set(msg.fieldnames) - set(names) | {"no_such_field"}
    assert not any(frame.has_field(name) for name in unreadable), msg.get_type()
    declared = DECLARED.get(msg.get_msgId())
    if declared is None:
        return
    scalars = [f.name for f in declared.wire_order if not f.array and f.type != "char"]
    for name in scalars:
        assert frame.read_fields(fields(declared.name, name)) == (getattr(frame, name),)
    every = fields(declared.name, *scalars)
    assert frame.read_fields(every) == tuple(getattr(frame, name) for name in scalars)


@pytest.mark.parametrize(
    ("signed", "mavlink1"),
    [(False, False), (True, False), (False, True)],
    ids=["unsigned", "signed", "mavlink1"],
)
def test_every_message_type_reads_as_pymavlink_reads_it(signed: bool, mavlink1: bool) -> None:
    frames = _encoded(signed, mavlink1)
    assert len(frames) >= 2 * (256 if mavlink1 else len(mavlink.mavlink_map)) * 0.5
    for data in frames:
        got, used = scan(data)
        assert used == len(data)
        (expected,), _ = _pymavlink(data)
        (frame,) = got
        _same(frame, expected)


def test_a_datagram_of_several_frames_gives_them_in_order() -> None:
    data = b"".join(_encoded()[:40])
    got, used = scan(data)
    expected, _ = _pymavlink(data)
    assert used == len(data) and len(got) == len(expected) == 40
    for frame, msg in zip(got, expected, strict=True):
        _same(frame, msg)


def test_a_stream_split_anywhere_gives_the_same_frames() -> None:
    data = b"".join(_encoded(signed=True)[:12]) + b"\x00\x01" + b"".join(_encoded()[:5])
    whole, _ = scan(data)
    for step in (1, 7, 64):
        parser = StreamParser()
        parts = [parser.feed(data[i : i + step]) for i in range(0, len(data), step)]
        got = [item for part in parts for item in part]
        # garbage split across reads comes as several pieces of bad data, frames whole
        assert [x.get_msgbuf() for x in got if isinstance(x, Frame)] == [
            x.get_msgbuf() for x in whole if isinstance(x, Frame)
        ]
        bad = b"".join(x.get_msgbuf() for x in got if isinstance(x, BadData))
        assert bad == b"\x00\x01" and parser.pending() == 0


def _kind(item: Any) -> str:
    name = item.get_type()
    if name.startswith("UNKNOWN_") and int(name[8:]) in EXTRA_MESSAGES:
        return "EXTRA"  # pymavlink's dialect lacks it; the codec checks it (tested below)
    return name


def test_damaged_bytes_are_judged_as_pymavlinks_robust_parser_judges_them() -> None:
    """Random corruption, truncation, insertion and garbage over runs of real frames:
    the same items (bad data, unknown ids, good frames of the same type and bytes) and
    the same unfinished tail."""
    rng = random.Random(11)
    frames = _encoded() + _encoded(signed=True) + _encoded(mavlink1=True)
    for _ in range(3000):
        data = bytearray(b"".join(rng.sample(frames, rng.randint(1, 4))))
        for _ in range(rng.randint(0, 3)):
            at = rng.randrange(len(data))
            action = rng.randrange(4)
            if action == 0:
                data[at] = rng.randrange(256)
            elif action == 1:
                del data[at:]
            elif action == 2:
                data[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 5)))
            else:
                data[at] = rng.choice((0xFD, 0xFE))
            if not data:
                break
        got, used = scan(bytes(data))
        expected, waiting = _pymavlink(bytes(data))
        assert len(data) - used == waiting
        assert len(got) == len(expected), data.hex()
        for item, msg in zip(got, expected, strict=True):
            assert bytes(item.get_msgbuf()) == bytes(msg.get_msgbuf())
            if _kind(msg) == "EXTRA":
                continue
            assert item.get_type() == msg.get_type(), data.hex()
            if isinstance(item, Frame):
                _same(item, msg)


def _corrupt(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0x55]) + data[at + 1 :]


def test_what_is_not_a_good_frame_is_named_as_such() -> None:
    good = _encoded()[0]
    unknown = bytearray(good)
    unknown[7:10] = (0xFFFFFF).to_bytes(3, "little")
    flagged = bytearray(good)
    flagged[2] = 0x02
    assert [type(x) for x in scan(_corrupt(good, len(good) - 1))[0]] == [BadData]
    assert [type(x) for x in scan(_corrupt(good, 12))[0]] == [BadData]
    assert [type(x) for x in scan(bytes(unknown))[0]] == [UnknownFrame]
    assert [type(x) for x in scan(bytes(flagged))[0]] == [BadData]
    assert scan(good[:-1]) == ([], 0)
    assert scan(b"") == ([], 0)
    items, used = scan(b"\x00\x01" + good)
    assert [type(x) for x in items] == [BadData, Frame] and used == len(good) + 2
    assert all(layout(msg_id) is not None for msg_id in mavlink.mavlink_map)
    assert layout(0xFFFFFF) is None and crc_extra_of(0xFFFFFF) is None


def test_a_field_the_message_lacks_raises_attribute_error() -> None:
    heartbeat = next(d for d in _encoded() if d[7] == 0 and d[8] == 0)
    ((frame,), _) = scan(heartbeat)
    assert frame.get_type() == "HEARTBEAT"
    assert getattr(frame, "time_boot_ms", None) is None
    assert frame.to_dict()["mavpackettype"] == "HEARTBEAT"
    with pytest.raises(AttributeError):
        _ = frame.lat


def test_fields_are_read_in_wire_order_and_only_from_their_own_message() -> None:
    values = dict.fromkeys(("yaw", "rollspeed", "pitchspeed", "yawspeed"), 0.0)
    values |= {"time_boot_ms": 5, "roll": 0.5, "pitch": 0.25}
    attitude = encode(DECLARED[30], values, seq=0, system=1, component=1)
    ((frame,), _) = scan(attitude)
    assert len(frame.get_msgbuf()) < 12 + 28  # yaw and the rates are zero: cut off
    assert frame.read_fields(fields("ATTITUDE", "roll", "pitch")) == (0.5, 0.25)
    assert frame.read_fields(fields("ATTITUDE", "time_boot_ms", "yawspeed")) == (5, 0.0)
    assert frame.boot_time() == 5
    with pytest.raises(ValueError, match="wire order"):
        fields("ATTITUDE", "pitch", "roll")
    with pytest.raises(KeyError):
        fields("ATTITUDE", "lat")
    with pytest.raises(ValueError, match="GLOBAL_POSITION_INT fields asked of a ATTITUDE"):
        frame.read_fields(fields("GLOBAL_POSITION_INT", "relative_alt", "vz"))


# -- what the agent sends -----------------------------------------------------------------


@pytest.mark.parametrize("msg_id", sorted(AGENT_MESSAGES))
def test_what_the_codec_encodes_pymavlink_encodes_identically(msg_id: int) -> None:
    rng = random.Random(msg_id)
    cls = mavlink.mavlink_map[msg_id]
    for seq, zero_tail in enumerate((False, True, False)):
        msg = _message(cls, rng, zero_tail)
        packer = mavlink.MAVLink(None, srcSystem=7, srcComponent=191)
        packer.seq = seq
        values = {name: getattr(msg, name) for name in cls.fieldnames}
        ours = encode(AGENT_MESSAGES[msg_id], values, seq=seq, system=7, component=191)
        assert ours == bytes(msg.pack(packer)), cls.msgname


def test_the_encoder_numbers_its_frames_and_defaults_extensions_to_zero() -> None:
    encoder = Encoder(system=4, component=191)
    first = encoder.encode("COMMAND_ACK", command=400, result=0)
    second = encoder.encode("COMMAND_ACK", command=400, result=0)
    ((a, b), _) = scan(first + second)
    assert (a.get_seq(), b.get_seq()) == (0, 1)
    assert (a.command, a.progress, a.target_system) == (400, 0, 0)
    with pytest.raises(ValueError, match="no value"):
        encoder.encode("COMMAND_ACK", command=400)
    with pytest.raises(ValueError, match="no field"):
        encoder.encode("COMMAND_ACK", command=400, result=0, bogus=1)


def test_with_field_is_pymavlinks_reencoding_of_the_changed_message() -> None:
    """(What the hub does to a client's frame addressed to the vehicle.)"""
    for force_v1 in (False, True):
        for msg in (
            mavlink.MAVLink_command_long_message(42, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0),
            mavlink.MAVLink_set_mode_message(42, 1, 4),
            mavlink.MAVLink_manual_control_message(42, 0, 0, 500, 0, 0),
        ):
            packer = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
            packer.seq = 9
            data = bytes(msg.pack(packer, force_mavlink1=force_v1))
            ((frame,), _) = scan(data)
            name = "target" if hasattr(msg, "target") else "target_system"
            setattr(msg, name, 3)
            expected = bytes(msg.pack(packer, force_mavlink1=force_v1))
            if force_v1:  # pymavlink's MAVLink 1 packs extension fields too; ours does not
                ((parsed,), _) = scan(frame.with_field(name, 3))
                assert getattr(parsed, name) == 3 and parsed.get_seq() == 9
                continue
            assert frame.with_field(name, 3) == expected, msg.get_type()


# -- the table and the declarations against pymavlink's dialect ------------------------------


def test_the_committed_table_is_what_pymavlinks_dialect_gives() -> None:
    """Regenerate with ``python -m roost_mavlink.table_gen`` when this fails."""
    assert build() == CHECKED_MESSAGES
    assert not set(CHECKED_MESSAGES) & set(DECLARED)
    assert set(CHECKED_MESSAGES) | set(AGENT_MESSAGES) == set(mavlink.mavlink_map)
    assert COMMON_FIELDS  # what a table row locates


def test_the_declared_messages_are_pymavlinks() -> None:
    for msg_id, message in AGENT_MESSAGES.items():
        assert declared(mavlink.mavlink_map[msg_id]) == message, message.name


def test_wire_order_and_crc_extra_are_computed_as_the_generators_compute_them() -> None:
    """Against every message of pymavlink's dialect (extension fields are not in CRC_EXTRA
    and keep their declared place after the base fields)."""
    for cls in mavlink.mavlink_map.values():
        message = declared(cls)
        assert message.crc_extra == cls.crc_extra, cls.msgname
        assert [f.name for f in message.wire_order] == list(cls.ordered_fieldnames)
        assert message.unpacker.size == message.max_length == cls.unpacker.size, cls.msgname


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
    ((frame,), _) = scan(_current_mode_frame(0x04030000))
    assert isinstance(frame, Frame)
    assert frame.get_type() == "CURRENT_MODE" and frame.get_msgId() == 436
    assert (frame.standard_mode, frame.custom_mode, frame.intended_custom_mode) == (
        4,
        0x04030000,
        0x04030001,
    )
    assert getattr(frame, "time_boot_ms", None) is None
    ((bad,), _) = scan(_current_mode_frame(1, corrupt=True))
    assert isinstance(bad, BadData)
