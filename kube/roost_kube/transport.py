"""How a :class:`roost_kube.client.Kube` reaches the API server: two transports, one client.

Why two: the ``kubernetes`` package's ``ApiClient`` brings its config loaders (every
auth plugin kubectl knows) and, imported, its generated models: nearly as much memory as
the rest of the node agent (docs/performance.md#memory). The operator and the CLI run
where that does not matter and keep it (:class:`ApiClientTransport`). The node agent
runs on a vehicle's companion computer and needs one cluster and two ways in: the
service account it runs as (token and CA from the pod's mounted secret, the token
re-read as the kubelet rotates it) or a kubeconfig with a client certificate or a bearer
token (a vehicle configured by hand, the local sandbox). :class:`DirectTransport` is
that, on urllib3 (which the ``kubernetes`` client uses too, so failures are the same
exceptions and :func:`roost_kube.errors.transport_of` classifies them the same way). A
kubeconfig that needs more (an exec or auth-provider plugin) is refused with a
:class:`~roost_kube.kubeconfig.KubeconfigError` saying so.

Both send exactly what :class:`~roost_kube.client.Kube` asks (a :class:`Request`) and
answer with a :class:`Response` over urllib3's response.
"""

from __future__ import annotations

import base64
import json
import os
import ssl
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import urllib3

from roost_kube.kubeconfig import KubeconfigError, check, read_file

Timeout = tuple[float, float]

SERVICE_ACCOUNT = Path("/var/run/secrets/kubernetes.io/serviceaccount")
TOKEN_REREAD_S = 60.0  # the kubelet rotates projected tokens well before they expire


@dataclass(frozen=True)
class Request:
    """What :class:`~roost_kube.client.Kube` sends: ``path`` carries its query; a body is
    sent as JSON."""

    method: str
    path: str
    headers: Mapping[str, str]
    body: Any
    timeout: Timeout


@dataclass(frozen=True)
class Response:
    """The status and the body, unread (a watch reads it line by line)."""

    status: int
    raw: urllib3.BaseHTTPResponse

    def read(self) -> bytes:
        data = self.raw.read()
        self.raw.release_conn()
        return bytes(data)

    def lines(self) -> Iterator[bytes]:
        yield from self.raw  # urllib3 yields the body line by line

    def release(self) -> None:
        self.raw.release_conn()


class Transport(Protocol):
    @property
    def host(self) -> str:
        """The API server's URL."""
        ...

    def send(self, request: Request) -> Response:
        """One request; urllib3's exceptions propagate."""
        ...

    def close(self) -> None:
        """Close the connections (the transport is not used afterwards)."""
        ...


class ApiClientTransport:
    """Through the ``kubernetes`` client's ``ApiClient`` (its auth and TLS settings)."""

    def __init__(self, api: Any) -> None:
        self.api = api

    @property
    def host(self) -> str:
        return str(self.api.configuration.host)

    def send(self, request: Request) -> Response:
        route, _, query = request.path.partition("?")
        _, url, signed, _, _ = self.api.param_serialize(
            request.method,
            route,
            header_params=dict(request.headers),
            auth_settings=["BearerToken"],
        )
        if query:
            url = f"{url}?{query}"
        answer = self.api.call_api(
            request.method,
            url,
            header_params=signed,
            body=request.body,
            _request_timeout=request.timeout,
        )
        return Response(int(answer.status), answer.response)

    def close(self) -> None:
        self.api.close()


@dataclass(frozen=True)
class Credentials:
    """Where the API server is and how to prove who we are (one of token, token file,
    client certificate)."""

    host: str
    ca_file: Path | None = None
    ca_data: bytes | None = None
    verify: bool = True
    token: str | None = None
    token_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    cert_data: bytes | None = None
    key_data: bytes | None = None
    tls_server_name: str | None = None  # the name the server's certificate must carry


class DirectTransport:
    """urllib3 with the credentials' TLS and auth; thread-safe (one connection pool)."""

    def __init__(
        self,
        credentials: Credentials,
        *,
        retries: int | None = None,
        connections: int | None = None,
    ) -> None:
        self.credentials = credentials
        self._retries: urllib3.Retry | bool | int | None = retries if retries is not None else None
        name = credentials.tls_server_name
        named: dict[str, Any] = {"server_hostname": name, "assert_hostname": name} if name else {}
        self._pool = urllib3.PoolManager(
            ssl_context=_ssl_context(credentials), maxsize=connections or 4, **named
        )
        self._token_lock = threading.Lock()
        self._token: tuple[str, float] | None = None

    @property
    def host(self) -> str:
        return self.credentials.host

    def _bearer(self) -> str | None:
        c = self.credentials
        if c.token is not None:
            return c.token
        if c.token_file is None:
            return None
        with self._token_lock:
            now = time.monotonic()
            if self._token is None or now - self._token[1] >= TOKEN_REREAD_S:
                self._token = (c.token_file.read_text().strip(), now)
            return self._token[0]

    def send(self, request: Request) -> Response:
        headers = dict(request.headers)
        token = self._bearer()
        if token:
            headers["Authorization"] = f"Bearer {token}"
        body = None if request.body is None else json.dumps(request.body).encode()
        raw = self._pool.request(
            request.method,
            self.credentials.host + request.path,
            body=body,
            headers=headers,
            timeout=urllib3.Timeout(connect=request.timeout[0], read=request.timeout[1]),
            retries=self._retries,
            preload_content=False,
        )
        return Response(int(raw.status), raw)

    def close(self) -> None:
        self._pool.clear()


