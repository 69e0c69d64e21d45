"""What a hub endpoint lets through, as decision tables: signature, scope, start-up plan.

No sockets: frames are built with Roost's own encoder and signed with
:mod:`roost_mavlink.signing`; the gate judges the bytes the hub would judge.
"""

from __future__ import annotations

import pytest

from roost_agent.hub_policy import (
    ACCEPT,
    BAD_SIGNATURE,
    COMMAND_INT_ID,
    COMMAND_LONG_ID,
    NO_COMMAND,
    NOT_ALLOWED,
    REPLAYED,
    UNSIGNED,
    Drops,
    Gate,
    HubConfigError,
    Scope,
    authenticated,
    is_loopback,
    must_sign,
    open_to_the_network,
    plan_endpoints,
)
from roost_api.autopilot_enums import HubScope, HubSigning, HubTransport
from roost_api.plain import HubSpec
from roost_mavlink.codec import Encoder
from roost_mavlink.signing import NEW_STREAM_SLACK_TICKS, Signer, Timestamps, Verifier

KEY = bytes(range(32))
WRONG_KEY = bytes(range(1, 33))
NOW_TICKS = 400_000_000_000  # a fixed signing clock (10 us units since 2015)

HEARTBEAT = 0
PARAM_REQUEST_READ = 20
PARAM_SET = 23
SET_MODE = 11
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_NAV_TAKEOFF = 22


# -- scope -------------------------------------------------------------------------------

ALLOW = Scope(HubScope.ALLOW_LIST, messages=[SET_MODE], commands=[MAV_CMD_NAV_TAKEOFF])

SCOPE_TABLE = [
    # scope, message id, command, allowed
    (Scope(HubScope.EVERYTHING), PARAM_SET, NO_COMMAND, True),
    (Scope(HubScope.EVERYTHING), COMMAND_LONG_ID, MAV_CMD_COMPONENT_ARM_DISARM, True),
    (Scope(HubScope.EVERYTHING), 60000, NO_COMMAND, True),  # an id nobody declared
    (Scope(HubScope.READ_ONLY), PARAM_REQUEST_READ, NO_COMMAND, True),
    (Scope(HubScope.READ_ONLY), 21, NO_COMMAND, True),  # PARAM_REQUEST_LIST
    (Scope(HubScope.READ_ONLY), 43, NO_COMMAND, True),  # MISSION_REQUEST_LIST
    (Scope(HubScope.READ_ONLY), COMMAND_LONG_ID, MAV_CMD_REQUEST_MESSAGE, True),
    (Scope(HubScope.READ_ONLY), COMMAND_INT_ID, MAV_CMD_REQUEST_MESSAGE, True),
    (Scope(HubScope.READ_ONLY), COMMAND_LONG_ID, MAV_CMD_COMPONENT_ARM_DISARM, False),
    (Scope(HubScope.READ_ONLY), COMMAND_INT_ID, MAV_CMD_NAV_TAKEOFF, False),
    (Scope(HubScope.READ_ONLY), PARAM_SET, NO_COMMAND, False),
    (Scope(HubScope.READ_ONLY), SET_MODE, NO_COMMAND, False),
    (Scope(HubScope.READ_ONLY), HEARTBEAT, NO_COMMAND, False),  # GCS-loss failsafe
    (Scope(HubScope.READ_ONLY), 66, NO_COMMAND, False),  # REQUEST_DATA_STREAM
    (Scope(HubScope.READ_ONLY), COMMAND_LONG_ID, 511, False),  # SET_MESSAGE_INTERVAL
    (Scope(HubScope.READ_ONLY), 47, NO_COMMAND, False),  # MISSION_ACK
    (ALLOW, SET_MODE, NO_COMMAND, True),
    (ALLOW, COMMAND_LONG_ID, MAV_CMD_NAV_TAKEOFF, True),
    (ALLOW, COMMAND_INT_ID, MAV_CMD_NAV_TAKEOFF, True),
    (ALLOW, COMMAND_LONG_ID, MAV_CMD_COMPONENT_ARM_DISARM, False),
    (ALLOW, PARAM_SET, NO_COMMAND, False),
    (Scope(HubScope.ALLOW_LIST), SET_MODE, NO_COMMAND, False),  # an empty list
    # COMMAND_LONG in the message list does not allow every command
    (Scope(HubScope.ALLOW_LIST, messages=[COMMAND_LONG_ID]), COMMAND_LONG_ID, 400, False),
]


