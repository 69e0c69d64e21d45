"""Closing an audit window waits for the marker line the API server writes late.

A thread appends the lines a moment after the probe is answered, as the API server
does; counting requests from a written log is in ``tests/unit/test_localcluster_audit.py``.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from roost_localcluster.audit import RequestKind, Window, stamp
from tests.support.auditlog import append, event


def test_closing_waits_for_the_marker_the_api_server_writes_late(tmp_path: Path) -> None:
    log = tmp_path / "audit.log"
    log.touch()
    window = Window.open(log)
    answered = stamp()

    def probe(marker: str) -> None:
        def late() -> None:  # the API server writes lines a moment after the answer
            time.sleep(0.2)
            append(log, event(answered, "kopf/1.0", "delete", "configmaps"))
            append(log, event(stamp(), "kubectl/v1", "get", "namespaces", name=marker))

        threading.Thread(target=late).start()

    assert window.close(probe) == {RequestKind("kopf", "delete", "configmaps"): 1}


def test_a_marker_that_never_lands_is_an_error_that_names_the_log(tmp_path: Path) -> None:
    log = tmp_path / "audit.log"
    log.touch()
    with pytest.raises(TimeoutError, match=r"audit\.log"):
        Window.open(log).close(lambda marker: None, timeout_s=0.2)
