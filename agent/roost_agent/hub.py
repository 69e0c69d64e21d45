"""The vehicle's MAVLink hub: one endpoint for every client, routed to the active autopilot.

Why the agent is the hub: it already owns every autopilot link (a serial port opens
once), and it is the one process that knows, within the decision tick, which autopilot
drives the motors. Routing here means a failover moves the clients' route in the same
tick as the bridge write (:meth:`Hub.set_active`, one attribute store), so mavros, a
mission's MAVSDK controller or a ground station keep their connection and their setpoint
stream simply continues on the new autopilot: no pod restart, no reconnect.

Identity. The autopilots keep distinct system ids on their own links (the spec requires
it: the agent's health tracking, source locks and command acks tell them apart by it),
and the hub shows clients one vehicle identity (``HubSpec.sysid``) by rewriting the
source system id in each forwarded frame's header and recomputing its CRC
(:func:`rewrite_source`); client frames addressed to the vehicle get the target system of
the autopilot they go to (:func:`retarget`). Only the active autopilot's frames are ever
rewritten and forwarded: a standby's or a failed autopilot's frames are read by the agent
(health, in-step checks) and dropped, so nothing from them can reach a client as if from
the vehicle. The alternative, one sysid configured on every autopilot and frames passed
through untouched, was rejected: two autopilots answering to one id cannot be told apart
on any shared path (a router, a radio, a log), and a standby's acknowledgement would be
indistinguishable from the active's. Rewriting costs a header rewrite and a CRC per frame
(measured: ``hub.added_latency_p99_ms``); when an autopilot's sysid already equals the
vehicle's, its frames pass unchanged. Signed frames from an autopilot lose their
signature on the way to clients (the rewritten header would not verify); clients of a
signed endpoint get every frame signed again by the hub with the vehicle's key.

Endpoints (:mod:`roost_agent.hub_policy`): the ``udp`` and ``tcp`` endpoints and each of
``hub.endpoints`` have a gate: MAVLink 2 signature (with the vehicle's key; required
beyond loopback unless the spec says Unauthenticated) and a scope (everything, reads
only, or an allow-list). What fails either is dropped and counted per client, never
forwarded. The open gate (loopback, everything) keeps the original per-frame path.

Standbys in step. What clients send that changes flight state (:data:`MIRRORED_COMMANDS`
inside COMMAND_LONG/INT, and :data:`MIRRORED_MESSAGES`: modes, mission items, setpoints,
parameter writes, the ground station's heartbeat so no standby triggers a GCS failsafe)
goes to every standby too; their answers never reach the client but are recorded, so a standby that
rejects a mirrored command or does not answer is seen at once. Whether each standby is in
step with the active is judged from what the hub read of them (:mod:`roost_agent.instep`).
Mode commands and parameter writes are mirrored only between autopilots of the same
stack (a custom mode number or a parameter name means something else on the other stack).

ArduPilot standbys: ArduPilot's auxiliary function 76 (STANDBY) tells a flight controller
its outputs are not on the motors, so it relaxes its controllers' integrators instead of
winding them up against a vehicle it does not fly. The hub sends it (MAV_CMD_DO_AUX_FUNCTION,
switch high) to every ArduPilot standby, and low to an ArduPilot autopilot that becomes
active, right after the route moved (never before the bridge write).
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

from roost_agent.fastpath import PUMP, FastRoute, routine_bitmap
from roost_agent.health import LATEST_ONLY_KINDS as HEALTH_LATEST_ONLY_KINDS
from roost_agent.health import READ_KINDS as HEALTH_READ_KINDS
from roost_agent.health import STATE_FIELDS as HEALTH_STATE_FIELDS
from roost_agent.hub_policy import (
    ACCEPT,
    COMMAND_INT_ID,
    COMMAND_LONG_ID,
    NO_COMMAND,
    Drops,
    EndpointPlan,
    Gate,
    Scope,
    authenticated,
    open_to_the_network,
    plan_endpoints,
)
from roost_agent.instep import (
    MIRRORED_COMMANDS,
    InStep,
    InStepTracker,
    Snapshot,
    judge_standby,
    note_answer,
)
from roost_agent.link import LOG_REPLIES
from roost_agent.link import READ_KINDS as LINK_READ_KINDS
from roost_agent.reader import Session
from roost_agent.signing import LinkSigning
from roost_agent.transport import receive_all
from roost_api.autopilot_enums import HubTransport, StandbyInStepReason
from roost_api.core import Stack
from roost_api.plain import AutopilotSpec, HubEndpointStatus, HubSpec, RedundantAutopilotSpec
from roost_mavlink import (
    AGENT_COMPONENT_ID,
    MAV_CMD_DO_SET_MODE,
    MAV_MODE_FLAG_SAFETY_ARMED,
    mode_name,
)
from roost_mavlink.codec import (
    CRC_BYTES,
    V1_HEADER,
    V1_MAGIC,
    V2_HEADER,
    V2_MAGIC,
    BadData,
    Frame,
    Parsed,
    StreamParser,
    crc_extra_of,
    frame_crc,
    message,
    scan,
)
from roost_mavlink.signing import Signer

log = logging.getLogger(__name__)

Address = tuple[str, int]

SIGNED_FLAG = 0x01

CLIENT_TIMEOUT_S = 30.0  # a UDP client not heard this long gets nothing more
MAX_CLIENTS = 32
"""The most clients the hub serves at once (one more pushes one out: :meth:`Hub._add`).
The one limit: the fast path (``_udpbatch.c``) serves every client it is given."""
HUB_LINK_ID = 0xF0  # the MAVLink signing link id of the hub's frames to clients
READ_KINDS: Final = frozenset({"HEARTBEAT", "GLOBAL_POSITION_INT", "COMMAND_ACK"}) | LOG_REPLIES
"""The message types whose content the hub reads (:meth:`Hub._from_autopilot`: a
snapshot for the standby judgement, an answer from a standby, the log session)."""
_ACTIVE_IN_STEP: Final = InStep(
    True, StandbyInStepReason.ACTIVE, "the active autopilot: clients fly it"
)
"""The active autopilot's verdict (the same at every tick: built once)."""
ROUTINE: Final = routine_bitmap(READ_KINDS | LINK_READ_KINDS | HEALTH_READ_KINDS)
"""The message ids the fast path hands Python summarised (:mod:`roost_agent.fastpath`)."""
LATEST_ONLY_KINDS: Final = frozenset({"GLOBAL_POSITION_INT"})
"""Of :data:`READ_KINDS`, those of which the hub keeps only the latest (a snapshot)."""
_KEPT_KINDS: Final = LATEST_ONLY_KINDS | HEALTH_LATEST_ONLY_KINDS
RUN_KINDS: Final = routine_bitmap(
    (READ_KINDS | LINK_READ_KINDS | HEALTH_READ_KINDS)
    - _KEPT_KINDS
    - frozenset(HEALTH_STATE_FIELDS)
)
"""The message ids whose routed frames may be taken as a run (:mod:`roost_agent.fastpath`):
the routine ones, those of which the hub and the tracker read only the latest, and the
tracker's state kinds (a frame joins while it repeats the state held)."""
KEPT_IDS: Final = tuple(sorted(message(name).id for name in _KEPT_KINDS))
"""The message ids whose last frame in a run Python reads whole."""
SELECT_WAIT_S = 1.0  # the hub thread's longest sleep: clients expire after 30 s; stop wakes it
UDP_MAX = 65535
TCP_SEND_BUFFER = 1 << 18

