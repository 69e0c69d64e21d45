"""One MAVLink link per autopilot: a transport, one reader for all links, locked writes.

Why one link per autopilot (not one shared socket): two autopilots behind one socket are
merged by a MAVLink router and a command can reach both. Why a single reader: a stream
parser holds the unfinished frame of the last read, so the reader is the only thing that
ever parses; it feeds the health tracker and hands COMMAND_ACKs to whoever waits for
them. One :class:`LinkReader` thread reads every link of the agent (a selector; a link
started on its own gets a reader of its own), and the agent runs its decision loop on it too
(:meth:`LinkReader.drive`): a thread per link woke once per datagram, which cost more
than parsing. Every frame is checked by header and CRC and decoded field by field on
demand by the agent's own codec (:mod:`roost_mavlink.codec`, which judges bad data as
pymavlink's parser does); the agent's own frames are encoded by it too. Writes (the
agent's heartbeat, safety commands) take a lock, which also keeps the MAVLink sequence
numbers in order.

Why our own transports instead of ``pymavlink.mavutil`` connections: mavutil imports
numpy and a MAVLink 1 dialect (more memory than the whole agent needs, on a companion
computer), prints to stdout, parses every sender's bytes with one parser and sends every
reply to every address that ever sent it a datagram, spoofers included. (The agent does
not import pymavlink at all: see :mod:`roost_mavlink.codec`.)

Trust, on UDP, where anyone who can reach the port can send:

- **Each datagram on its own.** A datagram is parsed by itself, and whatever it leaves
  unfinished is discarded with it and counted ``truncated`` (MAVLink over UDP never
  splits a frame across datagrams). Garbage, truncated or bad-CRC frames therefore cost
  only their own datagram; the autopilot's next frame always starts clean.
- **Source lock.** A link hears one address: the autopilot's. ``udpout://`` is locked to
  its destination, ``udp://HOST:PORT@PEER:PORT`` to the configured peer (``@PEER`` alone:
  any port of that host may prove itself). Otherwise the lock goes to the first address
  that proves itself: :data:`PROOF_HEARTBEATS` autopilot HEARTBEATs of the configured
  system and component id (``autopilot`` not INVALID; signed when signing is required),
  each no more than the heartbeat-error threshold after the previous one. Re-lock: when
  the locked address has sent nothing acceptable for the heartbeat-error threshold (the
  autopilot rebooted onto another port, or was replaced), the next address to prove itself
  takes the lock, with a warning Event. While the autopilot is alive nothing can take its
  lock. Until the first lock nothing reaches the health tracker, so a link counts as
  silent (not healthy) until its autopilot proved itself.
- **Foreign traffic** (datagrams from any other address while locked) is dropped unparsed
  and counted (``foreign``); more than :data:`FOREIGN_ALERT_PER_S` per second over
  :data:`ALERT_WINDOW_S` raises a warning Event (at most one per
  :data:`ALERT_QUIET_S`): a second sender is misconfigured or someone injects MAVLink.
- **Replies** go to the locked address only; before a lock a UDP listener sends nothing.
- **Signing** (:mod:`roost_agent.signing`): every frame sent is signed; while signing is
  required, unsigned, badly signed and replayed frames are dropped and counted, and
  repeated ones raise a warning Event the same way.

Without signing, the lock keeps off-path senders out but cannot stop a host that forges
the autopilot's own address and port; signing can.

A reader never dies: any exception is counted, reported (``error``, shown in the status,
and a warning Event) and the link reopened with exponential backoff
(:data:`REOPEN_DELAY_S` doubling to :data:`REOPEN_MAX_S`). Opening (which can block: a
TCP connect) happens beside the reader, so one unreachable autopilot never delays
reading the others.

The agent talks as component 191 (onboard computer) with the autopilot's own system id,
as a companion computer does, and addresses commands to the autopilot's component
(never the broadcast component 0). Connection URLs are read by
:func:`roost_mavlink.pymavlink_device`, the one parser of ``AutopilotSpec.connection``.
"""

from __future__ import annotations

import contextlib
import errno
import heapq
import logging
import math
import selectors
import socket
import struct
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Final, Generic, TypeVar

from roost_agent.health import Fix, HealthTracker, Motion
from roost_agent.signing import LinkSigning
from roost_agent.steering import steered_sockets
from roost_api.core import Stack
from roost_api.plain import AutopilotSpec
from roost_mavlink import AGENT_COMPONENT_ID, MavResult, pymavlink_device
from roost_mavlink.codec import MAVLINK_VERSION, BadData, Encoder, Frame, StreamParser, Value, scan
from roost_mavlink.signing import Signer, Verdict, Verifier
from roost_mavlink.status import MAV_AUTOPILOT_INVALID, MAV_TYPE_ONBOARD_CONTROLLER, MavState

log = logging.getLogger(__name__)

Params = tuple[float, float, float, float, float, float, float]
Address = tuple[str, int]
EventSink = Callable[[str, str, bool], None]  # (reason, message, warning)
Received = tuple[bytes, Address | None, float | None]  # data, sender, kernel arrival stamp

READ_WAIT_S = 0.5  # longest the reader blocks in select() (timers and stop wake it sooner)
DRAIN_MAX: Final = 256  # datagrams read from one transport per wake-up
# While no hub client waits for routed frames, the reader lets datagrams gather this long
# after each wake-up: one wake-up then reads several (a PX4 onboard stream is ~400 a
# second), which is most of the agent's CPU time. Arrival times come from the kernel's
# receive timestamps, so the health judgement sees when a message arrived, not when it
# was read; only the wake-up for a changed fact (MAV_STATE, sensors) waits this long.
# (Linux turns arrival stamping on globally a moment after the first socket asks for it;
# until then a datagram's stamp is its read time, which is what an unstamped read gets.)
BATCH_S = 0.005
# A kernel arrival stamp older than the read by more is taken as only this old. Stamps
# are CLOCK_REALTIME: a step of the wall clock between two offset readings shifts them,
# and a shift backwards makes every message look older than it is. This bounds that to
# 0.1 s (a silence is 0.2 s). A datagram really older than this (the bulk of a steered
# link waits up to a 0.1 s read interval, a loaded machine oversleeps) is judged a few
# milliseconds younger than it is, never a whole interval: taking the read time instead
# would delay a silence by the interval.
STAMP_SLACK_S = 0.1
OFFSET_TRIES: Final = 3
OFFSET_TIGHT_S: Final = 1e-4  # two clock reads this close together were not interrupted


