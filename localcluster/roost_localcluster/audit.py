"""The API server's audit log, for counting what each client asks of it.

Why: the API server's own request metrics count requests by verb and resource, but not
by who sent them, and at fleet scale the operator shares the API server with the
controller manager, the scheduler, kwok and whoever applies the Vehicles. The audit log
names the client of every request (its user agent), so the operator's share can be
counted on its own. ``Settings(audit=True)`` turns it on (:func:`audit_args`); it costs
the API server CPU, so timings are taken without it.

The policy records metadata only (no bodies) and one line per request, when its answer
is complete (a watch is counted when it ends). Lines land a moment after the answer, so a
reader of "everything until now" first sends a request naming a marker and reads once the
marker's line is there (:class:`Window`).
"""

from __future__ import annotations

import json
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import yaml

AUDIT_LOG = "audit.log"
POLICY = {
    "apiVersion": "audit.k8s.io/v1",
    "kind": "Policy",
    "omitStages": ["RequestReceived", "ResponseStarted"],
    "rules": [{"level": "Metadata"}],
}
# The user agents of Roost's operator: its own API layer and kopf's watches and patches.
OPERATOR_CLIENTS = frozenset({"roost-operator", "kopf"})
WRITE_VERBS = frozenset({"create", "update", "patch", "delete", "deletecollection"})


def audit_args(state_dir: Path, logs_dir: Path) -> list[str]:
    """The API server's flags for an audit log in ``logs_dir`` (its policy in ``state_dir``)."""
    policy = state_dir / "audit-policy.yaml"
    policy.write_text(yaml.safe_dump(POLICY, sort_keys=False))
    logs_dir.mkdir(parents=True, exist_ok=True)
    return [
        f"--audit-policy-file={policy}",
        f"--audit-log-path={logs_dir / AUDIT_LOG}",
        "--audit-log-format=json",
        "--audit-log-mode=batch",
        "--audit-log-maxsize=0",
    ]


@dataclass(frozen=True, order=True)
class RequestKind:
    """Who asked what: the client program, the verb, the resource (``deployments``,
    ``vehicles/status``) and whether the answer was an error (its HTTP code) or not ("")."""

    client: str
    verb: str
    resource: str
    error: str = ""


def client_of(user_agent: str) -> str:
    """The program in a user agent: ``kubectl/v1.35.4 (linux/amd64) …`` → ``kubectl``."""
    return user_agent.split("/", 1)[0].split(" ", 1)[0] or "?"


def stamp() -> str:
    """Now as the audit log writes times (RFC 3339, microseconds, UTC): a ``since`` or
    ``until`` for :func:`requests`."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def requests(
    log: Path, *, since: str = "", until: str = "", offset: int = 0
) -> Iterator[RequestKind]:
    """Every resource request in ``log`` received in [``since``, ``until``) (RFC 3339
    timestamps as the log writes them, compared as strings; empty: unbounded). Reading
    starts ``offset`` bytes in: the log's size when the window began skips what came
    before without parsing it."""
    with log.open() as lines:
        lines.seek(offset)
        for line in lines:
            event = json.loads(line)
            received = event.get("requestReceivedTimestamp", "")
            ref = event.get("objectRef")
            if ref is None or received < since or (until and received >= until):
                continue
            resource = ref.get("resource", "?")
            if ref.get("subresource"):
                resource = f"{resource}/{ref['subresource']}"
            code = (event.get("responseStatus") or {}).get("code", 0)
            yield RequestKind(
                client_of(event.get("userAgent", "")),
                event.get("verb", "?"),
                resource,
                str(code) if code >= 400 else "",
            )


def count_requests(
    log: Path, *, since: str = "", until: str = "", offset: int = 0
) -> Counter[RequestKind]:
    """How many requests of each kind :func:`requests` finds."""
    return Counter(requests(log, since=since, until=until, offset=offset))


@dataclass(frozen=True)
class Window:
    """The requests received from :meth:`open` until :meth:`close`.

    ``probe`` sends any request whose audit line names the string it is given (a GET of a
    namespace by that name will do): :meth:`close` waits for that line, so every request
    answered before the window closed has been written by then.
    """

    log: Path
    offset: int
    since: str

    @classmethod
    def open(cls, log: Path) -> Window:
        return cls(log, log.stat().st_size if log.exists() else 0, stamp())

    def close(
        self, probe: Callable[[str], object], timeout_s: float = 30.0
    ) -> Counter[RequestKind]:
        until = stamp()
        marker = f"roost-audit-marker-{uuid.uuid4().hex[:12]}"
        probe(marker)
        deadline = time.monotonic() + timeout_s
        while not self._logged(marker):
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"the audit log {self.log} did not show {marker} in {timeout_s} s"
                )
            time.sleep(0.05)
        return count_requests(self.log, since=self.since, until=until, offset=self.offset)

    def _logged(self, marker: str) -> bool:
        with self.log.open() as lines:
            lines.seek(self.offset)
            return any(marker in line for line in lines)
