"""Shared pytest fixtures for Roost's tests. Keep each fixture small; logic lives in packages."""

from __future__ import annotations

import gc
import os
import socket
from collections.abc import Iterator

import pytest

from roost_kube.client import Kube
from roost_localcluster.cluster import Cluster, FakeNodes
from roost_localcluster.controlplane import DATASTORES, ControlPlane, Settings
from tests.support.compiled import check_compiled_imports, left_to_compiled
from tests.support.natports import hold, nat_rules, redirected_loopback_ports
from tests.support.operator import OperatorProcess


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--datastore",
        choices=DATASTORES,
        default=os.environ.get("ROOST_DATASTORE", "etcd"),
        help="the control plane's datastore: etcd, or kine over SQLite as in K3s "
        "(default: $ROOST_DATASTORE, else etcd)",
    )
    parser.addoption(
        "--leave-to-compiled",
        action="store_true",
        help="deselect the integration tests that tests/integration/test_compiled_agent.py "
        "runs against the compiled build (make test: each runs once, against what the "
        "images ship)",
    )


_COMPILED_MODULES = pytest.StashKey[list[str]]()
_HELD_PORTS = pytest.StashKey[list[socket.socket]]()


def pytest_configure(config: pytest.Config) -> None:
    """A run against Roost's compiled build (``ROOST_COMPILED_TREE``) proves it is one.

    Loopback ports the host's NAT table redirects are held for the session, so no test
    server is given one (tests/support/natports.py)."""
    try:
        config.stash[_COMPILED_MODULES] = check_compiled_imports()
    except RuntimeError as error:
        raise pytest.UsageError(str(error)) from error
    config.stash[_HELD_PORTS] = hold(redirected_loopback_ports(nat_rules()))


def pytest_report_header(config: pytest.Config) -> list[str]:
    lines = [f"control-plane datastore: {config.getoption('--datastore')}"]
    if compiled := config.stash.get(_COMPILED_MODULES, []):
        lines.append(f"compiled (mypyc): {', '.join(compiled)}")
    if held := config.stash.get(_HELD_PORTS, []):
        ports = ", ".join(str(sock.getsockname()[1]) for sock in held)
        lines.append(f"held (the host's NAT redirects them): 127.0.0.1 port {ports}")
    return lines


@pytest.fixture(autouse=True)
def _no_collector_pause() -> None:
    """Start every test with what pytest holds so far out of the garbage collector's way.

    Simulated autopilots, agents and hub clients of many tests run as threads of this
    process, in real time. A full collection of everything pytest has accumulated (the
    collected suite alone: about 200 000 objects, 115 ms on a quiet machine; more later
    in the run and on a loaded one) stops every one of those threads at once, which an
    agent rightly judges as every autopilot falling silent together (it then orders a
    landing for want of a healthy standby). Collecting first and freezing what survives
    leaves the collector only the test's own objects.
    """
    gc.collect()
    gc.freeze()


LONGEST_FIRST = (
    # the integration tier's first pass, longest first (about 180 to 50 s each)
    "test_agent_cluster.py",
    "test_compiled_agent.py",
    "test_firmware_truth.py",
    "test_simulator.py",
    "test_mission_operator.py",
    "test_vehicle_operator.py",
    "test_control_plane.py",
    "test_agent_records_flight.py",
    # the e2e tier's (its arm64 cases under qemu: minutes on a loaded machine)
    "test_image_run.py",
    "test_chart_real.py",
)
"""Files that take longest, in that order. The Makefile's workers (``--dist loadfile
--no-loadscope-reorder``) take whole files in collection order, and each queues the next
file as soon as its own has two tests left: a long file taken last keeps one worker busy
for minutes after the other ran out of work."""


def _duration_rank(item: pytest.Item) -> int:
    name = item.path.name
    return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test that uses the control plane is marked ``cluster`` (run/skip as a group);
    against the compiled build, tests marked ``interpreted_only`` are skipped; with
    ``--leave-to-compiled``, the compiled run's integration tests are deselected here
    (not those marked ``interpreted_only``: the compiled run skips them). The files of
    :data:`LONGEST_FIRST` come first (the order within a file stays)."""
    compiled = config.stash.get(_COMPILED_MODULES, [])
    leave = config.getoption("--leave-to-compiled") and not compiled
    kept, left = [], []
    for item in items:
        if "cluster" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.cluster)
        only_interpreted = item.get_closest_marker("interpreted_only") is not None
        if compiled and only_interpreted:
            item.add_marker(
                pytest.mark.skip(reason="a stand-in in a class the compiled build makes native")
            )
        if leave and not only_interpreted and left_to_compiled(item.nodeid):
            left.append(item)
        else:
            kept.append(item)
    if left:
        config.hook.pytest_deselected(items=left)
    items[:] = sorted(kept, key=_duration_rank)


@pytest.fixture(scope="session")
def datastore(pytestconfig: pytest.Config) -> str:
    """The datastore control planes of this session run on (``--datastore``)."""
    return str(pytestconfig.getoption("--datastore"))


@pytest.fixture(scope="session")
def cluster(tmp_path_factory: pytest.TempPathFactory, datastore: str) -> Iterator[Cluster]:
    """A real control plane (etcd or kine, API server, controller manager, scheduler, kwok)
    for the whole session (``--datastore`` picks the datastore); builds the binaries first
    if they are missing. Component logs are in the session's temp dir under
    ``control-plane*/logs``, with the audit log that lets tests count the operator's own
    requests (``tests.support.apiwrites``). See localcluster/README.md."""
    settings = Settings(datastore=datastore, audit=True)
    with ControlPlane(tmp_path_factory.mktemp("control-plane"), settings=settings) as plane:
        yield Cluster.of(plane)


@pytest.fixture(scope="session")
def roost_crds(cluster: Cluster) -> Cluster:
    """The session cluster with Roost's CRDs (crds/) applied and Established."""
    cluster.install_crds()
    return cluster


@pytest.fixture
def fake_nodes(cluster: Cluster) -> Iterator[FakeNodes]:
    """``fake_nodes(name, **kwargs)`` adds a Ready kwok node (``Cluster.add_node`` kwargs);
    the nodes a test added are deleted when it ends. Use test-unique names and labels: the
    cluster is shared by the whole session."""
    pool = FakeNodes(cluster)
    yield pool
    pool.cleanup()


@pytest.fixture(scope="session")
def kube(roost_crds: Cluster) -> Iterator[Kube]:
    """Roost's own API access layer (:class:`roost_kube.client.Kube`) as the cluster's
    admin, for tests that read and write objects the way the operator does."""
    yield roost_crds.kube("roost-tests")


@pytest.fixture(scope="module")
def operator(
    request: pytest.FixtureRequest, roost_crds: Cluster, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[OperatorProcess]:
    """One ``roost-operator`` per test module, watching the session cluster.

    The module sets ``OPERATOR_NAMESPACE`` (the operator's own namespace, so modules do
    not share one) and optionally ``OPERATOR_ENV`` (more settings, as environment
    variables). Its log is in the session's temp dir under ``operator*/``.
    """
    module = request.module
    with OperatorProcess(
        roost_crds,
        tmp_path_factory.mktemp(f"operator-{module.__name__.rsplit('.', 1)[-1]}") / "operator.log",
        namespace=module.OPERATOR_NAMESPACE,
        environment=getattr(module, "OPERATOR_ENV", None),
    ) as proc:
        yield proc
