"""Which watch events queue a Vehicle reconcile, and when a silent agent's vehicle is due.

The kopf handlers only decide this and queue (see ``roost_operator.vehicles.handlers``);
these are the decisions, without kopf or a cluster.
"""

from __future__ import annotations

import math
import time
from datetime import UTC, datetime, timedelta
from types import SimpleNamespace
from typing import Any

import pytest

from roost_api.wellknown import ANNOTATION_PAUSE_FAILOVER_ACTIONS, FINALIZER, PREFIX
from roost_operator.settings import Settings
from roost_operator.vehicles.handlers import (
    STALE_MARGIN_S,
    Fingerprints,
    _stale_deadline,
    _vehicle_relevant,
)
from roost_operator.vehicles.watched import owned_relevant, pod_relevant

META: dict[str, Any] = {
    "name": "drone-1",
    "generation": 3,
    "labels": {"fleet": "lab"},
    "annotations": {},
    "resourceVersion": "100",
}


def _changed(before: dict[str, Any], after: dict[str, Any]) -> bool:
    prints = Fingerprints()
    prints.changed("drone-1", _vehicle_relevant(before))
    return prints.changed("drone-1", _vehicle_relevant(after))


def test_the_controllers_own_status_write_queues_nothing() -> None:
    # a status write bumps resourceVersion only (status is not in the generation)
    assert not _changed(META, {**META, "resourceVersion": "101"})


@pytest.mark.parametrize("finalizer", ["example.org/keep", FINALIZER])
def test_a_finalizer_queues_nothing(finalizer: str) -> None:
    # another controller's, or kopf removing the one earlier versions put on Vehicles:
    # Vehicles need none (their leftovers carry their label)
    assert not _changed(META, {**META, "finalizers": [finalizer]})


def test_kopfs_bookkeeping_annotation_queues_nothing() -> None:
    kopf_note = {f"{PREFIX}last-handled-configuration": "{...}"}
    assert not _changed(META, {**META, "annotations": kopf_note})


@pytest.mark.parametrize(
    "change",
    [
        {"generation": 4},  # the spec changed
        {"labels": {"fleet": "field"}},
        {"annotations": {ANNOTATION_PAUSE_FAILOVER_ACTIONS: "true"}},  # a guard
        {"deletionTimestamp": "2026-11-24T06:00:00Z"},
    ],
)
def test_what_the_controller_acts_on_queues_a_reconcile(change: dict[str, Any]) -> None:
    assert _changed(META, {**META, **change})


def _runtime(stale_s: float) -> Any:
    return SimpleNamespace(settings=Settings(agent_stale_after=timedelta(seconds=stale_s)))


def test_no_report_time_means_no_deadline() -> None:
    assert _stale_deadline(_runtime(30), None) is None
    assert _stale_deadline(_runtime(30), "not a time") is None


@pytest.mark.parametrize("stale_s", [6.0, 6.5, 30.0])
def test_the_deadline_falls_where_whole_second_clocks_see_the_report_stale(
    stale_s: float,
) -> None:
    """reportedAt and the controller's clock are whole seconds: the reconcile at the
    deadline must find ``floor(now) - reportedAt > stale``."""
    wall = datetime.now(UTC)
    reported = wall.replace(microsecond=0) - timedelta(seconds=2)
    text = reported.isoformat().replace("+00:00", "Z")
    mono = time.monotonic()
    deadline = _stale_deadline(_runtime(stale_s), text)
    assert deadline is not None
    fires_at = wall + timedelta(seconds=deadline - mono)
    seen_age = math.floor(fires_at.timestamp()) - reported.timestamp()
    assert seen_age > stale_s
    assert (fires_at - reported).total_seconds() <= stale_s + STALE_MARGIN_S + 0.1


def test_a_report_already_stale_is_due_now() -> None:
    old = (datetime.now(UTC) - timedelta(minutes=5)).isoformat().replace("+00:00", "Z")
    deadline = _stale_deadline(_runtime(30), old)
    assert deadline is not None
    assert deadline - time.monotonic() <= STALE_MARGIN_S


def _pod(phase: str = "Running", ready: str = "True", **extra: Any) -> dict[str, Any]:
    return {
        "metadata": {"labels": {"app": "mavros"}, "annotations": {}},
        "status": {
            "phase": phase,
            "conditions": [
                {"type": "Ready", "status": ready, "lastTransitionTime": extra.pop("at", "t0")}
            ],
            **extra,
        },
    }


def test_a_pods_status_noise_queues_nothing() -> None:
    before = _pod(at="t0", podIP="10.0.0.1")
    after = _pod(at="t1", podIP="10.0.0.2", containerStatuses=[{"restartCount": 1}])
    assert pod_relevant(before) == pod_relevant(after)


def test_pod_progress_and_hand_edits_queue_a_reconcile() -> None:
    base = _pod("Pending", "False")
    assert pod_relevant(base) != pod_relevant(_pod("Running", "False"))
    assert pod_relevant(_pod("Running", "False")) != pod_relevant(_pod())
    leaving = _pod()
    leaving["metadata"]["deletionTimestamp"] = "t2"
    assert pod_relevant(_pod()) != pod_relevant(leaving)
    edited = {"metadata": {"labels": {}}, "data": {"vehicle.yaml": "edited by hand"}}
    assert owned_relevant({"metadata": {"labels": {}}, "data": {}}) != owned_relevant(edited)
