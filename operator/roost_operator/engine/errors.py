"""Whether a failed reconcile may succeed if tried again: the engine's one rule.

:mod:`roost_kube.errors` already splits every API failure into temporary (conflict,
timeout, 5xx, 429) and permanent (400/422/403/404-on-write). The engine's queue reads
that split directly: a permanent failure is reported once and not retried until the
object changes, anything else (a temporary API error, a bug, a dropped connection) is
retried with backoff. kopf's error types are for kopf's handlers only
(:mod:`roost_operator.edge`); nothing here imports kopf.
"""

from __future__ import annotations

from roost_kube.errors import ApiError
from roost_operator.engine.workqueue import Permanent


def is_permanent(error: BaseException) -> bool:
    """Whether ``error`` will repeat until the object changes."""
    if isinstance(error, Permanent):
        return True
    return isinstance(error, ApiError) and not error.temporary


def error_kind(error: BaseException) -> str:
    """``temporary``, ``permanent`` or ``other``, as the metrics count reconcile failures."""
    if is_permanent(error):
        return "permanent"
    return "temporary" if isinstance(error, ApiError) else "other"
