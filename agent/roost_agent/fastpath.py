"""The hub's fast path: the active autopilot's frames to plain UDP clients without Python.

Why: routed frames must not wait for the decision loop's next read, so while a hub
client was connected the link reader woke for every datagram, and in Python each wake-up
(poll, read, parse, source lock, health bookkeeping, send) cost more than a C router
spends per message. With the C extension ``_udpbatch.c`` built, the reader waits in C
instead: each datagram of the active autopilot is read, checked and sent to the clients
there at once (without the GIL, which C takes again only to make what Python is to
read), and Python reads what C read in one batch when the decision loop is due (or
something must be seen at once: a wake-up call, a heartbeat or command answer on a
steered link's urgent socket, a datagram C does not forward). The health tracker, the
source lock and the hub's bookkeeping see every datagram as before, with its kernel
arrival stamp, in arrival order; a datagram C routed whose frames are all routine
(:func:`routine_bitmap`: no one reads their content) comes with their summary instead of
being parsed again (id, sequence number, ``time_boot_ms``), which is all the link, the
hub and the tracker read of them.

C forwards only what the Python path would forward unchanged to a plain client
(``_udpbatch.c`` lists the checks); the hub offers a route (:class:`FastRoute`) only when
that is all there is to do: the active autopilot's system id is the vehicle's (no source
rewrite), its link is UDP with kernel stamps and does not require signatures, it holds
its source lock, and every client is a UDP client of an unsigned endpoint. Anything else
(a TCP or signed client, a rewrite, an unlocked or signed link, the extension not built)
is the Python path, as before.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, cast

from roost_agent.health import STATE_FIELDS, RunState, StateHeld
from roost_agent.transport import recent_realtime_offset
from roost_mavlink import AGENT_COMPONENT_ID
from roost_mavlink.checked_messages import CHECKED_MESSAGES
from roost_mavlink.codec import DECLARED, Layout, layout, message

if TYPE_CHECKING:
    from roost_agent.reader import Session
    from roost_agent.transport import Address, Received

Routed = tuple[bytes, "Address | None", "float | None", bool, "tuple[int, ...] | None"]
"""A datagram the fast path read: data, sender, kernel arrival stamp, routed by C, and for
a routed datagram of routine frames only (:func:`routine_bitmap`) their summary: message
id, sequence number and ``time_boot_ms`` (-1: none) of each, in order (else None)."""

Run = tuple[
    float,
    float,
    float,
    int,
    int,
    int,
    int,
    int,
    float,
    tuple[int, ...],
    tuple["bytes | float", ...],
]
"""Consecutive routed datagrams taken together (``_udpbatch.c`` says when a run ends):
first and last arrival and the worst gap between them (the agent's monotonic clock,
seconds), frames, datagrams, bytes, the last sequence number, the highest
``time_boot_ms`` (-1: none) and its arrival, (message id, frames, ...), and the last
frame of each kept kind whole with its arrival (frame, at, ...)."""
RUN_FIELDS: Final = 11

PumpResult = tuple[list["Routed | Run"], list["Received"], bool]


def _pump() -> Callable[..., PumpResult] | None:
    """The C extension's ``pump`` with the known messages loaded, or None (not built)."""
    try:
        module = importlib.import_module("roost_agent._udpbatch")
    except ImportError:
        return None
    module.set_messages(message_table())
    return cast("Callable[..., PumpResult]", module.pump)


def _known_layouts() -> dict[int, Layout]:
    """Every message id the agent's codec knows, with its layout: what C checks frames
    against, summarises and names."""
    known = {msg_id: layout(msg_id) for msg_id in {*DECLARED, *CHECKED_MESSAGES}}
    return {msg_id: found for msg_id, found in known.items() if found is not None}


def message_table() -> dict[int, tuple[int, int, int, int]]:
    """What C checks a frame against: per known message id, its CRC_EXTRA and the
    payload offsets of ``target_system`` and ``target_component`` (-1: none), the fields
    by which the hub keeps answers to the agent from clients, and of ``time_boot_ms``
    (-1: none), which a routine frame's summary carries."""
    table: dict[int, tuple[int, int, int, int]] = {}
    for msg_id, known in _known_layouts().items():
        system = known.scalars.get("target_system")
        component = known.scalars.get("target_component")
        table[msg_id] = (
            known.crc_extra,
            -1 if system is None else system[0],
            -1 if component is None else component[0],
            known.boot_at,
        )
    return table


def routine_bitmap(read: frozenset[str]) -> bytes:
    """Which message ids are routine, a bit per id: known and not of the kinds in
    ``read`` (those whose content the agent reads). Of a routed datagram of routine
    frames only, C hands Python a summary (:data:`Routed`): the agent does no more with
    such a frame than count it and judge its arrival, sequence number and
    ``time_boot_ms``. A kind with a target (PING, OPEN_DRONE_ID_*) is routine too: the
    one thing the agent reads in it, whether it is addressed to the agent, C has read
    already, and it routes (and so summarises) no frame that is."""
    ids = [msg_id for msg_id, known in _known_layouts().items() if known.name not in read]
    bits = bytearray((max(ids, default=0) >> 3) + 1)
    for msg_id in ids:
        bits[msg_id >> 3] |= 1 << (msg_id & 7)
    return bytes(bits)


