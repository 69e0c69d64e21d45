"""The edge of every kopf handler: API errors become kopf's, and every run is timed.

Every handler the operator registers goes through :func:`handler_edge` (the controllers'
``register`` functions wrap them), so this module is the one place where a handler run
begins and ends.

Errors: temporary → retry, permanent → stop.

:mod:`roost_kube.errors` splits every API failure into temporary (conflict, timeout,
5xx, 429: the same request may succeed later) and permanent (400/422/403/404-on-write:
it will fail the same way again). kopf has the same split —
``kopf.TemporaryError(delay=…)`` retries the handler after the delay,
``kopf.PermanentError`` marks it failed and never retries — so the mapping is one
function, :func:`kopf_error`, applied at the edge of a handler by :func:`handler_edge`.
The layer itself never imports kopf (the agent and the CLI use it too).

Every message names the object (kind namespace/name), so an operator log line says
which object failed.

Timing: when the operator's memo carries a :class:`HandlerTiming` (``memo.handler_timing``,
the metrics of :mod:`roost_operator.metrics`), every run reports its resource plural,
handler name, duration and how it failed, if it did. Without one (metrics off, unit tests)
nothing is measured; kopf's own registry is never touched.
"""

from __future__ import annotations

import functools
import inspect
import time
from collections.abc import Awaitable, Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any, Final, Protocol, TypeVar, cast

import kopf

from roost_kube.errors import ApiError, ApiUnavailableError, ConflictError

FIELD_MANAGER: Final = "roost-operator"
"""Who the operator's writes are from (server-side apply field manager, Event source)."""

CONFLICT_DELAY_S: Final = 1.0
"""Retry delay after a 409: someone wrote in between; re-read and retry soon."""
UNAVAILABLE_DELAY_S: Final = 10.0
"""Retry delay when the API server gave no usable answer (timeout, 5xx, 429)."""

F = TypeVar("F", bound=Callable[..., Any])


def object_name(kwargs: Mapping[str, Any]) -> str:
    """``Kind namespace/name`` of the object a kopf handler was called for."""
    resource = kwargs.get("resource")
    kind = getattr(resource, "kind", None) or getattr(resource, "plural", None) or "object"
    name = kwargs.get("name") or "?"
    namespace = kwargs.get("namespace")
    return f"{kind} {namespace}/{name}" if namespace else f"{kind} {name}"


def kopf_error(error: ApiError, what: str) -> kopf.TemporaryError | kopf.PermanentError:
    """The kopf error for an API error met while handling ``what``."""
    message = f"{what}: {error}"
    if isinstance(error, ConflictError):
        return kopf.TemporaryError(message, delay=CONFLICT_DELAY_S)
    if isinstance(error, ApiUnavailableError) or error.temporary:
        return kopf.TemporaryError(message, delay=UNAVAILABLE_DELAY_S)
    return kopf.PermanentError(message)


def describe(kind: str, name: str, namespace: str | None = None) -> str:
    """``Kind namespace/name`` (or ``Kind name`` for a cluster-scoped object)."""
    return f"{kind} {namespace}/{name}" if namespace else f"{kind} {name}"


@contextmanager
def at_the_edge(kind: str, name: str, *, namespace: str | None = None) -> Iterator[None]:
    """Map API errors of the block to kopf's, naming the object the work was about.

    For handlers that work on another object than their own (a Node event reconciling a
    Vehicle): the message must name the object that failed, not the one that triggered.
    """
    try:
        yield
    except ApiError as error:
        raise kopf_error(error, describe(kind, name, namespace)) from error


class HandlerTiming(Protocol):
    """Where handler runs are reported (the operator's reconcile metrics)."""

    def observe(self, resource: str, handler: str, seconds: float, error: str | None) -> None:
        """One run of ``handler`` for ``resource`` took ``seconds``; ``error`` is
        ``temporary``, ``permanent`` or ``other`` when it raised, else ``None``."""


def error_kind(error: BaseException) -> str:
    """How a handler run failed, as kopf will treat it."""
    if isinstance(error, kopf.TemporaryError):
        return "temporary"
    if isinstance(error, kopf.PermanentError):
        return "permanent"
    return "other"


class _Run:
    """One handler run: maps its API error and reports its time when it ends."""

    def __init__(self, fn: Callable[..., Any], kwargs: Mapping[str, Any]) -> None:
        self.kwargs = kwargs
        self.handler = fn.__name__
        self.started = time.perf_counter()
        self.error: str | None = None

    def failed(self, error: Exception) -> Exception:
        """The exception to raise for ``error`` (a kopf error for an API error)."""
        raised: Exception = error
        if isinstance(error, ApiError):
            raised = kopf_error(error, object_name(self.kwargs))
        self.error = error_kind(raised)
        return raised

    def ended(self) -> None:
        timing = getattr(self.kwargs.get("memo"), "handler_timing", None)
        if timing is None:
            return
        resource = str(getattr(self.kwargs.get("resource"), "plural", "") or "")
        timing.observe(resource, self.handler, time.perf_counter() - self.started, self.error)


def handler_edge(fn: F) -> F:
    """Wrap a kopf handler (sync or async): API errors leave it as kopf errors, and its
    runs are timed. Sync stays sync (kopf runs it in a thread), async stays async."""
    if inspect.iscoroutinefunction(fn):
        coroutine = cast(Callable[..., Awaitable[Any]], fn)

        @functools.wraps(fn)
        async def async_edge(*args: Any, **kwargs: Any) -> Any:
            run = _Run(fn, kwargs)
            try:
                return await coroutine(*args, **kwargs)
            except Exception as error:
                raised = run.failed(error)
                if raised is error:
                    raise
                raise raised from error
            finally:
                run.ended()

        return cast(F, async_edge)

    @functools.wraps(fn)
    def edge(*args: Any, **kwargs: Any) -> Any:
        run = _Run(fn, kwargs)
        try:
            return fn(*args, **kwargs)
        except Exception as error:
            raised = run.failed(error)
            if raised is error:
                raise
            raise raised from error
        finally:
            run.ended()

    return cast(F, edge)