MAV_CMD_DO_AUX_FUNCTION = 218
AUX_FUNCTION_STANDBY = 76  # ArduPilot RC_OPTION / aux function "Standby"
AUX_SWITCH_LOW = 0
AUX_SWITCH_HIGH = 2

MODE_COMMANDS: frozenset[int] = frozenset({MAV_CMD_DO_SET_MODE})

# Whole messages mirrored to every standby.
MIRRORED_MESSAGES: frozenset[str] = frozenset(
    {
        "HEARTBEAT",
        "SET_MODE",
        "SET_POSITION_TARGET_LOCAL_NED",
        "SET_POSITION_TARGET_GLOBAL_INT",
        "SET_ATTITUDE_TARGET",
        "MANUAL_CONTROL",
        "RC_CHANNELS_OVERRIDE",
        "MISSION_COUNT",
        "MISSION_ITEM_INT",
        "MISSION_ITEM",
        "MISSION_CLEAR_ALL",
        "MISSION_SET_CURRENT",
        "SET_HOME_POSITION",
        "PARAM_SET",
    }
)
# Mirrored only to standbys of the active autopilot's stack: a custom mode number, a
# parameter name and its unit mean something else (or nothing) on the other stack.
SAME_STACK_MESSAGES: frozenset[str] = frozenset({"SET_MODE", "PARAM_SET"})
COMMAND_MESSAGES: frozenset[str] = frozenset({"COMMAND_LONG", "COMMAND_INT"})


# -- frames ----------------------------------------------------------------------------


def rewrite_source(frame: bytes, sysid: int) -> bytes | None:
    """``frame`` with its source system id set to ``sysid`` and its CRC recomputed.

    A signature is dropped (it covers the header). None when the frame is not a whole
    MAVLink 1/2 frame of a known message (nothing to forward then).
    """
    if len(frame) < 8:
        return None
    magic = frame[0]
    if magic == V2_MAGIC:
        header, sys_at = V2_HEADER, 5
        msgid = frame[7] | frame[8] << 8 | frame[9] << 16
    elif magic == V1_MAGIC:
        header, sys_at = V1_HEADER, 3
        msgid = frame[5]
    else:
        return None
    end = header + frame[1]
    if len(frame) < end + CRC_BYTES:
        return None
    if frame[sys_at] == sysid:
        return frame
    crc_extra = crc_extra_of(msgid)
    if crc_extra is None:
        return None
    out = bytearray(frame[: end + CRC_BYTES])
    out[sys_at] = sysid
    if magic == V2_MAGIC and out[2] & SIGNED_FLAG:
        out[2] &= ~SIGNED_FLAG
    crc = frame_crc(out[1:end], crc_extra)
    out[end] = crc & 0xFF
    out[end + 1] = crc >> 8
    return bytes(out)