def _ssl_context(c: Credentials) -> ssl.SSLContext:
    context = ssl.create_default_context(
        cafile=None if c.ca_file is None else str(c.ca_file),
        cadata=None if c.ca_data is None else c.ca_data.decode(),
    )
    if not c.verify:
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
    if c.cert_file is not None and c.key_file is not None:
        context.load_cert_chain(str(c.cert_file), str(c.key_file))
    elif c.cert_data is not None and c.key_data is not None:
        # ssl loads a key pair from files only: written to a private directory and gone
        # again as soon as it is loaded.
        with tempfile.TemporaryDirectory(prefix="roost-kube-") as tmp:
            cert, key = Path(tmp) / "cert.pem", Path(tmp) / "key.pem"
            cert.write_bytes(c.cert_data)
            key.touch(mode=0o600)
            key.write_bytes(c.key_data)
            context.load_cert_chain(str(cert), str(key))
    return context


def in_cluster(root: Path = SERVICE_ACCOUNT) -> Credentials | None:
    """The pod's service account, or None outside a pod."""
    host, port = (
        os.environ.get("KUBERNETES_SERVICE_HOST"),
        os.environ.get("KUBERNETES_SERVICE_PORT"),
    )
    token = root / "token"
    if not host or not port or not token.is_file():
        return None
    if ":" in host:
        host = f"[{host}]"
    return Credentials(f"https://{host}:{port}", ca_file=root / "ca.crt", token_file=token)


def _named(files: Sequence[Path], section: str, name: str) -> tuple[dict[str, Any], Path]:
    """The first entry ``name`` of ``section`` among the files (kubectl's merge: the
    first file to define it wins) and the directory relative paths in it start from."""
    for path in files:
        for entry in read_file(path).get(section) or []:
            if isinstance(entry, dict) and entry.get("name") == name:
                key = section[:-1]  # clusters -> cluster, users -> user, contexts -> context
                body = entry.get(key) or {}
                if isinstance(body, dict):
                    return body, path.parent
    shown = ", ".join(str(p) for p in files)
    raise KubeconfigError(f"{shown}: {section[:-1]} {name!r} is not defined")


def _path(value: Any, base: Path) -> Path:
    path = Path(str(value)).expanduser()
    return path if path.is_absolute() else base / path


def _data(value: Any) -> bytes:
    return base64.b64decode(str(value))


UNSUPPORTED_AUTH = ("exec", "auth-provider", "username", "password")


def from_kubeconfig(files: Sequence[Path], context: str | None = None) -> Credentials:
    """The credentials of the kubeconfig ``files`` merged as kubectl merges them; a
    :class:`KubeconfigError` for what this transport does not do."""
    shown = ", ".join(str(p) for p in files)
    chosen = check(files, context)
    ctx, _ = _named(files, "contexts", chosen)
    cluster, cluster_dir = _named(files, "clusters", str(ctx.get("cluster", "")))
    user, user_dir = (
        _named(files, "users", str(ctx.get("user", ""))) if ctx.get("user") else ({}, Path())
    )
    unsupported = [key for key in UNSUPPORTED_AUTH if user.get(key)]
    if unsupported:
        raise KubeconfigError(
            f"{shown}: user of context {chosen!r} authenticates with {', '.join(unsupported)}, "
            "which the agent's client does not support (use a client certificate or a token)"
        )
    server = str(cluster.get("server", "")).rstrip("/")
    if not server:
        raise KubeconfigError(f"{shown}: cluster of context {chosen!r} has no server")
    return Credentials(
        host=server,
        ca_file=_path(cluster["certificate-authority"], cluster_dir)
        if cluster.get("certificate-authority")
        else None,
        ca_data=_data(cluster["certificate-authority-data"])
        if cluster.get("certificate-authority-data")
        else None,
        verify=not cluster.get("insecure-skip-tls-verify", False),
        token=str(user["token"]) if user.get("token") else None,
        token_file=_path(user["tokenFile"], user_dir) if user.get("tokenFile") else None,
        cert_file=_path(user["client-certificate"], user_dir)
        if user.get("client-certificate")
        else None,
        key_file=_path(user["client-key"], user_dir) if user.get("client-key") else None,
        cert_data=_data(user["client-certificate-data"])
        if user.get("client-certificate-data")
        else None,
        key_data=_data(user["client-key-data"]) if user.get("client-key-data") else None,
        tls_server_name=str(cluster["tls-server-name"]) if cluster.get("tls-server-name") else None,
    )
