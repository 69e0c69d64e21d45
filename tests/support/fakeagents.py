"""Stand-in node agents: RedundantAutopilot status written as the agent writes it.

For tests and benchmarks of the *cluster* side (operator, missions) where running the
real agent with simulated autopilots on every fake vehicle would cost more than it
shows. :class:`FakeAgents` reports each vehicle's autopilots periodically — conditions
``ActiveHealthy``/``Redundant``/``FailedOver``/``Ready``, per-autopilot health with
landed state and armed flag, ``lastFailover``, ``failoverCount``, ``nodeName`` and a
fresh ``reportedAt`` — and executes ``spec.command`` once per id the way the agent does:
the safety routine ends on the ground and disarmed, an emergency stop disarms, and the
result goes to ``status.lastCommand``. A test changes what the autopilots look like with
:meth:`FakeAgents.set` and :meth:`FakeAgents.fail_over`.

The real agent (``roost_agent``) decides health from MAVLink; nothing here does. Tests
that need that use the agent with ``roost-sim`` autopilots instead.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from roost_api.autopilot import CommandAction
from roost_api.fence import held_message
from roost_api.meta import GROUP, VERSION, Condition, set_condition
from roost_kube.errors import NotFoundError
from roost_kube.resources import REDUNDANT_AUTOPILOTS
from roost_localcluster.cluster import Cluster


def rfc3339(at: datetime) -> str:
    """A UTC timestamp as Kubernetes writes it."""
    return at.astimezone(UTC).isoformat().replace("+00:00", "Z")


def redundant_autopilot(vehicle: str) -> dict[str, Any]:
    """The RedundantAutopilot of ``vehicle`` (named after it) the stand-in agents report for:
    two PX4 autopilots, ``fc1`` (primary) and ``fc2``."""
    return {
        "apiVersion": f"{GROUP}/{VERSION}",
        "kind": "RedundantAutopilot",
        "metadata": {"name": vehicle},
        "spec": {
            "vehicleName": vehicle,
            "primary": "fc1",
            "autopilots": [
                {
                    "name": f"fc{i}",
                    "stack": "px4",
                    "connection": f"udp://127.0.0.1:{14539 + i}",
                    "sysid": i,
                    "bridgeChannel": i - 1,
                }
                for i in (1, 2)
            ],
        },
    }


@dataclass
class AgentState:
    """What one vehicle's (simulated) autopilots look like to its agent."""

    vehicle: str
    node: str
    active: str = "fc1"
    healthy: bool = True
    redundant: bool = True
    landed: str = "InAir"
    armed: bool = True
    execute_commands: bool = True
    failover: dict[str, Any] | None = None
    failover_count: int = 0
    last_command: dict[str, Any] | None = None
    conditions: list[Condition] = field(default_factory=list)
    fence: dict[str, Any] | None = None  # spec.fence as last read
    fence_refused: tuple[str, ...] = ()  # autopilots whose fence upload fails


def _execute(state: AgentState, command: dict[str, Any] | None) -> None:
    """Run ``command`` once per id, as the agent would (see the module docstring)."""
    if command is None or not state.execute_commands:
        return
    if state.last_command is not None and state.last_command["id"] == command["id"]:
        return
    action = command["action"]
    if action == CommandAction.SAFETY_ROUTINE:
        state.landed, state.armed = "OnGround", False
    elif action == CommandAction.EMERGENCY_STOP:
        state.armed = False
    state.last_command = {
        "id": command["id"],
        "result": "Executed",
        "message": f"{action} done",
        "time": rfc3339(datetime.now(UTC)),
    }


def _fence_conditions(state: AgentState, autopilot: str) -> list[dict[str, Any]]:
    """The autopilot's FenceInSync condition, as the agent reports it for ``spec.fence``:
    held (naming the fence's id) unless the test made its upload fail."""
    if state.fence is None:
        return []
    at = rfc3339(datetime.now(UTC))
    if autopilot in state.fence_refused:
        verdict = ("False", "UploadRefused", "uploading: MISSION_ACK result 1")
    else:
        verdict = ("True", "FenceHeld", held_message(state.fence["id"], "as uploaded"))
    status, reason, message = verdict
    return [
        {
            "type": "FenceInSync",
            "status": status,
            "reason": reason,
            "message": message,
            "lastTransitionTime": at,
        }
    ]


