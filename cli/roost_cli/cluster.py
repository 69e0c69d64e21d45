"""Finding the cluster and reading or patching Roost objects in it.

Which cluster: ``--kubeconfig`` first, then ``$KUBECONFIG`` (what kubectl uses), then a
running sandbox's kubeconfig, then ``~/.kube/config``. The sandbox comes after
``$KUBECONFIG`` so a user who exported a kubeconfig always gets the cluster they named.

Every API failure is turned into a :class:`~roost_cli.errors.CliError` that names the
cluster and says what to do: an unreachable server, missing CRDs, a missing object.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import urllib3
from kubernetes import client, config
from kubernetes.client.exceptions import ApiException

from roost_api.resources import MISSION, REDUNDANT_AUTOPILOT, VEHICLE, ResourceKind
from roost_cli.errors import CliError

REQUEST_TIMEOUT_S = 10.0
NO_CLUSTER = (
    "no cluster: run `roost sandbox up` (a local fleet) or set KUBECONFIG "
    "(or pass --kubeconfig) to use an existing cluster"
)


@dataclass(frozen=True)
class Target:
    """The kubeconfig to use and where it came from (shown to the user)."""

    kubeconfig: Path
    source: str
    """``--kubeconfig``, ``$KUBECONFIG``, ``sandbox`` or ``~/.kube/config``."""


def resolve_kubeconfig(
    explicit: Path | None,
    environ: Mapping[str, str],
    sandbox_kubeconfig: Path | None,
    home: Path,
) -> Target:
    """Pick the kubeconfig as described in the module docstring (pure: no I/O but stat)."""
    if explicit is not None:
        if not explicit.is_file():
            raise CliError(f"--kubeconfig {explicit} does not exist")
        return Target(explicit, "--kubeconfig")
    from_env = environ.get("KUBECONFIG", "")
    if from_env:
        first = Path(from_env.split(":")[0])
        if not first.is_file():
            raise CliError(
                f"KUBECONFIG={from_env} does not exist: unset it to use the sandbox, or "
                "point it at a kubeconfig file"
            )
        return Target(first, "$KUBECONFIG")
    if sandbox_kubeconfig is not None and sandbox_kubeconfig.is_file():
        return Target(sandbox_kubeconfig, "sandbox")
    default = home / ".kube" / "config"
    if default.is_file():
        return Target(default, "~/.kube/config")
    raise CliError(NO_CLUSTER)


class Fleet:
    """Roost's custom objects in one cluster, with errors a user can act on."""

    def __init__(self, target: Target) -> None:
        self.target = target
        configuration = client.Configuration()
        try:
            config.load_kube_config(  # type: ignore[no-untyped-call]
                config_file=str(target.kubeconfig), client_configuration=configuration
            )
        except (config.ConfigException, OSError, ValueError) as error:
            raise CliError(
                f"cannot read kubeconfig {target.kubeconfig} ({target.source}): {error}"
            ) from error
        # Fail fast on a dead server: one retry, not urllib3's default three with backoff.
        configuration.retries = 1
        self.server: str = configuration.host
        self._client = client.ApiClient(configuration)
        self._api = client.CustomObjectsApi(self._client)
        self._core = client.CoreV1Api(self._client)

    def _call(
        self, what: str, kind: ResourceKind | None, fn: Any, *args: Any, **kwargs: Any
    ) -> Any:
        """``fn(*args)`` with a timeout; ``kind`` (None for core objects) shapes the errors."""
        try:
            return fn(*args, _request_timeout=REQUEST_TIMEOUT_S, **kwargs)
        except urllib3.exceptions.HTTPError as error:
            raise CliError(
                f"cannot reach the API server at {self.server} (kubeconfig from "
                f"{self.target.source}: {self.target.kubeconfig}). Is the cluster running? "
                "Start the sandbox with `roost sandbox up`, or set KUBECONFIG to a running "
                "cluster."
            ) from error
        except ApiException as error:
            raise api_error(what, kind, error) from error

    def _list(self, kind: ResourceKind, namespace: str | None = None) -> list[dict[str, Any]]:
        if kind.namespaced and namespace:
            result = self._call(
                f"list {kind.plural}",
                kind,
                self._api.list_namespaced_custom_object,
                kind.group,
                kind.version,
                namespace,
                kind.plural,
            )
        else:
            result = self._call(
                f"list {kind.plural}",
                kind,
                self._api.list_cluster_custom_object,
                kind.group,
                kind.version,
                kind.plural,
            )
        items: list[dict[str, Any]] = result.get("items", [])
        return items

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
            self._call(f"read namespace {namespace}", None, self._core.read_namespace, namespace)
        except CliError as error:
            cause = error.__cause__
            status = cause.status if isinstance(cause, ApiException) else None
            if status == 404:
                raise CliError(
                    f"namespace {namespace!r} does not exist in the cluster at {self.server}: "
                    "`kubectl get namespaces` lists them"
                ) from cause
            if status != 403:
                raise

    def events(self) -> list[dict[str, Any]]:
        """Every Event in the cluster, as API dicts (camelCase), for the Roost event feed."""
        result = self._call(
            "list events", None, self._core.list_event_for_all_namespaces, limit=500
        )
        raw = self._client.sanitize_for_serialization(result)  # type: ignore[no-untyped-call]
        items: list[dict[str, Any]] = raw["items"]
        return items

    def autopilot(self, name: str) -> dict[str, Any]:
        obj: dict[str, Any] = self._call(
            f"get RedundantAutopilot {name}",
            REDUNDANT_AUTOPILOT,
            self._api.get_cluster_custom_object,
            REDUNDANT_AUTOPILOT.group,
            REDUNDANT_AUTOPILOT.version,
            REDUNDANT_AUTOPILOT.plural,
            name,
        )
        return obj

    def patch_autopilot(self, name: str, body: Mapping[str, Any]) -> dict[str, Any]:
        """Merge-patch one RedundantAutopilot (spec only: status belongs to the agent)."""
        obj: dict[str, Any] = self._call(
            f"patch RedundantAutopilot {name}",
            REDUNDANT_AUTOPILOT,
            self._api.patch_cluster_custom_object,
            REDUNDANT_AUTOPILOT.group,
            REDUNDANT_AUTOPILOT.version,
            REDUNDANT_AUTOPILOT.plural,
            name,
            dict(body),
        )
        return obj

    def patch_mission(self, namespace: str, name: str, body: Mapping[str, Any]) -> dict[str, Any]:
        obj: dict[str, Any] = self._call(
            f"patch Mission {namespace}/{name}",
            MISSION,
            self._api.patch_namespaced_custom_object,
            MISSION.group,
            MISSION.version,
            namespace,
            MISSION.plural,
            name,
            dict(body),
        )
        return obj


def api_error(what: str, kind: ResourceKind | None, error: ApiException) -> CliError:
    """A message for an API error that says what to do about it."""
    reason = _server_message(error)
    if kind is not None and error.status == 404 and what.startswith("list "):
        return CliError(
            f"the {kind.kind} API is not installed in this cluster: "
            "`kubectl apply -f crds/` (the sandbox installs it for you)"
        )
    if kind is not None and error.status == 404:
        listing = "roost missions" if kind is MISSION else "roost status"
        return CliError(f"cannot {what}: not found. `{listing}` lists what exists")
    if error.status in (401, 403):
        return CliError(f"cannot {what}: {reason}. Use a kubeconfig with the rights to do it")
    if error.status == 422:
        return CliError(f"cannot {what}: the API server rejected it: {reason}")
    return CliError(f"cannot {what}: HTTP {error.status} {reason}")


def _server_message(error: ApiException) -> str:
    """The Status message the API server sent, else the HTTP reason."""
    try:
        body = json.loads(error.body or "{}")
    except (TypeError, ValueError):
        body = {}
    message = body.get("message") if isinstance(body, dict) else None
    return str(message or error.reason or "")
