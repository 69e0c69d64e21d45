"""Fixtures of the real-node suite: real kubelets (with containerd and CNI) in the harness.

The control plane is the session's (``cluster`` in tests/conftest.py); real nodes join it
in network namespaces of their own (:mod:`roost_localcluster.realnode`). Everything here
needs root (namespaces, cgroups, mounts): elsewhere the suite skips and says so.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from roost_localcluster.cluster import Cluster
from roost_localcluster.nodenet import missing_prerequisites
from roost_localcluster.realnode import RealNodes

LONGEST_FIRST = ("test_image_run.py",)
"""The parallel pass's longest file (its arm64 cases under qemu: minutes on a loaded machine)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The longest files first: ``make e2e``'s workers take whole files in collection
    order, and a worker that started one of these last would leave the other idle for
    minutes. Within a file the order stays. (Every collected item passes here, those of
    tests/e2e too.)"""
    items.sort(key=lambda item: item.path.name not in LONGEST_FIRST)


@pytest.fixture(scope="session")
def real_nodes(cluster: Cluster, tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealNodes]:
    """The pool real nodes are added to (builds the node programs when missing). Modules
    add nodes with names of their own and remove them; the pool removes what is left."""
    reasons = missing_prerequisites()
    if reasons:
        pytest.skip("real nodes cannot run here: " + "; ".join(reasons))
    with RealNodes(cluster, tmp_path_factory.mktemp("real-nodes")) as pool:
        yield pool