def realtime_offset() -> float:
    """CLOCK_REALTIME minus CLOCK_MONOTONIC, to turn the kernel's receive stamps (realtime)
    into the agent's clock.

    Read as monotonic, realtime, monotonic, against the midpoint: a thread descheduled
    between two plain reads (tens of milliseconds on a loaded core) would shift every
    stamp of the drain by that much, and a stamp shifted past the read time is thrown
    away. The tightest of a few tries is kept.
    """
    best_gap, best_offset = float("inf"), 0.0
    for _ in range(OFFSET_TRIES):
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        if after - before < best_gap:
            best_gap, best_offset = after - before, wall - (before + after) / 2
        if best_gap < OFFSET_TIGHT_S:
            break
    return best_offset


OFFSET_REUSE_S: Final = 0.5


class RecentOffset:
    """:func:`realtime_offset`, read again only every :data:`OFFSET_REUSE_S`: the reader
    drains every link at every tick, and three clock reads per drain were a tenth of an
    idle agent's work. Within that half second the clocks drift apart by at most what NTP
    slews (0.5 ms/s); a step of the wall clock moves the stamps until the next read, and
    a stamp moved past the read time or the slack is not trusted anyway."""

    def __init__(self) -> None:
        self._read_at = -math.inf
        self._offset = 0.0

    def __call__(self) -> float:
        now = time.monotonic()
        if now - self._read_at >= OFFSET_REUSE_S:
            self._offset, self._read_at = realtime_offset(), now
        return self._offset


recent_realtime_offset: Final = RecentOffset()


REOPEN_DELAY_S: Final = 0.5
REOPEN_MAX_S: Final = 30.0
CONNECT_TIMEOUT_S = 2.0
UDP_MAX: Final = 65535
RECEIVE_BUFFER_BYTES = 1 << 20  # absorbs a burst of foreign datagrams

MAX_SENDERS: Final = 16  # candidate addresses a source lock remembers
PROOF_HEARTBEATS: Final = 2
ALERT_WINDOW_S: Final = 10.0
FOREIGN_ALERT_PER_S: Final = 1.0
ALERT_QUIET_S: Final = 60.0


@dataclass
class LinkCounters:
    """What the reader saw; exposed for diagnostics, the status line and the benchmarks."""

    bytes: int = 0  # every datagram or read, dropped or not
    accepted: int = 0  # from the locked address, this autopilot's sysid/component
    foreign: int = 0  # datagrams from another address while locked (not parsed)
    unlocked: int = 0  # parsed before any address proved itself (not used)
    other: int = 0  # from the locked address but another sysid or component
    bad: int = 0  # bytes that did not parse or failed their CRC (BAD_DATA)
    unknown: int = 0  # framed, but a message id nobody declared: its CRC cannot be checked
    truncated: int = 0  # datagrams that ended inside a frame
    unsigned: int = 0  # dropped while signing is required: no signature
    bad_signature: int = 0  # dropped while signing is required: wrong or replayed
    errors: int = 0  # exceptions from the parser or the transport
    reopened: int = 0
    relocked: int = 0


class Transport:
    """A byte pipe to one autopilot. ``receive`` never blocks (the reader selects first)."""

    datagrams = False  # True: each receive is one datagram holding whole frames
    fixed_peer: Address | None = None  # the one address datagrams are accepted from

    def fileno(self) -> int:
        raise NotImplementedError

    def receive(self) -> tuple[bytes, Address | None]:
        """Available bytes and who sent them (None where the transport has one peer)."""
        raise NotImplementedError

    def receive_stamped(self) -> Received:
        """:meth:`receive` plus the kernel's arrival time (CLOCK_REALTIME s) where known."""
        data, sender = self.receive()
        return data, sender, None

    def receive_batch(self, limit: int) -> list[Received]:
        """What is there to read, up to ``limit`` receives, in arrival order."""
        return _read_all(self.receive_stamped, limit)

    def urgent_fileno(self) -> int | None:
        """A descriptor that becomes readable when something must be read at once (a
        steered UDP link's urgent socket), or None: then every read is urgent."""
        return None

    def send(self, data: bytes) -> None:
        raise NotImplementedError

    def lock_to(self, address: Address) -> None:
        """Replies go to ``address`` from now on (only UDP listeners care)."""

    def close(self) -> None:
        raise NotImplementedError


SO_TIMESTAMPNS: Final = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; the module lacks the name
_TIMESPEC: Final = struct.Struct("@qq")


class _Udp(Transport):
    """A UDP socket, or a steered pair of them (:mod:`roost_agent.steering`) where the
    kernel can steer: then heartbeats and command answers land on :attr:`urgent`."""

    datagrams = True

    def __init__(self, bind: Address | None, *, steer: bool = False) -> None:
        self.urgent: socket.socket | None = None
        if steer and bind is not None and _STEERING_WORKS[0]:
            try:
                self._sock, self.urgent = steered_sockets(bind)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise
                _STEERING_WORKS[0] = False
                log.warning(
                    "the kernel does not steer UDP datagrams (%s): reading every link "
                    "at the short interval",
                    exc,
                )
        if self.urgent is None:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                if bind is not None:
                    self._sock.bind(bind)
            except BaseException:
                self._sock.close()
                raise
        self._stamped = all(self._prepare(sock) for sock in self._sockets())

    def _sockets(self) -> list[socket.socket]:
        return [self._sock] if self.urgent is None else [self._sock, self.urgent]

    @staticmethod
    def _prepare(sock: socket.socket) -> bool:
        """Non-blocking, a deep buffer, kernel arrival stamps; whether stamps work."""
        sock.setblocking(False)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:  # not Linux: arrival is the time the reader reads it
            return False
        return True

    def fileno(self) -> int:
        return self._sock.fileno()

    def urgent_fileno(self) -> int | None:
        return None if self.urgent is None else self.urgent.fileno()

    def local_address(self) -> Address:
        """Where this link receives (host, port)."""
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    def receive(self) -> tuple[bytes, Address | None]:
        try:
            data, address = self._sock.recvfrom(UDP_MAX)
        except (BlockingIOError, ConnectionRefusedError):
            return b"", None
        return data, (str(address[0]), int(address[1]))

    def receive_stamped(self) -> tuple[bytes, Address | None, float | None]:
        if not self._stamped:
            data, sender = self.receive()
            return data, sender, None
        return _receive_stamped(self._sock)

    def receive_batch(self, limit: int) -> list[Received]:
        """Up to ``limit`` datagrams in arrival order. Steered: the urgent socket is read
        before and after the bulk, and whatever it held is merged in by arrival stamp;
        once the bulk is read to its end, anything arriving on either socket after that
        read is later than all of these."""
        urgent = self.urgent
        if urgent is None or not self._stamped:
            return super().receive_batch(limit)
        first = _read_all(partial(_receive_stamped, urgent), limit)
        bulk = _read_all(partial(_receive_stamped, self._sock), limit)
        later = _read_all(partial(_receive_stamped, urgent), limit)
        if not first and not later:
            return bulk
        return sorted(first + bulk + later, key=_arrival)

    def close(self) -> None:
        for sock in self._sockets():
            sock.close()


