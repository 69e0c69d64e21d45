"""Where Roost's errors meet kopf's: temporary ones are retried, permanent ones are not.

The controllers below the handlers raise the Kubernetes layer's errors; the kopf
handlers wrap their work in :func:`at_the_edge`, which turns them into kopf's two
kinds, with a message that names the object (``Kind namespace/name: …``), because a
handler of one object (a Node event) often works on another (a Vehicle):

* **temporary** — a conflict (409), throttling (429), a server error (5xx), a timeout or
  a lost connection: the same request may succeed later, so kopf retries after a
  backoff (:class:`kopf.TemporaryError`);
* **permanent** — anything else the API server refused (400, 403, 404 on a write, 422):
  retrying the same request cannot succeed, so kopf stops retrying
  (:class:`kopf.PermanentError`). The controllers report what the user must change in a
  condition or an Event before it gets here, so a permanent error is reported once,
  never in a traceback loop.

:func:`roost_operator.errors.is_temporary` is the one classification every controller
uses (the mission controller backs off on temporary errors and reports permanent ones).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import kopf

from roost_operator.errors import TRANSPORT_ERRORS, describe, is_temporary
from roost_operator.kube import ApiError


@contextmanager
def at_the_edge(
    kind: str, name: str, delay: float, *, namespace: str | None = None
) -> Iterator[None]:
    """Map errors of the block to kopf's temporary/permanent errors, naming the object."""
    try:
        yield
    except (ApiError, *TRANSPORT_ERRORS) as error:
        what = describe(kind, name, namespace)
        if is_temporary(error):
            raise kopf.TemporaryError(f"{what}: {error}", delay=delay) from error
        raise kopf.PermanentError(f"{what}: {error}") from error
