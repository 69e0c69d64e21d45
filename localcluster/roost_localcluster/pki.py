"""The certificates, keys and kubeconfigs a throw-away control plane needs.

A real API server insists on TLS, on client identities it can authorise with RBAC and on a
key pair for signing service-account tokens. We make them with the ``cryptography`` package
rather than by shelling out to ``openssl``: it is one typed Python API, needs no config files,
and behaves the same on every machine. Keys are ECDSA P-256: fast to generate, and accepted
by the API server both for TLS and as the ES256 service-account token signing key.

Identities (each a client certificate signed by the cluster CA):

- ``admin``: group ``system:masters``; the kubeconfig handed to tests, kubectl and helm.
- ``kube-controller-manager`` and ``kube-scheduler``: the user names the API server's
  bootstrap RBAC policy already binds, so they run with exactly their upstream rights.
- ``kwok``: group ``system:masters``. kwok impersonates every fake kubelet at once (node
  status, leases, pod status of all nodes); upstream ships no role for that, and its rights
  are not what our tests examine.
- ``kube-apiserver-kubelet-client``: group ``system:masters``; what the API server presents
  to a real node's kubelet (``kubectl logs``/``exec``/port-forward), which authorises it
  with a SubjectAccessReview like any other client (as kubeadm sets it up).
- ``front-proxy-client``: what the API server presents when it proxies to aggregated API
  servers; the controller manager and scheduler also read its CA to authenticate their own
  health endpoints (without it they log errors about a missing request-header CA).

The front proxy has a CA of its own, as kubeadm sets it up. The API server tries the
request-header authenticator first on every request that carries a client certificate,
and verifies that certificate against the request-header CA before it looks at the name:
with one CA for everything, every ordinary client's certificate passed that ECDSA check
for nothing (about 5 % of the API server's CPU while a thousand Vehicles roll out). With
its own CA, an ordinary certificate is turned away by its issuer's name, before any
signature is checked; ``--requestheader-allowed-names`` still names the one identity
that may assert proxied users.
"""

from __future__ import annotations

import base64
import datetime
import ipaddress
from dataclasses import dataclass
from pathlib import Path

import yaml
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

# The first address of the service range is the in-cluster "kubernetes" service.
SERVICE_CLUSTER_IP_RANGE = "10.96.0.0/16"
KUBERNETES_SERVICE_IP = "10.96.0.1"
SERVING_DNS_NAMES = (
    "localhost",
    "kubernetes",
    "kubernetes.default",
    "kubernetes.default.svc",
    "kubernetes.default.svc.cluster.local",
)
VALIDITY = datetime.timedelta(days=30)


@dataclass(frozen=True)
class ClientIdentity:
    """A client certificate's subject: user name (CN) and groups (O)."""

    file_stem: str
    user: str
    groups: tuple[str, ...] = ()


ADMIN = ClientIdentity("admin", "roost-admin", ("system:masters",))
CONTROLLER_MANAGER = ClientIdentity("kube-controller-manager", "system:kube-controller-manager")
SCHEDULER = ClientIdentity("kube-scheduler", "system:kube-scheduler")
KWOK = ClientIdentity("kwok", "kwok-controller", ("system:masters",))
FRONT_PROXY = ClientIdentity("front-proxy-client", "front-proxy-client")
APISERVER_KUBELET = ClientIdentity(
    "apiserver-kubelet-client", "kube-apiserver-kubelet-client", ("system:masters",)
)
CLIENTS = (ADMIN, CONTROLLER_MANAGER, SCHEDULER, KWOK, FRONT_PROXY, APISERVER_KUBELET)
# The identity kube-proxy authenticates as: the bootstrap policy binds system:node-proxier.
KUBE_PROXY = ClientIdentity("kube-proxy", "system:kube-proxy")


def node_identity(node: str) -> ClientIdentity:
    """A kubelet's identity: what the Node authoriser and NodeRestriction admission expect."""
    return ClientIdentity(f"kubelet-{node}", f"system:node:{node}", ("system:nodes",))


