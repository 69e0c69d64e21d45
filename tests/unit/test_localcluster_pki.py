"""The throw-away control plane's PKI: who signs what, and what the API server trusts."""

from __future__ import annotations

from pathlib import Path

from cryptography import x509

from roost_localcluster import pki
from roost_localcluster.controlplane import Ports, _args_apiserver


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_the_front_proxy_has_a_ca_of_its_own(tmp_path: Path) -> None:
    keys = pki.write_pki(tmp_path / "pki")
    cluster_ca, front_proxy_ca = _cert(keys.ca_cert), _cert(keys.front_proxy_ca_cert)
    assert cluster_ca.subject != front_proxy_ca.subject
    front_proxy = _cert(keys.client_cert(pki.FRONT_PROXY))
    front_proxy.verify_directly_issued_by(front_proxy_ca)
    for who in pki.CLIENTS:
        if who is not pki.FRONT_PROXY:
            # An ordinary client's issuer is not the request-header CA's name, so the API
            # server's request-header authenticator turns it away without a signature check.
            assert _cert(keys.client_cert(who)).issuer == cluster_ca.subject


def test_the_api_server_trusts_only_the_front_proxy_ca_for_request_headers(
    tmp_path: Path,
) -> None:
    keys = pki.Pki(tmp_path / "pki")
    args = _args_apiserver(tmp_path / "bin", Ports(1, 2, 3, 4, 5, 6), keys)
    assert f"--requestheader-client-ca-file={keys.front_proxy_ca_cert}" in args
    assert f"--client-ca-file={keys.ca_cert}" in args
    assert f"--requestheader-allowed-names={pki.FRONT_PROXY.user}" in args
