"""The stream keeper's decision table: when it asks for which streams, how, and when it
trusts them. Pure: counters and times in, requests out (the same keeper runs against the
simulated ArduPilot over UDP in tests/integration/test_firmware_truth.py)."""

from __future__ import annotations

import itertools

from roost_agent.health import StreamFacts
from roost_agent.streams import (
    CHECK_S,
    LINK_LOST_S,
    MAX_BACKOFF_S,
    VERIFIED_CHECK_S,
    WANTED,
    Method,
    Request,
    StreamKeeper,
    Why,
)
from roost_api.meta import Stack
from roost_mavlink import MavResult


class Feed:
    """Counts messages as an autopilot streaming ``rates`` (Hz) would produce them."""

    def __init__(self) -> None:
        self.counts: dict[str, float] = {}
        self.t = 0.0
        self.heartbeat_at: float | None = None
        self.last_at: float | None = None
        self.reboots = 0

    def run(self, seconds: float, rates: dict[str, float]) -> None:
        for name, hz in rates.items():
            self.counts[name] = self.counts.get(name, 0) + hz * seconds
        self.t += seconds
        if rates:
            self.last_at = self.heartbeat_at = self.t

    def facts(self) -> StreamFacts:
        return StreamFacts(
            {k: int(v) for k, v in self.counts.items()},
            self.heartbeat_at,
            self.last_at,
            self.reboots,
        )


HEARTBEAT_ONLY = {"HEARTBEAT": 1.0}


def names(requests: list[Request], method: Method) -> set[str]:
    return {r.message for r in requests if r.method is method}


def test_nothing_is_requested_before_the_first_heartbeat() -> None:
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    assert keeper.step(feed.facts(), 5.0) == []
    assert keeper.epoch is None


def test_ardupilot_heartbeat_only_gets_every_stream_then_the_fallback() -> None:
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    feed.run(0.1, HEARTBEAT_ONLY)
    assert keeper.step(feed.facts(), feed.t) == []  # connect: measure one window first
    assert keeper.epoch is Why.CONNECT
    feed.run(CHECK_S, HEARTBEAT_ONLY)
    first = keeper.step(feed.facts(), feed.t)
    assert names(first, Method.INTERVAL) == set(WANTED[Stack.ARDUPILOT])
    assert names(first, Method.DATA_STREAM) == set()
    assert {r.hz for r in first if r.message == "ATTITUDE"} == {50.0}
    feed.run(CHECK_S, HEARTBEAT_ONLY)  # SET_MESSAGE_INTERVAL brought nothing
    second = keeper.step(feed.facts(), feed.t)
    assert names(second, Method.INTERVAL) == set(WANTED[Stack.ARDUPILOT])
    # one REQUEST_DATA_STREAM per group, at the fastest member's rate
    groups = [r for r in second if r.method is Method.DATA_STREAM]
    assert len(groups) == 4 and not keeper.verified
    assert {r.message: r.hz for r in groups}["EXTENDED_SYS_STATE"] == 5.0


def test_refused_set_message_interval_falls_back_at_once() -> None:
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    feed.run(CHECK_S, HEARTBEAT_ONLY)
    first = keeper.step(feed.facts(), feed.t, last_ack=MavResult.UNSUPPORTED)
    assert names(first, Method.DATA_STREAM)


# PX4 v1.16's onboard link as recorded (rates in Hz, the messages the keeper wants).
PX4_ONBOARD = {
    "ATTITUDE": 100.0,
    "GLOBAL_POSITION_INT": 50.0,
    "SYS_STATUS": 5.0,
    "EXTENDED_SYS_STATE": 5.0,
    "ESTIMATOR_STATUS": 1.0,
    "HEARTBEAT": 1.0,
}


def test_px4_streaming_everything_is_verified_without_a_request() -> None:
    keeper, feed = StreamKeeper(Stack.PX4), Feed()
    px4 = PX4_ONBOARD
    feed.run(0.1, px4)
    keeper.step(feed.facts(), feed.t)
    feed.run(CHECK_S, px4)
    assert keeper.step(feed.facts(), feed.t) == []  # a faster stream is never slowed down
    assert keeper.verified and keeper.total_rate == sum(WANTED[Stack.PX4].values())


def test_px4_missing_one_stream_asks_only_for_it_and_never_data_streams() -> None:
    keeper, feed = StreamKeeper(Stack.PX4), Feed()
    px4 = {k: v for k, v in PX4_ONBOARD.items() if k != "ESTIMATOR_STATUS"}
    feed.run(0.1, px4)
    keeper.step(feed.facts(), feed.t)
    for _ in range(3):
        feed.run(CHECK_S * 4, px4)
        requests = keeper.step(feed.facts(), feed.t)
        assert requests == [Request("ESTIMATOR_STATUS", 1.0, Method.INTERVAL)]