def target_of(msg: Any) -> int | None:
    """The target system a message addresses (None: it addresses no system)."""
    for name in ("target_system", "target"):
        value = getattr(msg, name, None)
        if isinstance(value, int):
            return value
    return None


def retarget(msg: Parsed, vehicle_sysid: int, sysid: int) -> bytes:
    """The client's frame for the autopilot with ``sysid``: a message addressed to the
    vehicle is re-encoded addressed to that autopilot (sender ids and sequence kept,
    unsigned); anything else passes unchanged."""
    frame = bytes(msg.get_msgbuf())
    if sysid == vehicle_sysid or not isinstance(msg, Frame) or target_of(msg) != vehicle_sysid:
        return frame
    name = "target_system" if hasattr(msg, "target_system") else "target"
    return msg.with_field(name, sysid)


# -- the hub ---------------------------------------------------------------------------


def _note_position(seen: Snapshot, msg: Any, now: float) -> None:
    """The position a GLOBAL_POSITION_INT gives the autopilot's snapshot."""
    seen.position_at = now
    seen.lat_deg = msg.lat / 1e7
    seen.lon_deg = msg.lon / 1e7
    seen.relative_alt_m = msg.relative_alt / 1000


def _nothing() -> None:
    pass


class HubLink(Protocol):
    """What the hub needs from an autopilot link (:class:`roost_agent.link.AutopilotLink`)."""

    name: str
    spec: AutopilotSpec
    tap: Callable[[Any, float], None] | None
    log_sink: Callable[[Any], None] | None
    """Set while the agent's own log download holds the autopilot's log session."""
    routed: bool
    """The datagram being read was routed to the fast route's clients in C already."""
    tap_routed: Callable[[int], bool] | None
    """Given the count of a routed datagram's routine frames (read no further)."""

    tap_run: Callable[[int, Sequence[tuple[str, Any, float]]], None] | None
    """Given a run's frame count and the last frame of each kept kind (type, message,
    arrival): a run of datagrams routed in C (:mod:`roost_agent.fastpath`)."""

    def fast_source(self) -> tuple[Session, Address] | None: ...

    def send_frame(self, frame: bytes) -> bool: ...

    def send_command(
        self, command: int, params: tuple[float, float, float, float, float, float, float]
    ) -> bool: ...


@dataclass
class HubCounters:
    """What the hub routed; for diagnostics, leak tests and the benchmarks."""

    to_clients: int = 0  # frames sent to clients (each client counted)
    from_clients: int = 0  # client messages routed to the active autopilot
    mirrored: int = 0  # client messages also sent to a standby (each standby counted)
    dropped_standby: int = 0  # standby / failed autopilot messages kept from clients
    dropped_from_clients: int = 0  # client frames an endpoint's gate refused
    kept_for_agent: int = 0  # active autopilot frames addressed to the agent, not forwarded
    forwarded: dict[str, int] = field(default_factory=dict)  # per autopilot, to clients
    switches: int = 0
    routed_in_c: int = 0  # active autopilot frames the fast path routed (roost_agent.fastpath)


class _Endpoint:
    """One socket the hub serves (UDP, or a TCP listener) with its gate and drop counts."""

    def __init__(self, plan: EndpointPlan, gate: Gate, sock: socket.socket) -> None:
        self.plan = plan
        self.name = plan.name
        self.gate = gate
        self.sock = sock
        self.udp = plan.transport is HubTransport.UDP
        self.drops = Drops(plan.name)


ClientKey = tuple[str, Address]  # (endpoint name, client address)


class _Client:
    """One connected client: where its frames go and the parser for its bytes."""

    def __init__(
        self, endpoint: _Endpoint, address: Address, sock: socket.socket | None, now: float
    ) -> None:
        self.endpoint = endpoint
        self.key: ClientKey = (endpoint.name, address)
        self.address = address
        self.sock = sock  # TCP clients only
        self.out = endpoint.sock  # UDP clients: the endpoint's socket sends to them
        self.signs = endpoint.plan.signed  # what it gets is signed
        self.signing_key: bytes | None = None  # the key it proved (a rotation may differ)
        # Gets the vehicle's messages: at once on an open endpoint, else once a frame of
        # it passed the signature check (a TCP connection alone proves nothing).
        self.ready = endpoint.gate.open
        self.parser = StreamParser()  # TCP clients' stream (a UDP datagram stands alone)
        self.last_seen = now
        self.broken = False  # a TCP client whose stream could not be written whole