_STEERING_WORKS = [sys.platform == "linux"]  # cleared by the first refusal, for the process


def _receive_stamped(sock: socket.socket) -> Received:
    try:
        data, ancillary, _, address = sock.recvmsg(UDP_MAX, 64)
    except (BlockingIOError, ConnectionRefusedError):
        return b"", None, None
    # The arrival stamp is the only ancillary item asked for; an IPv4 datagram socket's
    # sender is already a (host, port) tuple.
    if ancillary and ancillary[0][1] == SO_TIMESTAMPNS:
        seconds, nanoseconds = _TIMESPEC.unpack_from(ancillary[0][2])
        return data, address, seconds + nanoseconds * 1e-9
    return data, address, None


def _read_all(receive: Callable[[], Received], limit: int) -> list[Received]:
    """Receive until there is nothing more (an empty datagram) or ``limit`` times."""
    out = []
    for _ in range(limit):
        received = receive()
        if not received[0]:
            break
        out.append(received)
    return out


def _arrival(received: Received) -> float:
    stamp = received[2]
    return math.inf if stamp is None else stamp


class UdpListen(_Udp):
    """``udp://HOST:PORT``: listen; reply only to the locked autopilot address."""

    def __init__(self, host: str, port: int, *, steer: bool = False) -> None:
        super().__init__((host, port), steer=steer)
        self._peer: Address | None = None

    def lock_to(self, address: Address) -> None:
        self._peer = address

    def send(self, data: bytes) -> None:
        if self._peer is not None:  # no autopilot proved itself yet: nowhere to send
            self._sock.sendto(data, self._peer)


class UdpOut(_Udp):
    """``udpout://HOST:PORT``: send there; datagrams from elsewhere are foreign."""

    def __init__(self, host: str, port: int, *, steer: bool = False) -> None:
        peer = (socket.gethostbyname(host), port)
        # Steered: both sockets take one free port on the address the peer is reached
        # from, as the first send would give one.
        super().__init__((_local_address_to(peer), 0) if steer else None, steer=steer)
        self.fixed_peer = peer

    def send(self, data: bytes) -> None:
        assert self.fixed_peer is not None
        self._sock.sendto(data, self.fixed_peer)


def _local_address_to(peer: Address) -> str:
    """The local address datagrams to ``peer`` leave from (a connected UDP socket is
    routed at once; nothing is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect(peer)
        return str(probe.getsockname()[0])


class TcpClient(Transport):
    """``tcp://HOST:PORT``: connect (ArduPilot SITL serves MAVLink on TCP)."""

    def __init__(self, host: str, port: int) -> None:
        self._sock = socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.setblocking(False)

    def fileno(self) -> int:
        return self._sock.fileno()

    def receive(self) -> tuple[bytes, Address | None]:
        try:
            data = self._sock.recv(UDP_MAX)
        except BlockingIOError:
            return b"", None
        if not data:
            raise ConnectionError("the autopilot closed the TCP connection")
        return data, None

    def send(self, data: bytes) -> None:
        self._sock.sendall(data)

    def close(self) -> None:
        self._sock.close()


class TcpListen(Transport):
    """``tcpin://HOST:PORT``: accept one autopilot connection at a time."""

    def __init__(self, host: str, port: int) -> None:
        self._server = socket.create_server((host, port))
        self._server.setblocking(False)
        self._client: socket.socket | None = None

    def fileno(self) -> int:
        return (self._client or self._server).fileno()

    def receive(self) -> tuple[bytes, Address | None]:
        if self._client is None:
            try:
                client, _ = self._server.accept()
            except BlockingIOError:
                return b"", None
            client.setblocking(False)
            self._client = client
            return b"", None
        try:
            data = self._client.recv(UDP_MAX)
        except BlockingIOError:
            return b"", None
        if not data:
            self._client.close()
            self._client = None
        return data, None

    def send(self, data: bytes) -> None:
        if self._client is not None:
            self._client.sendall(data)

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        self._server.close()


class SerialPort(Transport):
    """``serial:///dev/ttyX:BAUD``: a UART (or a pseudo-terminal) via pyserial."""

    def __init__(self, path: str, baud: int) -> None:
        import serial  # noqa: PLC0415 - only serial links need pyserial

        self._port = serial.Serial(path, baud, timeout=0, write_timeout=0.5)

    def fileno(self) -> int:
        return int(self._port.fileno())

    def receive(self) -> tuple[bytes, Address | None]:
        return bytes(self._port.read(self._port.in_waiting or 1)), None

    def send(self, data: bytes) -> None:
        self._port.write(data)

    def close(self) -> None:
        self._port.close()


def open_transport(connection: str, *, steer: bool = False) -> Transport:
    """Open the transport an ``AutopilotSpec.connection`` URL names; ``steer``: a UDP
    link gets an urgent socket where the kernel can steer (:mod:`roost_agent.steering`)."""
    device = pymavlink_device(connection)
    kind, _, rest = device.device.partition(":")
    host, _, port = rest.rpartition(":")
    if kind == "udpin":
        return UdpListen(host, int(port), steer=steer)
    if kind == "udpout":
        return UdpOut(host, int(port), steer=steer)
    if kind == "tcp":
        return TcpClient(host, int(port))
    if kind == "tcpin":
        return TcpListen(host, int(port))
    return SerialPort(device.device, device.baud)


def configured_peer(connection: str) -> tuple[str, int | None] | None:
    """The ``@PEER[:PORT]`` of a UDP listener URL, its host resolved to an address."""
    peer = pymavlink_device(connection).peer
    if peer is None:
        return None
    return socket.gethostbyname(peer[0]), peer[1]


class SourceLock:
    """Which sender address a link believes is its autopilot (rules: module docstring).

    Pure bookkeeping with explicit times, so the rule is unit-tested without sockets.
    """

    def __init__(
        self,
        *,
        relock_after_s: float,
        fixed: Address | None = None,
        host: str | None = None,
        proof_heartbeats: int = PROOF_HEARTBEATS,
    ) -> None:
        self.relock_after_s = relock_after_s
        self.fixed = fixed
        self.host = host
        self.proof_heartbeats = proof_heartbeats
        self.locked: Address | None = fixed
        self.last_seen: float | None = None
        self._candidates: OrderedDict[Address, tuple[int, float]] = OrderedDict()

    def open_to_candidates(self, now: float) -> bool:
        """Whether another address may prove itself now."""
        if self.fixed is not None:
            return False
        if self.locked is None:
            return True
        return self.last_seen is None or now - self.last_seen >= self.relock_after_s

    def hears(self, address: Address, now: float) -> bool:
        """Whether frames from ``address`` are parsed at all."""
        if address == self.locked:
            return True
        if self.host is not None and address[0] != self.host:
            return False
        return self.open_to_candidates(now)

    def seen(self, now: float) -> None:
        """The locked address delivered an acceptable message."""
        self.last_seen = now

    def prove(self, address: Address, now: float) -> bool:
        """A valid autopilot heartbeat from a candidate; True when it takes the lock now."""
        if not self.hears(address, now) or address == self.locked:
            return False
        count, last = self._candidates.pop(address, (0, now))
        count = count + 1 if now - last <= self.relock_after_s else 1
        if count < self.proof_heartbeats:
            self._candidates[address] = (count, now)
            while len(self._candidates) > MAX_SENDERS:
                self._candidates.popitem(last=False)
            return False
        self._candidates.clear()
        self.locked, self.last_seen = address, now
        return True


