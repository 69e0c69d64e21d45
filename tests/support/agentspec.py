"""A three-autopilot PX4 spec on loopback UDP ports nobody listens on (the links' tests
give one of its autopilots another connection)."""

from __future__ import annotations

from roost_api.autopilot import RedundantAutopilotSpec

SPEC = RedundantAutopilotSpec.model_validate(
    {
        "vehicleName": "v1",
        "primary": "fc1",
        "autopilots": [
            {
                "name": f"fc{i}",
                "stack": "px4",
                "connection": f"udp://127.0.0.1:{14540 + i}",
                "sysid": i,
                "bridgeChannel": i - 1,
            }
            for i in (1, 2, 3)
        ],
    }
)
