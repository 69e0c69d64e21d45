"""Building status conditions in unit tests."""

from __future__ import annotations

from datetime import UTC, datetime

from roost_api.meta import Condition

T0 = datetime(2026, 1, 1, tzinfo=UTC)


def cond(
    type_: str, status: str = "True", reason: str = "R", message: str = "m", *, at: datetime = T0
) -> Condition:
    """A condition of ``type_``; ``at`` is its lastTransitionTime."""
    return Condition.model_validate(
        {
            "type": type_,
            "status": status,
            "reason": reason,
            "message": message,
            "lastTransitionTime": at,
        }
    )
