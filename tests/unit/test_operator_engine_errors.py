"""Which reconcile failures the engine's queue retries, read from the API layer's own
split (no kopf types)."""

from __future__ import annotations

import pytest

from roost_kube.errors import error_for_status
from roost_operator.engine.errors import error_kind, is_permanent
from roost_operator.engine.workqueue import Permanent


@pytest.mark.parametrize(
    ("error", "permanent"),
    [
        (Permanent("the spec cannot be written"), True),
        (error_for_status(422, "PATCH", "/x", "{}"), True),
        (error_for_status(403, "PATCH", "/x", "{}"), True),
        (error_for_status(409, "PATCH", "/x", "{}"), False),
        (error_for_status(503, "GET", "/x", "{}"), False),
        (RuntimeError("a bug or a dropped connection"), False),
    ],
)
def test_which_failures_are_retried(error: BaseException, permanent: bool) -> None:
    assert is_permanent(error) is permanent


def test_failures_are_counted_by_kind() -> None:
    assert error_kind(error_for_status(422, "PATCH", "/x", "{}")) == "permanent"
    assert error_kind(error_for_status(409, "PATCH", "/x", "{}")) == "temporary"
    assert error_kind(RuntimeError("a bug")) == "other"
