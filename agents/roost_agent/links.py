"""One MAVLink link per autopilot: a transport, one reader thread, locked writes.

Why one link per autopilot (not one shared socket): two autopilots behind one socket are
merged by a MAVLink router and a command can reach both. Why a single reader: the
pymavlink parser is not thread-safe, so the reader is the only thing that ever parses;
it feeds the health tracker and hands COMMAND_ACKs to whoever waits for them. Writes
(the agent's heartbeat, safety commands) take a lock, which also keeps the MAVLink
sequence numbers in order.

Why our own transports instead of ``pymavlink.mavutil`` connections: mavutil imports
numpy and a MAVLink 1 dialect (about 30 MB of the agent's memory, on a companion
computer), prints to stdout, and its UDP listener sends every reply to every address
that ever sent it a datagram, spoofers included. Here the pymavlink dialect does the
parsing and encoding; a UDP listener replies only to the address this autopilot's
messages come from; a UDP sender accepts datagrams only from its destination.

Only messages whose source is this autopilot's system id and component id count. A
spoofed or foreign sysid on the same port, a non-autopilot component sharing the sysid,
and bytes that do not parse are counted and otherwise ignored; a reader never dies on
bad input (it reopens the connection after a run of errors).

The agent talks as component 191 (onboard computer) with the autopilot's own system id,
as a companion computer does, and addresses commands to the autopilot's component
(never the broadcast component 0). Connection URLs are read by
:func:`roost_mavlink.pymavlink_device`, the one parser of ``AutopilotSpec.connection``.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent.health import HealthTracker, Motion
from roost_api.autopilot import AutopilotSpec
from roost_api.meta import Stack
from roost_mavlink import AGENT_COMPONENT_ID, MavResult, pymavlink_device
from roost_mavlink.status import MAV_AUTOPILOT_INVALID, MAV_TYPE_ONBOARD_CONTROLLER, MavState

log = logging.getLogger(__name__)

Params = tuple[float, float, float, float, float, float, float]
Address = tuple[str, int]

READ_WAIT_S = 0.1  # how long the reader blocks in select() before checking for stop
REOPEN_DELAY_S = 0.5
CONNECT_TIMEOUT_S = 2.0
MAX_CONSECUTIVE_ERRORS = 50
UDP_MAX = 65535


@dataclass
class LinkCounters:
    """What the reader saw; exposed for diagnostics and the benchmarks."""

    accepted: int = 0  # from this autopilot's sysid/component
    foreign: int = 0  # parsed, but from another sysid or component
    bad: int = 0  # bytes that did not parse (BAD_DATA)
    errors: int = 0  # exceptions from the parser or the transport
    reopened: int = 0


class Transport:
    """A byte pipe to one autopilot. ``receive`` never blocks (the reader selects first)."""

    def fileno(self) -> int:
        raise NotImplementedError

    def receive(self) -> tuple[bytes, Address | None]:
        """Available bytes and who sent them (None where the transport has one peer)."""
        raise NotImplementedError

    def send(self, data: bytes) -> None:
        raise NotImplementedError

    def confirm_peer(self, address: Address) -> None:
        """The autopilot itself sent from ``address`` (only UDP listeners care)."""

    def close(self) -> None:
        raise NotImplementedError


class _Udp(Transport):
    def __init__(self, bind: Address | None) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if bind is not None:
            self._sock.bind(bind)
        self._sock.setblocking(False)

    def fileno(self) -> int:
        return self._sock.fileno()

    def receive(self) -> tuple[bytes, Address | None]:
        try:
            data, address = self._sock.recvfrom(UDP_MAX)
        except (BlockingIOError, ConnectionRefusedError):
            return b"", None
        return data, (str(address[0]), int(address[1]))

    def close(self) -> None:
        self._sock.close()


class UdpListen(_Udp):
    """``udp://HOST:PORT``: listen; reply to where this autopilot's messages come from."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__((host, port))
        self._peer: Address | None = None

    def confirm_peer(self, address: Address) -> None:
        self._peer = address

    def send(self, data: bytes) -> None:
        if self._peer is not None:  # nothing heard from the autopilot yet: nowhere to send
            self._sock.sendto(data, self._peer)


class UdpOut(_Udp):
    """``udpout://HOST:PORT``: send there; accept datagrams only from there."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(None)
        self._dest: Address = (socket.gethostbyname(host), port)

    def receive(self) -> tuple[bytes, Address | None]:
        data, address = super().receive()
        return (data, address) if address == self._dest else (b"", None)

    def send(self, data: bytes) -> None:
        self._sock.sendto(data, self._dest)


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


def open_transport(connection: str) -> Transport:
    """Open the transport an ``AutopilotSpec.connection`` URL names."""
    device = pymavlink_device(connection)
    kind, _, rest = device.device.partition(":")
    host, _, port = rest.rpartition(":")
    if kind == "udpin":
        return UdpListen(host, int(port))
    if kind == "udpout":
        return UdpOut(host, int(port))
    if kind == "tcp":
        return TcpClient(host, int(port))
    if kind == "tcpin":
        return TcpListen(host, int(port))
    return SerialPort(device.device, device.baud)


class _Writer:
    """The file object the pymavlink encoder writes finished frames to."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport

    def write(self, data: bytes) -> None:
        self.transport.send(bytes(data))


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


