"""Which Missions an event queues, and when a Mission is looked at without one
(roost_operator.missions.interest)."""

from __future__ import annotations

import pytest

from roost_operator.missions.interest import Interest, next_look


def test_events_reach_the_holder_the_claimant_and_the_waiting_missions() -> None:
    interest = Interest()
    interest.track("ns/holder", vehicles=["a"], waiting=False)
    interest.track("ns/waiting", vehicles=[], waiting=True)
    interest.track("ns/other", vehicles=["b"], waiting=False)
    assert interest.holder("a") == {"ns/holder"}
    assert interest.holder("c") == set()
    assert interest.for_vehicle("a", None) == {"ns/holder", "ns/waiting"}
    assert interest.for_vehicle("c", "ns/new") == {"ns/waiting", "ns/new"}
    assert interest.waiting() == {"ns/waiting"}


def test_a_reconcile_replaces_what_the_mission_held_and_forgetting_drops_it() -> None:
    interest = Interest()
    interest.track("ns/m", vehicles=["a", "b"], waiting=True)
    interest.track("ns/m", vehicles=["b"], waiting=False)  # started; released a
    assert interest.holder("a") == set()
    assert interest.holder("b") == {"ns/m"}
    assert interest.waiting() == frozenset()
    interest.track("ns/m", vehicles=["b"], waiting=True)
    interest.forget("ns/m")
    assert interest.for_vehicle("b", None) == set()


@pytest.mark.parametrize(
    ("finished", "requeue_after", "resync_s", "expected"),
    [
        # finished and holding nothing: only an event brings it back
        (True, None, 10.0, None),
        (True, 0.5, 10.0, None),
        # the plan asked for a look (abort poll, records round, lost claim race)
        (False, 0.0, 10.0, 0.0),
        (False, 1.0, 10.0, 1.0),
        (False, 30.0, 10.0, 30.0),  # a records round later than the resync: as asked
        (False, 1.0, 0.0, 1.0),
        # nothing asked: the resync period, or none when it is off
        (False, None, 10.0, 10.0),
        (False, None, 0.0, None),
    ],
)
def test_next_look(
    finished: bool, requeue_after: float | None, resync_s: float, expected: float | None
) -> None:
    got = next_look(finished=finished, requeue_after=requeue_after, resync_s=resync_s)
    assert got == expected
