"""``roost`` against a real API server: a user error is one line and a non-zero exit."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from roost_localcluster.cluster import Cluster

pytestmark = pytest.mark.cluster

ROOST = Path(sys.executable).parent / "roost"


def roost(cluster: Cluster, tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            str(ROOST),
            "--kubeconfig",
            str(cluster.kubeconfig),
            "--sandbox-dir",
            str(tmp_path),
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_missions_in_a_namespace_that_does_not_exist_is_an_error(
    roost_crds: Cluster, tmp_path: Path
) -> None:
    result = roost(roost_crds, tmp_path, "missions", "-n", "no-such-namespace-typo")
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "namespace 'no-such-namespace-typo' does not exist" in lines[0]


def test_missions_in_an_existing_namespace_lists_them(roost_crds: Cluster, tmp_path: Path) -> None:
    result = roost(roost_crds, tmp_path, "missions", "-n", "default", "-o", "json")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().startswith("[")
