"""The one attribute or two of a kopf resource that Roost's handler edge reads.

A stand-in because kopf builds its resources itself when it runs handlers; the handler
edge only names the kind and counts by plural.
"""

from __future__ import annotations


class Resource:
    def __init__(self, plural: str = "missions", kind: str | None = None) -> None:
        self.plural = plural
        self.kind = kind
