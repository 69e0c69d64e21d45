"""The operator's reconcile queue: coalescing, one run per name at a time, retries with
backoff, permanent failures reported once, deadlines that move."""

from __future__ import annotations

import threading
import time
from collections import Counter

import pytest

from roost_operator.engine.workqueue import Backoff, Permanent, WorkQueue
from tests.support.waiting import wait_until

WAIT_S = 5.0


def test_events_before_a_worker_picks_a_name_up_cost_one_reconcile() -> None:
    seen: Counter[str] = Counter()
    queue = WorkQueue(lambda key: seen.update([key]), workers=2)
    for _ in range(10):
        queue.add("drone-1")
    queue.add("drone-2")
    queue.start()
    try:
        wait_until(
            "the reconciles", lambda: queue.idle() and sum(seen.values()) >= 2, WAIT_S, poll_s=0.005
        )
        time.sleep(0.05)
        assert seen == {"drone-1": 1, "drone-2": 1}
    finally:
        queue.stop()


def test_a_name_added_while_it_runs_runs_once_more_and_never_twice_at_once() -> None:
    running: Counter[str] = Counter()
    overlaps: list[str] = []
    runs: list[str] = []
    gate = threading.Event()

    def reconcile(key: str) -> None:
        running[key] += 1
        if running[key] > 1:
            overlaps.append(key)
        if not runs:
            gate.wait(WAIT_S)
        runs.append(key)
        running[key] -= 1

    queue = WorkQueue(reconcile, workers=4)
    queue.start()
    try:
        queue.add("drone-1")
        wait_until("the first run", lambda: running["drone-1"] == 1, WAIT_S, poll_s=0.005)
        for _ in range(5):
            queue.add("drone-1")  # dirty while running
        gate.set()
        wait_until("the second run", lambda: len(runs) == 2 and queue.idle(), WAIT_S, poll_s=0.005)
        time.sleep(0.05)
        assert runs == ["drone-1", "drone-1"]
        assert overlaps == []
    finally:
        queue.stop()


def test_a_temporary_failure_is_retried_with_a_growing_backoff() -> None:
    times: list[float] = []

    def reconcile(key: str) -> None:
        times.append(time.monotonic())
        if len(times) < 3:
            raise RuntimeError("the API server timed out")

    queue = WorkQueue(reconcile, workers=1, backoff=Backoff(base_s=0.05, cap_s=1.0))
    queue.start()
    try:
        queue.add("drone-1")
        wait_until("two retries", lambda: len(times) == 3, WAIT_S, poll_s=0.005)
        first, second = times[1] - times[0], times[2] - times[1]
        assert first >= 0.05
        assert second >= 0.1  # doubled
    finally:
        queue.stop()


def test_a_permanent_failure_is_reported_once_and_not_retried() -> None:
    calls: list[str] = []
    reported: list[tuple[str, str]] = []

    def reconcile(key: str) -> None:
        calls.append(key)
        raise Permanent("the spec cannot be written")

    queue = WorkQueue(
        reconcile,
        workers=1,
        backoff=Backoff(base_s=0.01, cap_s=0.01),
        on_permanent=lambda key, error: reported.append((key, str(error))),
    )
    queue.start()
    try:
        queue.add("drone-1")
        wait_until("the report", lambda: reported, WAIT_S, poll_s=0.005)
        time.sleep(0.1)  # ten backoffs' worth: nothing more happens
        assert calls == ["drone-1"]
        assert reported == [("drone-1", "the spec cannot be written")]
        queue.add("drone-1")  # the object changed: one more attempt
        wait_until("the attempt after a change", lambda: len(calls) == 2, WAIT_S, poll_s=0.005)
    finally:
        queue.stop()


# serial: deadlines 50 ms apart, set before the first fires
@pytest.mark.serial
def test_a_deadline_fires_once_and_a_later_one_replaces_it() -> None:
    runs: list[tuple[str, float]] = []
    queue = WorkQueue(lambda key: runs.append((key, time.monotonic())), workers=1)
    queue.start()
    try:
        start = time.monotonic()
        queue.add_at("drone-1", start + 0.1)
        queue.add_at("drone-1", start + 0.3)  # the agent reported again: moved later
        queue.add_at("drone-2", start + 0.05)
        wait_until("both deadlines", lambda: len(runs) == 2, WAIT_S, poll_s=0.005)
        assert [key for key, _ in runs] == ["drone-2", "drone-1"]
        assert runs[1][1] - start >= 0.3
        time.sleep(0.2)
        assert len(runs) == 2  # the replaced deadline never fired
    finally:
        queue.stop()


# serial: forgotten within the 50 ms before its deadline
@pytest.mark.serial
def test_a_forgotten_name_loses_its_deadline() -> None:
    runs: list[str] = []
    queue = WorkQueue(runs.append, workers=1)
    queue.start()
    try:
        queue.add_at("drone-1", time.monotonic() + 0.05)
        queue.forget("drone-1")
        time.sleep(0.15)
        assert runs == []
    finally:
        queue.stop()


# serial: cancelled within the 50 ms before its deadline
@pytest.mark.serial
def test_a_cancelled_deadline_never_fires_but_one_moved_since_does() -> None:
    runs: list[str] = []
    queue = WorkQueue(runs.append, workers=1)
    queue.start()
    try:
        start = time.monotonic()
        queue.add_at("held", start + 0.05)
        queue.cancel_at("held", start + 0.05)  # its report was written before the deadline
        queue.add_at("moved", start + 0.05)
        queue.add_at("moved", start + 0.1)  # moved by someone else since
        queue.cancel_at("moved", start + 0.05)
        wait_until("the moved deadline", lambda: runs == ["moved"], WAIT_S, poll_s=0.005)
        time.sleep(0.1)
        assert runs == ["moved"]
    finally:
        queue.stop()


def test_stop_waits_for_the_running_reconcile() -> None:
    started, finished = threading.Event(), threading.Event()

    def reconcile(key: str) -> None:
        started.set()
        time.sleep(0.1)
        finished.set()

    queue = WorkQueue(reconcile, workers=1)
    queue.start()
    queue.add("drone-1")
    assert started.wait(WAIT_S)
    queue.stop()
    assert finished.is_set()