@pytest.mark.parametrize(("scope", "msg_id", "command", "allowed"), SCOPE_TABLE)
def test_scope(scope: Scope, msg_id: int, command: int, allowed: bool) -> None:
    assert scope.allows(msg_id, command) is allowed


# -- the gate: signature, then scope -----------------------------------------------------


def heartbeat(sysid: int = 255, comp: int = 190) -> bytes:
    return Encoder(sysid, comp).encode(
        "HEARTBEAT",
        type=6,
        autopilot=8,
        base_mode=0,
        custom_mode=0,
        system_status=4,
        mavlink_version=3,
    )


def arm(sysid: int = 255) -> bytes:
    return Encoder(sysid, 190).encode(
        "COMMAND_LONG",
        target_system=1,
        target_component=1,
        command=MAV_CMD_COMPONENT_ARM_DISARM,
        confirmation=0,
        param1=1.0,
        param2=0.0,
        param3=0.0,
        param4=0.0,
        param5=0.0,
        param6=0.0,
        param7=0.0,
    )


def signed(frame: bytes, ticks: int, key: bytes = KEY, link_id: int = 1) -> bytes:
    clock = Timestamps(start=ticks - 1, wall=lambda: 0.0)
    return Signer(key, link_id, clock).sign(frame)


def gate(scope: HubScope, *, signs: bool) -> Gate:
    clock = Timestamps(start=NOW_TICKS, wall=lambda: 0.0)
    return Gate(Scope(scope), Verifier(KEY, clock) if signs else None)


GOOD_HB = signed(heartbeat(), NOW_TICKS + 1)
GOOD_ARM = signed(arm(), NOW_TICKS + 2)

GATE_TABLE = [
    # description, scope, signs, frames in order (msg id, command), last frame's verdict
    ("open: unsigned arm", HubScope.EVERYTHING, False, [(arm(), 76, 400)], ACCEPT),
    ("signed endpoint: unsigned arm", HubScope.EVERYTHING, True, [(arm(), 76, 400)], UNSIGNED),
    ("signed: good arm", HubScope.EVERYTHING, True, [(GOOD_ARM, 76, 400)], ACCEPT),
    (
        "signed: wrong key",
        HubScope.EVERYTHING,
        True,
        [(signed(arm(), NOW_TICKS + 5, WRONG_KEY), 76, 400)],
        BAD_SIGNATURE,
    ),
    (
        "signed: a genuine frame replayed",
        HubScope.EVERYTHING,
        True,
        [(GOOD_ARM, 76, 400), (GOOD_ARM, 76, 400)],
        REPLAYED,
    ),
    (
        "signed: older timestamp on the same stream",
        HubScope.EVERYTHING,
        True,
        [(GOOD_ARM, 76, 400), (signed(arm(), NOW_TICKS + 1), 76, 400)],
        REPLAYED,
    ),
    (
        "signed: same timestamp on another link id is its own stream",
        HubScope.EVERYTHING,
        True,
        [(GOOD_ARM, 76, 400), (signed(arm(), NOW_TICKS + 2, link_id=2), 76, 400)],
        ACCEPT,
    ),
    (
        "signed: a new stream more than a minute old",
        HubScope.EVERYTHING,
        True,
        [(signed(arm(), NOW_TICKS - NEW_STREAM_SLACK_TICKS - 1), 76, 400)],
        REPLAYED,
    ),
    (
        "signed: tampered payload",
        HubScope.EVERYTHING,
        True,
        [(GOOD_ARM[:20] + bytes([GOOD_ARM[20] ^ 1]) + GOOD_ARM[21:], 76, 400)],
        BAD_SIGNATURE,
    ),
    ("read-only signed: good arm", HubScope.READ_ONLY, True, [(GOOD_ARM, 76, 400)], NOT_ALLOWED),
    ("read-only signed: unsigned arm", HubScope.READ_ONLY, True, [(arm(), 76, 400)], UNSIGNED),
    ("read-only open: arm", HubScope.READ_ONLY, False, [(arm(), 76, 400)], NOT_ALLOWED),
    (
        "read-only signed: its heartbeat",
        HubScope.READ_ONLY,
        True,
        [(GOOD_HB, 0, NO_COMMAND)],
        NOT_ALLOWED,
    ),
    (
        "read-only signed: a message request",
        HubScope.READ_ONLY,
        True,
        [(signed(arm(), NOW_TICKS + 3), 76, MAV_CMD_REQUEST_MESSAGE)],
        ACCEPT,
    ),
]