def agent_status(state: AgentState) -> dict[str, Any]:
    """The RedundantAutopilot status the agent would write for ``state``."""
    for kind, holds, problem in (
        ("ActiveHealthy", state.healthy, "HeartbeatLost"),
        ("Redundant", state.redundant, "StandbyUnhealthy"),
        ("FailedOver", state.failover is not None, "Switched"),
        ("Ready", state.healthy and state.redundant, "NotFit"),
    ):
        good = holds != (kind == "FailedOver")
        state.conditions = set_condition(
            state.conditions,
            type=kind,
            status="True" if holds else "False",
            reason="AsExpected" if good else problem,
        )
    health = [
        {
            "name": name,
            "level": "OK" if state.healthy or name != state.active else "ERROR",
            "landedState": state.landed,
            "armed": state.armed,
            "conditions": _fence_conditions(state, name),
        }
        for name in ("fc1", "fc2")
    ]
    status: dict[str, Any] = {
        "conditions": [c.to_api() for c in state.conditions],
        "activeAutopilot": state.active,
        "autopilots": health,
        "failoverCount": state.failover_count,
        "nodeName": state.node,
        "reportedAt": rfc3339(datetime.now(UTC)),
    }
    if state.failover is not None:
        status["lastFailover"] = state.failover
    if state.last_command is not None:
        status["lastCommand"] = state.last_command
    return status


class FakeAgents:
    """Stand-in agents for many vehicles, reporting every ``period_s`` from one thread."""

    def __init__(self, cluster: Cluster, period_s: float = 1.0) -> None:
        self.period_s = period_s
        self._kube = cluster.kube("roost-agent")
        self._states: dict[str, AgentState] = {}
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fake-agents", daemon=True)

    def add(self, autopilots: str, vehicle: str, node: str, **state: Any) -> None:
        """Start reporting for RedundantAutopilot ``autopilots`` (it should exist)."""
        with self._lock:
            self._states[autopilots] = AgentState(vehicle=vehicle, node=node, **state)
        self.report(autopilots)

    def forget(self, autopilots: str) -> None:
        """Stop reporting (before the object is deleted)."""
        with self._lock:
            self._states.pop(autopilots, None)

    def set(self, autopilots: str, **changes: Any) -> None:
        """Change what the autopilots look like and report at once."""
        with self._lock:
            for key, value in changes.items():
                setattr(self._states[autopilots], key, value)
        self.report(autopilots)

    def fail_over(self, autopilots: str) -> None:
        """The agent switched the bridge from fc1 to fc2 (fc1 lost its heartbeat)."""
        with self._lock:
            state = self._states[autopilots]
            state.active = "fc2"
            state.redundant = False
            state.failover_count += 1
            state.failover = {
                "time": rfc3339(datetime.now(UTC)),
                "from": "fc1",
                "to": "fc2",
                "reason": "heartbeat lost on fc1",
                "latencyMs": 21.0,
                "trigger": "Automatic",
            }
        self.report(autopilots)

    def report(self, autopilots: str) -> None:
        """One report: read the command, execute it, write the status (serialised)."""
        with self._lock:
            state = self._states.get(autopilots)
            if state is None:
                return
            try:
                body = self._kube.get(REDUNDANT_AUTOPILOTS, autopilots)
                if body is None:
                    return
                _execute(state, (body.get("spec") or {}).get("command"))
                state.fence = (body.get("spec") or {}).get("fence")
                self._kube.merge_patch(
                    REDUNDANT_AUTOPILOTS,
                    autopilots,
                    {"status": agent_status(state)},
                    subresource="status",
                )
            except NotFoundError:
                return  # deleted between the read and the write

    def _run(self) -> None:
        while not self._stopping.wait(self.period_s):
            with self._lock:
                names = list(self._states)
            for name in names:
                self.report(name)

    def __enter__(self) -> FakeAgents:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stopping.set()
        self._thread.join()
        self._kube.close()
