"""YAML parsed by libyaml when PyYAML was built with it.

``yaml.safe_load`` is PyYAML's pure-Python parser; a rendered chart with its CRDs is
several megabytes of YAML, and parsing it that way was most of the chart tests' time
(about 0.4 s per value set and CRD file). The C parser builds the same objects from the
same safe subset of YAML; without libyaml this falls back to the pure-Python one.
"""

from __future__ import annotations

from typing import Any

import yaml

SafeLoader: type[yaml.SafeLoader] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load(text: str) -> Any:
    """One YAML document, as ``yaml.safe_load``."""
    return yaml.load(text, Loader=SafeLoader)


def load_all(text: str) -> list[Any]:
    """Every document, as ``yaml.safe_load_all``."""
    return list(yaml.load_all(text, Loader=SafeLoader))
