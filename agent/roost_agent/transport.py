"""Byte pipes to one autopilot: UDP (listening or sending out), TCP (client or listener)
and serial, each opened from an ``AutopilotSpec.connection`` URL.

Why this module exists apart from the link: a transport only moves bytes and says who
sent them and when the kernel received them; what is believed, parsed and answered is
the link's (:mod:`roost_agent.link`) and the source lock's (:mod:`roost_agent.trust`).
It is on the per-message path, so it is compiled with the link in the images
(``setup.py``).

Why our own transports instead of ``pymavlink.mavutil`` connections: mavutil imports
numpy and a MAVLink 1 dialect (more memory than the whole agent needs, on a companion
computer), prints to stdout, parses every sender's bytes with one parser and sends every
reply to every address that ever sent it a datagram, spoofers included. (The agent does
not import pymavlink at all: see :mod:`roost_mavlink.codec`.)

A UDP transport asks the kernel for each datagram's arrival stamp (CLOCK_REALTIME);
:func:`realtime_offset` turns such stamps into the agent's monotonic clock, so a
message read late is still judged by when it arrived. Where the kernel steers
(:mod:`roost_agent.steering`), a UDP link is a pair of sockets: heartbeats and command
answers land on the urgent one. Connection URLs are read by
:func:`roost_mavlink.pymavlink_device`, the one parser of ``AutopilotSpec.connection``.
"""

from __future__ import annotations

import errno
import importlib
import logging
import math
import socket
import struct
import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Final, cast

from roost_agent.steering import steered_sockets
from roost_mavlink import pymavlink_device

log = logging.getLogger(__name__)

Address = tuple[str, int]
Received = tuple[bytes, Address | None, float | None]  # data, sender, kernel arrival stamp

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


CONNECT_TIMEOUT_S = 2.0
UDP_MAX: Final = 65535
RECEIVE_BUFFER_BYTES = 1 << 20  # absorbs a burst of foreign datagrams


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

    def fast_fds(self) -> tuple[int, int] | None:
        """(bulk socket, urgent socket or -1) where the hub's fast path
        (:mod:`roost_agent.fastpath`) may read this transport in C: a UDP link with
        kernel arrival stamps. None: it may not."""
        return None

    def take_held(self) -> list[Received]:
        """What a read left held for order (:meth:`_Udp.receive_batch`), handed over."""
        return []

    def keep_held(self, held: list[Received]) -> None:
        """Hold ``held`` for the next read (the fast path read it in C)."""

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
        self._held: list[Received] = []  # read, but not yet in order (receive_batch)

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

    def fast_fds(self) -> tuple[int, int] | None:
        if not self._stamped:
            return None
        return self._sock.fileno(), -1 if self.urgent is None else self.urgent.fileno()

    def take_held(self) -> list[Received]:
        held, self._held = self._held, []
        return held

    def keep_held(self, held: list[Received]) -> None:
        self._held = held

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
        """Up to ``limit`` datagrams from each socket per look, in arrival order.

        Steered, a frame must never be delivered before an older one of the other socket:
        the signing replay check and the settling of claims go by the order frames are
        read. So the time is noted, then both sockets are read, and only what arrived
        before that moment is delivered, merged by arrival stamp. Everything else read
        (arrived during the reads, or behind a socket read only up to ``limit``) waits in
        :attr:`_held` for the next look: it arrived after everything delivered now, and
        everything still queued arrived after the moment noted. A second look follows at
        once when something was held, so a frame waits for a later call only when another
        one arrived during that look too.
        """
        if not self._stamped:
            return super().receive_batch(limit)
        urgent = self.urgent
        if urgent is None:
            return receive_all(self._sock, limit)
        ready = self._in_order(urgent, limit)
        if self._held:
            ready += self._in_order(urgent, limit)
        return ready

    def _in_order(self, urgent: socket.socket, limit: int) -> list[Received]:
        """One look at both sockets (:meth:`receive_batch`)."""
        cutoff = time.time()  # the arrival stamps' clock (CLOCK_REALTIME)
        first = receive_all(urgent, limit)
        bulk = receive_all(self._sock, limit)
        looked = time.time()
        for read in (first, bulk):
            if len(read) >= limit:  # more queued behind it: complete only up to its last
                cutoff = min(cutoff, _arrival(read[-1]))
        ready: list[Received] = []
        held: list[Received] = []
        for received in sorted(self._held + first + bulk, key=_arrival):
            # Unstamped (stamping not on yet): as read, now. Stamped after the look
            # itself: from before the wall clock stepped back, so never held for it.
            stamp = received[2]
            later = stamp is not None and cutoff < stamp <= looked
            (held if later else ready).append(received)
        self._held = held
        return ready

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


def _from_extension(name: str) -> Callable[..., object] | None:
    """A function of the C extension ``_udpbatch.c``, or None where it is not built (no C
    compiler at install) or is a build from before the function existed."""
    try:
        module = importlib.import_module("roost_agent._udpbatch")
    except ImportError:
        return None
    return cast("Callable[..., object] | None", getattr(module, name, None))


BATCH_RECEIVE: Final = cast(
    "Callable[[int, int], list[Received]] | None", _from_extension("receive")
)
"""The C extension's ``receive``: one recvmmsg for the queue, no failing read at its end."""

DATAGRAM_SEND: Final = cast("Callable[[int, bytes, Address], None] | None", _from_extension("send"))
"""The C extension's ``send``: one datagram, the GIL held (Python's ``sendto`` lets it go,
and under contention the sending thread waits a switch interval to take it back)."""


def receive_all(sock: socket.socket, limit: int) -> list[Received]:
    """Every datagram queued on ``sock`` (up to ``limit``) with its sender and kernel
    arrival stamp: in one system call per 16 where the C extension is built, else one
    read each and a last one that finds the queue empty."""
    receive = BATCH_RECEIVE
    if receive is not None:
        return receive(sock.fileno(), limit)
    return receive_each(sock, limit)


def send_to(sock: socket.socket, data: bytes, address: Address) -> None:
    """One datagram to ``address``: without releasing the GIL where the C extension is
    built (a hub client's command then waits for no other Python thread), else
    ``sendto``. Raises OSError as ``sendto`` does (BlockingIOError: the queue is full)."""
    send = DATAGRAM_SEND
    if send is not None:
        send(sock.fileno(), data, address)
    else:
        sock.sendto(data, address)


def receive_each(sock: socket.socket, limit: int) -> list[Received]:
    """:func:`receive_all` in Python, a read per datagram (the C extension's fallback)."""
    return _read_all(partial(_receive_stamped, sock), limit)


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
            send_to(self._sock, data, self._peer)


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
        send_to(self._sock, data, self.fixed_peer)


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
