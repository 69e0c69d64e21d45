"""Counting requests from the API server's audit log: who asked, in which window.

The log here is written by the test in the API server's format (one JSON event per
line). Closing a window whose marker the API server writes late (a thread writes it) is
in ``tests/integration/test_localcluster_audit_late_marker.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from roost_localcluster.audit import RequestKind, Window, client_of, stamp
from tests.support.auditlog import append, event


def test_a_window_counts_only_what_was_received_inside_it_by_client(tmp_path: Path) -> None:
    log = tmp_path / "audit.log"
    append(log, event("2000-01-01T00:00:00.000000Z", "kopf/1.0", "patch", "vehicles"))
    window = Window.open(log)
    inside = stamp()
    append(
        log,
        event(inside, "roost-operator/0.1 (python)", "patch", "vehicles", subresource="status"),
        event(inside, "kube-controller-manager/v1.35.0", "patch", "nodes"),
        event(inside, "roost-operator/0.1 (python)", "patch", "vehicles", subresource="status"),
        event("2999-01-01T00:00:00.000000Z", "kopf/1.0", "patch", "vehicles"),  # after `until`
    )

    def probe(marker: str) -> None:
        append(log, event(stamp(), "kubectl/v1.35.0", "get", "namespaces", name=marker))

    counted = window.close(probe)
    assert counted == {
        RequestKind("roost-operator", "patch", "vehicles/status"): 2,
        RequestKind("kube-controller-manager", "patch", "nodes"): 1,
    }


@pytest.mark.parametrize(
    ("user_agent", "client"),
    [
        ("kubectl/v1.35.4 (linux/amd64) kubernetes/abc", "kubectl"),
        ("roost-operator", "roost-operator"),
        ("kopf/1.37", "kopf"),
        ("", "?"),
    ],
)
def test_the_client_is_the_program_in_the_user_agent(user_agent: str, client: str) -> None:
    assert client_of(user_agent) == client