def test_verified_streams_are_rechecked_and_rerequested_when_they_stop() -> None:
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    full = {**WANTED[Stack.ARDUPILOT], "HEARTBEAT": 1.0}
    feed.run(0.1, full)
    keeper.step(feed.facts(), feed.t)
    feed.run(CHECK_S, full)
    assert keeper.step(feed.facts(), feed.t) == [] and keeper.verified
    feed.run(VERIFIED_CHECK_S / 2, full)
    assert keeper.step(feed.facts(), feed.t) == []  # not due yet
    feed.run(VERIFIED_CHECK_S, {**HEARTBEAT_ONLY, "ATTITUDE": 50.0})
    again = keeper.step(feed.facts(), feed.t)
    assert "ATTITUDE" not in names(again, Method.INTERVAL)
    assert "SYS_STATUS" in names(again, Method.INTERVAL) and not keeper.verified


def test_reboot_and_link_regained_start_a_new_epoch() -> None:
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    full = {**WANTED[Stack.ARDUPILOT], "HEARTBEAT": 1.0}
    feed.run(0.1, full)
    keeper.step(feed.facts(), feed.t)
    feed.run(CHECK_S, full)
    keeper.step(feed.facts(), feed.t)
    assert keeper.verified
    feed.reboots = 1
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    assert keeper.epoch is Why.REBOOT and not keeper.verified
    feed.run(CHECK_S, HEARTBEAT_ONLY)
    assert names(keeper.step(feed.facts(), feed.t), Method.INTERVAL)
    feed.t += LINK_LOST_S + 1  # silence
    assert keeper.step(feed.facts(), feed.t) == [] and not keeper.verified
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    assert keeper.epoch is Why.RELINK and keeper.attempts == 0


def test_settled_while_there_is_nobody_to_ask_or_the_streams_arrive() -> None:
    """Decision table for ``settled`` (the agent's keepers then rest until the next
    heartbeat): not heard yet, verified, or the link lost, settled; just heard, streams
    missing, rebooted or heard again, not."""
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    full = {**WANTED[Stack.ARDUPILOT], "HEARTBEAT": 1.0}
    keeper.step(feed.facts(), 1.0)
    rows = [(keeper.settled, True)]  # not heard yet
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    rows.append((keeper.settled, False))  # just heard: measuring its first window
    feed.run(CHECK_S, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    rows.append((keeper.settled, False))  # streams missing: requested
    feed.run(CHECK_S, full)
    keeper.step(feed.facts(), feed.t)
    rows.append((keeper.settled, True))  # they arrive
    feed.reboots = 1
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    rows.append((keeper.settled, False))  # rebooted: asked again
    feed.t += LINK_LOST_S + 1
    keeper.step(feed.facts(), feed.t)
    rows.append((keeper.settled, True))  # the link lost: nobody to ask
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    rows.append((keeper.settled, False))  # heard again
    assert [got for got, _ in rows] == [want for _, want in rows]


def test_repeated_failures_back_off() -> None:
    keeper, feed = StreamKeeper(Stack.ARDUPILOT), Feed()
    feed.run(0.1, HEARTBEAT_ONLY)
    keeper.step(feed.facts(), feed.t)
    asked_at: list[float] = []
    while feed.t < 60:
        feed.run(0.1, HEARTBEAT_ONLY)
        if keeper.step(feed.facts(), feed.t):
            asked_at.append(feed.t)
    gaps = [b - a for a, b in itertools.pairwise(asked_at)]
    assert gaps[0] <= CHECK_S + 0.11 and max(gaps) <= MAX_BACKOFF_S + 0.11
    assert gaps[-1] > 5 * CHECK_S


def test_liveness_rate_is_what_arrives_of_the_requested_streams() -> None:
    keeper, feed = StreamKeeper(Stack.PX4), Feed()
    some = {"ATTITUDE": 50.0, "SYS_STATUS": 5.0, "HEARTBEAT": 1.0}
    feed.run(0.1, some)
    keeper.step(feed.facts(), feed.t)
    assert keeper.arriving_rate is None  # nothing measured yet
    feed.run(CHECK_S, some)
    keeper.step(feed.facts(), feed.t)
    assert keeper.arriving_rate == 55.0 and keeper.checks == 1
    feed.reboots = 1
    feed.run(0.1, some)
    keeper.step(feed.facts(), feed.t)
    assert keeper.arriving_rate is None  # a new epoch: measure again
