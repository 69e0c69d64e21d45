"""The operator's handler timing: runs and errors reported by kind to kopf's memo, for
sync and async handlers, the async ones on a real asyncio event loop.

The pure metric pieces are in ``tests/unit/test_operator_metrics.py``; the scraped
operator process in ``tests/integration/test_operator_metrics_endpoint.py``.
"""

from __future__ import annotations

import asyncio
from typing import Any

import kopf
import pytest
from prometheus_client import CollectorRegistry, generate_latest

from roost_operator.edge import handler_edge
from roost_operator.metrics import Reconciles
from tests.support.kopfstub import Resource
from tests.support.prometheus import parse


def test_handler_edge_reports_runs_and_errors_by_kind_to_the_memo() -> None:
    registry = CollectorRegistry()
    memo = kopf.Memo(handler_timing=Reconciles(registry))
    vehicles, missions = Resource("vehicles"), Resource("missions")

    @handler_edge
    def vehicle_changed(**_: Any) -> str:
        return "done"

    @handler_edge
    def vehicle_resync(**_: Any) -> None:
        raise kopf.TemporaryError("later", delay=1)

    @handler_edge
    async def mission_deleted(**_: Any) -> None:
        raise ValueError("bug")

    assert vehicle_changed(memo=memo, resource=vehicles) == "done"
    assert vehicle_changed(resource=vehicles) == "done"  # no timing in the memo: not counted
    with pytest.raises(kopf.TemporaryError):
        vehicle_resync(memo=memo, resource=vehicles)
    with pytest.raises(ValueError, match="bug"):
        asyncio.run(mission_deleted(memo=memo, resource=missions))
    got = parse(generate_latest(registry).decode())
    count = "roost_operator_reconcile_duration_seconds_count"
    assert got[(count, (("handler", "vehicle_changed"), ("resource", "vehicles")))] == 1
    assert got[(count, (("handler", "vehicle_resync"), ("resource", "vehicles")))] == 1
    assert got[(count, (("handler", "mission_deleted"), ("resource", "missions")))] == 1
    errors = "roost_operator_reconcile_errors_total"
    key = (("error", "temporary"), ("handler", "vehicle_resync"), ("resource", "vehicles"))
    assert got[(errors, key)] == 1
    key = (("error", "other"), ("handler", "mission_deleted"), ("resource", "missions"))
    assert got[(errors, key)] == 1
    assert not [k for k in got if k[0] == errors and ("handler", "vehicle_changed") in k[1]]
