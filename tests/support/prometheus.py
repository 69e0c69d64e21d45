"""Prometheus samples as a test reads them: exposition text read back with
prometheus_client's parser, keyed by (name, sorted labels)."""

from __future__ import annotations

from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def parse(text: str) -> Samples:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def samples(registry: object) -> Samples:
    """What ``registry`` exposes now."""
    return parse(generate_latest(registry).decode())  # type: ignore[arg-type]
