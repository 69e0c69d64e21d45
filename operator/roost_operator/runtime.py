"""What every handler needs at run time, created once at operator startup.

kopf hands each handler the operator's ``memo``; :func:`startup` (registered in
:mod:`roost_operator.main`) stores one :class:`Runtime` there, and handlers call
:func:`runtime` to get it typed. Nothing here talks to kopf's own API client: all of
Roost's reads and writes go through :class:`roost_kube.client.Kube`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

from roost_kube.client import Kube
from roost_operator.settings import Settings


@dataclass(frozen=True)
class Runtime:
    """The API client and settings shared by all handlers."""

    kube: Kube
    settings: Settings


def runtime(memo: Any) -> Runtime:
    """The :class:`Runtime` stored in kopf's ``memo`` at startup."""
    return cast(Runtime, memo.runtime)