@dataclass(frozen=True)
class Pki:
    """Paths of the files written by :func:`write_pki` (all PEM)."""

    directory: Path

    @property
    def ca_cert(self) -> Path:
        return self.directory / "ca.crt"

    @property
    def ca_key(self) -> Path:
        return self.directory / "ca.key"

    @property
    def front_proxy_ca_cert(self) -> Path:
        return self.directory / "front-proxy-ca.crt"

    @property
    def front_proxy_ca_key(self) -> Path:
        return self.directory / "front-proxy-ca.key"

    @property
    def serving_cert(self) -> Path:
        return self.directory / "serving.crt"

    @property
    def serving_key(self) -> Path:
        return self.directory / "serving.key"

    @property
    def service_account_key(self) -> Path:
        return self.directory / "sa.key"

    @property
    def service_account_pub(self) -> Path:
        return self.directory / "sa.pub"

    def client_cert(self, who: ClientIdentity) -> Path:
        return self.directory / f"{who.file_stem}.crt"

    def client_key(self, who: ClientIdentity) -> Path:
        return self.directory / f"{who.file_stem}.key"


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _write(path: Path, data: bytes, private: bool = False) -> None:
    path.write_bytes(data)
    if private:
        path.chmod(0o600)


def _name(common_name: str, groups: tuple[str, ...] = ()) -> x509.Name:
    attributes = [x509.NameAttribute(NameOID.ORGANIZATION_NAME, g) for g in groups]
    attributes.append(x509.NameAttribute(NameOID.COMMON_NAME, common_name))
    return x509.Name(attributes)


def _issue(
    subject: x509.Name,
    key: ec.EllipticCurvePrivateKey,
    issuer: x509.Name,
    issuer_key: ec.EllipticCurvePrivateKey,
    extensions: list[tuple[x509.ExtensionType, bool]],
) -> x509.Certificate:
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + VALIDITY)
    )
    for extension, critical in extensions:
        builder = builder.add_extension(extension, critical=critical)
    return builder.sign(issuer_key, hashes.SHA256())


def _leaf_usage() -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=False,
        crl_sign=False,
        encipher_only=False,
        decipher_only=False,
    )


def _new_ca(
    common_name: str, cert_path: Path, key_path: Path
) -> tuple[x509.Name, ec.EllipticCurvePrivateKey]:
    """A self-signed CA written to ``cert_path`` and ``key_path``: its name and key."""
    ca_key = _new_key()
    ca_name = _name(common_name)
    ca_usage = x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=True,
        crl_sign=True,
        encipher_only=False,
        decipher_only=False,
    )
    ca_cert = _issue(
        ca_name,
        ca_key,
        ca_name,
        ca_key,
        [(x509.BasicConstraints(ca=True, path_length=None), True), (ca_usage, True)],
    )
    _write(cert_path, ca_cert.public_bytes(serialization.Encoding.PEM))
    _write(key_path, _key_pem(ca_key), private=True)
    return ca_name, ca_key


