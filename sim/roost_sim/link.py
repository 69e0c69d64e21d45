"""Byte transports of the simulated autopilot, with injectable link impairments.

A link carries whole MAVLink frames out and raw chunks in. Impairments act where a real
radio or cable would: loss drops outgoing frames and incoming chunks with the given
probability; jitter delays each outgoing frame by a uniform 0..J ms while keeping their
order (a serial line never reorders, and PX4's UDP sender on one host does not either);
garbage is written between frames as if the line picked up noise.

Two transports:

- :class:`UdpLink`: one socket bound on 127.0.0.1 (port 0 = free port). Frames go to the
  configured target and to every address that has sent a datagram here, so a listening
  agent (``udpin``) and a client that talks first (``udpout``, MAVSDK) are both served.
- :class:`PtyLink`: the master side of a pseudo-terminal in raw mode; the slave path is
  what a serial client opens. Writes never block: with nobody reading, bytes beyond the
  kernel buffer are dropped, like a UART transmitting into an unplugged cable.

MAVLink 2 signing (:meth:`Link.enable_signing`) acts where a flight stack's MAVLink layer
does, on whole frames: every frame sent is signed, and incoming frames are checked and,
when signing is required, dropped unless their signature is good (counted in
:class:`SigningCounters`). Injected noise and spoofed frames stay unsigned, as an
attacker's would be. Incoming frames are checked per received chunk, which is exact on
UDP (whole frames per datagram); on a pseudo-terminal a frame split across two reads is
dropped, so signing tests use UDP.
"""

from __future__ import annotations

import contextlib
import os
import random
import select
import socket
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field

from roost_mavlink.signing import Signer, Timestamps, Verdict, Verifier, split_frames

Address = tuple[str, int]
_MAX_PEERS = 8
_PTY_BACKLOG_BYTES = 65536


@dataclass
class Impairment:
    """Current link impairments (all zero means a perfect link)."""

    loss_percent: float = 0.0
    jitter_ms: float = 0.0


@dataclass
class SigningCounters:
    """Incoming frames by signature verdict."""

    good: int = 0
    unsigned: int = 0
    bad: int = 0


@dataclass
class _Signing:
    signer: Signer
    verifier: Verifier
    require: bool
    clock: Timestamps
    counters: SigningCounters = field(default_factory=SigningCounters)

    def filter(self, data: bytes) -> bytes:
        kept: list[bytes] = []
        for frame in split_frames(data):
            verdict = self.verifier.check(frame)
            if verdict is Verdict.GOOD:
                self.counters.good += 1
            elif verdict is Verdict.UNSIGNED:
                self.counters.unsigned += 1
            else:
                self.counters.bad += 1
            if verdict is Verdict.GOOD or not self.require:
                kept.append(frame)
        return b"".join(kept)


class Link(ABC):
    """A bidirectional byte link with impairments; thread-safe sending."""

    def __init__(self, *, seed: int | None = None) -> None:
        self.impairment = Impairment()
        self._random = random.Random(seed)
        self._send_lock = threading.Lock()
        self._queue: deque[tuple[float, bytes]] = deque()
        self._queue_ready = threading.Condition()
        self._last_due = 0.0
        self._closed = threading.Event()
        self._delayer: threading.Thread | None = None
        self._wake_read = self._wake_write = -1  # a pipe that interrupts a receive
        self._signing: _Signing | None = None
        self.frames_sent = 0  # frames handed to the transport (after loss)

    # ---- implemented by transports ---------------------------------------------------

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _write(self, data: bytes) -> None:
        """Deliver bytes now (one datagram per call on UDP)."""

    @abstractmethod
    def _read(self, timeout: float) -> bytes:
        """Bytes that arrived within ``timeout`` seconds, b"" when none."""

    @property
    @abstractmethod
    def connection(self) -> str:
        """The ``AutopilotSpec.connection`` URL an agent uses to reach this link."""

    # ---- shared behaviour ------------------------------------------------------------

    def open(self) -> None:
        """Open the transport and start the jitter delay line."""
        self._closed.clear()
        self._wake_read, self._wake_write = os.pipe()
        self._open()
        self._delayer = threading.Thread(
            target=self._run_delayer, name="sim-link-delay", daemon=True
        )
        self._delayer.start()

    def close(self) -> None:
        """Stop sending and release the transport."""
        self._closed.set()
        with self._queue_ready:
            self._queue.clear()
            self._queue_ready.notify_all()
        if self._delayer is not None:
            self._delayer.join(timeout=2)
        self._close()
        for fd in (self._wake_read, self._wake_write):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_read = self._wake_write = -1

    def interrupt(self) -> None:
        """Make a :meth:`receive` waiting now return at once (before :meth:`close`)."""
        if self._wake_write >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_write, b"x")

    def _readable(self, fd: int, timeout: float) -> bool:
        """Wait until ``fd`` has bytes (True), or ``timeout`` passed or :meth:`interrupt`
        was called (False): a receive thread sleeps until there is work or it must stop."""
        ready, _, _ = select.select([fd, self._wake_read], [], [], timeout)
        return fd in ready

    def enable_signing(self, key: bytes, *, link_id: int = 0, require: bool = True) -> None:
        """Sign every frame from now on; with ``require`` hear only well-signed frames.

        Re-keying keeps the signing clock, as a flight stack keeps its persisted
        timestamp when given a new key: a fresh clock could start below the last
        timestamp a peer saw on the stream (the old one runs ahead of the wall clock by
        a tick per frame in a burst) and the peer would rightly drop it as a replay.
        """
        clock = self._signing.clock if self._signing is not None else Timestamps()
        self._signing = _Signing(Signer(key, link_id, clock), Verifier(key, clock), require, clock)

    @property
    def signing_counters(self) -> SigningCounters | None:
        """Incoming frames by verdict while signing is enabled."""
        return None if self._signing is None else self._signing.counters

    def send(self, frame: bytes) -> None:
        """Send one frame, subject to loss and jitter."""
        jitter = self.impairment.jitter_ms
        with self._queue_ready:
            # Signed under the lock that orders delivery, so frames of several threads
            # leave in the order of their signing timestamps, as from one autopilot's
            # link: a peer rightly drops a frame older than the last it saw on the
            # stream as a replay.
            signing = self._signing
            if signing is not None:
                frame = signing.signer.sign(frame)
            if self._closed.is_set() or self._lost():
                return
            self.frames_sent += 1
            if jitter <= 0 and not self._queue:
                self._deliver(frame)
                return
            due = time.monotonic() + self._random.uniform(0.0, max(jitter, 0.0)) / 1000.0
            self._last_due = max(due, self._last_due)
            self._queue.append((self._last_due, frame))
            self._queue_ready.notify()

    def receive(self, timeout: float) -> bytes:
        """Incoming bytes (b"" on timeout or when the chunk was lost)."""
        data = self._read(timeout)
        if data and self._lost():
            return b""
        signing = self._signing
        if data and signing is not None:
            return signing.filter(data)
        return data

    def _lost(self) -> bool:
        loss = self.impairment.loss_percent
        return loss > 0 and self._random.random() * 100.0 < loss

    def _deliver(self, data: bytes) -> None:
        # Nobody listening (ICMP unreachable) or the peer went away: a real autopilot
        # keeps streaming regardless.
        with self._send_lock, contextlib.suppress(OSError):
            self._write(data)

    def _run_delayer(self) -> None:
        while not self._closed.is_set():
            with self._queue_ready:
                while not self._queue and not self._closed.is_set():
                    self._queue_ready.wait()  # send and close notify
                if self._closed.is_set():
                    return
                due, frame = self._queue[0]
                wait = due - time.monotonic()
                if wait > 0:
                    self._queue_ready.wait(wait)
                    continue
                self._queue.popleft()
                self._deliver(frame)

    def flush_delayed(self) -> None:
        """Deliver every frame still held by the jitter delay line now (jitter cleared)."""
        with self._queue_ready:
            while self._queue:
                self._deliver(self._queue.popleft()[1])
            self._last_due = 0.0

    def write_noise(self, data: bytes) -> None:
        """Put raw bytes on the line immediately (garbage injection)."""
        if not self._closed.is_set():
            self._deliver(data)


