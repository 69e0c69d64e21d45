"""roost_agent.params: the decision table of one parameter and the keeper (the wire
encodings it uses are roost_mavlink.params', tested in test_mavlink_params)."""

from __future__ import annotations

import math
import struct

import pytest

from roost_agent.params import (
    MAX_READS,
    MAX_WRITES,
    READBACK_S,
    RETRY_S,
    WINDOW,
    Do,
    Facts,
    ParamKeeper,
    ParamType,
    Read,
    Write,
    decide,
    from_wire,
    nothing_declared,
    same,
    to_wire,
    value_problem,
)
from roost_api.autopilot_enums import ParametersReason as R
from roost_api.core import Stack

F, I32 = ParamType.REAL32, ParamType.INT32
NOW = 100.0

# -- one parameter: the decision table -----------------------------------------------------

never = -math.inf
CASES = [
    # (facts, armed, restore) -> (what to send, reason)
    # not read yet: read, then again after RETRY_S, then give up (the firmware lacks it)
    (Facts(desired=5), False, False, Do.READ, R.NO_DATA),
    (Facts(desired=5, reads=1, read_at=NOW - 0.1), False, False, Do.NOTHING, R.NO_DATA),
    (Facts(desired=5, reads=1, read_at=NOW - RETRY_S), False, False, Do.READ, R.NO_DATA),
    (Facts(desired=5, reads=MAX_READS, read_at=NOW - 0.1), False, False, Do.NOTHING, R.NO_DATA),
    (Facts(desired=5, reads=MAX_READS, read_at=NOW - RETRY_S), False, False, Do.NOTHING, R.MISSING),
    # armed changes nothing about reading
    (Facts(desired=5), True, False, Do.READ, R.NO_DATA),
    # a value the type cannot hold is never written
    (Facts(desired=1.5, observed=1, ptype=I32), False, False, Do.NOTHING, R.INVALID),
    (Facts(desired=2**31, observed=1, ptype=I32), False, False, Do.NOTHING, R.INVALID),
    # holds it
    (Facts(desired=5, observed=5, ptype=I32), False, False, Do.NOTHING, R.IN_SYNC),
    (Facts(desired=5, observed=5, ptype=I32, applied=True), True, True, Do.NOTHING, R.IN_SYNC),
    (Facts(desired=0.1, observed=float(struct.unpack("<f", struct.pack("<f", 0.1))[0]), ptype=F),
     False, False, Do.NOTHING, R.IN_SYNC),
    # first write: on the ground only
    (Facts(desired=5, observed=2, ptype=I32), False, False, Do.WRITE, R.WRITING),
    (Facts(desired=5, observed=2, ptype=I32), True, False, Do.NOTHING, R.DEFERRED),
    (Facts(desired=5, observed=2, ptype=I32), True, True, Do.NOTHING, R.DEFERRED),
    # a write waits RETRY_S for its echo, is repeated, and is refused after MAX_WRITES
    (Facts(desired=5, observed=2, ptype=I32, writes=1, write_at=NOW - 0.2), False, False,
     Do.NOTHING, R.WRITING),
    (Facts(desired=5, observed=2, ptype=I32, writes=1, write_at=NOW - RETRY_S), False, False,
     Do.WRITE, R.WRITING),
    (Facts(desired=5, observed=2, ptype=I32, writes=MAX_WRITES, write_at=NOW - RETRY_S), False,
     False, Do.NOTHING, R.REFUSED),
    # set once, changed by someone else: drift; written back only with Restore, disarmed
    (Facts(desired=5, observed=2, ptype=I32, applied=True), False, False, Do.NOTHING, R.DRIFTED),
    (Facts(desired=5, observed=2, ptype=I32, applied=True), False, True, Do.WRITE, R.DRIFTED),
    (Facts(desired=5, observed=2, ptype=I32, applied=True), True, True, Do.NOTHING, R.DRIFTED),
    (Facts(desired=5, observed=2, ptype=I32, applied=True, write_at=NOW - 0.1), False, True,
     Do.NOTHING, R.DRIFTED),
]  # fmt: skip


@pytest.mark.parametrize(("facts", "armed", "restore", "do", "reason"), CASES)
def test_one_parameter_decision_table(
    facts: Facts, armed: bool, restore: bool, do: Do, reason: R
) -> None:
    assert decide(facts, now=NOW, armed=armed, restore=restore) == (do, reason)


def test_values_are_checked_against_the_type() -> None:
    assert value_problem(255, ParamType.UINT8) is None
    assert "outside 0..255" in (value_problem(256, ParamType.UINT8) or "")
    assert "whole number" in (value_problem(1.5, ParamType.INT16) or "")
    assert "finite" in (value_problem(math.nan, F) or "")
    assert value_problem(1e39, F) is not None
    assert same(6.2, float(struct.unpack("<f", struct.pack("<f", 6.2))[0]), F)


# -- the keeper --------------------------------------------------------------------------------


def _answer(
    keeper: ParamKeeper, ops: list[Read | Write], held: dict[str, float], at: float
) -> None:
    """What a firmware holding ``held`` (INT32 on PX4) answers to ``ops``."""
    for op in ops:
        if isinstance(op, Write):
            held[op.name] = from_wire(op.wire, op.ptype, bytewise=True)
        if op.name in held:
            keeper.observe(op.name, to_wire(held[op.name], I32, bytewise=True), I32, at)


