"""Operator settings read once from the environment, so the chart can set them.

Environment variables (all optional):

``ROOST_NAMESPACE``
    Namespace of the objects the operator owns for vehicles (ConfigMaps, component
    Deployments). Default ``roost-system``; created at startup when missing.
``ROOST_RESYNC_SECONDS``
    Period of the level-based resync of every Vehicle (puts back hand edits of Roost's
    node labels, converges after missed events). Default 60. A resync that finds
    nothing to change makes no API writes, so a short period costs reads only.
``ROOST_PEERING``
    Name of the kopf peering object (one per operator deployment). Default ``roost``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class Settings:
    """What the environment configures; see the module docstring."""

    namespace: str = "roost-system"
    resync_seconds: float = 60.0
    peering: str = "roost"


def load_settings(environ: Mapping[str, str]) -> Settings:
    """Settings from ``environ`` with defaults for what is unset."""
    defaults = Settings()
    return Settings(
        namespace=environ.get("ROOST_NAMESPACE", defaults.namespace),
        resync_seconds=float(environ.get("ROOST_RESYNC_SECONDS", defaults.resync_seconds)),
        peering=environ.get("ROOST_PEERING", defaults.peering),
    )


SETTINGS = load_settings(os.environ)