def kind_names() -> dict[int, str]:
    """Every known message id's name (a routine frame's summary carries its id)."""
    return {msg_id: known.name for msg_id, known in _known_layouts().items()}


PUMP: Final = _pump()


@dataclass(frozen=True)
class Due:
    """When the reader must wake unless the fast link's messages keep coming: ``in_s``
    from now, postponed by each routed datagram to its arrival plus ``age_s`` (negative:
    never postponed); and, while runs are taken, ``frozen_in_s`` from now, postponed by
    each routed frame whose ``time_boot_ms`` advances to its arrival plus
    ``frozen_age_s`` (negative: none; frozen telemetry)."""

    in_s: float
    age_s: float
    frozen_in_s: float = math.inf
    frozen_age_s: float = -1.0


NOT_POSTPONED: Final = Due(math.inf, -1.0)


@dataclass(frozen=True)
class FastRoute:
    """What the reader hands C: the active autopilot's session and where its frames go."""

    session: Session
    clients: tuple[tuple[int, Address], ...]  # (endpoint socket fd, client address)
    keys: frozenset[object]  # the hub's keys of those clients
    sinks: tuple[Any, ...]  # the hub's sinks when the route was made (all of them fast)
    locked: Address
    sysid: int
    compid: int
    log_busy: bool
    bulk_fd: int
    urgent_fd: int  # -1: the link is one socket
    routine: bytes  # routine_bitmap: the ids whose routed frames Python takes summarised
    run_kinds: bytes  # routine_bitmap: the ids whose routed frames may join a run
    kept_ids: tuple[int, ...]  # the ids whose last frame in a run Python reads whole


def pump(
    route: FastRoute,
    wake_fds: list[int],
    timeout_s: float,
    due: Due,
    *,
    urgent_returns: bool,
    limit: int,
    runs: RunState | None = None,
) -> tuple[list[Routed | Run], bool]:
    """Wait up to ``timeout_s`` in C, and up to ``due`` unless the autopilot's frames keep
    postponing it, forwarding as datagrams come; what was read (in arrival order) and
    whether a ``wake_fds`` descriptor woke it. What may be newer than something still
    queued on the other socket of a steered pair stays in the transport's held list, as
    the Python reads leave it. With ``runs`` (the tracker's state), the bulk of the
    stream comes as runs (:data:`Run`) instead of datagram by datagram."""
    assert PUMP is not None
    session = route.session
    transport = session.transport
    items, still_held, woke = PUMP(
        route.bulk_fd,
        route.urgent_fd,
        wake_fds,
        (
            timeout_s,
            due.in_s,
            due.age_s,
            recent_realtime_offset(),
            due.frozen_in_s,
            due.frozen_age_s,
        ),
        route.clients,
        route.locked,
        route.sysid,
        route.compid,
        AGENT_COMPONENT_ID,
        route.log_busy,
        urgent_returns,
        transport.take_held(),
        limit,
        route.routine,
        None if runs is None else _run_rules(route, runs),
    )
    transport.keep_held(still_held)
    return items, woke


def _attitude_offsets() -> tuple[int, int, int]:
    """ATTITUDE's id and the payload offsets of its roll and pitch (C classifies tilt)."""
    found = layout(message("ATTITUDE").id)
    assert found is not None
    return found.msg_id, found.scalars["roll"][0], found.scalars["pitch"][0]


HEARTBEAT_ID: Final = message("HEARTBEAT").id
_ATTITUDE: Final = _attitude_offsets()


def _state_layouts() -> dict[str, tuple[int, tuple[tuple[int, int], ...]]]:
    """Per state kind (:data:`roost_agent.health.STATE_FIELDS`): its id and the payload
    offset and size of each field the tracker reads (C compares them)."""
    out = {}
    for name, fields in STATE_FIELDS.items():
        found = layout(message(name).id)
        assert found is not None
        where = tuple((found.scalars[f][0], found.scalars[f][1].size) for f in fields)
        out[name] = (found.msg_id, where)
    return out


_STATE_LAYOUTS: Final = _state_layouts()


def _states(held: StateHeld) -> tuple[tuple[int, tuple[tuple[int, int, int], ...]], ...]:
    """The state kinds as C takes them: (id, ((offset, size, value held), ...)), ..."""
    return tuple(
        (
            msg_id,
            tuple((at, size, value) for (at, size), value in zip(where, held[name], strict=True)),
        )
        for name, (msg_id, where) in _STATE_LAYOUTS.items()
    )


def _run_rules(route: FastRoute, runs: RunState) -> tuple[object, ...]:
    warn_deg, max_deg, tilt_class, gap_s, window_end, boot_max, backstep, held = runs
    attitude_id, roll_at, pitch_at = _ATTITUDE
    return (
        route.run_kinds,
        route.kept_ids,
        HEARTBEAT_ID,
        (attitude_id, roll_at, pitch_at, warn_deg, max_deg, tilt_class),
        gap_s,
        window_end,
        boot_max,
        backstep,
        _states(held),
    )
