"""One error hierarchy for every Kubernetes call Roost makes: temporary or permanent.

Whoever calls the API has to decide one thing about a failure — will the same request
succeed later? — so the hierarchy is split on exactly that:

* :class:`TemporaryApiError`: try again, with backoff. :class:`ConflictError` (409: the
  object changed since it was read, or already exists) and :class:`ApiUnavailableError`
  (no answer — connection refused, TLS failure, timeout — or 408/429/5xx: the server
  cannot serve it right now).
* :class:`PermanentApiError`: the same request will fail the same way; report it once.
  :class:`InvalidError` (400/422: the object is malformed, e.g. built from a bad spec),
  :class:`ForbiddenError` (401/403: RBAC), :class:`NotFoundError` (404 where the object
  or its namespace must exist), and any other 4xx.

:func:`error_for_status` turns an HTTP answer into the right class and
:func:`from_client_exception` does the same for what the ``kubernetes`` client raises.
The operator maps the two branches onto kopf's ``TemporaryError``/``PermanentError`` at
its handler edge (:mod:`roost_operator.edge`); the agent treats
:class:`ApiUnavailableError` as "partitioned, keep state and retry"; the CLI words each
class as a one-line message.

Nothing here imports the ``kubernetes`` client at module level (the agent's footprint).
"""

from __future__ import annotations

import json
from typing import ClassVar, Literal

Transport = Literal["refused", "tls", "timeout", "network"]
"""Why no HTTP answer came: connection refused/unreachable, TLS handshake or certificate
failure, no answer in time, anything else on the wire."""


class ApiError(Exception):
    """A Kubernetes API request failed. ``status`` is None when no HTTP answer came."""

    temporary: ClassVar[bool] = False

    def __init__(
        self,
        status: int | None,
        method: str,
        path: str,
        body: str,
        *,
        transport: Transport | None = None,
    ) -> None:
        self.status = status
        self.method = method
        self.path = path
        self.body = body
        self.transport = transport
        self.reason = ""
        self.message = body[:500]
        try:
            decoded = json.loads(body)
        except (TypeError, ValueError):
            decoded = None
        if isinstance(decoded, dict):
            self.message = str(decoded.get("message") or body[:500])
            self.reason = str(decoded.get("reason") or "")
        what = f"HTTP {status}" if status is not None else f"no answer ({transport})"
        super().__init__(f"{method} {path}: {what}: {self.message}")


class TemporaryApiError(ApiError):
    """The same request may succeed later: retry with backoff."""

    temporary = True


class ConflictError(TemporaryApiError):
    """409: the object changed since it was read (or already exists)."""

    @property
    def already_exists(self) -> bool:
        return self.reason == "AlreadyExists"


class ApiUnavailableError(TemporaryApiError):
    """No answer (see :attr:`transport`), or 408/429/5xx: the server cannot serve it now."""


class PermanentApiError(ApiError):
    """The same request will fail again: report it, do not retry it."""


class InvalidError(PermanentApiError):
    """400/422: the request or the object in it is malformed."""


class ForbiddenError(PermanentApiError):
    """401/403: the credentials lack the right (see ``charts/roost/RBAC.md``)."""


class NotFoundError(PermanentApiError):
    """404 where something must exist (the object to patch, the namespace to create in)."""


def error_class(status: int) -> type[ApiError]:
    """The class of an HTTP error status (the decision table of the module docstring)."""
    if status == 409:
        return ConflictError
    if status in (408, 429) or status >= 500:
        return ApiUnavailableError
    if status in (400, 422):
        return InvalidError
    if status in (401, 403):
        return ForbiddenError
    if status == 404:
        return NotFoundError
    return PermanentApiError


def error_for_status(status: int, method: str, path: str, body: str) -> ApiError:
    """The :class:`ApiError` for an HTTP error answer."""
    return error_class(status)(status, method, path, body)


def transport_of(exc: BaseException) -> Transport | None:
    """Why a request got no answer, or None when ``exc`` is not a transport failure."""
    import ssl  # noqa: PLC0415 - only on the failure path

    import urllib3  # noqa: PLC0415 - only on the failure path

    seen: set[int] = set()
    chain: list[BaseException] = []
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        chain.append(current)
        reason = getattr(current, "reason", None)
        nxt = reason if isinstance(reason, BaseException) else None
        current = nxt or current.__cause__ or current.__context__
    if not any(isinstance(e, (urllib3.exceptions.HTTPError, OSError, TimeoutError)) for e in chain):
        return None
    if any(isinstance(e, (ssl.SSLError, urllib3.exceptions.SSLError)) for e in chain):
        return "tls"
    # Before timeouts: urllib3's NewConnectionError (refused, unreachable, no such host)
    # subclasses its ConnectTimeoutError.
    if any(
        isinstance(e, (ConnectionRefusedError, urllib3.exceptions.NewConnectionError))
        for e in chain
    ):
        return "refused"
    if any(isinstance(e, (TimeoutError, urllib3.exceptions.TimeoutError)) for e in chain):
        return "timeout"
    return "network"


def from_client_exception(exc: BaseException, method: str, path: str) -> ApiError | None:
    """The :class:`ApiError` for what the ``kubernetes`` client or urllib3 raised.

    None when ``exc`` is neither an API answer nor a transport failure (a bug: let it
    propagate).
    """
    from kubernetes.client.exceptions import ApiException  # noqa: PLC0415 - lazy client

    if isinstance(exc, ApiException) and exc.status:
        return error_for_status(int(exc.status), method, path, str(exc.body or exc.reason))
    transport = transport_of(exc)
    if transport is None:
        return None
    return ApiUnavailableError(
        None, method, path, f"{type(exc).__name__}: {exc}", transport=transport
    )