class UdpLink(Link):
    """MAVLink over UDP on the loopback interface."""

    def __init__(
        self,
        target: Address | None = None,
        *,
        bind: Address = ("127.0.0.1", 0),
        seed: int | None = None,
    ) -> None:
        super().__init__(seed=seed)
        self.target = target
        self._bind = bind
        self._sock: socket.socket | None = None
        self._peers: list[Address] = [target] if target else []

    @property
    def local_address(self) -> Address:
        """Where this sim listens (valid after open)."""
        if self._sock is None:
            raise RuntimeError("link not open")
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def connection(self) -> str:
        if self.target is not None:
            return f"udp://{self.target[0]}:{self.target[1]}"
        host, port = self.local_address
        return f"udpout://{host}:{port}"

    @property
    def peers(self) -> list[Address]:
        """Addresses frames are sent to."""
        return list(self._peers)

    def _open(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(self._bind)
        self._sock = sock

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()

    def _write(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            return
        for peer in self._peers:
            with contextlib.suppress(OSError):
                sock.sendto(data, peer)

    def _read(self, timeout: float) -> bytes:
        sock = self._sock
        if sock is None:
            return b""
        try:
            if not self._readable(sock.fileno(), timeout):
                return b""
            data, addr = sock.recvfrom(65535)
        except (OSError, ValueError):
            return b""
        peer = (str(addr[0]), int(addr[1]))
        if peer not in self._peers and len(self._peers) < _MAX_PEERS:
            self._peers.append(peer)
        return data


class PtyLink(Link):
    """MAVLink over a pseudo-terminal; clients open :attr:`device`."""

    def __init__(self, *, baud: int = 57600, seed: int | None = None) -> None:
        super().__init__(seed=seed)
        self.baud = baud
        self._master = -1
        self._slave = -1
        self._device = ""
        self._backlog = b""

    @property
    def device(self) -> str:
        """Path of the slave side, e.g. /dev/pts/7 (valid after open)."""
        return self._device

    @property
    def connection(self) -> str:
        return f"serial://{self._device}:{self.baud}"

    def _open(self) -> None:
        self._master, self._slave = os.openpty()
        # Raw mode: no echo of our own frames back to us, no newline translation.
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self._device = os.ttyname(self._slave)

    def _close(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def _write(self, data: bytes) -> None:
        if self._master < 0:
            return
        self._backlog = (self._backlog + data)[-_PTY_BACKLOG_BYTES:]
        try:
            written = os.write(self._master, self._backlog)
        except BlockingIOError:
            written = 0
        self._backlog = self._backlog[written:]

    def _read(self, timeout: float) -> bytes:
        if self._master < 0:
            return b""
        try:
            if not self._readable(self._master, timeout):
                return b""
            return os.read(self._master, 4096)
        except (BlockingIOError, OSError, ValueError):
            return b""
