"""``roost`` against a real API server: a user error is one line and a non-zero exit."""

from __future__ import annotations

import base64
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from roost_agent.signing import read_keys
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


def _entries(cluster: Cluster, namespace: str, name: str) -> dict[str, str]:
    found = cluster.kubectl("get", "secret", name, "-n", namespace, "-o", "json")
    secret = json.loads(found.stdout)
    return {k: base64.b64decode(v).decode() for k, v in (secret.get("data") or {}).items()}


def test_keys_create_and_rotate_a_vehicle_key_without_showing_it(
    cluster: Cluster, tmp_path: Path
) -> None:
    created = roost(cluster, tmp_path, "keys", "create", "drone-keys-1", "-n", "default")
    assert created.returncode == 0, created.stderr
    first = _entries(cluster, "default", "roost-signing-drone-keys-1")
    assert first["key"] == hashlib.sha256(first["passphrase"].encode()).hexdigest()
    assert first["previous"] == ""
    again = roost(cluster, tmp_path, "keys", "create", "drone-keys-1", "-n", "default")
    assert again.returncode == 1 and "roost keys rotate drone-keys-1" in again.stderr
    rotated = roost(cluster, tmp_path, "keys", "rotate", "drone-keys-1", "-n", "default")
    assert rotated.returncode == 0, rotated.stderr
    second = _entries(cluster, "default", "roost-signing-drone-keys-1")
    assert second["previous"] == first["key"] and second["key"] != first["key"]
    for result in (created, again, rotated):
        for secret in (first["key"], first["passphrase"], second["key"], second["passphrase"]):
            assert secret not in result.stdout + result.stderr
    # what the chart mounts (key and previous under the Vehicle's name) is what the agent reads
    vehicle_dir = tmp_path / "keys" / "drone-keys-1"
    vehicle_dir.mkdir(parents=True)
    for entry in ("key", "previous"):
        (vehicle_dir / entry).write_text(second[entry])
    assert read_keys(tmp_path / "keys", "drone-keys-1") == (
        bytes.fromhex(second["key"]),
        bytes.fromhex(first["key"]),
    )
    missing = roost(cluster, tmp_path, "keys", "rotate", "drone-keys-2", "-n", "default")
    assert missing.returncode == 1 and "roost keys create drone-keys-2" in missing.stderr
