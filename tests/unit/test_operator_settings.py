"""The operator's settings (roost_operator.settings): built from the environment once."""

from __future__ import annotations

import dataclasses
import inspect
from datetime import timedelta
from pathlib import Path

import roost_operator
from roost_operator.autopilots.guards import FleetGuards
from roost_operator.settings import (
    KopfTimings,
    MissionTimings,
    Settings,
    load_guards,
    load_settings,
)


def test_fleet_guards_come_from_the_environment() -> None:
    guards = load_guards(
        {
            "ROOST_FAILOVER_MAX_CONCURRENT": "2",
            "ROOST_FAILOVER_LATCH_AFTER": "4",
            "ROOST_FAILOVER_LATCH_WINDOW_SECONDS": "60",
            "ROOST_FAILOVER_ACTION_TIMEOUT_SECONDS": "15",
            "ROOST_FAILOVER_PAUSED": "yes",
        }
    )
    assert guards == FleetGuards(
        max_concurrent_actions=2,
        latch_after=4,
        latch_window=timedelta(seconds=60),
        action_timeout=timedelta(seconds=15),
        paused=True,
    )
    assert load_guards({}) == FleetGuards()


def test_an_empty_environment_gives_the_documented_defaults() -> None:
    settings = load_settings({})
    assert settings == Settings()
    assert settings.agent_stale_after == timedelta(seconds=30)
    assert settings.namespace == "roost-system"


def test_every_variable_reaches_its_field() -> None:
    settings = load_settings(
        {
            "ROOST_NAMESPACE": "fleet-ops",
            "ROOST_PEERING": "blue",
            "ROOST_AGENT_IMAGE": "registry.example/roost-agent:1.4.0",
            "ROOST_RESYNC_SECONDS": "5",
            "ROOST_AGENT_STALE_SECONDS": "4.5",
            "ROOST_FAILOVER_PAUSED": "true",
            "ROOST_MISSION_RESYNC_SECONDS": "3",
            "ROOST_MISSION_ERROR_BACKOFF_SECONDS": "0.5",
            "ROOST_WATCH_SERVER_TIMEOUT_SECONDS": "60",
            "ROOST_WATCH_CLIENT_TIMEOUT_SECONDS": "70",
            "ROOST_CONNECT_TIMEOUT_SECONDS": "3",
            "ROOST_REQUEST_TIMEOUT_SECONDS": "20",
        }
    )
    assert settings.namespace == "fleet-ops"
    assert settings.peering == "blue"
    assert settings.agent_image == "registry.example/roost-agent:1.4.0"
    assert settings.resync_seconds == 5.0
    assert settings.agent_stale_after == timedelta(seconds=4.5)
    assert settings.guards.paused is True
    assert settings.missions == dataclasses.replace(
        MissionTimings(), resync_seconds=3.0, error_backoff_seconds=0.5
    )
    assert settings.kopf == KopfTimings(
        watch_server_timeout_seconds=60,
        watch_client_timeout_seconds=70.0,
        connect_timeout_seconds=3.0,
        request_timeout_seconds=20.0,
    )


def test_every_field_is_documented() -> None:
    """kopf's model: each field has its own docstring right below it."""
    for cls in (Settings, MissionTimings, KopfTimings):
        source = inspect.getsource(cls)
        for field in dataclasses.fields(cls):
            after = source.split(f"    {field.name}:", 1)[1].split("\n", 2)
            assert after[1].strip().startswith('"""'), f"{cls.__name__}.{field.name}"


def test_no_module_reads_the_environment() -> None:
    """Settings are read once, in main(); nothing reads os.environ on import or later."""
    package = Path(roost_operator.__file__).parent
    readers = [
        str(path.relative_to(package))
        for path in package.rglob("*.py")
        if "os.environ" in path.read_text() or "getenv" in path.read_text()
    ]
    assert readers == ["main.py"]
