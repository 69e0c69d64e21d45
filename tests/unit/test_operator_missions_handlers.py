"""The Mission controller's retry policy (roost_operator.missions.handlers.backoff)."""

from __future__ import annotations

from roost_operator.missions.handlers import backoff
from roost_operator.settings import MissionTimings


def test_failed_reconciles_back_off_doubling_up_to_the_longest_wait() -> None:
    timings = MissionTimings(error_backoff_seconds=5.0, max_backoff_seconds=60.0)
    assert [backoff(timings, n) for n in range(1, 7)] == [5.0, 10.0, 20.0, 40.0, 60.0, 60.0]


def test_the_first_retry_waits_the_configured_backoff() -> None:
    assert backoff(MissionTimings(error_backoff_seconds=0.5), 1) == 0.5
