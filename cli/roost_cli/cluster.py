"""Finding the cluster and reading or patching Roost objects in it.

Which kubeconfig, as kubectl picks it with one addition: ``--kubeconfig`` first, then
``$KUBECONFIG`` (a ``:``-separated list, merged as kubectl merges it), then a running
sandbox's kubeconfig, then ``~/.kube/config``. The sandbox comes after ``$KUBECONFIG`` so
a user who exported a kubeconfig always gets the cluster they named. Loading, merging
and ``--context`` are :mod:`roost_kube.kubeconfig`; the requests go through
:class:`roost_kube.client.Kube`.

Every failure is turned into a :class:`~roost_cli.errors.CliError` that names the
cluster and says what to do: an unusable kubeconfig, an unreachable server, a TLS
failure, missing CRDs, a missing object.
"""

from __future__ import annotations

import ssl
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, TypeVar

from roost_api.resources import MISSION, REDUNDANT_AUTOPILOT, VEHICLE, ResourceKind
from roost_cli.errors import CliError
from roost_kube import kubeconfig
from roost_kube.errors import ApiError, ApiUnavailableError, ForbiddenError
from roost_kube.resources import EVENTS, NAMESPACES, SECRETS, Resource

if TYPE_CHECKING:
    from roost_cli.dashboard.sources import ApiProxy

FIELD_MANAGER: Final = "roost-cli"
REQUEST_TIMEOUT_S: Final = 10.0
NO_CLUSTER = (
    "no cluster: run `roost sandbox up` (a local fleet) or set KUBECONFIG "
    "(or pass --kubeconfig) to use an existing cluster"
)

T = TypeVar("T")
IN_CLUSTER: Final = "in-cluster"
SERVICE_ACCOUNT_DIR: Final = Path("/var/run/secrets/kubernetes.io/serviceaccount")


@dataclass(frozen=True)
class Target:
    """The kubeconfig to use and where it came from (shown to the user)."""

    kubeconfig: Path
    """The first file (the one shown in messages)."""
    source: str
    """``--kubeconfig``, ``$KUBECONFIG``, ``sandbox`` or ``~/.kube/config``."""
    files: tuple[Path, ...] = field(default=())
    """Every file to merge, in order (just :attr:`kubeconfig` when empty)."""
    context: str | None = None
    """The context to use instead of the merged ``current-context``."""

    @property
    def all_files(self) -> tuple[Path, ...]:
        return self.files or (self.kubeconfig,)

    @property
    def shown(self) -> str:
        return ":".join(str(path) for path in self.all_files)


def resolve_kubeconfig(
    explicit: Path | None,
    environ: Mapping[str, str],
    sandbox_kubeconfig: Path | None,
    home: Path,
    context: str | None = None,
) -> Target:
    """Pick the kubeconfig as described in the module docstring (pure: no I/O but stat)."""
    if explicit is not None:
        if not explicit.exists():
            raise CliError(f"--kubeconfig {explicit} does not exist")
        return Target(explicit, "--kubeconfig", context=context)
    from_env = environ.get("KUBECONFIG", "")
    listed = kubeconfig.split_list(from_env)
    if listed:
        found = kubeconfig.existing(listed)
        if not found:
            raise CliError(
                f"KUBECONFIG={from_env} does not exist: unset it to use the sandbox, or "
                "point it at a kubeconfig file"
            )
        return Target(found[0], "$KUBECONFIG", tuple(found), context)
    if sandbox_kubeconfig is not None and sandbox_kubeconfig.is_file():
        return Target(sandbox_kubeconfig, "sandbox", context=context)
    default = home / ".kube" / "config"
    if default.exists():
        return Target(default, "~/.kube/config", context=context)
    raise CliError(NO_CLUSTER)


def in_cluster_target() -> Target:
    """The pod's service account (a Deployment running ``roost dashboard``)."""
    return Target(SERVICE_ACCOUNT_DIR, IN_CLUSTER)


