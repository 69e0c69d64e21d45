"""The agent's minimal Kubernetes transport: where its credentials come from.

kubectl's merge (the first file to define a cluster, user or context wins; relative
paths start at the file that names them), inline and file credentials, the pod's
service account, and the refusal of what it does not do (exec and auth-provider
plugins). Requests through it are tested against the real API server in
``tests/integration/test_kube_client.py``.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_kube.kubeconfig import KubeconfigError
from roost_kube.transport import from_kubeconfig, in_cluster


def _write(path: Path, doc: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(doc))
    return path


def _config(
    context: str, cluster: dict[str, Any], user: dict[str, Any], current: str | None = None
) -> dict[str, Any]:
    return {
        "apiVersion": "v1",
        "kind": "Config",
        "current-context": current or context,
        "contexts": [{"name": context, "context": {"cluster": context, "user": context}}],
        "clusters": [{"name": context, "cluster": cluster}],
        "users": [{"name": context, "user": user}],
    }


def test_inline_certificates_and_the_server(tmp_path: Path) -> None:
    pem = b"-----BEGIN CERTIFICATE-----\nx\n-----END CERTIFICATE-----\n"
    encoded = base64.b64encode(pem).decode()
    cluster = {
        "server": "https://127.0.0.1:6443/",
        "certificate-authority-data": encoded,
        "tls-server-name": "kubernetes",
    }
    user = {"client-certificate-data": encoded, "client-key-data": encoded}
    got = from_kubeconfig([_write(tmp_path / "a", _config("sandbox", cluster, user))])
    assert got.host == "https://127.0.0.1:6443"
    assert got.ca_data == got.cert_data == got.key_data == pem
    assert got.verify and got.token is None and got.tls_server_name == "kubernetes"


def test_relative_paths_start_at_the_file_that_names_them(tmp_path: Path) -> None:
    (tmp_path / "certs").mkdir()
    cluster = {"server": "https://h:1", "certificate-authority": "certs/ca.crt"}
    user = {"client-certificate": "certs/c.crt", "client-key": "/abs/c.key"}
    got = from_kubeconfig([_write(tmp_path / "a", _config("x", cluster, user))])
    assert got.ca_file == tmp_path / "certs" / "ca.crt"
    assert got.cert_file == tmp_path / "certs" / "c.crt" and got.key_file == Path("/abs/c.key")


def test_the_first_file_to_define_a_name_wins(tmp_path: Path) -> None:
    first = _write(tmp_path / "first", _config("x", {"server": "https://first:1"}, {"token": "t1"}))
    second = _write(
        tmp_path / "second",
        _config("x", {"server": "https://second:1"}, {"token": "t2"}, current="x"),
    )
    got = from_kubeconfig([first, second])
    assert (got.host, got.token) == ("https://first:1", "t1")
    assert from_kubeconfig([second, first]).host == "https://second:1"


@pytest.mark.parametrize("auth", ["exec", "auth-provider"])
def test_plugins_are_refused_with_what_to_use_instead(tmp_path: Path, auth: str) -> None:
    path = _write(tmp_path / "a", _config("x", {"server": "https://h:1"}, {auth: {"x": 1}}))
    with pytest.raises(KubeconfigError, match=f"{auth}.*client certificate or a token"):
        from_kubeconfig([path])


def test_a_cluster_without_a_server_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "a", _config("x", {}, {"token": "t"}))
    with pytest.raises(KubeconfigError, match="has no server"):
        from_kubeconfig([path])


def test_the_pods_service_account(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("KUBERNETES_SERVICE_HOST", raising=False)
    assert in_cluster(tmp_path) is None  # not in a pod
    monkeypatch.setenv("KUBERNETES_SERVICE_HOST", "fd00::1")
    monkeypatch.setenv("KUBERNETES_SERVICE_PORT", "443")
    assert in_cluster(tmp_path) is None  # no token mounted
    (tmp_path / "token").write_text("abc\n")
    got = in_cluster(tmp_path)
    assert got is not None and got.host == "https://[fd00::1]:443"
    assert got.token_file == tmp_path / "token" and got.ca_file == tmp_path / "ca.crt"
