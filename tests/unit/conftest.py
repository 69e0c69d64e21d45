"""The unit tier's one rule, enforced: no sockets, no threads, no sleeps, no programs.

A unit test checks a pure function or a class against a decision table or a property,
with a fake clock where time matters; it runs in milliseconds and the same way on a busy
machine. What needs a socket, a thread, real time or another process is an integration
test (``tests/integration``). The guard below makes a slip fail at once, naming what the
test reached for, instead of slowing the tier down or making it flaky.
"""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from typing import Any, NoReturn

import pytest


def _refuse(what: str) -> Any:
    def refused(*_: object, **__: object) -> NoReturn:
        raise AssertionError(
            f"a unit test must not use {what}: move it to tests/integration "
            "(or give the code a fake clock / an injected transport)"
        )

    return refused


@pytest.fixture(autouse=True)
def _unit_tier_rules(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(socket.socket, "__init__", _refuse("a socket"))
    monkeypatch.setattr(threading.Thread, "start", _refuse("a thread"))
    monkeypatch.setattr(time, "sleep", _refuse("time.sleep (use a fake clock)"))
    monkeypatch.setattr(subprocess.Popen, "__init__", _refuse("another process"))
    yield