def test_the_keeper_reads_writes_confirms_and_finds_drift() -> None:
    keeper = ParamKeeper(Stack.PX4)
    keeper.declare({"GF_ACTION": 3, "NOPE": 1})
    held = {"GF_ACTION": 2.0}
    now = 0.0
    ops = keeper.step(now, armed=False, restore=False)
    assert ops == [Read("GF_ACTION"), Read("NOPE")]
    _answer(keeper, ops, held, now)
    ops = keeper.step(now + 0.1, armed=False, restore=False)
    assert ops == [Write("GF_ACTION", to_wire(3, I32, bytewise=True), I32)]
    _answer(keeper, ops, held, now + 0.1)
    assert keeper.reasons()["GF_ACTION"] is R.WRITING  # judged at the next step
    for _ in range(MAX_READS + 1):
        now += RETRY_S
        _answer(keeper, keeper.step(now, armed=False, restore=False), held, now)
    assert keeper.reasons() == {"GF_ACTION": R.IN_SYNC, "NOPE": R.MISSING}
    verdict = keeper.verdict()
    assert (verdict.status, verdict.reason) == ("False", R.MISSING)
    assert "NOPE" in verdict.message
    # another client sets it: the answer to the next read-back shows drift
    held["GF_ACTION"] = 1.0
    now += READBACK_S
    drift = None
    for op in keeper.step(now, armed=False, restore=False):
        drift = keeper.observe(op.name, to_wire(held[op.name], I32, bytewise=True), I32, now)
    assert drift is not None and (drift.desired, drift.observed) == (3, 1)
    keeper.declare({"GF_ACTION": 3})
    keeper.step(now, armed=False, restore=False)
    verdict = keeper.verdict()
    assert (verdict.reason, verdict.message) == (
        R.DRIFTED,
        "changed on the autopilot since the agent set it: GF_ACTION is 1, declared 3",
    )
    # with Restore it is written back, not while armed
    armed = keeper.step(now + RETRY_S, armed=True, restore=True)
    assert not [op for op in armed if isinstance(op, Write)]
    assert [type(op) for op in keeper.step(now + RETRY_S, armed=False, restore=True)] == [Write]


def test_the_keeper_keeps_a_window_of_requests_in_flight() -> None:
    keeper = ParamKeeper(Stack.ARDUPILOT)
    keeper.declare({f"RC{n}_MIN": 1000 for n in range(1, 17)} | {"FENCE_RADIUS": 50})
    first = keeper.step(0.0, armed=False, restore=False)
    assert len(first) == WINDOW
    assert keeper.step(0.1, armed=False, restore=False) == []  # nothing answered yet
    keeper.observe("RC1_MIN", 1100.0, ParamType.INT16, 0.15)
    assert keeper.step(0.2, armed=False, restore=False) == [
        Write("RC1_MIN", 1000.0, ParamType.INT16)  # ArduPilot: the number, its own type
    ]
    keeper.observe("RC1_MIN", 1000.0, ParamType.INT16, 0.25)
    assert keeper.step(0.3, armed=False, restore=False) == [Read("FENCE_RADIUS")]


def test_a_new_declared_value_is_written_not_drift() -> None:
    keeper = ParamKeeper(Stack.PX4)
    keeper.declare({"MIS_TAKEOFF_ALT": 2.5})
    keeper.observe("MIS_TAKEOFF_ALT", 2.5, F, 0.0)
    keeper.declare({"MIS_TAKEOFF_ALT": 6.2})
    [op] = keeper.step(1.0, armed=False, restore=False)
    assert op == Write("MIS_TAKEOFF_ALT", to_wire(6.2, F, bytewise=True), F)
    assert keeper.verdict().reason is R.WRITING


# -- the heartbeat round's skip: nothing declared, nothing to do -----------------------------


def _declared(names: dict[str, float]) -> ParamKeeper:
    keeper = ParamKeeper(Stack.PX4)
    keeper.declare(names)
    return keeper


@pytest.mark.parametrize(
    ("keepers", "verdicts", "skipped"),
    [
        ([], {}, True),  # no link keeper yet: a round would create empty ones
        ([_declared({}), _declared({})], {}, True),  # empty keepers, nothing reported
        ([_declared({}), _declared({"GF_ACTION": 2.0})], {}, False),  # a declaration to drop
        ([_declared({})], {"fc1": object()}, False),  # a verdict to withdraw
    ],
)
def test_a_round_with_nothing_declared_is_skipped_only_when_it_would_do_nothing(
    keepers: list[ParamKeeper], verdicts: dict[str, object], skipped: bool
) -> None:
    assert nothing_declared(keepers, verdicts) is skipped


def test_an_undeclared_keeper_ignores_what_it_receives_and_asks_nothing() -> None:
    """Why the skip may leave received values unread: an empty keeper reads none of them."""
    keeper = _declared({})
    assert keeper.observe("GF_ACTION", 2.0, int(I32), NOW) is None
    assert keeper.step(NOW, armed=False, restore=True) == []
    assert nothing_declared([keeper], {})
