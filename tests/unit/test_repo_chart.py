"""The Helm chart's files as data: the chart's CRDs are byte-identical copies of the
generated ones and valid CustomResourceDefinitions for Kubernetes 1.35, the appVersion is
the distribution's version, and every value in values.yaml is documented.

Everything that runs the real ``helm`` binary (lint, template, the privileges the
rendered objects grant) is in ``tests/integration/test_chart_offline.py``.
"""

from __future__ import annotations

import functools
import re
import tomllib

import kubernetes_validate
import yaml

from roost_localcluster.binaries import REPO_ROOT
from tests.support.chart import (
    CHART_CRDS_DIR,
    CHART_DIR,
    KUBERNETES_VERSION,
)

# Value sets every rendering test runs with: the defaults, both shipped values files,
# and the switches that change which objects exist.
# Custom resources of the Prometheus operator: no schema here, checked by the tests below.


@functools.cache
def test_chart_crds_are_byte_identical_copies_of_the_generated_crds() -> None:
    generated = {p.name: p.read_text() for p in (REPO_ROOT / "crds").glob("roost.dev_*.yaml")}
    copies = {p.name: p.read_text() for p in CHART_CRDS_DIR.glob("roost.dev_*.yaml")}
    assert sorted(copies) == sorted(generated), "run `make chart-crds`"
    stale = [name for name in generated if copies[name] != generated[name]]
    assert not stale, f"charts/roost/crds out of date, run `make chart-crds`: {stale}"


def test_chart_crds_are_valid_customresourcedefinitions() -> None:
    for path in sorted(CHART_CRDS_DIR.glob("*.yaml")):
        kubernetes_validate.validate(
            yaml.safe_load(path.read_text()), KUBERNETES_VERSION, strict=True
        )


def test_every_value_in_values_yaml_is_documented() -> None:
    """Each settable key has a comment right above it, or sits inside a documented map."""
    lines = (CHART_DIR / "values.yaml").read_text().splitlines()
    undocumented = []
    documented_at: list[int] = []  # indentation of documented ancestors
    for index, line in enumerate(lines):
        match = re.match(r"^( *)([A-Za-z][\w.-]*):(.*)$", line)
        if not match:
            continue
        indent, key, rest = len(match.group(1)), match.group(2), match.group(3).strip()
        documented_at = [level for level in documented_at if level < indent]
        previous = next((p for p in reversed(lines[:index]) if p.strip()), "")
        has_comment = previous.strip().startswith("#")
        is_section = rest == "" and index + 1 < len(lines) and not has_comment
        if has_comment:
            documented_at.append(indent)
        elif not is_section and not documented_at:
            undocumented.append(key)
    assert not undocumented, f"values without a comment: {undocumented}"


def test_chart_app_version_is_the_distribution_version() -> None:
    """Default image tags are the appVersion; the images are built from pyproject.toml."""
    chart = yaml.safe_load((CHART_DIR / "Chart.yaml").read_text())
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    assert chart["appVersion"] == project["version"]
