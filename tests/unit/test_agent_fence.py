"""The agent's fence keeper (roost_agent.fence) as a decision table: what one autopilot's
keeper sends and reports in each phase.

The autopilot here is a scripted peer in the test (a fence store and a parameter table
answering the keeper's messages the way roost_sim.fence and roost_sim.params do), so the
table runs without sockets or threads; tests/integration/test_agent_geofence.py runs the
same keeper inside the real agent against the simulator over real UDP.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest

from roost_agent.fence import REVERIFY_S, FenceKeeper, Fences, Phase, Send, Target, target_of
from roost_agent.params import Read, Write
from roost_api.autopilot import AssignedFence, Fence, FencePoint
from roost_api.autopilot_enums import FenceReason
from roost_api.core import Stack
from roost_api.fence import FenceAction, LatLon, held_id
from roost_api.plain import AssignedFence as PlainAssignedFence
from roost_mavlink.fence import MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION as V
from roost_mavlink.fence import Item
from roost_mavlink.params import ParamType, from_wire, to_wire

F = {"mission_type": 1}
PX4_TYPES = {"GF_ACTION": ParamType.INT32, "GF_MAX_VER_DIST": ParamType.REAL32}


@dataclass
class Peer:
    """A scripted PX4 autopilot answering the keeper (see the module docstring)."""

    items: list[Item] = field(default_factory=list)
    params: dict[str, float] = field(
        default_factory=lambda: {"GF_ACTION": 2.0, "GF_MAX_VER_DIST": 0.0}
    )
    refuse: bool = False
    silent: bool = False
    corrupt: bool = False  # stores the items with a shifted vertex
    keep_params: bool = False  # ignores PARAM_SET (echoes the old value)
    now: float = 0.0  # the test's clock, carried across run() calls
    _incoming: list[Item] | None = None
    _count: int = 0

    def answer(self, keeper: FenceKeeper, ops: list[Any], now: float) -> None:
        """Answer every op (and the ops those answers cause) at ``now``."""
        while ops and not self.silent:
            op, ops = ops[0], ops[1:]
            if isinstance(op, Read | Write):
                if isinstance(op, Write) and not self.keep_params:
                    self.params[op.name] = from_wire(op.wire, op.ptype, bytewise=True)
                ptype = PX4_TYPES[op.name]
                wire = to_wire(self.params[op.name], ptype, bytewise=True)
                keeper.observe_param(op.name, wire, int(ptype), now)
                continue
            for name, fields in self._mission(*op.message):
                ops += keeper.receive(name, fields, now)

    def _mission(self, name: str, f: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
        if name == "MISSION_REQUEST_LIST":
            return [("MISSION_COUNT", {"count": len(self.items), **F})]
        if name == "MISSION_REQUEST_INT":
            i = self.items[f["seq"]]
            return [
                (
                    "MISSION_ITEM_INT",
                    {
                        "seq": f["seq"],
                        "command": i.command,
                        "param1": i.param1,
                        "x": i.x,
                        "y": i.y,
                        **F,
                    },
                )
            ]
        if name == "MISSION_COUNT":
            self._incoming, self._count = [], f["count"]
            return self._next()
        if name == "MISSION_ITEM_INT" and self._incoming is not None:
            self._incoming.append(Item(f["command"], f["param1"], f["x"], f["y"]))
            return self._next()
        return []

    def _next(self) -> list[tuple[str, dict[str, Any]]]:
        assert self._incoming is not None
        if len(self._incoming) < self._count:
            return [("MISSION_REQUEST_INT", {"seq": len(self._incoming), **F})]
        if self.refuse:
            return [("MISSION_ACK", {"type": 1, **F})]
        stored = self._incoming
        if self.corrupt and stored:
            stored = [
                Item(stored[0].command, stored[0].param1, stored[0].x + 1, stored[0].y),
                *stored[1:],
            ]
        self.items, self._incoming = stored, None
        return [("MISSION_ACK", {"type": 0, **F})]


def target(fid: str = "f1", alt: float = 40) -> Target:
    fence = Fence(
        polygon=[
            FencePoint(latitude=47.0 + a, longitude=8.0 + b)
            for a, b in ((0, 0), (0, 0.001), (0.001, 0))
        ],
        max_altitude_m=alt,
        action=FenceAction.LAND,
    )
    plain = PlainAssignedFence.from_api(
        AssignedFence(mission="ns/m", id=fid, fence=fence).model_dump(by_alias=True, mode="json")
    )
    return target_of(plain, Stack.PX4)


def run(keeper: FenceKeeper, peer: Peer, *, armed: bool = False, steps: int = 20) -> None:
    for _ in range(steps):
        peer.now += 0.1
        peer.answer(keeper, keeper.step(peer.now, armed=armed), peer.now)


def test_a_fence_is_saved_uploaded_verified_and_its_parameters_written() -> None:
    keeper, peer = FenceKeeper(Stack.PX4), Peer(items=[Item(V, 3.0, 1, 2)] * 3)
    saved = list(peer.items)
    keeper.declare(target())
    assert keeper.phase is Phase.SAVE_ITEMS
    first = keeper.step(0.0, armed=False)
    assert [op.message[0] for op in first if isinstance(op, Send)] == ["MISSION_REQUEST_LIST"]
    peer.answer(keeper, first, 0.0)
    run(keeper, peer)
    assert keeper.phase is Phase.HELD
    assert keeper.previous_items == saved
    assert keeper.previous_params == {"GF_ACTION": 2.0, "GF_MAX_VER_DIST": 0.0}
    assert peer.items == list(target().items)
    assert peer.params == {"GF_ACTION": 5.0, "GF_MAX_VER_DIST": 40.0}
    verdict = keeper.verdict()
    assert verdict is not None and verdict.status == "True" and verdict.reason is FenceReason.HELD
    assert held_id(verdict.message) == "f1"
    assert "polygon of 3 vertices, max altitude 40 m, on breach Land" in verdict.message


@pytest.mark.parametrize(
    ("peer", "armed", "phase", "status", "reason", "detail"),
    [
        (Peer(), True, Phase.UPLOAD, "False", FenceReason.DEFERRED, "uploading the fence waits"),
        (
            Peer(refuse=True),
            False,
            Phase.FAILED,
            "False",
            FenceReason.REFUSED,
            "uploading: MISSION_ACK result 1",
        ),
        (
            Peer(corrupt=True),
            False,
            Phase.FAILED,
            "False",
            FenceReason.MISMATCH,
            "item 0 reads back as",
        ),
        (
            Peer(silent=True),
            False,
            Phase.FAILED,
            "False",
            FenceReason.NO_ANSWER,
            "reading the current fence: no answer",
        ),
        (
            Peer(keep_params=True),
            False,
            Phase.FAILED,
            "False",
            FenceReason.PARAMETERS,
            "the autopilot kept another value",
        ),
    ],
)
def test_decision_table(  # noqa: PLR0917 - one parameter per column of the table
    peer: Peer, armed: bool, phase: Phase, status: str, reason: FenceReason, detail: str
) -> None:
    keeper = FenceKeeper(Stack.PX4)
    keeper.declare(target())
    run(keeper, peer, armed=armed, steps=80)
    verdict = keeper.verdict()
    assert keeper.phase is phase
    assert verdict is not None and (verdict.status, verdict.reason) == (status, reason)
    assert verdict.message.startswith(detail)


def test_nothing_is_written_while_armed_and_the_upload_follows_the_landing() -> None:
    keeper, peer = FenceKeeper(Stack.PX4), Peer()
    keeper.declare(target())
    run(keeper, peer, armed=True)
    assert (peer.items, peer.params["GF_MAX_VER_DIST"]) == ([], 0.0)  # read, never written
    run(keeper, peer, armed=False)
    assert keeper.phase is Phase.HELD


def test_a_failed_fence_stays_failed_until_the_fence_changes() -> None:
    keeper, peer = FenceKeeper(Stack.PX4), Peer(refuse=True)
    keeper.declare(target())
    run(keeper, peer, steps=40)
    assert keeper.phase is Phase.FAILED
    keeper.declare(target())  # the same fence: no retry
    assert keeper.phase is Phase.FAILED
    peer.refuse = False
    keeper.declare(target("f2"))
    run(keeper, peer)
    assert keeper.phase is Phase.HELD


def test_without_the_fence_the_previous_one_is_restored_then_nothing_is_reported() -> None:
    old = [Item(V, 3.0, 7, 8)] * 3
    keeper, peer = FenceKeeper(Stack.PX4), Peer(items=list(old))
    keeper.declare(target())
    run(keeper, peer)
    keeper.declare(target("f2", alt=60))  # a second Mission's fence: the first save stays
    run(keeper, peer)
    assert peer.params["GF_MAX_VER_DIST"] == 60.0
    keeper.declare(None)
    assert keeper.phase is Phase.RESTORE_ITEMS
    run(keeper, peer, armed=True)
    verdict = keeper.verdict()
    assert verdict is not None and verdict.reason is FenceReason.DEFERRED
    assert verdict.message == "restoring the previous fence waits until disarmed"
    run(keeper, peer)
    assert keeper.phase is Phase.IDLE and keeper.verdict() is None
    assert peer.items == old
    assert peer.params == {"GF_ACTION": 2.0, "GF_MAX_VER_DIST": 0.0}


def test_a_vehicle_outside_the_fence_gets_no_upload() -> None:
    keeper, peer = FenceKeeper(Stack.PX4), Peer()
    keeper.declare(target())
    keeper.position = LatLon(47.01, 8.0)  # about 1 km north of the triangle
    run(keeper, peer)
    verdict = keeper.verdict()
    assert verdict is not None and verdict.reason is FenceReason.OUTSIDE
    assert verdict.message.startswith("the vehicle is at 47.010000,8.000000, outside the fence")
    assert peer.items == []
    keeper.position = LatLon(47.0002, 8.0002)  # inside: a new fence is uploaded
    keeper.declare(target("f2"))
    run(keeper, peer)
    assert keeper.phase is Phase.HELD


def test_a_held_fence_changed_by_someone_else_is_reported() -> None:
    keeper, peer = FenceKeeper(Stack.PX4), Peer()
    keeper.declare(target())
    run(keeper, peer)
    assert keeper.phase is Phase.HELD
    peer.params["GF_ACTION"] = 1.0  # another link sets it: no echo to the agent
    run(keeper, peer, armed=True)  # read back, not written in the air
    verdict = keeper.verdict()
    assert verdict is not None and (verdict.status, verdict.reason) == (
        "False",
        FenceReason.PARAMETERS,
    )
    assert "GF_ACTION is 1, declared 5" in verdict.message
    run(keeper, peer)  # on the ground it is put back
    assert peer.params["GF_ACTION"] == 5.0
    verdict = keeper.verdict()
    assert verdict is not None and verdict.reason is FenceReason.HELD
    peer.items = peer.items[:2]  # another client uploads a fence of its own
    run(keeper, peer, steps=int(REVERIFY_S / 0.1) + 10)
    verdict = keeper.verdict()
    assert verdict is not None and verdict.reason is FenceReason.MISMATCH
    assert verdict.message.startswith("changed on the autopilot: read back 2 item(s)")


def test_nothing_declared_nothing_sent() -> None:
    keeper = FenceKeeper(Stack.PX4)
    keeper.declare(None)
    assert keeper.step(0.0, armed=False) == [] and keeper.verdict() is None


# -- the heartbeat round's skip: Fences at rest ---------------------------------------------


@dataclass
class QuietLink:
    """A heard autopilot's link that records what the keepers send it (the Fences'
    FenceLink protocol; the keeper's exchanges with a real autopilot are the Peer's)."""

    name: str
    stack: Stack = Stack.PX4
    sent: list[object] = field(default_factory=list)

    def heartbeat(self) -> tuple[int, int, float] | None:
        return (0, 0, 0.0)

    def read_param(self, name: str) -> bool:
        self.sent.append(name)
        return True

    def write_param(self, name: str, wire: float, ptype: int) -> bool:
        self.sent.append(name)
        return True

    def send_mission(self, name: str, fields: Any) -> bool:
        self.sent.append(name)
        return True


def _step(fences: Fences, links: dict[str, QuietLink], emitted: list[str]) -> None:
    fences.step(
        links,
        None,
        messages={},
        params={},
        capabilities={},
        positions={},
        armed=False,
        now=1.0,
        emit=lambda reason, *_: emitted.append(reason),
    )


def _held_then(change: str) -> tuple[Fences, dict[str, QuietLink]]:
    links = {"fc1": QuietLink("fc1"), "fc2": QuietLink("fc2")}
    fences = Fences()
    _step(fences, links, [])
    keeper = fences.keeper(links["fc1"])
    if change == "new link":
        links["fc2"] = QuietLink("fc2")
    elif change == "link gone":
        del links["fc2"]
    elif change == "fence declared":
        keeper.declare(target())
    elif change == "restoring":
        keeper.previous_items = [Item(V, 3.0, 7, 8)]
        keeper.declare(target())
        keeper.declare(None)
    elif change == "deferred":
        keeper.declare(target())
        keeper.phase = Phase.UPLOAD
        keeper.step(2.0, armed=True)
        keeper.declare(None)
    elif change == "transfer":
        peer = Peer(silent=True)
        keeper.declare(target())
        run(keeper, peer, steps=1)
    elif change == "failed":
        keeper.declare(target())
        run(keeper, Peer(refuse=True), steps=40)
        _step(fences, links, [])  # the failure is reported
        keeper.declare(None)
    return fences, links


@pytest.mark.parametrize(
    ("change", "at_rest"),
    [
        ("nothing", True),
        ("new link", False),  # a replaced link gets a new keeper
        ("link gone", False),  # its keeper is dropped
        ("fence declared", False),
        ("restoring", False),  # the previous fence is to be put back
        ("deferred", False),
        ("transfer", False),
        ("failed", False),  # a verdict is still reported
    ],
)
def test_fences_are_at_rest_only_when_a_step_would_do_nothing(change: str, at_rest: bool) -> None:
    fences, links = _held_then(change)
    assert fences.at_rest(links) is at_rest


def test_fresh_fences_are_stepped_once_before_they_rest() -> None:
    links = {"fc1": QuietLink("fc1")}
    fences = Fences()
    assert not fences.at_rest(links)
    emitted: list[str] = []
    _step(fences, links, emitted)
    assert fences.at_rest(links)
    _step(fences, links, emitted)  # what a skipped step would have done: nothing
    assert (emitted, links["fc1"].sent, fences.at_rest(links)) == ([], [], True)
