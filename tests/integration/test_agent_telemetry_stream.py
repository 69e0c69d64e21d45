"""The agent's telemetry stream, read from a real ``roost-agent`` process.

Two simulated autopilots stream MAVLink over real UDP to the console script started with
``--telemetry-port auto``; the test reads the URL the agent announces on stdout, connects
with a WebSocket client, and checks the samples: at most 10 Hz, the vehicle climbing
(position from GLOBAL_POSITION_INT), health per autopilot, and after a fault the new
active autopilot, the failed one's level and the last failover — all in the stream,
nothing through an API server (there is none here).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from websockets.sync.client import connect

from roost_api.autopilot import FinalAction
from roost_sim import FaultKind, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.flight import make_spec, take_off

pytestmark = pytest.mark.slow


def read_until(url: str, predicate: Any, timeout: float) -> list[dict[str, Any]]:
    """Samples until one satisfies ``predicate`` (all of them returned), or fail."""
    samples: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    with connect(url, open_timeout=5) as ws:
        while time.monotonic() < deadline:
            samples.append(json.loads(ws.recv(timeout=max(0.1, deadline - time.monotonic()))))
            if predicate(samples[-1]):
                return samples
    pytest.fail(f"no matching sample in {timeout} s; last: {samples[-1:]}")


def test_stream_pushes_position_health_and_failover(tmp_path: Path) -> None:
    sims = start_vehicle_sims(["px4", "px4"])
    config = tmp_path / "ra.yaml"
    config.write_text(yaml.safe_dump({"spec": make_spec(sims, FinalAction.HOLD).to_api()}))
    agent = AgentProcess.standalone(
        tmp_path, extra_args=["--config", str(config), "--telemetry-port", "auto"]
    )
    try:
        url = str(agent.wait_for(lambda d: "telemetry" in d, 10)["telemetry"])
        assert url.startswith("ws://127.0.0.1:")
        take_off(sims)
        names = [s.name for s in sims]
        samples = read_until(
            url,
            lambda s: (
                s["position"] is not None
                and s["position"]["down"] < -2.0
                and all(s["health"].get(n) == "OK" for n in names)
            ),
            15,
        )
        last = samples[-1]
        assert last["active"] == names[0]
        assert last["lastFailover"] is None
        assert last["origin"] is not None and -90 <= last["position"]["lat"] <= 90
        assert 0 <= last["position"]["heading"] < 360

        # Rate: ten samples a second at most, never a burst.
        with connect(url) as ws:
            times = [json.loads(ws.recv(timeout=2))["time"] for _ in range(11)]
        assert times[-1] - times[0] >= 0.9, times

        sims[0].inject(FaultKind.SILENCE)
        samples = read_until(url, lambda s: s["active"] == names[1], 10)
        failed = read_until(url, lambda s: s["health"][names[0]] in ("ERROR", "STALE"), 5)[-1]
        assert failed["latched"] is True
        record = failed["lastFailover"]
        assert (record["from"], record["to"]) == (names[0], names[1])
    finally:
        agent.stop()
        stop_sims(sims)


def test_stream_is_off_by_default(tmp_path: Path) -> None:
    sims = start_vehicle_sims(["px4", "px4"])
    config = tmp_path / "ra.yaml"
    config.write_text(yaml.safe_dump({"spec": make_spec(sims, FinalAction.HOLD).to_api()}))
    agent = AgentProcess.standalone(tmp_path, extra_args=["--config", str(config)])
    try:
        agent.wait_for(lambda d: d.get("reason") == "AgentStarted", 10)
        time.sleep(0.5)
        assert not [d for d in agent.read() if "telemetry" in d]
    finally:
        agent.stop()
        stop_sims(sims)
