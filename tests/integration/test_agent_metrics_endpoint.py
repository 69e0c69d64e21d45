"""The agent's Prometheus endpoint, scraped from a real ``roost-agent`` process.

Three simulated autopilots stream MAVLink over real UDP to the console script started
with ``--metrics-port``; the test scrapes ``/metrics`` over HTTP, parses it with
prometheus_client's own parser, fails the active autopilot over and sees the failover
counter and both latency histograms move, the active autopilot change and the link
counters grow.
"""

from __future__ import annotations

import socket
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample

from roost_api.autopilot import FinalAction
from roost_api.ports import free_port
from roost_sim import FaultKind, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.flight import CLEAR_S, make_spec, take_off
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow


def scrape(port: int) -> dict[str, list[Sample]]:
    """Samples by family name (counters without their ``_total`` suffix)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as response:
        text = response.read().decode()
    return {f.name: f.samples for f in text_string_to_metric_families(text)}


def value(samples: list[Sample], name: str, **labels: str) -> float:
    matching = [
        s.value
        for s in samples
        if s.name == name and all(s.labels.get(k) == v for k, v in labels.items())
    ]
    assert len(matching) == 1, (name, labels, samples)
    return matching[0]


def metrics_agent(config: Path, work_dir: Path, port: int) -> AgentProcess:
    """A standalone ``roost-agent`` serving its metrics on ``port``."""
    args = ["--config", str(config), "--metrics-port", str(port)]
    return AgentProcess.standalone(work_dir, extra_args=args)


def test_scraped_agent_counts_a_failover_and_its_latency(tmp_path: Path) -> None:
    sims = start_vehicle_sims(["px4", "px4", "px4"])
    config = tmp_path / "ra.yaml"
    config.write_text(yaml.safe_dump({"spec": make_spec(sims, FinalAction.HOLD).to_api()}))
    port = free_port()
    agent = metrics_agent(config, tmp_path, port)
    try:
        agent.wait_for(lambda d: d.get("reason") == "AgentStarted", 10)
        take_off(sims)

        def all_ok() -> bool:
            levels = scrape(port)["roost_agent_autopilot_health_level"]
            return len(levels) == 3 and all(s.value == 0 for s in levels)

        wait_until("three autopilots OK in the metrics", all_ok, 10, 0.1)
        before = scrape(port)
        assert (
            value(
                before["roost_agent_active_autopilot"],
                "roost_agent_active_autopilot",
                autopilot="fc1",
            )
            == 1
        )
        assert "roost_agent_failovers" not in before or not before["roost_agent_failovers"]
        hist = "roost_agent_failover_detection_to_switch_seconds"
        assert value(before[hist], f"{hist}_count") == 0
        accepted = value(
            before["roost_agent_link_frames"],
            "roost_agent_link_frames_total",
            autopilot="fc2",
            result="accepted",
        )
        assert accepted > 0
        assert (
            value(
                before["roost_agent_link_received_bytes"],
                "roost_agent_link_received_bytes_total",
                autopilot="fc2",
            )
            > accepted
        )

        time.sleep(CLEAR_S + 0.3)  # T_off, a required duration: standbys become targets
        sims[0].inject(FaultKind.SILENCE)
        agent.wait_for(lambda d: d.get("event") == "Failover", 10)

        def counted() -> bool:
            return bool(scrape(port).get("roost_agent_failovers"))

        wait_until("the failover in the metrics", counted, 5, 0.05)
        after = scrape(port)
        assert (
            value(
                after["roost_agent_failovers"],
                "roost_agent_failovers_total",
                reason="FailedOver",
                from_autopilot="fc1",
            )
            == 1
        )
        assert value(after[hist], f"{hist}_count") == 1
        assert value(after[hist], f"{hist}_bucket", le="+Inf") == 1
        onset = "roost_agent_failover_onset_to_switch_seconds"
        assert value(after[onset], f"{onset}_count") == 1
        assert value(after[onset], f"{onset}_sum") > value(after[hist], f"{hist}_sum")
        active = {s.labels["autopilot"]: s.value for s in after["roost_agent_active_autopilot"]}
        assert active["fc1"] == 0 and sum(active.values()) == 1
        assert value(after["roost_agent_latched"], "roost_agent_latched") == 1
        assert (
            value(
                after["roost_agent_autopilot_health_level"],
                "roost_agent_autopilot_health_level",
                autopilot="fc1",
            )
            >= 2  # ERROR, later STALE
        )
        assert (
            value(
                after["roost_agent_link_frames"],
                "roost_agent_link_frames_total",
                autopilot="fc2",
                result="accepted",
            )
            > accepted
        )
        assert agent.stop() == 0
    finally:
        agent.stop()
        stop_sims(sims)


def test_a_taken_metrics_port_does_not_keep_the_agent_from_flying(tmp_path: Path) -> None:
    """Supervising the autopilots matters more than metrics: the agent logs and flies on."""
    sims = start_vehicle_sims(["px4", "px4"])
    config = tmp_path / "ra.yaml"
    config.write_text(yaml.safe_dump({"spec": make_spec(sims).to_api()}))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        agent = metrics_agent(config, tmp_path, port)
        try:
            agent.wait_for(lambda d: d.get("reason") == "AgentStarted", 10)
            take_off(sims)

            def both_ok(doc: dict[str, Any]) -> bool:
                aps = doc.get("status", {}).get("autopilots", [])
                return len(aps) == 2 and all(a["level"] == "OK" for a in aps)

            agent.wait_for(both_ok, 10)
            assert agent.stop() == 0
        finally:
            agent.stop()
            stop_sims(sims)