@pytest.mark.parametrize(
    ("what", "scope", "signs", "frames", "verdict"), GATE_TABLE, ids=[r[0] for r in GATE_TABLE]
)
def test_gate(
    what: str,
    scope: HubScope,
    signs: bool,
    frames: list[tuple[bytes, int, int]],
    verdict: int,
) -> None:
    g = gate(scope, signs=signs)
    got = [g.judge(frame, msg_id, command) for frame, msg_id, command in frames]
    assert got[-1] == verdict, what


def test_only_a_proven_sender_counts_as_authenticated() -> None:
    table = {
        ACCEPT: True,
        NOT_ALLOWED: True,
        UNSIGNED: False,
        BAD_SIGNATURE: False,
        REPLAYED: False,
    }
    for reason, proven in table.items():
        assert authenticated(reason) is proven


def test_an_open_gate_is_only_everything_unsigned() -> None:
    assert gate(HubScope.EVERYTHING, signs=False).open
    assert not gate(HubScope.EVERYTHING, signs=True).open
    assert not gate(HubScope.READ_ONLY, signs=False).open


def test_a_forged_far_future_frame_does_not_lock_out_the_genuine_stream() -> None:
    g = gate(HubScope.EVERYTHING, signs=True)
    forged = signed(arm(), NOW_TICKS + 10**9, WRONG_KEY)
    assert g.judge(forged, 76, 400) == BAD_SIGNATURE
    assert g.judge(GOOD_ARM, 76, 400) == ACCEPT


# -- drops: counted per client, Events rate-limited ------------------------------------------


def test_drops_are_counted_per_client_and_reported_once_a_minute() -> None:
    drops = Drops("gcs")
    first = drops.note(("10.0.0.9", 5000), UNSIGNED, 0.0)
    assert first is not None and "10.0.0.9:5000 (1 unsigned)" in first
    assert drops.note(("10.0.0.9", 5000), UNSIGNED, 1.0) is None
    assert drops.note(("10.0.0.7", 6000), NOT_ALLOWED, 30.0) is None
    later = drops.note(("10.0.0.9", 5000), BAD_SIGNATURE, 60.0)
    assert later is not None
    assert "10.0.0.9:5000 (1 unsigned, 1 bad_signature)" in later
    assert "10.0.0.7:6000 (1 not_allowed)" in later
    assert drops.by_client[("10.0.0.9", 5000)] == [0, 2, 1, 0, 0]
    assert drops.total == 4


def test_drop_counts_forget_the_oldest_of_many_addresses() -> None:
    drops = Drops("gcs")
    for port in range(1000):
        drops.note(("10.0.0.9", port), UNSIGNED, float(port))
    assert len(drops.by_client) == 64
    assert drops.total == 1000


# -- which endpoints, and which must sign ---------------------------------------------------


def test_loopback_addresses() -> None:
    for host, loopback in [
        ("127.0.0.1", True),
        ("127.0.0.53", True),
        ("localhost", True),
        ("::1", True),
        ("0.0.0.0", False),
        ("192.168.1.20", False),
        ("drone-1.local", False),  # a name may resolve anywhere
    ]:
        assert is_loopback(host) is loopback, host


