"""A standby operator replica stops on SIGTERM even as the init of its PID namespace.

In a pod the operator is PID 1 of the container's PID namespace, and the kernel drops a
signal sent to a namespace's init unless the init handles it. kopf installs its handlers
only when it starts, which a standby never does: without a handler of its own a standby
pod sat out its whole termination grace period (30 s) and was then killed, on every
rollout, scale-down and ``helm uninstall``. Here the real ``roost-operator
--leader-election`` runs as the init of a new PID namespace (``unshare``) against the
real control plane, standing by behind a Lease another identity holds; SIGTERM must end
it cleanly without it ever taking the Lease.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from datetime import UTC, datetime
from pathlib import Path

import pytest

from roost_kube.resources import LEASES
from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.cluster import Cluster
from roost_operator.claims import micro_time
from roost_operator.engine.leader import LEASE_NAME
from tests.support.waiting import wait_until


def _pid_namespaces() -> bool:
    """Whether this machine lets the test start a PID namespace (root, util-linux's
    ``unshare``, and a kernel or container that allows it)."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        return False
    probe = subprocess.run(
        ["unshare", "--pid", "--fork", "true"], capture_output=True, timeout=30, check=False
    )
    return probe.returncode == 0


pytestmark = [
    pytest.mark.cluster,
    pytest.mark.skipif(
        not _pid_namespaces(),
        reason="a new PID namespace needs root, util-linux's unshare and a kernel that allows it",
    ),
]

NAMESPACE = "roost-standby-signals"
HOLDER = "another-replica"


def _namespace_init(unshare: subprocess.Popen[bytes]) -> int:
    """The pid (in this namespace) of the process ``unshare --fork`` started: the new PID
    namespace's init."""
    children = Path(f"/proc/{unshare.pid}/task/{unshare.pid}/children").read_text().split()
    return int(children[0]) if children else 0


def test_a_standby_that_is_its_namespaces_init_stops_on_sigterm(
    roost_crds: Cluster, tmp_path: Path
) -> None:
    kube = roost_crds.kube()
    kube.apply({"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": NAMESPACE}})
    kube.create(
        {
            "apiVersion": LEASES.api_version,
            "kind": LEASES.kind,
            "metadata": {"name": LEASE_NAME, "namespace": NAMESPACE},
            "spec": {
                "holderIdentity": HOLDER,
                "leaseDurationSeconds": 3600,
                "renewTime": micro_time(datetime.now(UTC)),
            },
        }
    )
    log = tmp_path / "operator.log"
    env = {**os.environ, "KUBECONFIG": str(roost_crds.kubeconfig), "ROOST_NAMESPACE": NAMESPACE}
    with log.open("wb") as out:
        unshare = subprocess.Popen(
            [
                "unshare",
                "--pid",
                "--fork",
                "--kill-child",
                str(REPO_ROOT / ".venv" / "bin" / "roost-operator"),
                "--leader-election",
                "--identity=standby",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        wait_until("the replica standing by", lambda: b"standing by" in log.read_bytes(), 60)
        init = _namespace_init(unshare)
        assert init, "unshare's child (the namespace's init)"
        os.kill(init, signal.SIGTERM)
        # A dropped signal leaves it running: standing by, then (once it has seen the
        # Lease unchanged for Timings.lease_s) leading. Waiting for its exit is the test.
        assert unshare.wait(timeout=30) == 0, log.read_text()
    finally:
        if unshare.poll() is None:
            unshare.kill()
            unshare.wait()
    assert b"stopped while standing by" in log.read_bytes()
    lease = kube.get(LEASES, LEASE_NAME, NAMESPACE)
    assert lease is not None and lease["spec"]["holderIdentity"] == HOLDER
