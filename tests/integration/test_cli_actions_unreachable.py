"""``roost`` naming an unreachable API server (a closed loopback port) and what to do.

The decisions behind ``roost abort`` and ``roost estop`` are tables in
``tests/unit/test_cli_actions.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from roost_api.ports import free_port
from roost_cli.cluster import Fleet, Target
from roost_cli.errors import CliError


def test_an_unreachable_api_server_is_named_with_what_to_do(tmp_path: Path) -> None:
    port = free_port()  # nobody listens on it
    kubeconfig = tmp_path / "kubeconfig"
    kubeconfig.write_text(
        yaml.safe_dump(
            {
                "apiVersion": "v1",
                "kind": "Config",
                "clusters": [{"name": "c", "cluster": {"server": f"http://127.0.0.1:{port}"}}],
                "users": [{"name": "u", "user": {"token": "t"}}],
                "contexts": [{"name": "x", "context": {"cluster": "c", "user": "u"}}],
                "current-context": "x",
            }
        )
    )
    fleet = Fleet(Target(kubeconfig, "$KUBECONFIG"))
    with pytest.raises(CliError) as error:
        fleet.vehicles()
    message = str(error.value)
    assert f"cannot reach the API server at http://127.0.0.1:{port}" in message
    assert "roost sandbox up" in message
