"""What every handler needs at run time, created once at operator startup.

:func:`roost_operator.main.main` builds the :class:`~roost_operator.settings.Settings`
and hands them to kopf in the operator's ``memo``; the startup handler adds the API
client and the controllers that keep per-process state (locks, the failover ledger).
Handlers call :func:`runtime` to get it typed. Nothing here talks to kopf's own API
client: all of Roost's reads and writes go through :class:`roost_kube.client.Kube`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

from roost_kube.client import Kube
from roost_operator.settings import Settings
from roost_operator.vehicles.controller import VehicleController


@dataclass(frozen=True)
class Runtime:
    """The API client, the settings and the Vehicle controller shared by all handlers."""

    kube: Kube
    settings: Settings
    vehicles: VehicleController

    @classmethod
    def start(cls, kube: Kube, settings: Settings) -> Runtime:
        """The runtime of an operator with ``settings`` talking through ``kube``."""
        controller = VehicleController(
            kube=kube,
            namespace=settings.namespace,
            guards=settings.guards,
            stale_after=settings.agent_stale_after,
        )
        return cls(kube=kube, settings=settings, vehicles=controller)


def runtime(memo: Any) -> Runtime:
    """The :class:`Runtime` stored in kopf's ``memo`` at startup."""
    return cast(Runtime, memo.runtime)


def settings_of(memo: Any) -> Settings:
    """The :class:`Settings` :func:`roost_operator.main.main` put in kopf's ``memo``."""
    return cast(Settings, memo.settings)
