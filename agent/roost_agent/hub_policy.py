"""Who may send what through a hub endpoint: signature, then scope, decided per frame.

Why a policy per endpoint and not per client: a client on UDP is only an address, which
anyone on the network can take, so what it may do has to follow from where it connected
(the endpoint) and from what it proves (the vehicle's signing key), never from who it
says it is. Each endpoint therefore carries a :class:`Gate`: an optional
:class:`~roost_mavlink.signing.Verifier` (MAVLink 2 signing with the vehicle's key:
signature, link id, timestamp window and per-stream replay protection as the signing
specification describes) and a :class:`Scope` (every message, reads only, or an
allow-list of message and command ids).

The order is signature first, then scope: a frame that proves the vehicle's key makes
its sender a client (it gets the vehicle's messages, signed) even when the frame itself
is outside the scope and dropped (a read-only ground station's own HEARTBEAT, say);
without that proof nothing from the sender is forwarded and nothing is sent to it.

Read-only means the vehicle's state cannot change through the endpoint: parameter reads,
mission downloads and one-shot message requests (MAV_CMD_REQUEST_MESSAGE and the
capability/protocol requests). Deliberately left out: the client's HEARTBEAT (it would
keep an autopilot's ground-station-loss failsafe from firing after the flying ground
station is gone), REQUEST_DATA_STREAM and MAV_CMD_SET_MESSAGE_INTERVAL (they can stop
the streams the agent judges health from), MISSION_ACK (it can end another client's
mission upload), TIMESYNC, SYSTEM_TIME and log downloads (bandwidth on a serial link).

Endpoint planning (:func:`plan_endpoints`) is the start-up rule: an endpoint bound beyond
loopback signs unless its spec says ``Unauthenticated``, and one that must sign without
a key refuses to start (:class:`HubConfigError`), one line, no key material.

Everything here is plain code without sockets, so the decision tables are unit tests
(tests/unit/test_agent_hub_policy.py), and compile-friendly (int reasons, slots) because
:meth:`Gate.judge` runs for every client frame.
"""

from __future__ import annotations

import ipaddress
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass

from roost_api.autopilot_enums import HubScope, HubSigning, HubTransport
from roost_api.plain import HubSpec
from roost_mavlink.signing import Verdict, Verifier

Address = tuple[str, int]

COMMAND_INT_ID = 75
COMMAND_LONG_ID = 76
NO_COMMAND = -1

# What a read-only client may send: message ids of common.xml with their names.
READ_ONLY_MESSAGES: dict[int, str] = {
    20: "PARAM_REQUEST_READ",
    21: "PARAM_REQUEST_LIST",
    320: "PARAM_EXT_REQUEST_READ",
    321: "PARAM_EXT_REQUEST_LIST",
    43: "MISSION_REQUEST_LIST",
    40: "MISSION_REQUEST",
    51: "MISSION_REQUEST_INT",
}
# ... and the commands (in COMMAND_LONG / COMMAND_INT) it may send.
READ_ONLY_COMMANDS: dict[int, str] = {
    512: "MAV_CMD_REQUEST_MESSAGE",
    519: "MAV_CMD_REQUEST_PROTOCOL_VERSION",
    520: "MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES",
}

# Why a client frame was dropped (ints: the hub's per-frame path compares them).
ACCEPT = 0
UNSIGNED = 1
BAD_SIGNATURE = 2
REPLAYED = 3
NOT_ALLOWED = 4
REASONS: tuple[str, ...] = ("accepted", "unsigned", "bad_signature", "replayed", "not_allowed")
"""Names of the reasons above, by value (metric labels and Event text)."""

_VERDICT_REASON: dict[Verdict, int] = {
    Verdict.GOOD: ACCEPT,
    Verdict.UNSIGNED: UNSIGNED,
    Verdict.BAD_SIGNATURE: BAD_SIGNATURE,
    Verdict.REPLAYED: REPLAYED,
}

EVENT_QUIET_S = 60.0  # at most one HubFramesDropped Event per endpoint a minute
CLIENTS_COUNTED = 64  # per endpoint; the least recently dropped address is forgotten


class HubConfigError(ValueError):
    """An endpoint the hub must not serve as specified (one line, no key material)."""


class Scope:
    """What one endpoint's clients may send."""

    __slots__ = ("commands", "everything", "kind", "messages")

    def __init__(
        self,
        kind: HubScope,
        messages: Iterable[int] = (),
        commands: Iterable[int] = (),
    ) -> None:
        self.kind = kind
        self.everything = kind is HubScope.EVERYTHING
        if kind is HubScope.READ_ONLY:
            messages, commands = READ_ONLY_MESSAGES, READ_ONLY_COMMANDS
        self.messages: frozenset[int] = frozenset(messages)
        self.commands: frozenset[int] = frozenset(commands)

    def allows(self, msg_id: int, command: int) -> bool:
        """Whether a frame of ``msg_id`` (with MAV_CMD ``command`` when it is a
        COMMAND_LONG/INT, else :data:`NO_COMMAND`) may pass."""
        if self.everything:
            return True
        if msg_id in (COMMAND_LONG_ID, COMMAND_INT_ID):
            return command in self.commands
        return msg_id in self.messages


