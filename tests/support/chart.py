"""Roost's Helm chart as tests use it: render it, lint it, install it.

One place that knows where the chart lives and how values reach helm (always through a
values file, never ``--set``, so nested keys and lists need no escaping), for the
offline chart tests (``tests/integration/test_chart_offline.py``) and the control-plane ones
(``tests/e2e/test_chart.py``). Rendering uses the real ``helm`` binary from
:mod:`roost_localcluster.clients`, not a template engine of our own.
"""

from __future__ import annotations

import subprocess
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.clients import tool_path
from tests.support import yamldocs

CHART_DIR = REPO_ROOT / "charts" / "roost"
CHART_CRDS_DIR = CHART_DIR / "crds"
HARDWARE_VALUES = CHART_DIR / "values-hardware.yaml"
KIND_VALUES = CHART_DIR / "values-kind.yaml"
KUBERNETES_VERSION = "1.35.0"
"""The Kubernetes release the chart's objects and CRDs are validated against."""

Manifest = dict[str, Any]


class ChartError(RuntimeError):
    """helm refused to render the chart; the message is helm's own error output."""


def _values_file(values: Mapping[str, Any], directory: Path) -> Path:
    path = directory / "values.yaml"
    path.write_text(yaml.safe_dump(dict(values)))
    return path


def helm(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess[str]:
    """Run the pinned helm binary; output is captured, the exit status is not checked."""
    return subprocess.run(
        [str(tool_path("helm")), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


def render(
    values: Mapping[str, Any] | None = None,
    *,
    values_files: Sequence[Path] = (),
    release: str = "roost",
    namespace: str = "roost-system",
    include_crds: bool = False,
    kube_version: str | None = None,
) -> list[Manifest]:
    """``helm template`` the chart; the documents it prints, parsed, in order.

    Raises :class:`ChartError` (helm's message) when the chart refuses the values.
    """
    with tempfile.TemporaryDirectory(prefix="roost-chart-") as tmp:
        args = ["template", release, str(CHART_DIR), "--namespace", namespace]
        for path in values_files:
            args += ["--values", str(path)]
        if values:
            args += ["--values", str(_values_file(values, Path(tmp)))]
        if include_crds:
            args.append("--include-crds")
        if kube_version:
            args += ["--kube-version", kube_version]
        result = helm(*args)
    if result.returncode != 0:
        raise ChartError(result.stderr.strip())
    return [doc for doc in yamldocs.load_all(result.stdout) if doc]


def find(manifests: Sequence[Manifest], kind: str, name_suffix: str = "") -> Manifest:
    """The one rendered object of ``kind`` whose name ends with ``name_suffix``."""
    matches = [
        m for m in manifests if m["kind"] == kind and m["metadata"]["name"].endswith(name_suffix)
    ]
    if len(matches) != 1:
        names = [m["metadata"]["name"] for m in matches]
        raise LookupError(f"expected one {kind} *{name_suffix}, rendered {names}")
    return matches[0]


def install_args(
    release: str,
    namespace: str,
    values: Mapping[str, Any] | None,
    values_dir: Path,
) -> list[str]:
    """Arguments of ``helm upgrade --install`` for :meth:`Cluster.helm`.

    ``--force-conflicts``: Helm 4 installs the chart's CRDs with server-side apply, which
    conflicts with CRDs a test applied earlier with client-side ``kubectl apply``; on a
    fresh cluster it changes nothing.
    """
    args = [
        "upgrade",
        "--install",
        release,
        str(CHART_DIR),
        "--namespace",
        namespace,
        "--create-namespace",
        "--force-conflicts",
        "--wait",
        "--timeout",
        "3m",
    ]
    # The harness clusters have no volume provisioner: the operator's Mission records
    # go to an emptyDir there (a claim would stay Pending, and with it the operator).
    args += ["--set", "operator.records.persistence.enabled=false"]
    if values:
        args += ["--values", str(_values_file(values, values_dir))]
    return args
