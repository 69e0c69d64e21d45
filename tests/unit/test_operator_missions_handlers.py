"""Which of a Mission's own watch events queue its reconcile.

The kopf handlers only decide this and queue (see ``roost_operator.missions.handlers``);
this is the decision, without kopf or a cluster. Which Missions another object's event
concerns is in ``test_operator_missions_interest.py``.
"""

from __future__ import annotations

from typing import Any

import pytest

from roost_api.wellknown import FINALIZER
from roost_operator.missions.handlers import Fingerprints, _mission_relevant

META: dict[str, Any] = {
    "name": "survey",
    "namespace": "flights",
    "uid": "u1",
    "generation": 1,
    "resourceVersion": "100",
    "finalizers": [FINALIZER],
}


def _changed(before: dict[str, Any] | None, after: dict[str, Any]) -> bool:
    prints = Fingerprints()
    if before is not None:
        prints.changed("flights/survey", _mission_relevant(before))
    return prints.changed("flights/survey", _mission_relevant(after))


@pytest.mark.parametrize(
    ("change", "queued"),
    [
        (None, True),  # first seen: kopf's listing at start (a new leader) or a new Mission
        ({"resourceVersion": "101"}, False),  # the controller's own status write
        ({"finalizers": []}, False),  # kopf releasing the finalizer
        ({"generation": 2}, True),  # the spec changed: an abort in spec.command
        ({"deletionTimestamp": "2026-11-28T00:00:00Z"}, True),  # marked for deletion
        ({"uid": "u2"}, True),  # deleted and created again under the same name
    ],
)
def test_a_missions_own_event_queues_it_only_for_what_it_acts_on(
    change: dict[str, Any] | None, queued: bool
) -> None:
    if change is None:
        assert _changed(None, META) is queued
    else:
        assert _changed(META, {**META, **change}) is queued