class Fleet:
    """Roost's custom objects in one cluster, with errors a user can act on."""

    def __init__(self, target: Target) -> None:
        from kubernetes import client  # noqa: PLC0415 - only commands that talk to a cluster
        from kubernetes import config as k8s_config  # noqa: PLC0415

        from roost_kube.client import Kube  # noqa: PLC0415 - imports the client

        self.target = target
        try:
            if target.source == IN_CLUSTER:
                configuration = client.Configuration()
                k8s_config.load_incluster_config(client_configuration=configuration)  # type: ignore[no-untyped-call]
            else:
                configuration = kubeconfig.load(target.all_files, target.context)
        except kubeconfig.KubeconfigError as error:
            raise CliError(f"kubeconfig ({target.source}): {error}") from None
        except k8s_config.ConfigException as error:
            raise CliError(f"in-cluster service account: {error}") from None
        # Fail fast on a dead server: one retry, not urllib3's default three with backoff.
        configuration.retries = 1
        self.kube = Kube(
            client.ApiClient(configuration),
            FIELD_MANAGER,
            timeout=(REQUEST_TIMEOUT_S, REQUEST_TIMEOUT_S),
        )
        self.server: str = configuration.host
        self.configuration = configuration

    def api_proxy(self) -> ApiProxy:
        """The API server's pod proxy with this fleet's credentials (the dashboard's way
        to the agents' telemetry streams)."""
        from roost_cli.dashboard.sources import ApiProxy  # noqa: PLC0415 - websockets

        c = self.configuration
        context = ssl.create_default_context(cafile=c.ssl_ca_cert)
        if not c.verify_ssl:
            context.check_hostname = False
            context.verify_mode = ssl.CERT_NONE
        if c.cert_file and c.key_file:
            context.load_cert_chain(c.cert_file, c.key_file)

        def headers() -> dict[str, str]:
            token = c.get_api_key_with_prefix("authorization")
            return {"Authorization": token} if token else {}

        return ApiProxy(self.server, context, headers)

    def _call(self, what: str, kind: ResourceKind | None, fn: Callable[[], T]) -> T:
        """``fn()``; ``kind`` (None for core objects) shapes the errors."""
        try:
            return fn()
        except ApiUnavailableError as error:
            raise unavailable_error(error, self.server, self.target) from None
        except ApiError as error:
            raise api_error(what, kind, error) from None

    def _list(self, kind: ResourceKind, namespace: str | None = None) -> list[dict[str, Any]]:
        resource = Resource.of(kind)
        return self._call(
            f"list {kind.plural}",
            kind,
            lambda: self.kube.list_objects(
                resource, namespace=namespace if kind.namespaced and namespace else None
            ),
        )

    def vehicles(self) -> list[dict[str, Any]]:
        return self._list(VEHICLE)

    def autopilots(self) -> list[dict[str, Any]]:
        return self._list(REDUNDANT_AUTOPILOT)

    def missions(self, namespace: str | None = None) -> list[dict[str, Any]]:
        return self._list(MISSION, namespace)

    def require_namespace(self, namespace: str) -> None:
        """Refuse a namespace that does not exist (a list there would just be empty).

        A user allowed to list Missions but not to read namespaces is not refused here.
        """
        try:
            found = self.kube.get(NAMESPACES, namespace)
        except ForbiddenError:
            return
        except ApiUnavailableError as error:
            raise unavailable_error(error, self.server, self.target) from None
        except ApiError as error:
            raise api_error(f"read namespace {namespace}", None, error) from None
        if found is None:
            raise CliError(
                f"namespace {namespace!r} does not exist in the cluster at {self.server}: "
                "`kubectl get namespaces` lists them"
            )

    def events(self) -> list[dict[str, Any]]:
        """Every Event in the cluster (the latest 500), for the Roost event feed."""
        return self._call("list events", None, lambda: self.kube.list_objects(EVENTS, limit=500))

    def autopilot(self, name: str) -> dict[str, Any]:
        what = f"get RedundantAutopilot {name}"
        obj = self._call(
            what, REDUNDANT_AUTOPILOT, lambda: self.kube.get(Resource.of(REDUNDANT_AUTOPILOT), name)
        )
        if obj is None:
            raise not_found(what, REDUNDANT_AUTOPILOT)
        return obj

    def operator_pod(self, namespace: str) -> str:
        """The running operator pod in ``namespace`` (its records server's way in)."""
        from roost_kube.resources import PODS  # noqa: PLC0415

        pods = self._call(
            f"list the operator's pods in {namespace}",
            None,
            lambda: self.kube.list_objects(
                PODS, namespace=namespace, labels={"app.kubernetes.io/component": "operator"}
            ),
        )
        running = [p for p in pods if (p.get("status") or {}).get("phase") == "Running"]
        if not running:
            raise CliError(
                f"no running operator pod in namespace {namespace} (--operator-namespace, "
                "or --records-url where the operator's records server is reachable)"
            )
        return str(running[0]["metadata"]["name"])

    def mission(self, namespace: str, name: str) -> dict[str, Any]:
        what = f"get Mission {namespace}/{name}"
        obj = self._call(
            what, MISSION, lambda: self.kube.get(Resource.of(MISSION), name, namespace=namespace)
        )
        if obj is None:
            raise not_found(what, MISSION)
        return obj

    def patch_autopilot(self, name: str, body: Mapping[str, Any]) -> dict[str, Any]:
        """Merge-patch one RedundantAutopilot (spec only: status belongs to the agent)."""
        return self._call(
            f"patch RedundantAutopilot {name}",
            REDUNDANT_AUTOPILOT,
            lambda: self.kube.merge_patch(Resource.of(REDUNDANT_AUTOPILOT), name, body),
        )

    def patch_mission(self, namespace: str, name: str, body: Mapping[str, Any]) -> dict[str, Any]:
        return self._call(
            f"patch Mission {namespace}/{name}",
            MISSION,
            lambda: self.kube.merge_patch(Resource.of(MISSION), name, body, namespace=namespace),
        )

    def secret(self, namespace: str, name: str) -> dict[str, Any] | None:
        """A Secret (None: absent); its data is never shown by the CLI."""
        return self._call(
            f"read Secret {namespace}/{name}", None, lambda: self.kube.get(SECRETS, name, namespace)
        )

    def create_secret(self, manifest: Mapping[str, Any]) -> None:
        meta = manifest["metadata"]
        what = f"create Secret {meta['namespace']}/{meta['name']}"
        self._call(what, None, lambda: self.kube.create(manifest))

    def patch_secret(self, namespace: str, name: str, body: Mapping[str, Any]) -> None:
        self._call(
            f"update Secret {namespace}/{name}",
            None,
            lambda: self.kube.merge_patch(SECRETS, name, body, namespace=namespace),
        )


