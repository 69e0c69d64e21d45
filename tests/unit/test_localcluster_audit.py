"""Counting requests from the API server's audit log: who asked, in which window.

The log here is written by the test in the API server's format (one JSON event per
line); the window's probe appends the marker's line, as the API server would once the
probe's request is answered.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from roost_localcluster.audit import RequestKind, Window, client_of, stamp


def event(received: str, user_agent: str, verb: str, resource: str, **ref: str) -> str:
    return json.dumps(
        {
            "requestReceivedTimestamp": received,
            "userAgent": user_agent,
            "verb": verb,
            "objectRef": {"resource": resource, **ref},
            "responseStatus": {"code": 200},
        }
    )


def append(log: Path, *lines: str) -> None:
    with log.open("a") as out:
        out.writelines(line + "\n" for line in lines)


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
