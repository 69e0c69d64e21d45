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


@pytest.fixture(scope="session")
def real_nodes(cluster: Cluster, tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealNodes]:
    """The pool real nodes are added to (builds the node programs when missing). Modules
    add nodes with names of their own and remove them; the pool removes what is left."""
    reasons = missing_prerequisites()
    if reasons:
        pytest.skip("real nodes cannot run here: " + "; ".join(reasons))
    with RealNodes(cluster, tmp_path_factory.mktemp("real-nodes")) as pool:
        yield pool
