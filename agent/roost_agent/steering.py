"""The kernel sorts an autopilot's datagrams: what must be read at once, and the bulk.

Why: most of an idle agent's CPU goes into waking up, not into the messages it reads
(docs/performance.md). The bulk of a PX4 or ArduPilot stream (attitude, position, IMU,
~400 messages a second) can wait for the decision loop's next read: every judgement
made from it is timed from the kernel's arrival stamps, so a longer wait changes when a
message is read, not what it says or when it arrived. A few messages state a fact the
arbiter must see at once: a HEARTBEAT (MAV_STATE EMERGENCY or FLIGHT_TERMINATION, a
reboot, disarmed in the air, a pilot taking a manual mode) and a COMMAND_ACK (the safety
routine and the hub wait for them).

So a UDP link opens two sockets on one port, an ``SO_REUSEPORT`` group, and attaches a
classic BPF program to the group (``SO_ATTACH_REUSEPORT_CBPF``) that picks the socket for
each datagram: the second ("urgent") when any of its first :data:`MAX_FRAMES` MAVLink
frames is one of :data:`URGENT_MESSAGES`, the first ("bulk") otherwise. The reader sleeps
on the urgent socket alone between reads, so a heartbeat wakes it within microseconds
while telemetry waits for the read interval.

What the program reads: MAVLink 2 (``0xFD``: payload length at byte 1, incompatibility
flags at 2, the 24-bit message id at 7-9, then payload, CRC and the 13-byte signature
when flag 1 is set) and MAVLink 1 (``0xFE``: length at 1, id at 5, then payload and CRC).
Several frames in one datagram (ArduPilot's UDP sender fills a datagram with what it
has) are walked frame by frame. Anything it cannot read (a short datagram, garbage, a
frame past :data:`MAX_FRAMES`) goes to the bulk socket: the steering only decides how
soon a datagram is read, never whether it is, and every datagram still passes the
link's source lock, CRC and signature checks after it is read.

Order: the two sockets are read together and merged by arrival stamp (the UDP
transport's ``receive_batch`` in :mod:`roost_agent.transport`), because claims are settled
by the sequence numbers of the frames that follow them (:mod:`roost_agent.health`).

Linux only; elsewhere, and where the kernel refuses the program, a link keeps one
socket and the reader the short read interval.
"""

from __future__ import annotations

import ctypes
import socket
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from roost_mavlink.codec import (
    CRC_BYTES,
    IFLAG_SIGNED,
    SIGNATURE_BYTES,
    V1_HEADER,
    V1_MAGIC,
    V2_HEADER,
    V2_MAGIC,
    message,
)

HEARTBEAT = message("HEARTBEAT").id
COMMAND_ACK = message("COMMAND_ACK").id
URGENT_MESSAGES: tuple[int, ...] = (HEARTBEAT, COMMAND_ACK)
MAX_FRAMES = 8  # frames of one datagram the program looks at
SO_ATTACH_REUSEPORT_CBPF = 51  # Linux, include/uapi/asm-generic/socket.h
BULK, URGENT = 0, 1  # the sockets' places in the reuseport group (the order of binding)

# Classic BPF opcodes (include/uapi/linux/filter.h).
_LDB_IND = 0x50  # A = packet[X + k], one byte (out of range: the program returns 0)
_ADD_K = 0x04  # A += k
_ADD_X = 0x0C  # A += X
_TAX = 0x07  # X = A
_JA = 0x05  # jump k forward
_JEQ_K = 0x15  # A == k ? jt : jf
_JSET_K = 0x45  # A & k ? jt : jf
_RET_K = 0x06  # return k
_INSTRUCTION = struct.Struct("=HBBI")

V2_OVERHEAD = V2_HEADER + CRC_BYTES
V1_OVERHEAD = V1_HEADER + CRC_BYTES


@dataclass(frozen=True)
class _Op:
    code: int
    k: int = 0
    jt: str | None = None  # labels, resolved by _assemble
    jf: str | None = None
    label: str | None = None  # this instruction's label