def write_pki(directory: Path) -> Pki:
    """Create a fresh cluster CA and front-proxy CA, a serving certificate for 127.0.0.1,
    client certificates for :data:`CLIENTS` and a service-account signing key pair in
    ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    pki = Pki(directory)
    ca_name, ca_key = _new_ca("roost-harness-ca", pki.ca_cert, pki.ca_key)
    front_proxy_ca = _new_ca(
        "roost-harness-front-proxy-ca", pki.front_proxy_ca_cert, pki.front_proxy_ca_key
    )

    serving_key = _new_key()
    alt_names: list[x509.GeneralName] = [x509.DNSName(n) for n in SERVING_DNS_NAMES]
    alt_names += [
        x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
        x509.IPAddress(ipaddress.ip_address(KUBERNETES_SERVICE_IP)),
    ]
    serving_cert = _issue(
        _name("roost-harness-serving"),
        serving_key,
        ca_name,
        ca_key,
        [
            (x509.BasicConstraints(ca=False, path_length=None), True),
            (_leaf_usage(), True),
            (x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), False),
            (x509.SubjectAlternativeName(alt_names), False),
        ],
    )
    _write(pki.serving_cert, serving_cert.public_bytes(serialization.Encoding.PEM))
    _write(pki.serving_key, _key_pem(serving_key), private=True)

    for who in CLIENTS:
        _issue_client(pki, who, *(front_proxy_ca if who is FRONT_PROXY else (ca_name, ca_key)))

    sa_key = _new_key()
    _write(pki.service_account_key, _key_pem(sa_key), private=True)
    _write(
        pki.service_account_pub,
        sa_key.public_key().public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        ),
    )
    return pki


def _issue_client(
    pki: Pki, who: ClientIdentity, ca_name: x509.Name, ca_key: ec.EllipticCurvePrivateKey
) -> None:
    key = _new_key()
    cert = _issue(
        _name(who.user, who.groups),
        key,
        ca_name,
        ca_key,
        [
            (x509.BasicConstraints(ca=False, path_length=None), True),
            (_leaf_usage(), True),
            (x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH]), False),
        ],
    )
    _write(pki.client_cert(who), cert.public_bytes(serialization.Encoding.PEM))
    _write(pki.client_key(who), _key_pem(key), private=True)


def _load_ca(pki: Pki) -> tuple[x509.Name, ec.EllipticCurvePrivateKey]:
    ca_cert = x509.load_pem_x509_certificate(pki.ca_cert.read_bytes())
    ca_key = serialization.load_pem_private_key(pki.ca_key.read_bytes(), password=None)
    assert isinstance(ca_key, ec.EllipticCurvePrivateKey)
    return ca_cert.subject, ca_key


def issue_client(pki: Pki, who: ClientIdentity) -> None:
    """A client certificate for ``who`` signed by the existing CA of ``pki``."""
    _issue_client(pki, who, *_load_ca(pki))


def issue_kubelet_serving(pki: Pki, node: str, address: str) -> tuple[Path, Path]:
    """The serving certificate of a real node's kubelet (for ``node`` and its ``address``),
    signed by the cluster CA so the API server can verify whom it streams logs from.
    Returns (certificate, key) paths in ``pki``'s directory."""
    ca_name, ca_key = _load_ca(pki)
    key = _new_key()
    alt_names: list[x509.GeneralName] = [
        x509.DNSName(node),
        x509.IPAddress(ipaddress.ip_address(address)),
    ]
    cert = _issue(
        _name(f"system:node:{node}", ("system:nodes",)),
        key,
        ca_name,
        ca_key,
        [
            (x509.BasicConstraints(ca=False, path_length=None), True),
            (_leaf_usage(), True),
            (x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), False),
            (x509.SubjectAlternativeName(alt_names), False),
        ],
    )
    cert_path = pki.directory / f"kubelet-{node}-serving.crt"
    key_path = pki.directory / f"kubelet-{node}-serving.key"
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM))
    _write(key_path, _key_pem(key), private=True)
    return cert_path, key_path


def write_kubeconfig(
    path: Path, pki: Pki, server: str, who: ClientIdentity, tls_server_name: str | None = None
) -> Path:
    """Write a self-contained kubeconfig (certificates embedded) for ``who`` at ``path``.

    ``tls_server_name`` is the name the server's certificate is checked against when
    ``server`` is an address the certificate does not list (a real node reaches the API
    server through an address of its own network).
    """

    def b64(file: Path) -> str:
        return base64.b64encode(file.read_bytes()).decode()

    name = "roost-harness"
    config = {
        "apiVersion": "v1",
        "kind": "Config",
        "clusters": [
            {
                "name": name,
                "cluster": {
                    "server": server,
                    "certificate-authority-data": b64(pki.ca_cert),
                    **({"tls-server-name": tls_server_name} if tls_server_name else {}),
                },
            }
        ],
        "users": [
            {
                "name": who.user,
                "user": {
                    "client-certificate-data": b64(pki.client_cert(who)),
                    "client-key-data": b64(pki.client_key(who)),
                },
            }
        ],
        "contexts": [{"name": name, "context": {"cluster": name, "user": who.user}}],
        "current-context": name,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    _write(path, yaml.safe_dump(config, sort_keys=False).encode(), private=True)
    return path
