"""The pinned KinD version and node image, and kind-config.yaml as data."""

from __future__ import annotations

from typing import Any

import yaml

from roost_localcluster.binaries import REPO_ROOT

KIND_DIR = REPO_ROOT / "tests" / "e2e" / "kind"


CONFIG = REPO_ROOT / "kind-config.yaml"


def kind_versions() -> dict[str, str]:
    pairs = {}
    for line in (KIND_DIR / "versions.env").read_text().splitlines():
        if line and not line.startswith("#"):
            key, _, value = line.partition("=")
            pairs[key] = value
    return pairs


def kind_config() -> dict[str, Any]:
    config: dict[str, Any] = yaml.safe_load(CONFIG.read_text())
    return config
