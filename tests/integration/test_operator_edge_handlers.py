"""roost_operator.edge: sync and async kopf handlers leave with the same kopf errors.

The handlers run as kopf runs them: sync ones directly, async ones on an asyncio event
loop (whose self-pipe is a socket pair). The decision table is in ``tests/unit``.
"""

from __future__ import annotations

import asyncio
from typing import Any

import kopf
import pytest

from roost_kube.errors import error_for_status
from roost_operator.edge import (
    handler_edge,
)
from tests.support.kopfstub import Resource


def test_sync_and_async_handlers_are_wrapped_alike() -> None:
    @handler_edge
    def sync_handler(**_: Any) -> None:
        raise error_for_status(422, "POST", "/jobs", '{"message": "bad name"}')

    @handler_edge
    async def async_handler(**_: Any) -> str:
        raise error_for_status(409, "PATCH", "/v", "{}")

    @handler_edge
    async def fine(**_: Any) -> str:
        return "ok"

    with pytest.raises(kopf.PermanentError, match="Mission ns/m: POST /jobs: HTTP 422: bad name"):
        sync_handler(resource=Resource(kind="Mission"), name="m", namespace="ns")
    with pytest.raises(kopf.TemporaryError):
        asyncio.run(async_handler(name="v"))
    assert asyncio.run(fine()) == "ok"
    assert asyncio.iscoroutinefunction(async_handler)
