"""One MAVLink link per autopilot: a pymavlink connection, one reader thread, locked writes.

Why one connection per autopilot (not one shared socket): two autopilots behind one
socket are merged by pymavlink and a command can reach both. Why a single reader:
pymavlink is not thread-safe and ``recv_match`` discards messages other than the one it
waits for, so the reader is the only thing that ever reads; it feeds the health tracker
and hands COMMAND_ACKs to whoever waits for them. Writes (the agent's heartbeat, safety
commands) take a lock.

Only messages whose source is this autopilot's system id and component id count. A
spoofed or foreign sysid on the same port, a non-autopilot component sharing the sysid,
and bytes that do not parse are counted and otherwise ignored; a reader never dies on
bad input (it reopens the connection after a run of errors).

The agent talks as component 191 (onboard computer) with the autopilot's own system id,
as a companion computer does, and addresses commands to the autopilot's component
(never the broadcast component 0).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from roost_agent.health import HealthTracker
from roost_api.autopilot import AutopilotSpec
from roost_api.meta import Stack
from roost_mavlink import AGENT_COMPONENT_ID, MavResult, pymavlink_device
from roost_mavlink.status import MAV_AUTOPILOT_INVALID, MAV_TYPE_ONBOARD_CONTROLLER, MavState

# pymavlink picks its wire protocol when mavutil is first imported; Roost speaks MAVLink 2.
os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
    mavutil.set_dialect(mavutil.current_dialect)  # imported earlier without MAVLINK20

log = logging.getLogger(__name__)

Params = tuple[float, float, float, float, float, float, float]

READ_WAIT_S = 0.1  # how long the reader blocks in select() before checking for stop
REOPEN_DELAY_S = 0.5
MAX_CONSECUTIVE_ERRORS = 50
TCP_EOF_READS = 20  # readable-but-empty reads in a row that mean the TCP peer is gone


@dataclass
class LinkCounters:
    """What the reader saw; exposed for diagnostics and the benchmarks."""

    accepted: int = 0  # from this autopilot's sysid/component
    foreign: int = 0  # parsed, but from another sysid or component
    bad: int = 0  # bytes that did not parse (BAD_DATA)
    errors: int = 0  # exceptions from the parser or the socket
    reopened: int = 0


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
        self._conn: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Start the reader thread; the connection is opened (and reopened) by it."""
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"link-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the reader and close the connection."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        self._close()

    def wait_open(self, timeout_s: float) -> bool:
        """Block until the connection is open (tests and startup diagnostics)."""
        deadline = time.monotonic() + timeout_s
        while self._conn is None and time.monotonic() < deadline:
            time.sleep(0.01)
        return self._conn is not None

    def _open(self) -> Any:
        device = pymavlink_device(self.spec.connection)
        # A TCP connection is reopened by this link's own loop, not by pymavlink.
        extra: dict[str, Any] = {"retries": 0} if device.device.startswith("tcp") else {}
        return mavutil.mavlink_connection(
            device.device,
            baud=device.baud,
            source_system=self.spec.sysid,
            source_component=AGENT_COMPONENT_ID,
            robust_parsing=True,
            **extra,
        )

    def _close(self) -> None:
        with self._write_lock:
            conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except OSError:
                log.debug("closing %s failed", self.name, exc_info=True)

    # -- reading ---------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn = self._open()
            except Exception as exc:  # any failure to open: retry, never kill the agent
                log.warning("%s: cannot open %s: %s", self.name, self.spec.connection, exc)
                self._stop.wait(REOPEN_DELAY_S)
                continue
            with self._write_lock:
                self._conn = conn
            self._read_until_broken(conn)
            self._close()
            if not self._stop.is_set():
                self.counters.reopened += 1
                self._stop.wait(REOPEN_DELAY_S)

    def _read_until_broken(self, conn: Any) -> None:
        """Read and dispatch until stopped or the connection is beyond repair."""
        errors = 0
        empty_reads = 0
        is_tcp = str(getattr(conn, "address", "")).startswith("tcp:")
        while not self._stop.is_set():
            try:
                msg = conn.recv_msg()
            except Exception:  # the parser or socket choked: count it and go on
                self.counters.errors += 1
                errors += 1
                if errors >= MAX_CONSECUTIVE_ERRORS:
                    log.warning("%s: %d read errors in a row; reopening", self.name, errors)
                    return
                continue
            errors = 0
            if msg is None:
                readable = conn.select(READ_WAIT_S)
                empty_reads = empty_reads + 1 if readable else 0
                if is_tcp and empty_reads >= TCP_EOF_READS:
                    return  # readable yet nothing arrives: the peer closed the socket
                continue
            empty_reads = 0
            self._dispatch(msg)

    def _dispatch(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.counters.bad += 1
            return
        if (
            msg.get_srcSystem() != self.spec.sysid
            or msg.get_srcComponent() != self.spec.component_id
        ):
            self.counters.foreign += 1
            return
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

    # -- writing ---------------------------------------------------------------------

    def _send(self, write: Callable[[Any], None]) -> bool:
        with self._write_lock:
            if self._conn is None:
                return False
            try:
                write(self._conn.mav)
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
