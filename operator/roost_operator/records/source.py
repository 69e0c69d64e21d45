"""How the operator reaches a vehicle's records server.

In a cluster: the API server's pod proxy of the agent pod on the vehicle's node
(``/api/v1/namespaces/NS/pods/POD:PORT/proxy/records``), with the operator's own
credentials; nothing on the vehicle is opened beyond what the API server dials, the way
the dashboard reaches the agent's telemetry stream. Where the operator can reach an
agent directly (the sandbox runs agents as processes on the loopback), the Vehicle's
``roost.dev/records`` annotation names its server's URL and that wins.

Every answer is a urllib3 response whose body is read in chunks, so a file is written
to disk as it arrives and a cut transfer keeps what came through.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Protocol
from urllib.parse import quote

import urllib3

from roost_api.wellknown import ANNOTATION_RECORDS
from roost_kube.client import Kube
from roost_kube.resources import PODS

CHUNK_BYTES = 1 << 16
AGENT_COMPONENT = {"app.kubernetes.io/component": "agent"}
"""The chart's label on agent pods."""


class SourceError(Exception):
    """The vehicle's records server could not be reached or gave an unusable answer."""


class Endpoint(Protocol):
    """A vehicle's records server."""

    def get(self, path: str, offset: int = 0) -> urllib3.BaseHTTPResponse:
        """``GET /<path>`` (from ``offset`` on, with a Range header); body unread."""
        ...


def chunks(response: urllib3.BaseHTTPResponse) -> Iterator[bytes]:
    """The body in chunks, whether or not the client already read it."""
    body = getattr(response, "_body", None)
    if body:
        yield bytes(body)
        return
    yield from response.stream(CHUNK_BYTES)


def _range(offset: int) -> dict[str, str]:
    return {"Range": f"bytes={offset}-"} if offset > 0 else {}


@dataclass
class DirectEndpoint:
    """A records server at ``base`` (``http://HOST:PORT/``)."""

    base: str
    pool: urllib3.PoolManager
    timeout: float = 30.0

    def get(self, path: str, offset: int = 0) -> urllib3.BaseHTTPResponse:
        try:
            return self.pool.request(
                "GET",
                self.base.rstrip("/") + "/" + quote(path),
                headers=_range(offset),
                preload_content=False,
                retries=False,
                timeout=urllib3.Timeout(connect=5.0, read=self.timeout),
            )
        except urllib3.exceptions.HTTPError as error:
            raise SourceError(f"{type(error).__name__}: {error}") from error


@dataclass
class ProxyEndpoint:
    """The records server of agent pod ``namespace/pod`` on ``port``, through the API
    server's pod proxy."""

    kube: Kube
    namespace: str
    pod: str
    port: int

    def get(self, path: str, offset: int = 0) -> urllib3.BaseHTTPResponse:
        route = f"/api/v1/namespaces/{self.namespace}/pods/{self.pod}:{self.port}/proxy/"
        try:
            return self.kube.get_bytes(route + quote(path), headers=_range(offset)).raw
        except Exception as error:  # the API server unreachable: the same as the vehicle
            raise SourceError(f"{type(error).__name__}: {error}") from error


def agent_pod(kube: Kube, namespace: str, node: str) -> str | None:
    """The running agent pod on ``node``, if any."""
    pods = kube.list_objects(
        PODS, namespace=namespace, labels=AGENT_COMPONENT, field_selector=f"spec.nodeName={node}"
    )
    running = [p for p in pods if (p.get("status") or {}).get("phase") == "Running"]
    return running[0]["metadata"]["name"] if running else None


def endpoint_for(
    kube: Kube,
    pool: urllib3.PoolManager,
    *,
    annotations: Mapping[str, str],
    node: str,
    namespace: str,
    port: int,
) -> Endpoint:
    """The way to one vehicle's records server (see the module docstring)."""
    direct = annotations.get(ANNOTATION_RECORDS)
    if direct:
        return DirectEndpoint(direct, pool)
    if not node:
        raise SourceError("the vehicle has no node")
    pod = agent_pod(kube, namespace, node)
    if pod is None:
        raise SourceError(f"no running agent pod on node {node}")
    return ProxyEndpoint(kube, namespace, pod, port)


def read_json(endpoint: Endpoint, path: str) -> Any:
    """A JSON answer; SourceError for anything but a 200 with JSON."""
    response = endpoint.get(path)
    try:
        body = b"".join(chunks(response))
    except urllib3.exceptions.HTTPError as error:
        raise SourceError(f"{type(error).__name__}: {error}") from error
    finally:
        response.release_conn()
    if response.status != 200:
        raise SourceError(
            f"GET /{path}: HTTP {response.status}: {body[:200].decode(errors='replace')}"
        )
    try:
        return json.loads(body)
    except ValueError as error:
        raise SourceError(f"GET /{path}: not JSON: {error}") from error