class _RateAlarm:
    """Counts events in a window; fires when the rate passes a bound, then stays quiet."""

    def __init__(self, per_s: float, window_s: float = ALERT_WINDOW_S) -> None:
        self.threshold = max(1, round(per_s * window_s))
        self.window_s = window_s
        self._times: deque[float] = deque()
        self._quiet_until = 0.0
        self.sources: OrderedDict[str, int] = OrderedDict()

    def note(self, now: float, source: str) -> str | None:
        """Record one; "N in S s" when the alarm fires, else None."""
        times = self._times
        times.append(now)
        while times and now - times[0] > self.window_s:
            times.popleft()
        self.sources[source] = self.sources.pop(source, 0) + 1
        while len(self.sources) > 4:
            self.sources.popitem(last=False)
        if len(times) < self.threshold or now < self._quiet_until:
            return None
        self._quiet_until = now + ALERT_QUIET_S
        text = f"{len(times)} in {max(now - times[0], 0.001):.2f} s"
        times.clear()
        return text

    def describe(self) -> str:
        text = ", ".join(self.sources)
        self.sources.clear()
        return text


def _address_text(address: Address | None) -> str:
    return "the serial/TCP peer" if address is None else f"{address[0]}:{address[1]}"


LOG_REPLIES = frozenset({"LOG_ENTRY", "LOG_DATA"})
"""The log protocol's answers: no target field, so routed by who holds the session."""


class _Writer:
    """Where the link's frames go: its own (encoded and numbered as the agent) and hub
    clients' (as they are), signed when the link signs."""

    def __init__(self, transport: Transport, signer: Signer | None, encoder: Encoder) -> None:
        self.transport = transport
        self.signer = signer
        self.encoder = encoder
        self.record: Callable[[bytes], None] | None = None  # the flight recorder's tap

    def write(self, frame: bytes) -> None:
        if self.signer is not None:
            frame = self.signer.sign(frame)
        self.transport.send(frame)
        record = self.record  # after the send: recording never delays a frame
        if record is not None:
            record(frame)

    def send(self, name: str, **values: Value) -> None:
        """Encode one message from the agent and write it."""
        self.write(self.encoder.encode(name, **values))


class AckMailbox:
    """COMMAND_ACKs by command number, so a sender can wait for the answer to its command."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._acks: dict[int, tuple[int, int]] = {}  # command -> (serial, result)

    def serial(self, command: int) -> int:
        """Number of acks seen so far for ``command`` (take it before sending)."""
        with self._cond:
            return self._acks.get(command, (0, 0))[0]

    def put(self, command: int, result: int) -> None:
        """Record an ack (called by the reader)."""
        with self._cond:
            serial = self._acks.get(command, (0, 0))[0] + 1
            self._acks[command] = (serial, result)
            self._cond.notify_all()

    def latest(self, command: int) -> int | None:
        """The last ack result for ``command``, None when none came yet."""
        with self._cond:
            entry = self._acks.get(command)
            return None if entry is None else entry[1]

    def wait(self, command: int, after_serial: int, timeout_s: float) -> int | None:
        """The first ack result for ``command`` newer than ``after_serial``, or None."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                serial, result = self._acks.get(command, (0, 0))
                if serial > after_serial:
                    return result
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._cond.wait(remaining):
                    serial, result = self._acks.get(command, (0, 0))
                    return result if serial > after_serial else None


PARAM_INBOX_MAX: Final = 4096  # a client's full parameter list is about 1,000 on PX4
T = TypeVar("T")
MISSION_INBOX_MAX: Final = 1024  # a fence download is one message per item
MISSION_MESSAGES: Final = frozenset(
    {"MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK"}
)
"""The mission protocol messages an autopilot sends the agent (roost_agent.fence)."""


