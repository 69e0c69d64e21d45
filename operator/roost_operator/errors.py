"""Which errors of the Kubernetes API are worth retrying; no kopf here.

A request that failed on a conflict (409), throttling (429), a server error (5xx), a
timeout or a lost connection may succeed when sent again: the error is **temporary**.
Anything else the API server refused (400, 403, 422, …) is **permanent** for that
request: Roost built it from the user's spec (a name too long for a label, a template
the Job API rejects), and only a change of that spec can help. Controllers report a
permanent error once, in a condition or an Event, and go on; temporary errors are
retried with a backoff. :mod:`roost_operator.edge` maps both to kopf's errors.
"""

from __future__ import annotations

from typing import Final

from urllib3.exceptions import HTTPError as TransportError

from roost_operator.kube import ApiError

TEMPORARY_STATUSES: Final = frozenset({408, 409, 425, 429})
"""HTTP statuses that may succeed when retried, besides every 5xx."""

TRANSPORT_ERRORS: Final = (TransportError, TimeoutError, ConnectionError)
"""Failures below HTTP (the request may not even have reached the API server)."""


def is_temporary(error: BaseException) -> bool:
    """Whether retrying the request that raised ``error`` may succeed."""
    if isinstance(error, ApiError):
        return error.status in TEMPORARY_STATUSES or error.status >= 500
    return isinstance(error, TRANSPORT_ERRORS)


def describe(kind: str, name: str, namespace: str | None = None) -> str:
    """``Kind namespace/name`` (or ``Kind name`` for a cluster-scoped object)."""
    return f"{kind} {namespace}/{name}" if namespace else f"{kind} {name}"
