"""roost_kube.client against the real API server: what each answer becomes.

The operator, the agent and the CLI rely on these semantics: a missing object reads as
None, a stale write and a duplicate create are ConflictError (temporary), a malformed
object is InvalidError and a patch of a missing one NotFoundError (permanent), an
unchanged apply sends nothing, a retried Event post is a duplicate, a watch starts with
the object as it is, and a server that is not there is ApiUnavailableError. Through
either transport (roost_kube.transport): the same answers.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_api.ports import free_port
from roost_cli.cluster import Fleet, Target
from roost_cli.errors import CliError
from roost_kube.client import Kube
from roost_kube.errors import (
    ApiUnavailableError,
    ConflictError,
    InvalidError,
    NotFoundError,
)
from roost_kube.patches import precondition
from roost_kube.resources import CONFIGMAPS, REDUNDANT_AUTOPILOTS
from roost_kube.transport import Credentials, DirectTransport
from roost_localcluster.cluster import Cluster
from tests.support.fakeagents import redundant_autopilot
from tests.support.waiting import unique

NAMESPACE = "default"


@pytest.fixture(params=["ApiClient", "direct"])
def kube(roost_crds: Cluster, request: pytest.FixtureRequest) -> Iterator[Kube]:
    """Every test through both transports: the ``kubernetes`` client's (operator, CLI)
    and the agent's minimal one (the cluster's kubeconfig: client certificate)."""
    if request.param == "direct":
        yield Kube.from_environment(
            "roost-tests", kubeconfig=roost_crds.kubeconfig, timeout=(5.0, 30.0), direct=True
        )
        return
    yield roost_crds.kube("roost-tests")


def config_map(name: str, **data: str) -> dict[str, Any]:
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": name, "namespace": NAMESPACE},
        "data": data,
    }


def test_reads_writes_and_their_errors(kube: Kube) -> None:
    name = unique("kube-client")
    assert kube.get(CONFIGMAPS, name, NAMESPACE) is None
    with pytest.raises(NotFoundError) as missing:
        kube.merge_patch(CONFIGMAPS, name, {"data": {"a": "1"}}, namespace=NAMESPACE)
    assert missing.value.status == 404 and not missing.value.temporary

    created = kube.create(config_map(name, a="1"))
    try:
        with pytest.raises(ConflictError) as duplicate:
            kube.create(config_map(name, a="1"))
        assert duplicate.value.already_exists and duplicate.value.temporary

        kube.merge_patch(CONFIGMAPS, name, {"data": {"b": "2"}}, namespace=NAMESPACE)
        with pytest.raises(ConflictError):  # written in between: the precondition fails
            kube.merge_patch(
                CONFIGMAPS, name, precondition(created, {"data": {"c": "3"}}), namespace=NAMESPACE
            )
        patched = kube.merge_patch(CONFIGMAPS, name, {"data": {"b": None}}, namespace=NAMESPACE)
        assert patched["data"] == {"a": "1"}  # an explicit null removes the key

        with pytest.raises(InvalidError) as invalid:
            kube.merge_patch(CONFIGMAPS, name, {"data": {"bad key!": "x"}}, namespace=NAMESPACE)
        assert invalid.value.status == 422 and "bad key!" in invalid.value.message
    finally:
        assert kube.delete(CONFIGMAPS, name, NAMESPACE)
    assert not kube.delete(CONFIGMAPS, name, NAMESPACE)


def test_an_unchanged_apply_sends_nothing(kube: Kube) -> None:
    name = unique("kube-apply")
    manifest = config_map(name, a="1")
    try:
        _, sent = kube.apply(manifest)
        assert sent
        writes = sum(kube.writes.values())
        live, sent = kube.apply(manifest)
        assert not sent and sum(kube.writes.values()) == writes
        assert live["data"] == {"a": "1"}
        _, sent = kube.apply(config_map(name, a="2"))
        assert sent
    finally:
        kube.delete(CONFIGMAPS, name, NAMESPACE)


def test_a_retried_event_post_is_a_duplicate(kube: Kube) -> None:
    name = unique("kube-event")
    regarding = kube.create(config_map(name))
    try:
        at = datetime.now(UTC)
        assert kube.post_event(regarding, reason="Tested", message="once", at=at)
        assert not kube.post_event(regarding, reason="Tested", message="once", at=at)
    finally:
        kube.delete(CONFIGMAPS, name, NAMESPACE)


def test_a_watch_starts_with_the_object_as_it_is(kube: Kube) -> None:
    created = kube.create(redundant_autopilot(unique("kube-watch")))
    name = created["metadata"]["name"]
    try:
        kind, obj = next(iter(kube.watch(REDUNDANT_AUTOPILOTS, name, timeout_s=5)))
        assert (kind, obj["metadata"]["name"]) == ("ADDED", name)
        events = [k for k, _ in kube.watch(REDUNDANT_AUTOPILOTS, unique("none"), timeout_s=1)]
        assert events == []  # ends after its timeout when nothing matches
    finally:
        kube.delete(REDUNDANT_AUTOPILOTS, name)


def test_a_server_that_is_not_there_is_unavailable(roost_crds: Cluster) -> None:
    port = free_port()  # nobody listens on it
    kube = roost_crds.kube("roost-tests")
    kube.api.configuration.host = f"https://127.0.0.1:{port}"
    kube.api.configuration.retries = 0
    kube.timeout = (2.0, 2.0)
    with pytest.raises(ApiUnavailableError) as error:
        kube.get(CONFIGMAPS, "x", NAMESPACE)
    assert error.value.transport == "refused" and error.value.status is None


def test_a_server_that_is_not_there_is_unavailable_through_the_direct_transport() -> None:
    port = free_port()  # nobody listens on it
    nowhere = Credentials(f"https://127.0.0.1:{port}", verify=False)
    kube = Kube(DirectTransport(nowhere, retries=0), "roost-tests", timeout=(2.0, 2.0))
    with pytest.raises(ApiUnavailableError) as error:
        kube.get(CONFIGMAPS, "x", NAMESPACE)
    assert error.value.transport == "refused" and error.value.status is None


def test_the_cli_refuses_a_namespace_that_does_not_exist(roost_crds: Cluster) -> None:
    fleet = Fleet(Target(roost_crds.kubeconfig, "--kubeconfig"))
    fleet.require_namespace(NAMESPACE)
    missing = unique("no-such-namespace")
    with pytest.raises(CliError, match=f"namespace '{missing}' does not exist"):
        fleet.require_namespace(missing)


@pytest.mark.parametrize(("name", "works"), [("kubernetes", True), ("not-the-server", False)])
def test_the_direct_transport_checks_the_servers_certificate_against_tls_server_name(
    roost_crds: Cluster, tmp_path: Path, name: str, works: bool
) -> None:
    """A real node reaches the API server through a relay under another address and
    checks its certificate against ``tls-server-name`` (roost_localcluster.pki)."""
    doc = yaml.safe_load(roost_crds.kubeconfig.read_text())
    for entry in doc["clusters"]:
        entry["cluster"]["tls-server-name"] = name
    path = tmp_path / "kubeconfig"
    path.write_text(yaml.safe_dump(doc))
    kube = Kube.from_environment("roost-tests", kubeconfig=path, retries=0, direct=True)
    if works:
        assert kube.get(CONFIGMAPS, unique("absent"), NAMESPACE) is None
    else:
        with pytest.raises(ApiUnavailableError) as error:
            kube.get(CONFIGMAPS, "x", NAMESPACE)
        assert error.value.transport == "tls"