class Gate:
    """One endpoint's verdict on each client frame: signature (when it signs), then scope."""

    __slots__ = ("open", "scope", "verifier")

    def __init__(self, scope: Scope, verifier: Verifier | None) -> None:
        self.scope = scope
        self.verifier = verifier
        # Nothing to decide: the hub takes its unchanged loopback path.
        self.open = verifier is None and scope.everything

    def judge(self, frame: bytes, msg_id: int, command: int) -> int:
        """:data:`ACCEPT` or why ``frame`` (whole, as received) must be dropped. Any
        reason but the signature ones means the sender proved the key (or need not)."""
        verifier = self.verifier
        if verifier is not None:
            verdict = verifier.check(frame)
            if verdict is not Verdict.GOOD:
                return _VERDICT_REASON[verdict]
        if self.scope.allows(msg_id, command):
            return ACCEPT
        return NOT_ALLOWED


def authenticated(reason: int) -> bool:
    """Whether a frame judged ``reason`` proved its sender (signature good, or none asked)."""
    return reason in (ACCEPT, NOT_ALLOWED)


class Drops:
    """Frames one endpoint dropped: by reason, by client address (bounded), and when to
    say so in an Event (the first drop, then at most once per :data:`EVENT_QUIET_S`)."""

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self.by_reason: list[int] = [0] * len(REASONS)
        self.by_client: OrderedDict[Address, list[int]] = OrderedDict()
        self._since_event: OrderedDict[Address, list[int]] = OrderedDict()
        self._quiet_until: float | None = None

    @property
    def total(self) -> int:
        return sum(self.by_reason)

    def note(self, client: Address, reason: int, now: float) -> str | None:
        """Count one dropped frame; an Event message when one is due, else None."""
        self.by_reason[reason] += 1
        for table in (self.by_client, self._since_event):
            counts = table.pop(client, None) or [0] * len(REASONS)
            counts[reason] += 1
            table[client] = counts
            while len(table) > CLIENTS_COUNTED:
                table.popitem(last=False)
        if self._quiet_until is not None and now < self._quiet_until:
            return None
        self._quiet_until = now + EVENT_QUIET_S
        text = describe_drops(self.endpoint, self._since_event)
        self._since_event.clear()
        return text


def describe_drops(endpoint: str, clients: OrderedDict[Address, list[int]]) -> str:
    """One line naming the clients (at most four, most recent first) and their reasons."""
    parts: list[str] = []
    for (host, port), counts in reversed(clients.items()):
        reasons = ", ".join(f"{n} {REASONS[r]}" for r, n in enumerate(counts) if n and r)
        parts.append(f"{host}:{port} ({reasons})")
        if len(parts) == 4:
            break
    more = f" and {len(clients) - 4} more" if len(clients) > 4 else ""
    return f"endpoint {endpoint}: dropped client frames from {'; '.join(parts)}{more}"


# -- which endpoints, signed or not ------------------------------------------------------


@dataclass(frozen=True)
class EndpointPlan:
    """One endpoint the hub serves."""

    name: str
    transport: HubTransport
    address: str
    scope: HubScope
    allow_messages: tuple[int, ...]
    allow_commands: tuple[int, ...]
    signed: bool


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (a name other than localhost is not:
    it may resolve anywhere)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def must_sign(signing: HubSigning, loopback: bool) -> bool:
    """Whether an endpoint's clients must sign."""
    if signing is HubSigning.REQUIRED:
        return True
    if signing is HubSigning.UNAUTHENTICATED:
        return False
    return not loopback


def plan_endpoints(hub: HubSpec, has_key: bool) -> list[EndpointPlan]:
    """Every endpoint of ``hub``: its own ``udp`` and ``tcp`` (scope Everything, signing
    Auto) and ``endpoints``. Raises :class:`HubConfigError` for an endpoint that must sign
    while the agent has no key, and for a name used twice."""
    plans: list[EndpointPlan] = []
    wanted: list[tuple[str, HubTransport, str, HubScope, list[int], list[int], HubSigning]] = [
        ("udp", HubTransport.UDP, hub.udp, HubScope.EVERYTHING, [], [], HubSigning.AUTO)
    ]
    if hub.tcp is not None:
        wanted.append(
            ("tcp", HubTransport.TCP, hub.tcp, HubScope.EVERYTHING, [], [], HubSigning.AUTO)
        )
    for e in hub.endpoints:
        wanted.append(
            (
                e.name,
                e.transport,
                e.address,
                e.scope,
                list(e.allow_messages),
                list(e.allow_commands),
                e.signing,
            )
        )
    names: set[str] = set()
    for name, transport, address, scope, messages, commands, signing in wanted:
        if name in names:
            raise HubConfigError(f"hub endpoint name {name!r} is used twice")
        names.add(name)
        host = address.rpartition(":")[0]
        signed = must_sign(signing, is_loopback(host))
        if signed and not has_key:
            where = "on loopback" if is_loopback(host) else "beyond loopback"
            raise HubConfigError(
                f"hub endpoint {name} ({address}, {where}) needs signed clients but the "
                "agent has no signing key for this vehicle: give the agent the Vehicle's "
                "key (docs/mavlink-signing.md) or declare the endpoint "
                "signing: Unauthenticated"
            )
        plans.append(
            EndpointPlan(name, transport, address, scope, tuple(messages), tuple(commands), signed)
        )
    return plans


def open_to_the_network(plans: Iterable[EndpointPlan]) -> list[EndpointPlan]:
    """The endpoints beyond loopback that do not check signatures (declared
    ``Unauthenticated``): the agent warns about each when it starts."""
    return [p for p in plans if not p.signed and not is_loopback(p.address.rpartition(":")[0])]
