"""The Vehicle status patch: only changed owned fields."""

from __future__ import annotations

from roost_api.vehicle import VehicleStatus
from roost_operator.vehicles.status import status_patch


def test_status_patch_sends_only_changed_owned_fields_with_nulls_for_removals() -> None:
    old = VehicleStatus.model_validate(
        {
            "nodeName": "node-a",
            "fcuUrl": "udp://a",
            "managedLabels": ["x"],
            "activeAutopilot": "fc1",
        }
    )
    new = VehicleStatus.model_validate(
        {"fcuUrl": "udp://a", "managedLabels": [], "activeAutopilot": "fc2"}
    )
    fields = ("nodeName", "fcuUrl", "managedLabels")
    assert status_patch(old, new, fields) == {"nodeName": None, "managedLabels": []}
    assert status_patch(new, new, fields) is None
