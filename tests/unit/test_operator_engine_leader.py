"""The leader election's decision (roost_operator.engine.leader.decide), without a cluster:
who may write itself into the Lease, and when a standby may take it."""

from __future__ import annotations

from typing import Any

import pytest

from roost_operator.engine.leader import Seen, Step, decide

LEASE_S = 8.0


def lease(holder: str | None, renewed: str = "t1") -> dict[str, Any]:
    return {
        "metadata": {"resourceVersion": "5"},
        "spec": {"holderIdentity": holder, "renewTime": renewed},
    }


@pytest.mark.parametrize(
    ("case", "read", "seen", "now", "step"),
    [
        ("no Lease yet: create it", None, None, 0.0, Step.CREATE),
        ("a released Lease: take it", lease(None), None, 0.0, Step.TAKE),
        ("our own Lease: renew it", lease("me"), None, 0.0, Step.TAKE),
        ("another's, first seen: wait a whole lease", lease("other"), None, 100.0, Step.WAIT),
        (
            "another's, renewed since we looked: wait again",
            lease("other", "t2"),
            Seen(("other", "t1"), 0.0),
            100.0,
            Step.WAIT,
        ),
        (
            "another's, unchanged for less than a lease: wait",
            lease("other"),
            Seen(("other", "t1"), 95.0),
            100.0,
            Step.WAIT,
        ),
        (
            "another's, unchanged for a whole lease: take it",
            lease("other"),
            Seen(("other", "t1"), 92.0),
            100.0,
            Step.TAKE,
        ),
    ],
)
def test_leader_decision_table(
    case: str, read: dict[str, Any] | None, seen: Seen | None, now: float, step: Step
) -> None:
    assert decide(read, "me", seen, now, LEASE_S)[0] is step, case


def test_a_standby_times_the_holder_on_its_own_clock_from_the_last_change_it_saw() -> None:
    step, seen = decide(lease("other", "t1"), "me", None, 10.0, LEASE_S)
    assert step is Step.WAIT and seen == Seen(("other", "t1"), 10.0)
    step, seen = decide(lease("other", "t1"), "me", seen, 17.0, LEASE_S)
    assert step is Step.WAIT and seen == Seen(("other", "t1"), 10.0)
    step, _ = decide(lease("other", "t1"), "me", seen, 18.0, LEASE_S)
    assert step is Step.TAKE
