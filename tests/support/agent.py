"""``roost-agent`` as a child process on a fake vehicle node, for tests and benchmarks.

The agent runs as the chart runs it: no config file, ``NODE_NAME`` naming its (kwok)
node, and a kubeconfig instead of the in-cluster service account, so it finds its
Vehicle and RedundantAutopilot in the API and reports there. Its simulated autopilots
live in the calling process (``roost_sim``), reached over real UDP.

The agent prints one JSON object per event on stdout (``{"event": "Failover", ...}``);
:meth:`AgentProcess.events` reads them back from the log, so a caller can tell what the
agent did locally even while the API server is down.
"""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.cluster import Cluster
from roost_localcluster.processes import ManagedProcess


class AgentProcess:
    """One ``roost-agent`` reporting to a harness cluster for node ``node_name``."""

    def __init__(
        self,
        cluster: Cluster,
        node_name: str,
        work_dir: Path,
        *,
        report_interval_s: float = 2.0,
        api_retry_max_s: float = 1.0,
        extra_args: Sequence[str] = (),
        environment: Mapping[str, str] | None = None,
    ) -> None:
        self.node_name = node_name
        self.state_dir = work_dir / "state"
        self.log = work_dir / "agent.log"
        self.process = ManagedProcess(
            f"roost-agent-{node_name}",
            [
                str(REPO_ROOT / ".venv" / "bin" / "roost-agent"),
                "--state-dir",
                str(self.state_dir),
                "--report-interval",
                str(report_interval_s),
                "--api-retry-max",
                str(api_retry_max_s),
                "--status-interval",
                "0",
                *extra_args,
            ],
            self.log,
        )
        self.env = {
            **os.environ,
            "KUBECONFIG": str(cluster.kubeconfig),
            "NODE_NAME": node_name,
            **(environment or {}),
        }

    def start(self) -> None:
        """Launch the agent (it keeps its state directory across restarts)."""
        self.process.launch(self.env, die_with_parent=True)

    def crash(self) -> None:
        """SIGKILL, like a companion computer losing power."""
        assert self.process.pid is not None
        os.killpg(self.process.pid, signal.SIGKILL)
        self.process.stop()

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after a grace period."""
        self.process.stop()

    def events(self, kind: str | None = None) -> list[dict[str, Any]]:
        """The agent's JSON events so far (all runs), optionally only one ``event`` kind."""
        if not self.log.exists():
            return []
        found = []
        for line in self.log.read_text(errors="replace").splitlines():
            if not line.startswith('{"event"'):
                continue
            try:
                doc: dict[str, Any] = json.loads(line)
            except ValueError:
                continue
            if kind is None or doc.get("event") == kind:
                found.append(doc)
        return found