@pytest.mark.parametrize(
    ("signing", "loopback", "signs"),
    [
        (HubSigning.AUTO, True, False),
        (HubSigning.AUTO, False, True),
        (HubSigning.REQUIRED, True, True),
        (HubSigning.REQUIRED, False, True),
        (HubSigning.UNAUTHENTICATED, True, False),
        (HubSigning.UNAUTHENTICATED, False, False),
    ],
)
def test_must_sign(signing: HubSigning, loopback: bool, signs: bool) -> None:
    assert must_sign(signing, loopback) is signs


def endpoint(name: str, address: str, **more: object) -> dict[str, object]:
    return {"name": name, "address": address, **more}


PLAN_TABLE = [
    # description, hub spec, agent has a key, (name, signed) per endpoint or an error
    ("default: loopback udp, no key", {}, False, [("udp", False)]),
    ("default with a key: loopback stays unsigned", {}, True, [("udp", False)]),
    ("udp beyond loopback, no key", {"udp": "0.0.0.0:14550"}, False, "beyond loopback"),
    ("udp beyond loopback, key", {"udp": "0.0.0.0:14550"}, True, [("udp", True)]),
    (
        "tcp beyond loopback, key",
        {"tcp": "0.0.0.0:5760"},
        True,
        [("udp", False), ("tcp", True)],
    ),
    (
        "gcs endpoint, no key",
        {"endpoints": [endpoint("gcs", "0.0.0.0:14560", scope="ReadOnly")]},
        False,
        "gcs",
    ),
    (
        "gcs endpoint declared unauthenticated, no key",
        {"endpoints": [endpoint("gcs", "0.0.0.0:14560", signing="Unauthenticated")]},
        False,
        [("udp", False), ("gcs", False)],
    ),
    (
        "loopback endpoint that requires signing, key",
        {"endpoints": [endpoint("local", "127.0.0.1:14561", signing="Required")]},
        True,
        [("udp", False), ("local", True)],
    ),
    (
        "loopback endpoint that requires signing, no key",
        {"endpoints": [endpoint("local", "127.0.0.1:14561", signing="Required")]},
        False,
        "on loopback",
    ),
    (
        "a name used twice",
        {"endpoints": [endpoint("udp", "127.0.0.1:14561")]},
        True,
        "used twice",
    ),
]


@pytest.mark.parametrize(
    ("what", "doc", "has_key", "expected"), PLAN_TABLE, ids=[r[0] for r in PLAN_TABLE]
)
def test_plan_endpoints(
    what: str, doc: dict[str, object], has_key: bool, expected: list[tuple[str, bool]] | str
) -> None:
    hub = HubSpec.from_api(doc)
    if isinstance(expected, str):
        with pytest.raises(HubConfigError, match=expected):
            plan_endpoints(hub, has_key)
        return
    plans = plan_endpoints(hub, has_key)
    assert [(p.name, p.signed) for p in plans] == expected, what


def test_an_endpoint_keeps_its_transport_scope_and_lists() -> None:
    hub = HubSpec.from_api(
        {
            "endpoints": [
                endpoint(
                    "gcs",
                    "0.0.0.0:5761",
                    transport="TCP",
                    scope="AllowList",
                    allowMessages=[11],
                    allowCommands=[22, 400],
                )
            ]
        }
    )
    gcs = plan_endpoints(hub, True)[1]
    assert gcs.transport is HubTransport.TCP
    assert gcs.scope is HubScope.ALLOW_LIST
    assert (gcs.allow_messages, gcs.allow_commands) == ((11,), (22, 400))


def test_unauthenticated_endpoints_beyond_loopback_are_the_ones_warned_about() -> None:
    hub = HubSpec.from_api(
        {
            "udp": "127.0.0.1:14550",
            "endpoints": [
                endpoint("open", "0.0.0.0:14560", signing="Unauthenticated", scope="ReadOnly"),
                endpoint("local", "127.0.0.1:14561", signing="Unauthenticated"),
                endpoint("gcs", "0.0.0.0:14562"),
            ],
        }
    )
    assert [p.name for p in open_to_the_network(plan_endpoints(hub, True))] == ["open"]