class Inbox(Generic[T]):
    """Messages from the autopilot for a keeper on another thread (parameters, the
    mission protocol); the oldest go first when nobody takes them."""

    def __init__(self, limit: int) -> None:
        self._lock = threading.Lock()
        self._items: deque[T] = deque(maxlen=limit)

    def put(self, item: T) -> None:
        with self._lock:
            self._items.append(item)

    def take(self) -> list[T]:
        """Everything received since the last take, oldest first."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


ParamInbox = Inbox[tuple[str, float, int, float]]
"""PARAM_VALUEs: name, wire value, type, arrival."""
MissionInbox = Inbox[tuple[str, dict[str, Any], float]]
"""Mission protocol messages addressed to the agent: name, fields, arrival."""


@dataclass
class _Session:
    """What one opened transport needs while it reads."""

    transport: Transport
    lock: SourceLock
    verifier: Verifier | None
    parser: StreamParser = field(default_factory=StreamParser)  # streams (TCP, serial) only
    accepted_at_open: int = 0
    link: AutopilotLink | None = None
    fd: int = -1  # the descriptor the reader selects on
    urgent_fd: int | None = None  # a steered link's urgent socket (it selects on it too)
    arrived: float = float("-inf")  # the time given to the last datagram read


class LinkReader:
    """One thread that reads every link: a selector over their transports.

    Why one thread, not one per link: a thread per link woke once per datagram and
    handed the GIL over each time, which cost several times the parsing itself. Here one
    wake-up reads whatever every link has. Driven by a tick (:meth:`drive`, the agent's
    decision loop) it wakes once per tick, reads, then ticks; on its own it lets
    datagrams gather for :data:`BATCH_S` after each read. Either way it wakes for every
    datagram while :attr:`hurry` says a client waits for routed frames, and messages keep
    their kernel arrival time.

    Opening a transport can block (a TCP connect, a serial port), so it happens on a
    short-lived thread per attempt; the opened session is handed to the reader. Failures
    and reopen timers are the links' (:meth:`AutopilotLink._failed`); the reader only
    runs them. Everything that touches the selector runs on the reader thread
    (:meth:`call`), so a closed file descriptor is never polled.
    """

    def __init__(
        self,
        *,
        hurry: Callable[[], bool] = lambda: False,
        batch_s: float = BATCH_S,
        name: str = "link-reader",
    ) -> None:
        self.hurry = hurry
        self.batch_s = batch_s
        self._name = name
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, None)
        self._calls: deque[tuple[Callable[[], None], threading.Event]] = deque()
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._timer_serial = 0
        # While nothing hurries it, the reader sleeps on the wake-up socket and the
        # steered links' urgent sockets; for the short interval after an urgent socket
        # woke it, on the wake-up socket alone (_calls_only): a sender flooding the
        # urgent socket (heartbeats are easy to forge) cannot make it wake more often
        # than the unsteered reader would.
        self._idle = selectors.DefaultSelector()
        self._idle.register(self._wake_r, selectors.EVENT_READ, None)
        self._calls_only = selectors.DefaultSelector()
        self._calls_only.register(self._wake_r, selectors.EVENT_READ, None)
        self._urgent_quiet_until = -math.inf
        self._sessions: dict[int, _Session] = {}
        self._stopping = False
        self._serving_thread: threading.Thread | None = None
        self._tick: Callable[[], float | None] | None = None
        self._tick_s = self._short_tick_s = self._steered_tick_s = 0.0
        self._urgent = False
        # When (time.monotonic) the last read of every link began: what had arrived by
        # then has been read (the ticking loop only).
        self._read_at = -math.inf

    def drive(
        self, tick: Callable[[], float | None], tick_s: float, steered_tick_s: float | None = None
    ) -> None:
        """Run ``tick`` on the reader thread every ``tick_s`` (and at once when :meth:`poke`
        d), right after reading: the agent's decision loop. Every datagram that arrived by
        then is read first, so one wake-up per tick serves reading and deciding. ``tick``
        returns when (``time.monotonic``) it is next due sooner than that, if it is.
        While every link read is steered (an urgent socket wakes the reader for what must
        be read at once: :mod:`roost_agent.steering`), the interval is ``steered_tick_s``.
        Call before :meth:`start`."""
        self._tick, self._short_tick_s = tick, tick_s
        self._steered_tick_s = tick_s if steered_tick_s is None else steered_tick_s
        self._tick_s = tick_s

    @property
    def tick_s(self) -> float:
        """The read interval now (it depends on whether every link read is steered)."""
        return self._tick_s

    def as_of(self, now: float) -> float:
        """The time a health judgement made at ``now`` (``time.monotonic``) outside the
        decision loop stands for: the start of the last read, as what arrived since is
        not read yet, so a message age does not grow between reads, nor while a loaded
        machine runs the reader late. Never more than :data:`READ_WAIT_S` before
        ``now``: the links of a reader stalled longer than that still age."""
        if self._serving_thread is None or self._tick is None:
            return now
        return max(min(now, self._read_at), now - READ_WAIT_S)

    def poke(self) -> None:
        """Tick as soon as possible (from any thread; on the reader thread: after reading)."""
        self._urgent = True
        if threading.current_thread() is not self._serving_thread:
            self._wake()

    def start(self) -> None:
        self._serving_thread = threading.Thread(target=self._serve, name=self._name, daemon=True)
        self._serving_thread.start()

    def stop(self) -> None:
        self._stopping = True
        self._wake()
        if self._serving_thread is not None:
            self._serving_thread.join(timeout=2)
        self._selector.close()
        self._idle.close()
        self._calls_only.close()
        self._wake_r.close()
        self._wake_w.close()

    def call(self, fn: Callable[[], None], timeout_s: float = 2.0) -> None:
        """Run ``fn`` on the reader thread and wait for it (at once when already there)."""
        thread = self._serving_thread
        if thread is None or threading.current_thread() is thread or not thread.is_alive():
            fn()
            return
        done = threading.Event()
        self._calls.append((fn, done))
        self._wake()
        done.wait(timeout_s)

    def after(self, delay_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the reader thread ``delay_s`` from now (reader thread only)."""
        self._timer_serial += 1
        heapq.heappush(self._timers, (time.monotonic() + delay_s, self._timer_serial, fn))

    def attach(self, session: _Session) -> None:
        """Read ``session``'s transport from now on (reader thread only)."""
        fd = session.transport.fileno()
        self._sessions[fd] = session
        session.fd = fd
        self._selector.register(fd, selectors.EVENT_READ, session)
        session.urgent_fd = session.transport.urgent_fileno()
        if session.urgent_fd is not None:  # wakes the reader whether it hurries or not
            self._selector.register(session.urgent_fd, selectors.EVENT_READ, session)
            self._idle.register(session.urgent_fd, selectors.EVENT_READ, session)
        self._choose_interval()

    def detach(self, session: _Session) -> None:
        """Stop reading ``session`` (reader thread only; closing it is the caller's)."""
        for fd, known in list(self._sessions.items()):
            if known is session:
                del self._sessions[fd]
                with contextlib.suppress(KeyError, ValueError):
                    self._selector.unregister(fd)
        if session.urgent_fd is not None:
            for selector in (self._selector, self._idle):
                with contextlib.suppress(KeyError, ValueError):
                    selector.unregister(session.urgent_fd)
            session.urgent_fd = None
        self._choose_interval()

    def _choose_interval(self) -> None:
        sessions = self._sessions.values()
        steered = bool(sessions) and all(s.urgent_fd is not None for s in sessions)
        self._tick_s = self._steered_tick_s if steered else self._short_tick_s

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # already awake (full), or closing
            self._wake_w.send(b"\0")

    def _run_calls(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass
        while self._calls:
            fn, done = self._calls.popleft()
            try:
                fn()
            except Exception:
                log.exception("link reader call failed")
            finally:
                done.set()

    def _run_timers(self) -> float:
        """Run due timers; seconds until the next one (capped at READ_WAIT_S)."""
        timers = self._timers
        while timers and timers[0][0] <= time.monotonic():
            _, _, fn = heapq.heappop(timers)
            try:
                fn()
            except Exception:
                log.exception("link reader timer failed")
        return (
            READ_WAIT_S
            if not timers
            else max(0.0, min(READ_WAIT_S, timers[0][0] - time.monotonic()))
        )

    def _serve(self) -> None:
        if self._tick is not None:
            self._serve_ticking(self._tick)
        else:
            self._serve_reading()
        for session in list(self._sessions.values()):
            self.detach(session)

    def _read(self, ready: list[tuple[selectors.SelectorKey, int]]) -> None:
        drained: set[int] = set()  # a steered link can be ready on both of its sockets
        for key, _ in ready:
            session = key.data
            if session is None:
                self._run_calls()
            elif id(session) not in drained:
                drained.add(id(session))
                self._drain(session)

    def _drain(self, session: _Session) -> None:
        if self._sessions.get(session.fd) is not session:
            return  # detached since the select (a link stopped by a call): not ours to read
        link = session.link
        assert link is not None
        try:
            link._drain(session)
            if session.transport.fileno() != session.fd:  # a TCP listener took a client
                self.detach(session)
                self.attach(session)
        except Exception as exc:  # every failure: the link reports and reopens
            self.detach(session)
            link._failed(exc, session)

    def _drain_ready(self) -> None:
        """Read the links that have data: one poll that does not wait asks which, cheaper
        than a failing read of every idle link at every tick."""
        self._read(self._select(self._selector, 0.0))

    def _select(self, selector: selectors.BaseSelector, timeout: float) -> list[Any]:
        try:
            return selector.select(timeout)
        except OSError:
            if self._stopping:
                return []
            raise

    def _serve_reading(self) -> None:
        """Read as datagrams come (batched while nothing hurries)."""
        while not self._stopping:
            timeout = self._run_timers()
            self._read(self._select(self._selector, timeout))
            if self.batch_s > 0 and not self._calls and not self.hurry():
                time.sleep(self.batch_s)

    def _sleep(self, timeout: float) -> None:
        """Wait up to ``timeout`` for a call, a timer or an urgent datagram (urgent
        datagrams at most once per short interval), reading what woke the reader."""
        now = time.monotonic()
        if now < self._urgent_quiet_until:
            self._read(self._select(self._calls_only, min(timeout, self._urgent_quiet_until - now)))
            return
        ready = self._select(self._idle, timeout)
        if any(key.data is not None for key, _ in ready):
            self._urgent_quiet_until = time.monotonic() + self._short_tick_s
        self._read(ready)

    def _serve_ticking(self, tick: Callable[[], float | None]) -> None:
        """Read and decide: wake for the next tick (for data too while hurried), read
        everything that arrived, then tick when due or poked; the next tick is
        ``tick_s`` later, or sooner when the tick says it is due sooner."""
        next_tick = time.monotonic()
        while not self._stopping:
            timeout = min(self._run_timers(), max(0.0, next_tick - time.monotonic()))
            if self.hurry():
                ready = self._select(self._selector, timeout)
                self._read_at = time.monotonic()
                self._read(ready)
            else:
                if timeout > 0 and not self._urgent:
                    self._sleep(timeout)
                self._read_at = time.monotonic()
                self._drain_ready()
            now = time.monotonic()
            if now >= next_tick or self._urgent:
                self._urgent = False
                due = None
                try:
                    due = tick()
                except Exception:  # the loop must outlive any bug in one tick
                    log.exception("decision tick failed")
                now = time.monotonic()
                next_tick = now + self._tick_s
                if due is not None and now < due < next_tick:
                    next_tick = due
                elif due is not None and due <= now:
                    # A decision the tick waits for is already due (the tick ran late,
                    # or the time it named passed while it ran): look again as soon as
                    # an unsteered reader would, not a whole steered interval later.
                    next_tick = now + self._short_tick_s


class AutopilotLink:
    """The agent's connection to one autopilot."""

    def __init__(
        self,
        spec: AutopilotSpec,
        tracker: HealthTracker,
        on_change: Callable[[], None] = lambda: None,
        clock: Callable[[], float] = time.monotonic,
        *,
        signing: LinkSigning | None = None,
        on_event: EventSink = lambda reason, message, warning: None,
        reader: LinkReader | None = None,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.stack = Stack(spec.stack)
        # Whose frames this link accepts.
        self._sysid: int = spec.sysid
        self._component: int = spec.component_id
        self.tracker = tracker
        self.counters = LinkCounters()
        self.acks = AckMailbox()
        self.signing = signing
        self.error: str | None = None  # the last failure while the link is down
        self._on_change = on_change
        self._on_event = on_event
        self._clock = clock
        self._write_lock = threading.Lock()
        self._transport: Transport | None = None
        self._writer: _Writer | None = None
        self._stop = threading.Event()
        # The reader this link is read by: shared by the agent's links, or its own.
        self._reader = reader
        self._own_reader: LinkReader | None = None
        self._session: _Session | None = None
        self._delay = REOPEN_DELAY_S
        # Kernel arrival timestamps are CLOCK_REALTIME: usable where the clock is monotonic.
        self._stamps = clock is time.monotonic
        self._foreign_alarm = _RateAlarm(FOREIGN_ALERT_PER_S)
        self._signature_alarm = _RateAlarm(FOREIGN_ALERT_PER_S)
        self._locked: Address | None = None
        # Called by the reader with every accepted message (the hub routes them to clients).
        self.tap: Callable[[Any, float], None] | None = None
        # The flight recorder's tap (roost_agent.records_recorder): every frame accepted
        # from the autopilot (after the hub routed it and the tracker judged it) and
        # every frame written to it (after the write).
        self._record: Callable[[bytes], None] | None = None
        # LOG_ENTRY and LOG_DATA go here while an autopilot log is being fetched
        # (roost_agent.records_logs); dropped otherwise.
        self.log_sink: Callable[[Frame], None] | None = None
        self.params = ParamInbox(PARAM_INBOX_MAX)
        self.mission = MissionInbox(MISSION_INBOX_MAX)
        # The autopilot's last AUTOPILOT_VERSION (roost_agent.firmware reads it).
        self.version: Frame | None = None

    @property
    def record(self) -> Callable[[bytes], None] | None:
        return self._record

    @record.setter
    def record(self, record: Callable[[bytes], None] | None) -> None:
        with self._write_lock:
            self._record = record
            if self._writer is not None:
                self._writer.record = record

    @property
    def locked_address(self) -> Address | None:
        """The address this link hears (None: not locked yet, or a serial/TCP link)."""
        return self._locked

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Start reading (on the shared reader, else on one of its own); the transport is
        opened (and reopened) in the background."""
        self._stop.clear()
        reader = self._reader
        if reader is None:
            reader = self._own_reader = LinkReader(name=f"link-{self.name}")
            reader.start()
        self._delay = REOPEN_DELAY_S
        reader.call(lambda: self._open_soon(reader, 0.0))

    def stop(self) -> None:
        """Stop reading and close the transport."""
        self._stop.set()
        reader = self._own_reader or self._reader
        if reader is not None:
            reader.call(self._forget)
        if self._own_reader is not None:
            self._own_reader.stop()
            self._own_reader = None
        self._close()

    def _forget(self) -> None:
        session, self._session = self._session, None
        reader = self._own_reader or self._reader
        if session is not None and reader is not None:
            reader.detach(session)

    def _close(self) -> None:
        with self._write_lock:
            transport, self._transport, self._writer = self._transport, None, None
        if transport is not None:
            try:
                transport.close()
            except OSError:
                log.debug("closing %s failed", self.name, exc_info=True)

    def _event(self, reason: str, message: str, warning: bool) -> None:
        try:
            self._on_event(reason, f"{self.name}: {message}", warning)
        except Exception:  # a reporting bug must not stop the reader
            log.exception("%s: reporting %s failed", self.name, reason)

    # -- opening, failing, reopening (on the reader thread; opening itself beside it) --

    def _open_soon(self, reader: LinkReader, delay_s: float) -> None:
        def begin() -> None:
            if not self._stop.is_set():
                threading.Thread(
                    target=self._open_beside, args=(reader,), name=f"open-{self.name}", daemon=True
                ).start()

        reader.after(delay_s, begin)

    def _open_beside(self, reader: LinkReader) -> None:
        """Open the transport (may block) and hand the session to the reader."""
        try:
            session = self._open()
        except Exception as exc:
            failure = exc
            reader.call(lambda: self._failed(failure, None))
            return
        session.link = self

        def adopt() -> None:
            if self._stop.is_set():
                self._close()
                return
            try:
                reader.attach(session)
            except Exception as exc:
                self._failed(exc, session)
                return
            self._session = session

        reader.call(adopt)

    def _failed(self, exc: Exception, session: _Session | None) -> None:
        """Report a failure, close, and reopen with backoff (on the reader thread)."""
        self._session = None
        self.counters.errors += 1
        text = " ".join(f"{type(exc).__name__}: {exc}".split())
        if text != self.error:
            log.warning("%s: link failed (%s); retrying", self.name, text)
            self._event("LinkError", f"link failed: {text}; retrying", True)
        self.error = text
        self._close()
        if self._stop.is_set():
            return
        if session is not None and self.counters.accepted > session.accepted_at_open:
            self._delay = REOPEN_DELAY_S  # it worked for a while: retry soon
        self.counters.reopened += 1
        reader = self._own_reader or self._reader
        if reader is not None:
            self._open_soon(reader, self._delay)
        self._delay = min(self._delay * 2, REOPEN_MAX_S)

    # -- reading ---------------------------------------------------------------------

    def _open(self) -> _Session:
        transport = open_transport(self.spec.connection, steer=True)
        try:
            peer = configured_peer(self.spec.connection)
            relock_s = self.tracker.thresholds.heartbeat_error_ms / 1000
            if transport.fixed_peer is not None:
                lock = SourceLock(relock_after_s=relock_s, fixed=transport.fixed_peer)
            elif peer is not None and peer[1] is not None:
                lock = SourceLock(relock_after_s=relock_s, fixed=(peer[0], peer[1]))
            else:
                host = None if peer is None else peer[0]
                lock = SourceLock(relock_after_s=relock_s, host=host)
            if lock.locked is not None:
                transport.lock_to(lock.locked)
            self._locked = lock.locked
            signing = self.signing
            signer = signing.signer(self.spec.bridge_channel) if signing is not None else None
            verifier = signing.verifier() if signing is not None and signing.require else None
            writer = _Writer(transport, signer, Encoder(self.spec.sysid, AGENT_COMPONENT_ID))
            writer.record = self._record
        except BaseException:
            transport.close()
            raise
        with self._write_lock:
            self._transport, self._writer = transport, writer
        return _Session(transport, lock, verifier, accepted_at_open=self.counters.accepted)

    def _drain(self, session: _Session) -> None:
        """Read what the transport has (up to :data:`DRAIN_MAX`); failures propagate."""
        stamps = self._stamps
        offset = recent_realtime_offset() if stamps else 0.0
        for data, sender, stamp in session.transport.receive_batch(DRAIN_MAX):
            now = self._clock()
            if stamp is not None and stamps:
                arrived = stamp - offset
                if arrived < now:  # a stamp after the read is not believed at all
                    # never before an earlier datagram's time, nor more than the slack
                    # before the read (compared one by one: max() would box the floats)
                    earliest = now - STAMP_SLACK_S
                    now = arrived if arrived > earliest else earliest
                    last = session.arrived
                    now = last if last > now else now
            session.arrived = now
            self._datagram(session, data, sender, now)

    def _datagram(self, session: _Session, data: bytes, sender: Address | None, now: float) -> None:
        self.counters.bytes += len(data)
        lock = session.lock
        locked = sender is None or sender == lock.locked
        if not locked and sender is not None and not lock.hears(sender, now):
            self.counters.foreign += 1
            fired = self._foreign_alarm.note(now, _address_text(sender))
            if fired is not None:
                self._event(
                    "ForeignMavlinkTraffic",
                    f"ignored datagrams ({fired}) from "
                    f"{self._foreign_alarm.describe()}; only the autopilot at "
                    f"{_address_text(lock.locked)} is heard (a misconfigured second sender, "
                    "or MAVLink injection)",
                    True,
                )
            return
        if session.transport.datagrams:
            items, used = scan(data)
            if used < len(data):  # a frame never continues in the next datagram
                self.counters.truncated += 1
        else:
            items = session.parser.feed(data)
        try:
            for item in items:
                if isinstance(item, Frame):
                    # A frame of this datagram may have taken the lock for its sender.
                    locked = locked or sender == lock.locked
                    self._message(session, item, sender, now, locked)
                elif isinstance(item, BadData):
                    self.counters.bad += 1
                else:
                    self.counters.unknown += 1
        except Exception:  # a bug reading one message must not stop the reader
            self.counters.errors += 1

    def _message(
        self, session: _Session, msg: Frame, sender: Address | None, now: float, locked: bool
    ) -> None:
        """One frame of a datagram; ``locked``: from the address the link is locked to."""
        kind = msg.get_type()
        lock = session.lock
        if msg.get_srcSystem() != self._sysid or msg.get_srcComponent() != self._component:
            if locked:
                self.counters.other += 1
            else:
                self.counters.unlocked += 1
            return
        if session.verifier is not None and not self._signed(session.verifier, msg, sender, now):
            return
        if not locked:
            assert sender is not None
            proof = kind == "HEARTBEAT" and int(msg.autopilot) != MAV_AUTOPILOT_INVALID
            if not (proof and lock.prove(sender, now)):
                self.counters.unlocked += 1
                return
            self._took_lock(session, sender)
        lock.seen(now)
        self.counters.accepted += 1
        if self.error is not None:
            self.error = None
            self._event("LinkRecovered", "receiving again", False)
        tap = self.tap
        if tap is not None:
            tap(msg, now)
        if kind == "COMMAND_ACK":
            target_system = getattr(msg, "target_system", 0)
            target_component = getattr(msg, "target_component", 0)
            if target_system in (0, self.spec.sysid) and target_component in (
                0,
                AGENT_COMPONENT_ID,
            ):
                self.acks.put(int(msg.command), int(msg.result))
        elif kind == "PARAM_VALUE":
            name = bytes(msg.param_id).decode("ascii", "replace")
            self.params.put((name, float(msg.param_value), int(msg.param_type), now))
        elif kind in MISSION_MESSAGES:
            if msg.target_system in (0, self.spec.sysid) and msg.target_component in (
                0,
                AGENT_COMPONENT_ID,
            ):
                self.mission.put((kind, msg.to_dict(), now))
        elif kind == "AUTOPILOT_VERSION":
            self.version = msg
        elif kind in LOG_REPLIES:
            sink = self.log_sink
            if sink is not None:
                sink(msg)
        if self.tracker.observe(msg, now):
            self._on_change()
        record = self._record  # last: routed and judged before it is recorded
        if record is not None:
            record(msg.get_msgbuf())

    def _signed(self, verifier: Verifier, msg: Frame, sender: Address | None, now: float) -> bool:
        verdict = verifier.check(msg.get_msgbuf())
        if verdict is Verdict.GOOD:
            writer = self._writer
            signer = writer.signer if writer is not None else None
            if signer is not None and signer.key is not verifier.used:
                signer.use(verifier.used)  # answer with the key the autopilot has
            return True
        if verdict is Verdict.UNSIGNED:
            self.counters.unsigned += 1
        else:
            self.counters.bad_signature += 1
        fired = self._signature_alarm.note(now, f"{_address_text(sender)} ({verdict.value})")
        if fired is not None:
            self._event(
                "UnsignedMavlink",
                f"dropped frames ({fired}) that carry the autopilot's ids without a valid "
                f"signature, from {self._signature_alarm.describe()}",
                True,
            )
        return False

    def _took_lock(self, session: _Session, sender: Address) -> None:
        previous, self._locked = self._locked, sender
        session.transport.lock_to(sender)
        if previous is None:
            self._event("AutopilotLocked", f"listening to {_address_text(sender)} only", False)
        else:
            self.counters.relocked += 1
            self._event(
                "AutopilotAddressChanged",
                f"{_address_text(previous)} fell silent and {_address_text(sender)} proved "
                "itself with the autopilot's heartbeats: listening there now",
                True,
            )

    # -- writing ---------------------------------------------------------------------

    def _send(self, write: Callable[[_Writer], None]) -> bool:
        with self._write_lock:
            if self._writer is None:
                return False
            try:
                write(self._writer)
            except (OSError, ValueError) as exc:
                log.debug("%s: write failed: %s", self.name, exc)
                return False
            return True

    def rekey(self, signing: LinkSigning) -> None:
        """Adopt a rotated key at once: frames from now on are signed with it and, when
        signing is required, checked against it (the autopilot's streams start afresh)."""
        with self._write_lock:
            self.signing = signing
            writer = self._writer
            if writer is not None and writer.signer is not None:
                writer.signer = signing.signer(self.spec.bridge_channel)
            session = self._session
            if session is not None and session.verifier is not None:
                session.verifier = signing.verifier()

    def send_frame(self, frame: bytes) -> bool:
        """Forward a finished MAVLink frame (a hub client's), signed like the agent's own."""
        return self._send(lambda writer: writer.write(frame))

    def send_heartbeat(self) -> bool:
        """The agent's own 1 Hz heartbeat (onboard controller, not an autopilot).

        It tells the autopilot an onboard computer is present and lets a ``udpout``
        or TCP peer learn where to send.
        """
        return self._send(
            lambda writer: writer.send(
                "HEARTBEAT",
                type=MAV_TYPE_ONBOARD_CONTROLLER,
                autopilot=MAV_AUTOPILOT_INVALID,
                base_mode=0,
                custom_mode=0,
                system_status=MavState.ACTIVE,
                mavlink_version=MAVLINK_VERSION,
            )
        )

    def _send_to_autopilot(self, name: str, **values: Value) -> bool:
        """One message addressed to this autopilot's system and component."""
        target = {"target_system": self.spec.sysid, "target_component": self.spec.component_id}
        return self._send(lambda writer: writer.send(name, **target, **values))

    def send_message(self, name: str, **values: Value) -> bool:
        """One message (``name`` of common.xml) addressed to this autopilot."""
        return self._send_to_autopilot(name, **values)

    def send_command(self, command: int, params: Params, confirmation: int = 0) -> bool:
        """COMMAND_LONG addressed to this autopilot's system and component."""
        param = {f"param{i}": value for i, value in enumerate(params, start=1)}
        return self._send_to_autopilot(
            "COMMAND_LONG", command=command, confirmation=confirmation, **param
        )

    def read_param(self, name: str) -> bool:
        """PARAM_REQUEST_READ of one parameter by name (answered by a PARAM_VALUE)."""
        return self._send_to_autopilot("PARAM_REQUEST_READ", param_id=name, param_index=-1)

    def write_param(self, name: str, wire: float, ptype: int) -> bool:
        """PARAM_SET of one parameter (answered by a PARAM_VALUE with what it now holds);
        ``wire``: the value as the float field carries it (roost_agent.params.to_wire)."""
        return self._send_to_autopilot(
            "PARAM_SET", param_id=name, param_value=wire, param_type=ptype
        )

    def send_mission(self, name: str, fields: Mapping[str, Value]) -> bool:
        """One mission protocol message (roost_agent.fence) addressed to this autopilot."""
        return self._send_to_autopilot(name, **fields)

    def request_data_stream(self, stream_id: int, hz: int) -> bool:
        """REQUEST_DATA_STREAM (start) for one MAV_DATA_STREAM group (ArduPilot)."""
        return self._send_to_autopilot(
            "REQUEST_DATA_STREAM", req_stream_id=stream_id, req_message_rate=hz, start_stop=1
        )

    def command(
        self, command: int, params: Params, *, confirmation: int, timeout_s: float
    ) -> int | None:
        """Send a command and wait for its COMMAND_ACK result (None: no answer in time).

        MAV_RESULT_IN_PROGRESS is not an answer: the wait goes on (once more for
        ``timeout_s``) for the final result.
        """
        serial = self.acks.serial(command)
        if not self.send_command(command, params, confirmation):
            return None
        result = self.acks.wait(command, serial, timeout_s)
        if result == MavResult.IN_PROGRESS:
            final = self.acks.wait(command, serial + 1, timeout_s)
            return MavResult.IN_PROGRESS if final is None else final
        return result

    def heartbeat(self) -> tuple[int, int, float] | None:
        """(custom_mode, base_mode, received_at) of the autopilot's last heartbeat."""
        return self.tracker.heartbeat()

    def landed_state(self) -> int | None:
        """The autopilot's last reported landed state."""
        return self.tracker.landed_state()

    def system_status(self) -> int | None:
        """The autopilot's last reported MAV_STATE."""
        return self.tracker.system_status()

    def motion(self) -> Motion | None:
        """The autopilot's last altitude and vertical speed."""
        return self.tracker.motion()

    def fix(self) -> Fix | None:
        """The autopilot's last position and heading (decoded now, not by the reader)."""
        return self.tracker.fix()
