"""A RedundantAutopilot spec as the API server returns it (camelCase JSON): the input the
agent's generated loaders and a standalone agent's config file are tested with."""

from __future__ import annotations

SPEC = {
    "vehicleName": "v1",
    "primary": "fc1",
    "autopilots": [
        {
            "name": "fc1",
            "stack": "px4",
            "connection": "udp://127.0.0.1:14541",
            "sysid": 1,
            "bridgeChannel": 0,
        },
        {
            "name": "fc2",
            "stack": "ardupilot",
            "connection": "udp://127.0.0.1:14542",
            "sysid": 2,
            "bridgeChannel": 1,
            "componentId": 1,
            "fcuUrl": "udp://:1@127.0.0.1:2",
        },
    ],
    "failoverPolicy": {"thresholds": {"messageWarnMs": 100}, "safetyRoutine": {}},
    "command": {
        "id": "c-1",
        "action": "Switch",
        "target": "fc2",
        "issuedAt": "2026-05-01T12:00:00Z",
    },
    "hub": {"tcp": "127.0.0.1:5760", "standbyLimits": {"positionM": 2}},
}
