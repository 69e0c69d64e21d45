"""Waiting on a condition, and names no other test uses.

Every test that waits for something polls the condition with :func:`wait_until` and
fails with what it was waiting for; none sleeps for a fixed time and then asserts.
The only fixed waits left prove that nothing happens for a while, and say so.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def wait_until(
    what: str,
    check: Callable[[], T | None],
    timeout_s: float = 60.0,
    poll_s: float = 0.2,
    explain: Callable[[], str] | None = None,
) -> T:
    """Poll ``check`` until it returns something truthy and return that.

    Raises :class:`TimeoutError` naming ``what`` when ``timeout_s`` passes first, followed
    by what ``explain`` returns then (the logs or the state that say why), if given.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        result = check()
        if result:
            return result
        if time.monotonic() > deadline:
            why = f"; {explain()}" if explain is not None else ""
            raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}{why}")
        time.sleep(poll_s)


def unique(prefix: str) -> str:
    """``prefix`` plus a random suffix: the cluster is shared by a whole test session."""
    return f"{prefix}-{uuid.uuid4().hex[:6]}"
