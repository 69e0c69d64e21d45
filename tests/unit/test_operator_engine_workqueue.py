"""The operator's reconcile queue: coalescing, one run per name at a time, retries with
backoff, permanent failures reported once, deadlines that move.

Here the backoff arithmetic; the queue itself runs worker threads and is tested in
``tests/integration/test_operator_workqueue_threads.py``."""

from __future__ import annotations

import pytest

from roost_operator.engine.workqueue import Backoff


@pytest.mark.parametrize(("failures", "delay"), [(1, 1.0), (2, 2.0), (3, 4.0), (10, 60.0)])
def test_backoff_doubles_up_to_its_cap(failures: int, delay: float) -> None:
    assert Backoff(base_s=1.0, cap_s=60.0).delay(failures) == delay