def not_found(what: str, kind: ResourceKind) -> CliError:
    listing = "roost missions" if kind is MISSION else "roost status"
    return CliError(f"cannot {what}: not found. `{listing}` lists what exists")


def unavailable_error(error: ApiUnavailableError, server: str, target: Target) -> CliError:
    """A message for a server that gave no usable answer, by why it did not."""
    origin = f"kubeconfig from {target.source}: {target.shown}"
    if error.transport == "tls":
        return CliError(
            f"TLS with the API server at {server} failed ({origin}): {_short(error.body)}. "
            "The server's certificate does not match the kubeconfig's certificate-authority "
            "data (or the client certificate was refused): fix the kubeconfig"
        )
    if error.transport == "timeout":
        return CliError(
            f"the API server at {server} did not answer within {REQUEST_TIMEOUT_S:g} s "
            f"({origin}). Is it overloaded or behind a slow link?"
        )
    if error.transport is not None:
        return CliError(
            f"cannot reach the API server at {server} ({origin}). Is the cluster running? "
            "Start the sandbox with `roost sandbox up`, or set KUBECONFIG to a running "
            "cluster."
        )
    return CliError(
        f"the API server at {server} cannot serve the request now (HTTP {error.status}: "
        f"{error.message}); try again"
    )


def api_error(what: str, kind: ResourceKind | None, error: ApiError) -> CliError:
    """A message for an API error that says what to do about it."""
    reason = error.message
    if kind is not None and error.status == 404 and what.startswith("list "):
        return CliError(
            f"the {kind.kind} API is not installed in this cluster: "
            "`kubectl apply -f crds/` (the sandbox installs it for you)"
        )
    if kind is not None and error.status == 404:
        return not_found(what, kind)
    if error.status in (401, 403):
        return CliError(f"cannot {what}: {reason}. Use a kubeconfig with the rights to do it")
    if error.status == 422:
        return CliError(f"cannot {what}: the API server rejected it: {reason}")
    return CliError(f"cannot {what}: HTTP {error.status} {reason}")


def _short(text: str) -> str:
    """The last, most specific part of a urllib3/ssl error chain, on one line."""
    flat = " ".join(text.split())
    for marker in ("certificate verify failed", "SSLError", "SSL:"):
        at = flat.find(marker)
        if at >= 0:
            return flat[at : at + 160].rstrip(")'\"")
    return flat[:160]
