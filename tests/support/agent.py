"""``roost-agent`` as a child process, for tests and benchmarks: the one wrapper.

The agent runs in one of its two real modes:

- :meth:`AgentProcess.in_cluster` — as the chart runs it: no config file, ``NODE_NAME``
  naming its (kwok) node and a kubeconfig instead of the in-cluster service account, so
  it finds its Vehicle and RedundantAutopilot in the API and reports there;
- :meth:`AgentProcess.standalone` — ``--cluster off`` with a RedundantAutopilot file
  (rewritten and re-read on SIGHUP for commands), as on a vehicle without a cluster.

Its simulated autopilots live in the calling process (``roost_sim``), reached over real
UDP. The agent prints one JSON object per line on stdout — events (``{"event": ...}`` or
``{"reason": ...}``) and, with ``--status-interval``, its status (``{"status": ...}``);
stdout and stderr go to ``agent.log`` in the work directory, and the wrapper reads the
JSON lines back from there, so a caller can tell what the agent did locally even while
the API server is down, across restarts of the same wrapper.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from roost_api.autopilot import AutopilotCommand, RedundantAutopilotSpec
from roost_localcluster.binaries import REPO_ROOT
from roost_localcluster.cluster import Cluster
from roost_localcluster.processes import ManagedProcess
from roost_sim import free_udp_port

AGENT_EXE = REPO_ROOT / ".venv" / "bin" / "roost-agent"

Doc = dict[str, Any]


class AgentProcess:
    """One ``roost-agent`` process and the JSON lines it printed."""

    def __init__(
        self,
        work_dir: Path,
        args: Sequence[str],
        *,
        name: str = "roost-agent",
        environment: Mapping[str, str] | None = None,
        spec: RedundantAutopilotSpec | None = None,
    ) -> None:
        self.work_dir = work_dir
        self.state_dir = work_dir / "state"
        self.log = work_dir / "agent.log"
        self.config = work_dir / "redundantautopilot.yaml"
        self.spec = spec
        self.node_name = ""  # set for an agent in a cluster
        if spec is not None:
            self._write_config(None)
        argv = [str(AGENT_EXE), "--state-dir", str(self.state_dir)]
        if spec is not None:
            argv += ["--config", str(self.config)]
        self.process = ManagedProcess(name, [*argv, *args], self.log)
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", **(environment or {})}
        self.seen: list[Doc] = []  # every JSON line printed so far, in order
        self._cursor = 0  # seen[:_cursor] were returned by read() or a wait
        self._status: Doc = {}
        self._links: dict[str, dict[str, int]] = {}
        # a new wrapper on a work directory reads only what its own runs print
        self._read_offset = self.log.stat().st_size if self.log.exists() else 0
        self._partial = b""
        self._commands = 0

    @classmethod
    def in_cluster(
        cls,
        cluster: Cluster,
        node_name: str,
        work_dir: Path,
        *,
        report_interval_s: float = 2.0,
        api_retry_max_s: float = 1.0,
        extra_args: Sequence[str] = (),
        environment: Mapping[str, str] | None = None,
    ) -> AgentProcess:
        """An agent for ``node_name`` reporting to ``cluster`` (not started yet)."""
        args = [
            "--report-interval",
            str(report_interval_s),
            "--api-retry-max",
            str(api_retry_max_s),
            "--status-interval",
            "0",
            *extra_args,
        ]
        env = {"KUBECONFIG": str(cluster.kubeconfig), "NODE_NAME": node_name, **(environment or {})}
        agent = cls(work_dir, args, name=f"roost-agent-{node_name}", environment=env)
        agent.node_name = node_name
        return agent

    @classmethod
    def standalone(
        cls,
        work_dir: Path,
        spec: RedundantAutopilotSpec | None = None,
        *,
        status_interval_s: float = 0.25,
        log_level: str = "INFO",
        extra_args: Sequence[str] = (),
    ) -> AgentProcess:
        """A started ``--cluster off`` agent; without ``spec`` it resumes from its state."""
        args = [
            "--cluster",
            "off",
            "--status-interval",
            str(status_interval_s),
            "--log-level",
            log_level,
            *extra_args,
        ]
        agent = cls(work_dir, args, spec=spec)
        agent.start()
        return agent

    # -- the process ----------------------------------------------------------------------

    @property
    def pid(self) -> int:
        assert self.process.pid is not None, "the agent is not running"
        return self.process.pid

    def start(self) -> None:
        """Launch the agent (it keeps its state directory across restarts)."""
        self.process.launch(self.env, die_with_parent=True)

    def crash(self) -> None:
        """SIGKILL, like a companion computer losing power."""
        self.process.crash()

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL after a grace period; returns the exit code."""
        self.process.stop()
        return self.process.returncode

    def alive(self) -> bool:
        return self.process.alive()

    # -- what it printed ------------------------------------------------------------------

    def _pull(self) -> None:
        """Append what the agent printed since the last pull to :attr:`seen`."""
        if not self.log.exists():
            return
        with self.log.open("rb") as f:
            f.seek(self._read_offset)
            chunk = f.read()
        self._read_offset += len(chunk)
        lines = (self._partial + chunk).split(b"\n")
        self._partial = lines.pop()
        for line in lines:
            if not line.startswith(b"{"):
                continue  # log lines on stderr, the launcher's header
            try:
                doc: Doc = json.loads(line)
            except ValueError:
                continue
            if "status" in doc:
                self._status, self._links = doc["status"], doc.get("links", {})
            self.seen.append(doc)

    @property
    def status(self) -> Doc:
        """The latest status line's ``status``."""
        self._pull()
        return self._status

    @property
    def links(self) -> dict[str, dict[str, int]]:
        """The latest status line's link counters."""
        self._pull()
        return self._links

    def read(self) -> list[Doc]:
        """The JSON lines (status lines too) not returned by an earlier call or wait."""
        self._pull()
        new = self.seen[self._cursor :]
        self._cursor = len(self.seen)
        return new

    def events(self, kind: str | None = None) -> list[Doc]:
        """The agent's events so far (all runs), optionally only one ``event`` kind."""
        self._pull()
        found = [d for d in self.seen if "status" not in d]
        return found if kind is None else [d for d in found if d.get("event") == kind]

    def wait_for(self, predicate: Callable[[Doc], bool], timeout: float) -> Doc:
        """The first JSON line not yet read (status lines too) that matches ``predicate``."""
        deadline = time.monotonic() + timeout
        while True:
            exited = not self.process.alive()  # checked first: its last lines are read below
            self._pull()
            # One line at a time: the lines after the match stay unread for the next wait
            # (a busy machine delivers a failover and the routine's next phase together).
            while self._cursor < len(self.seen):
                doc = self.seen[self._cursor]
                self._cursor += 1
                if predicate(doc):
                    return doc
            if exited:
                raise AssertionError(f"roost-agent exited; log tail:\n{self._tail()}")
            if time.monotonic() > deadline:
                recent = [f"{d.get('reason')}: {d.get('message')}" for d in self.events()[-8:]]
                raise TimeoutError(
                    "no matching agent output; last events and log lines:\n"
                    + "\n".join([*recent, self._tail()])
                )
            time.sleep(0.01)

    def _tail(self, lines: int = 20) -> str:
        if not self.log.exists():
            return ""
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])

    def levels(self) -> dict[str, str]:
        """Health level per autopilot in the latest status line."""
        return {a["name"]: a["level"] for a in self.status.get("autopilots", [])}

    def wait_ok(self, names: Sequence[str], timeout: float = 15.0) -> None:
        """Until a status line printed after this call shows every one of ``names`` OK."""
        self.read()  # what was printed before this call does not count

        def ok(doc: Doc) -> bool:
            levels = {a["name"]: a["level"] for a in doc.get("status", {}).get("autopilots", [])}
            return all(levels.get(n) == "OK" for n in names)

        self.wait_for(ok, timeout)

    # -- commands (standalone) ------------------------------------------------------------

    def _write_config(self, command: AutopilotCommand | None) -> None:
        assert self.spec is not None
        spec = self.spec.model_copy(update={"command": command})
        self.config.parent.mkdir(parents=True, exist_ok=True)
        self.config.write_text(yaml.safe_dump({"spec": spec.to_api()}))

    def command(self, action: str, target: str | None = None, timeout: float = 10) -> Doc:
        """Execute a command through the config file and SIGHUP; returns its result."""
        self._commands += 1
        cid = f"test-{self._commands}"
        issued = datetime.now(UTC)
        self._write_config(AutopilotCommand(id=cid, action=action, target=target, issued_at=issued))
        os.kill(self.pid, signal.SIGHUP)
        doc = self.wait_for(lambda d: d.get("command", {}).get("id") == cid, timeout)
        return dict(doc["command"])


def run_agent_once(state_dir: Path, hub: Mapping[str, Any]) -> subprocess.CompletedProcess[str]:
    """``roost-agent`` run to its end on a two-PX4 config with ``hub``, out of cluster (for
    tests of what it refuses at start: its exit status and its one line on stderr)."""
    autopilots = [
        {
            "name": f"fc{i}",
            "stack": "px4",
            "connection": f"udp://127.0.0.1:{free_udp_port()}",
            "sysid": i,
            "bridgeChannel": i,
        }
        for i in (1, 2)
    ]
    config = state_dir / "ra.yaml"
    spec = {"vehicleName": "v1", "primary": "fc1", "autopilots": autopilots, "hub": dict(hub)}
    config.write_text(yaml.safe_dump(spec))
    exe = Path(sys.executable).with_name("roost-agent")
    return subprocess.run(
        [str(exe), "--config", str(config), "--state-dir", str(state_dir), "--cluster", "off"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