def parse_host_port(text: str) -> Address:
    host, _, port = text.rpartition(":")
    return host, int(port)


def hub_identity(spec: RedundantAutopilotSpec) -> tuple[object, ...] | None:
    """What a running hub cannot change: its endpoints and the vehicle's identity."""
    hub = spec.hub
    return None if hub is None else (hub.udp, hub.tcp, hub.endpoints, vehicle_sysid(spec))


def vehicle_sysid(spec: RedundantAutopilotSpec) -> int:
    """The system id clients see: ``hub.sysid``, else the primary autopilot's."""
    if spec.hub is not None and spec.hub.sysid is not None:
        return spec.hub.sysid
    return next(a.sysid for a in spec.autopilots if a.name == spec.primary)


class Hub:
    """Serves the vehicle's MAVLink endpoint(s) and routes it to the active autopilot."""

    def __init__(
        self,
        spec: RedundantAutopilotSpec,
        active: str,
        *,
        signing: LinkSigning | None = None,
        on_event: Callable[[str, str, bool], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Binds every endpoint; raises :class:`~roost_agent.hub_policy.HubConfigError`
        for an endpoint that must sign without a key (``signing`` None), OSError when
        an address cannot be bound."""
        hub = spec.hub if spec.hub is not None else HubSpec()
        self.settings = hub
        self.sysid = vehicle_sysid(spec)
        self.stale_s = spec.failover_policy.thresholds.heartbeat_error_ms / 1000
        self.counters = HubCounters()
        self._clock = clock
        self._on_event = on_event
        self._active = active
        self._links: dict[str, HubLink] = {}
        self._seen: dict[str, Snapshot] = {
            a.name: Snapshot(Stack(a.stack)) for a in spec.autopilots
        }
        self._tracker = InStepTracker(hub.standby_limits.confirm_ms / 1000)
        self._clients: OrderedDict[ClientKey, _Client] = OrderedDict()
        self._sinks: tuple[_Client, ...] = ()  # clients that get the vehicle's messages
        self._route: FastRoute | None = None  # the last fast route made (fast_route)
        # Told when the clients change: the reader waiting in C on a route made for the
        # clients before looks again (a run routed meanwhile would miss a new client).
        self.on_sinks_changed: Callable[[], None] = _nothing
        # Whether routes are offered to the fast path (it is built; tests turn it off).
        self.fast = PUMP is not None
        self._by_sock: dict[socket.socket, _Client] = {}  # TCP clients, ready or not
        self._clients_lock = threading.Lock()
        self._stop = threading.Event()
        # (not "_thread": compiled, that attribute becomes the C keyword __thread)
        self._serving: threading.Thread | None = None
        # Wakes the hub thread's select at once to stop (it sleeps up to SELECT_WAIT_S).
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        plans = plan_endpoints(hub, signing is not None)
        self._signing = signing
        self._signer: Signer | None = None
        self.endpoints: list[_Endpoint] = []
        try:
            for plan in plans:
                self.endpoints.append(self._open(plan))
        except BaseException:
            self.close()
            raise
        self._listening = {e.sock: e for e in self.endpoints}
        if any(e.plan.signed for e in self.endpoints) and signing is not None:
            self._signer = signing.signer(HUB_LINK_ID)

    def _open(self, plan: EndpointPlan) -> _Endpoint:
        verifier = None
        if plan.signed:
            assert self._signing is not None  # plan_endpoints refused it otherwise
            verifier = self._signing.verifier()
        gate = Gate(Scope(plan.scope, plan.allow_messages, plan.allow_commands), verifier)
        if plan.transport is HubTransport.UDP:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind(parse_host_port(plan.address))
            except BaseException:
                sock.close()
                raise
        else:
            sock = socket.create_server(parse_host_port(plan.address))
        sock.setblocking(False)
        return _Endpoint(plan, gate, sock)

    def rekey(self, signing: LinkSigning) -> None:
        """Adopt a rotated key: frames to clients are signed with it from the next one
        on, and clients must sign with it (their streams start afresh)."""
        self._signing = signing
        for endpoint in self.endpoints:
            if endpoint.plan.signed:
                endpoint.gate = Gate(endpoint.gate.scope, signing.verifier())
        if self._signer is not None:
            self._signer = signing.signer(HUB_LINK_ID)
        known = (signing.key, signing.previous)
        with self._clients_lock:  # a client with a key retired twice must sign in again
            for client in self._clients.values():
                key = client.signing_key
                if client.signs and key is not None and key not in known:
                    client.ready = False
                    client.signing_key = None
            self._resink()

    def _resink(self) -> None:
        """The clients that get the vehicle's messages, again (under the clients lock)."""
        self._sinks = tuple(c for c in self._clients.values() if c.ready)
        self.on_sinks_changed()

    # -- wiring ------------------------------------------------------------------------

    def endpoint_address(self, name: str) -> Address:
        """Where the endpoint called ``name`` listens."""
        sock = next(e.sock for e in self.endpoints if e.name == name)
        host, port = sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def udp_address(self) -> Address:
        return self.endpoint_address("udp")

    @property
    def tcp_address(self) -> Address | None:
        return None if self.settings.tcp is None else self.endpoint_address("tcp")

    def endpoint_status(self) -> list[HubEndpointStatus]:
        """Every endpoint as the status shows it (scope, signing, frames dropped)."""
        out: list[HubEndpointStatus] = []
        for e in self.endpoints:
            host, port = e.sock.getsockname()[:2]
            out.append(
                HubEndpointStatus(
                    name=e.name,
                    transport=e.plan.transport,
                    address=f"{host}:{port}",
                    scope=e.plan.scope,
                    signed=e.plan.signed,
                    dropped=e.drops.total,
                )
            )
        return out

    @property
    def active(self) -> str:
        return self._active

    def attach(self, link: HubLink) -> None:
        """Route ``link``'s messages through the hub (also for a link replaced later)."""
        name = link.name
        self._links[name] = link
        self._seen.setdefault(name, Snapshot(Stack(link.spec.stack)))

        def tap(msg: Any, now: float) -> None:
            self._from_autopilot(name, link.spec, msg, now, link.routed)

        def tap_routed(frames: int) -> bool:
            return self._routed_routine(name, frames)

        def tap_run(frames: int, latest: Sequence[tuple[str, Any, float]]) -> None:
            self._routed_run(name, frames, latest)

        link.tap = tap
        link.tap_routed = tap_routed
        link.tap_run = tap_run

    def set_active(self, name: str) -> None:
        """Move the clients' route to ``name`` (the agent calls it right after the bridge
        write, in the same decision tick)."""
        if name == self._active:
            return
        self._active = name
        self.counters.switches += 1

    def configure(self, hub: HubSpec) -> None:
        """Adopt new mirroring and in-step settings (endpoints need a restart)."""
        self.settings = hub
        self._tracker.confirm_s = hub.standby_limits.confirm_ms / 1000

    def start(self) -> None:
        for plan in open_to_the_network([e.plan for e in self.endpoints]):
            self._event(
                "HubEndpointUnauthenticated",
                f"endpoint {plan.name} ({plan.address}) does not check signatures: "
                f"anyone who reaches it may send what scope {plan.scope.value} allows",
                True,
            )
        self._serving = threading.Thread(target=self._serve, name="mavlink-hub", daemon=True)
        self._serving.start()

    def _event(self, reason: str, message: str, warning: bool) -> None:
        if self._on_event is not None:
            self._on_event(reason, message, warning)

    def stop(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):  # already awake (full), or closed
            self._wake_w.send(b"\0")
        if self._serving is not None:
            self._serving.join(timeout=2)
        self.close()

    def close(self) -> None:
        with self._clients_lock:
            clients, self._clients, self._sinks = list(self._clients.values()), OrderedDict(), ()
            self._by_sock = {}
        for client in clients:
            if client.sock is not None:
                client.sock.close()
        for endpoint in self.endpoints:
            endpoint.sock.close()
        self._wake_r.close()
        self._wake_w.close()

    def has_clients(self) -> bool:
        """Whether any client gets the vehicle's messages now (cheap: the reader asks
        after every wake-up)."""
        return bool(self._sinks)

    def clients(self) -> list[Address]:
        """Addresses of the clients that currently get the vehicle's messages."""
        return [c.address for c in self._sinks]

    # -- standby states ----------------------------------------------------------------

    def snapshot(self, name: str) -> Snapshot | None:
        return self._seen.get(name)

    def in_step(self, now: float) -> dict[str, InStep]:
        """Every autopilot's confirmed verdict (the active one is in step by definition)."""
        active_name = self._active
        active = self._seen.get(active_name)
        limits = self.settings.standby_limits
        out: dict[str, InStep] = {}
        for name, seen in self._seen.items():
            if name == active_name or active is None:
                self._tracker.forget(name)
                out[name] = _ACTIVE_IN_STEP
                continue
            verdict = judge_standby(active, seen, limits, stale_s=self.stale_s, now=now)
            out[name] = self._tracker.update(name, verdict, now)
        return out

    def aux_standby(self, active: str) -> None:
        """ArduPilot STANDBY aux function: high on every ArduPilot standby, low on the
        active one (fire and forget: answers land in the link's ack mailbox). Also sent
        to an ArduPilot autopilot whenever it is heard again after silence (a reboot
        forgets it)."""
        for name, link in self._links.items():
            if Stack(link.spec.stack) is Stack.ARDUPILOT:
                self._aux_standby(name, standby=name != active)

    def _aux_standby(self, name: str, *, standby: bool) -> None:
        link = self._links.get(name)
        if link is None:
            return
        switch = AUX_SWITCH_HIGH if standby else AUX_SWITCH_LOW
        link.send_command(
            MAV_CMD_DO_AUX_FUNCTION,
            (float(AUX_FUNCTION_STANDBY), float(switch), 0.0, 0.0, 0.0, 0.0, 0.0),
        )

    # -- autopilot -> clients ----------------------------------------------------------
    # What the agent asked for stays with the agent: answers addressed to its component,
    # and the log protocol's replies (LOG_ENTRY, LOG_DATA carry no target) while the
    # agent's own log download holds the autopilot's log session (the link's
    # ``log_sink`` is set, roost_agent.records_logs). A client's own log request, at any
    # other time, is answered to the clients as before. An autopilot serves one log
    # transfer at a time, so a ground station's download during the agent's (minutes,
    # after landing) would collide at the autopilot whatever the hub did.

    def _from_autopilot(
        self, name: str, spec: AutopilotSpec, msg: Any, now: float, routed: bool
    ) -> None:
        kind = msg.get_type()
        seen = self._seen[name]
        if kind == "HEARTBEAT":
            fresh = seen.heartbeat_at is None or now - seen.heartbeat_at > self.stale_s
            seen.heartbeat_at = now
            seen.armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            seen.mode = mode_name(seen.stack, int(msg.custom_mode))
            if fresh and seen.stack is Stack.ARDUPILOT:  # (re)connected: tell it its role
                self._aux_standby(name, standby=name != self._active)
        elif kind == "GLOBAL_POSITION_INT":
            _note_position(seen, msg, now)
        if isinstance(msg, Frame) and not msg.has_field("target_component"):
            targets_agent = False  # most of the stream: no lookup that raises
        else:
            targets_agent = (
                getattr(msg, "target_component", None) == AGENT_COMPONENT_ID
                and getattr(msg, "target_system", None) == spec.sysid
            )
        for_agent = targets_agent or (
            kind in LOG_REPLIES and self._links[name].log_sink is not None
        )
        if name != self._active:
            if kind == "COMMAND_ACK" and not for_agent:
                note_answer(seen, int(msg.command), int(msg.result), now)
            self.counters.dropped_standby += 1
            return
        if for_agent:  # the agent's own answers stay with it (a gap in clients' seq)
            self.counters.kept_for_agent += 1
            return
        sinks = self._sinks
        if routed:  # sent to the fast route's clients in C already
            sinks = self._not_routed(sinks)
        if not sinks:
            return
        frame = rewrite_source(bytes(msg.get_msgbuf()), self.sysid)
        if frame is None:
            return
        sent = 0
        signed: dict[bytes | None, bytes] | None = None  # signed once per key in use
        for client in sinks:
            out = frame
            if client.signs:
                if signed is None:
                    signed = {}
                key = client.signing_key
                found = signed.get(key)
                if found is None:
                    found = signed[key] = self._sign(frame, key)
                out = found
            try:
                if client.sock is None:
                    client.out.sendto(out, client.address)
                elif client.sock.send(out) < len(out):
                    # A TCP client that cannot keep up: a partial frame would corrupt its
                    # stream, so it is dropped (the hub thread closes it).
                    client.broken = True
                    continue
                sent += 1
            except OSError:
                client.broken = client.sock is not None
                log.debug("hub: sending to %s failed", client.address)
        counters = self.counters
        counters.to_clients += sent
        counters.forwarded[name] = counters.forwarded.get(name, 0) + 1

    def _routed_run(self, name: str, frames: int, latest: Sequence[tuple[str, Any, float]]) -> None:
        """A run of ``frames`` routed in C (:mod:`roost_agent.fastpath`) with the last
        frame of each kept kind, read for the snapshot (the position). Counted as routed
        to the route's clients: a client that came while C routed them (before
        :attr:`on_sinks_changed` woke the reader) missed them."""
        route = self._route
        if name == self._active and route is not None:
            counters = self.counters
            counters.routed_in_c += frames
            counters.to_clients += frames * len(route.clients)
        seen = self._seen[name]
        for kind, msg, now in latest:
            if kind == "GLOBAL_POSITION_INT":
                _note_position(seen, msg, now)

    def _routed_routine(self, name: str, frames: int) -> bool:
        """What :meth:`_from_autopilot` does with ``frames`` routine frames (none of
        :data:`READ_KINDS`, none addressed to the agent) routed in C, when that is only counting
        them: they are the active autopilot's and the route's clients are still all the
        clients. False otherwise, having done nothing (they come to the tap whole)."""
        route = self._route
        if name != self._active or route is None or self._sinks is not route.sinks:
            return False
        counters = self.counters
        counters.routed_in_c += frames
        counters.to_clients += frames * len(route.clients)
        return True

    def _not_routed(self, sinks: tuple[_Client, ...]) -> tuple[_Client, ...]:
        """Of ``sinks``, the clients a frame routed in C did not reach (those that came
        since the route was made); the routed ones are counted here."""
        route = self._route
        if route is None:
            return sinks
        counters = self.counters
        counters.routed_in_c += 1
        counters.to_clients += len(route.clients)
        if sinks is route.sinks:  # the common case: nobody came or went since
            return ()
        return tuple(c for c in sinks if c.key not in route.keys)

    def fast_route(self) -> FastRoute | None:
        """Where the fast path (:mod:`roost_agent.fastpath`) may route the active
        autopilot's frames in C, or None: the extension is not built, nobody listens,
        a frame would need its source rewritten, a client is on TCP or signs, or the
        active link cannot be read in C (not UDP, not locked, signatures required).
        Called by the reader before each wait while hurried (on the reader thread, as
        the routing itself)."""
        sinks = self._sinks
        link = self._links.get(self._active)
        if not self.fast or not sinks or link is None or link.spec.sysid != self.sysid:
            self._route = None
            return None
        source = link.fast_source()
        if source is None or any(c.sock is not None or c.signs for c in sinks):
            self._route = None
            return None
        session, locked = source
        log_busy = link.log_sink is not None
        route = self._route
        if (
            route is not None
            and route.sinks is sinks
            and route.session is session
            and route.locked == locked
            and route.log_busy == log_busy
        ):
            return route
        fds = session.transport.fast_fds()
        assert fds is not None  # fast_source checked it
        route = self._route = FastRoute(
            session=session,
            clients=tuple((c.out.fileno(), c.address) for c in sinks),
            keys=frozenset(c.key for c in sinks),
            sinks=sinks,
            locked=locked,
            sysid=link.spec.sysid,
            compid=link.spec.component_id,
            log_busy=log_busy,
            bulk_fd=fds[0],
            urgent_fd=fds[1],
            routine=ROUTINE,
            run_kinds=RUN_KINDS,
            kept_ids=KEPT_IDS,
        )
        return route

    def _sign(self, frame: bytes, key: bytes | None) -> bytes:
        """``frame`` signed with ``key`` (None: the current key) for a signed client."""
        signer = self._signer
        if signer is None:
            return frame
        signing = self._signing
        wanted = key if key is not None else signing.key if signing is not None else None
        return signer.sign(frame, wanted)  # the reader and hub threads both sign

    # -- clients -> autopilots ---------------------------------------------------------

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                self._serve_once()
            except Exception:  # the hub outlives any bug in one round
                log.exception("hub: serving failed")

    def _serve_once(self) -> None:
        watched: list[socket.socket] = [self._wake_r, *(e.sock for e in self.endpoints)]
        watched.extend(self._by_sock)
        readable, _, _ = select.select(watched, [], [], SELECT_WAIT_S)
        now = self._clock()
        for sock in readable:
            endpoint = self._listening.get(sock)
            if sock is self._wake_r:
                return  # stopping
            if endpoint is None:
                self._read_tcp(sock, now)
            elif endpoint.udp:
                self._read_udp(endpoint, now)
            else:
                self._accept(endpoint, now)
        self._expire(now)

    def _read_udp(self, endpoint: _Endpoint, now: float) -> None:
        sock = endpoint.sock
        name = endpoint.name
        for data, address, _ in receive_all(sock, 256):
            if address is None:
                continue
            peer = address
            client = self._clients.get((name, peer))
            items, _ = scan(data)  # a frame never continues in the next datagram
            if endpoint.gate.open:
                if client is None:
                    client = self._add(_Client(endpoint, peer, None, now))
                client.last_seen = now
                self._from_client(items)
            else:
                self._from_gated(endpoint, peer, client, items, now)

    def _accept(self, endpoint: _Endpoint, now: float) -> None:
        try:
            sock, address = endpoint.sock.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, TCP_SEND_BUFFER)
        self._add(_Client(endpoint, (str(address[0]), int(address[1])), sock, now))

    def _read_tcp(self, sock: socket.socket, now: float) -> None:
        client = self._by_sock.get(sock)
        if client is None:
            return
        try:
            data = sock.recv(UDP_MAX)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._remove(client)
            return
        items = client.parser.feed(data)
        endpoint = client.endpoint
        if endpoint.gate.open:
            client.last_seen = now
            self._from_client(items)
        else:
            self._from_gated(endpoint, client.address, client, items, now)

    def _add(self, client: _Client) -> _Client:
        with self._clients_lock:
            self._clients[client.key] = client
            if client.sock is not None:
                self._by_sock[client.sock] = client
            while len(self._clients) > MAX_CLIENTS:
                # One that has not proved itself goes first: a flood of connections
                # that cannot sign never pushes out a client that did.
                key = next((k for k, c in self._clients.items() if not c.ready), None)
                if key is None:
                    _, dropped = self._clients.popitem(last=False)
                else:
                    dropped = self._clients.pop(key)
                if dropped.sock is not None:
                    self._by_sock.pop(dropped.sock, None)
                    dropped.sock.close()
            self._resink()
        # an unproven connection is not news (a flood of them must not flood the log)
        (log.info if client.ready else log.debug)(
            "hub: client %s:%d connected to %s", *client.address, client.endpoint.name
        )
        return client

    def _ready(self, client: _Client) -> None:
        with self._clients_lock:
            client.ready = True
            self._resink()
        log.info("hub: client %s:%d signed in on %s", *client.address, client.endpoint.name)

    def _remove(self, client: _Client) -> None:
        with self._clients_lock:
            self._clients.pop(client.key, None)
            if client.sock is not None:
                self._by_sock.pop(client.sock, None)
            self._resink()
        if client.sock is not None:
            client.sock.close()
        (log.info if client.ready else log.debug)("hub: client %s:%d gone", *client.address)

    def _expire(self, now: float) -> None:
        for client in list(self._clients.values()):
            if client.broken or (client.sock is None and now - client.last_seen > CLIENT_TIMEOUT_S):
                self._remove(client)

    def _from_gated(
        self,
        endpoint: _Endpoint,
        peer: Address,
        client: _Client | None,
        items: list[Parsed],
        now: float,
    ) -> None:
        """A client's frames on an endpoint that checks signatures or scope: what passes
        is routed, the rest is dropped and counted (never forwarded)."""
        gate = endpoint.gate
        for msg in items:
            if isinstance(msg, BadData):
                continue
            frame = msg.get_msgbuf()
            msg_id = frame[7] | frame[8] << 8 | frame[9] << 16 if frame[0] == V2_MAGIC else frame[5]
            command = NO_COMMAND
            if (msg_id in (COMMAND_LONG_ID, COMMAND_INT_ID)) and isinstance(msg, Frame):
                command = int(msg.command)
            reason = gate.judge(frame, msg_id, command)
            if authenticated(reason):
                if client is None:  # a UDP sender proved itself: a client from now on
                    client = _Client(endpoint, peer, None, now)
                    client.ready = True
                    self._add(client)
                elif not client.ready:
                    self._ready(client)
                client.last_seen = now
                verifier = gate.verifier
                if verifier is not None:
                    client.signing_key = verifier.used
            if reason == ACCEPT:
                self._from_client([msg])
                continue
            self.counters.dropped_from_clients += 1
            text = endpoint.drops.note(peer, reason, now)
            if text is not None:
                self._event("HubFramesDropped", text, True)

    def _from_client(self, items: list[Parsed]) -> None:
        """Route a client's frames (of unknown ids too: the autopilot may know them)."""
        try:
            for msg in items:
                if not isinstance(msg, BadData):
                    self.route(msg)
        except Exception:  # a client's odd frame costs only that client's read
            log.debug("hub: routing a client's frame failed", exc_info=True)

    def route(self, msg: Parsed) -> None:
        """Send one client message to the active autopilot, and to every standby when it
        changes flight state (and mirroring is on)."""
        active = self._active
        links = self._links
        link = links.get(active)
        if link is not None and link.send_frame(retarget(msg, self.sysid, link.spec.sysid)):
            self.counters.from_clients += 1
        if not self.settings.mirror:
            return
        kind = msg.get_type()
        command: int | None = None
        if kind in COMMAND_MESSAGES and isinstance(msg, Frame):
            command = int(msg.command)
            if command not in MIRRORED_COMMANDS:
                return
        elif kind not in MIRRORED_MESSAGES:
            return
        target = target_of(msg)
        if target not in (None, 0, self.sysid):
            return  # addressed to another system on the client's network
        same_stack_only = kind in SAME_STACK_MESSAGES or command in MODE_COMMANDS
        active_stack = self._seen[active].stack if active in self._seen else None
        now = self._clock()
        for name, standby in links.items():
            if name == active:
                continue
            seen = self._seen[name]
            if same_stack_only and seen.stack != active_stack:
                continue
            # Awaited before it is sent: the standby's answer can be read (on the link
            # reader's thread) before ``send_frame`` returns here.
            awaited = None if command is None or command in seen.awaiting else command
            if awaited is not None:
                seen.awaiting[awaited] = now
            if standby.send_frame(retarget(msg, self.sysid, standby.spec.sysid)):
                self.counters.mirrored += 1
            elif awaited is not None:
                seen.awaiting.pop(awaited, None)


def hub_for(
    spec: RedundantAutopilotSpec,
    active: str,
    links: Mapping[str, HubLink],
    *,
    signing: LinkSigning | None = None,
    on_event: Callable[[str, str, bool], None] | None = None,
) -> Hub | None:
    """The hub the spec asks for, with ``links`` attached; None without ``spec.hub``."""
    if spec.hub is None:
        return None
    hub = Hub(spec, active, signing=signing, on_event=on_event)
    for link in links.values():
        hub.attach(link)
    return hub