class AutopilotLink:
    """The agent's connection to one autopilot."""

    def __init__(
        self,
        spec: AutopilotSpec,
        tracker: HealthTracker,
        on_change: Callable[[], None] = lambda: None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.stack = Stack(spec.stack)
        self.tracker = tracker
        self.counters = LinkCounters()
        self.acks = AckMailbox()
        self._on_change = on_change
        self._clock = clock
        self._write_lock = threading.Lock()
        self._transport: Transport | None = None
        self._mav: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Start the reader thread; the transport is opened (and reopened) by it."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"link-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the reader and close the transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        self._close()

    def _close(self) -> None:
        with self._write_lock:
            transport, self._transport, self._mav = self._transport, None, None
        if transport is not None:
            try:
                transport.close()
            except OSError:
                log.debug("closing %s failed", self.name, exc_info=True)

    # -- reading ---------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                transport = open_transport(self.spec.connection)
            except (OSError, ValueError, ImportError) as exc:
                log.warning("%s: cannot open %s: %s", self.name, self.spec.connection, exc)
                self._stop.wait(REOPEN_DELAY_S)
                continue
            mav = mavlink.MAVLink(
                _Writer(transport), srcSystem=self.spec.sysid, srcComponent=AGENT_COMPONENT_ID
            )
            mav.robust_parsing = True
            with self._write_lock:
                self._transport, self._mav = transport, mav
            self._read_until_broken(transport, mav)
            self._close()
            if not self._stop.is_set():
                self.counters.reopened += 1
                self._stop.wait(REOPEN_DELAY_S)

    def _read_until_broken(self, transport: Transport, mav: Any) -> None:
        """Read and dispatch until stopped or the transport is beyond repair."""
        errors = 0
        while not self._stop.is_set():
            try:
                readable, _, _ = select.select([transport.fileno()], [], [], READ_WAIT_S)
                if not readable:
                    continue
                data, sender = transport.receive()
                if not data:
                    continue
                msg = mav.parse_char(data)
                while msg is not None:
                    if self._dispatch(msg) and sender is not None:
                        transport.confirm_peer(sender)
                    msg = mav.parse_char(b"")
            except OSError as exc:  # socket or serial failure (ConnectionError included)
                log.warning("%s: transport failed (%s); reopening", self.name, exc)
                return
            except Exception:  # the parser choked on something: count it and go on
                self.counters.errors += 1
                errors += 1
                if errors >= MAX_CONSECUTIVE_ERRORS:
                    log.warning("%s: %d parse errors in a row; reopening", self.name, errors)
                    return
                continue
            errors = 0

    def _dispatch(self, msg: Any) -> bool:
        """Handle one parsed message; True when it came from this autopilot."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.counters.bad += 1
            return False
        if (
            msg.get_srcSystem() != self.spec.sysid
            or msg.get_srcComponent() != self.spec.component_id
        ):
            self.counters.foreign += 1
            return False
        self.counters.accepted += 1
        now = self._clock()
        if kind == "COMMAND_ACK":
            target_system = getattr(msg, "target_system", 0)
            target_component = getattr(msg, "target_component", 0)
            if target_system in (0, self.spec.sysid) and target_component in (
                0,
                AGENT_COMPONENT_ID,
            ):
                self.acks.put(int(msg.command), int(msg.result))
        if self.tracker.observe(msg, now):
            self._on_change()
        return True

    # -- writing ---------------------------------------------------------------------

    def _send(self, write: Callable[[Any], None]) -> bool:
        with self._write_lock:
            if self._mav is None:
                return False
            try:
                write(self._mav)
            except (OSError, ValueError) as exc:
                log.debug("%s: write failed: %s", self.name, exc)
                return False
            return True

    def send_heartbeat(self) -> bool:
        """The agent's own 1 Hz heartbeat (onboard controller, not an autopilot).

        It tells the autopilot an onboard computer is present and lets a ``udpout``
        or TCP peer learn where to send.
        """
        return self._send(
            lambda mav: mav.heartbeat_send(
                MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MavState.ACTIVE
            )
        )

    def send_command(self, command: int, params: Params, confirmation: int = 0) -> bool:
        """COMMAND_LONG addressed to this autopilot's system and component."""
        return self._send(
            lambda mav: mav.command_long_send(
                self.spec.sysid, self.spec.component_id, command, confirmation, *params
            )
        )

    def request_data_stream(self, stream_id: int, hz: int) -> bool:
        """REQUEST_DATA_STREAM (start) for one MAV_DATA_STREAM group (ArduPilot)."""
        return self._send(
            lambda mav: mav.request_data_stream_send(
                self.spec.sysid, self.spec.component_id, stream_id, hz, 1
            )
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
