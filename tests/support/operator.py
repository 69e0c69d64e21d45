"""``roost-operator`` as a child process against a local cluster, for tests and benchmarks.

The operator runs exactly as a user would run it (``roost-operator --standalone``, the
console script of the editable install), with its kopf liveness endpoint on a free
loopback port so a caller can wait until it serves. Settings go in through the
environment (``ROOST_NAMESPACE`` and friends, see :mod:`roost_operator.settings`), so a
test module can give its operator a namespace of its own.
"""

from __future__ import annotations

import os
import urllib.request
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType

from roost_api.ports import free_port
from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.cluster import Cluster
from roost_localcluster.processes import ManagedProcess
from tests.support.waiting import wait_until


class OperatorProcess:
    """One ``roost-operator`` process; start, crash (SIGKILL) and stop it."""

    def __init__(
        self,
        cluster: Cluster,
        log: Path,
        *,
        namespace: str,
        environment: Mapping[str, str] | None = None,
        standalone: bool = True,
        args: Sequence[str] = (),
    ) -> None:
        """``standalone=False`` runs with kopf peering, as the chart does (set the peering
        name with ``ROOST_PEERING`` in ``environment``; the peering object must exist);
        ``args``: more flags (``--leader-election``)."""
        self.cluster = cluster
        self.port = free_port()
        self.process = ManagedProcess(
            "roost-operator",
            [
                str(REPO_ROOT / ".venv" / "bin" / "roost-operator"),
                *(["--standalone"] if standalone else []),
                f"--liveness=http://127.0.0.1:{self.port}/healthz",
                *args,
            ],
            log,
        )
        self.env = {
            **os.environ,
            "KUBECONFIG": str(cluster.kubeconfig),
            "ROOST_NAMESPACE": namespace,
            **(environment or {}),
        }

    def healthy(self) -> bool:
        """kopf's liveness endpoint answers 200."""
        try:
            url = f"http://127.0.0.1:{self.port}/healthz"
            with urllib.request.urlopen(url, timeout=2) as answer:
                return bool(answer.status == 200)
        except OSError:
            return False

    def start(self, timeout_s: float = 60.0) -> None:
        """Launch and wait until the liveness endpoint answers."""
        self.process.launch(self.env, die_with_parent=True)
        wait_until("the operator's liveness endpoint", self.healthy, timeout_s)

    def crash(self) -> None:
        """SIGKILL: no shutdown handlers, no finalisation, like a node losing power."""
        self.process.crash()

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after a grace period."""
        self.process.stop()

    def __enter__(self) -> OperatorProcess:
        self.start()
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()