def _frame_ops(i: int, ids: Sequence[int]) -> list[_Op]:
    """One frame at offset X: urgent if its id is one of ``ids``, else X moves past it."""
    v1, v2, v2_low = f"v1_{i}", f"v2_{i}", f"v2_low_{i}"
    step2, step = f"step2_{i}", f"step_{i}"
    return [
        _Op(_LDB_IND, 0, label=f"frame{i}"),
        _Op(_JEQ_K, V2_MAGIC, jt=v2, jf=f"not_v2_{i}"),
        _Op(_JEQ_K, V1_MAGIC, jt=v1, jf="bulk", label=f"not_v2_{i}"),
        # MAVLink 2: the id's high bytes are zero for every urgent id, then the low byte.
        _Op(_LDB_IND, 9, label=v2),
        _Op(_JEQ_K, 0, jt=f"v2_mid_{i}", jf=step2),
        _Op(_LDB_IND, 8, label=f"v2_mid_{i}"),
        _Op(_JEQ_K, 0, jt=v2_low, jf=step2),
        _Op(_LDB_IND, 7, label=v2_low),
        *[_Op(_JEQ_K, msg_id, jt="urgent", jf=None) for msg_id in ids],
        _Op(_LDB_IND, 2, label=step2),
        _Op(_JSET_K, IFLAG_SIGNED, jt=f"signed_{i}", jf=f"unsigned_{i}"),
        _Op(_LDB_IND, 1, label=f"signed_{i}"),
        _Op(_ADD_K, V2_OVERHEAD + SIGNATURE_BYTES),
        _Op(_JA, jt=step),
        _Op(_LDB_IND, 1, label=f"unsigned_{i}"),
        _Op(_ADD_K, V2_OVERHEAD),
        _Op(_JA, jt=step),
        # MAVLink 1: one id byte.
        _Op(_LDB_IND, 5, label=v1),
        *[_Op(_JEQ_K, msg_id, jt="urgent", jf=None) for msg_id in ids],
        _Op(_LDB_IND, 1),
        _Op(_ADD_K, V1_OVERHEAD),
        _Op(_ADD_X, label=step),
        _Op(_TAX),
    ]


def urgent_program(ids: Iterable[int] = URGENT_MESSAGES, max_frames: int = MAX_FRAMES) -> bytes:
    """The classic BPF program (``struct sock_filter`` array) that returns :data:`URGENT`
    for a datagram holding one of ``ids`` in its first ``max_frames`` frames, else
    :data:`BULK`."""
    wanted = sorted(set(ids))
    if any(not 0 <= msg_id < 256 for msg_id in wanted):
        raise ValueError(f"only message ids below 256 can be steered, not {wanted}")
    ops = [op for i in range(max_frames) for op in _frame_ops(i, wanted)]
    ops.append(_Op(_RET_K, BULK, label=f"frame{max_frames}"))
    ops.append(_Op(_RET_K, BULK, label="bulk"))
    ops.append(_Op(_RET_K, URGENT, label="urgent"))
    return _assemble(ops)


def _assemble(ops: list[_Op]) -> bytes:
    """Resolve labels into jump offsets (relative to the next instruction). A comparison
    with no false label falls through to the next instruction; so does one chain of id
    comparisons to the step after it."""
    where = {op.label: n for n, op in enumerate(ops) if op.label is not None}

    def offset(label: str | None, n: int, limit: int) -> int:
        jump = 0 if label is None else where[label] - n - 1
        if not 0 <= jump < limit:
            raise ValueError(f"a jump to {label} is out of range ({jump})")
        return jump

    out = []
    for n, op in enumerate(ops):
        if op.code == _JA:
            out.append(_INSTRUCTION.pack(op.code, 0, 0, offset(op.jt, n, 1 << 32)))
        elif op.code in (_JEQ_K, _JSET_K):
            jt, jf = offset(op.jt, n, 256), offset(op.jf, n, 256)
            out.append(_INSTRUCTION.pack(op.code, jt, jf, op.k))
        else:
            out.append(_INSTRUCTION.pack(op.code, 0, 0, op.k))
    return b"".join(out)


_PROGRAM = urgent_program()  # the same for every link: built once


def attach(sock: socket.socket, program: bytes) -> None:
    """Attach ``program`` to the reuseport group ``sock`` belongs to."""
    count = len(program) // _INSTRUCTION.size
    buffer = ctypes.create_string_buffer(program, len(program))
    fprog = struct.pack("@HP", count, ctypes.addressof(buffer))  # struct sock_fprog
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_REUSEPORT_CBPF, fprog)


Address = tuple[str, int]


def steered_sockets(bind: Address) -> tuple[socket.socket, socket.socket]:
    """A bulk and an urgent UDP socket on ``bind`` (port 0: a free one), steered by
    :func:`urgent_program`; raises OSError where the kernel cannot steer.

    A port already in use is refused, as a single socket's bind would be: a plain socket
    binds it first, since members of a reuseport group would let another agent in. For
    port 0 the plain socket picks the port too: the kernel would give a reuseport socket
    a port another reuseport group of the same user holds, and join that group."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(bind)
        bind = (bind[0], int(probe.getsockname()[1]))
    bulk = _member(bind)
    try:
        urgent = _member((bind[0], bulk.getsockname()[1]))
    except BaseException:
        bulk.close()
        raise
    try:
        attach(bulk, _PROGRAM)
    except BaseException:
        bulk.close()
        urgent.close()
        raise
    return bulk, urgent


def _member(bind: Address) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind(bind)
    except BaseException:
        sock.close()
        raise
    return sock
