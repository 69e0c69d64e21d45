"""A ``roost-agent`` process killed in flight (SIGKILL, as a power cut to the companion
computer) leaves a tlog that pymavlink reads to within about the last second; the
restarted agent closes that flight as Failed with why, and serves it over HTTP.

Real agent process, two simulated PX4 autopilots over real UDP (in this process), the
simulated bridge (no GPIO here)."""

from __future__ import annotations

import http.client
import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymavlink import mavutil

from roost_agent.records import read_manifests
from roost_agent.records_recorder import SYNC_PERIOD_S, WRITE_PERIOD_S
from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.ports import free_port
from roost_api.records import FlightState
from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.model import SimConfig
from roost_sim.vehicle import autopilot_specs, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow


@pytest.fixture
def sims() -> Iterator[list[SimulatedAutopilot]]:
    started = start_vehicle_sims(["px4", "px4"], config=SimConfig.fast())
    try:
        yield started
    finally:
        stop_sims(started)


def _last_tlog_time(path: Path) -> tuple[float, int]:
    tlog = mavutil.mavlink_connection(str(path))
    last, count = 0.0, 0
    while (msg := tlog.recv_match()) is not None:
        if msg.get_type() != "BAD_DATA":
            last, count = msg._timestamp, count + 1
    return last, count


def _get(port: int, path: str) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path)
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        conn.close()


def _recording_agent(
    tmp_path: Path, sims: list[SimulatedAutopilot], vehicle: str, port: int
) -> AgentProcess:
    """A started roost-agent recording into ``tmp_path/records``."""
    spec = RedundantAutopilotSpec(
        vehicle_name=vehicle, autopilots=autopilot_specs(sims), primary=sims[0].name
    )
    args = ["--records-dir", str(tmp_path / "records"), "--records-port", str(port)]
    return AgentProcess.standalone(tmp_path / "agent", spec, extra_args=args)


def test_a_killed_agent_loses_at_most_about_the_last_second(
    tmp_path: Path, sims: list[SimulatedAutopilot]
) -> None:
    records = tmp_path / "records"
    agent = _recording_agent(tmp_path, sims, "crashy", 0)
    try:
        agent.wait_ok([s.name for s in sims])
        for sim in sims:
            sim.wait_ready(timeout=10)
            sim.fly(3.0)
        wait_until("a flight on disk", lambda: read_manifests(records), 10)
        flight = records / read_manifests(records)[0].flight_id
        # a few write rounds into the flight, then the power goes
        wait_until("frames written", lambda: (flight / "hub.tlog").stat().st_size > 20_000, 15)
        agent.crash()
        killed_at = time.time()
        last, count = _last_tlog_time(flight / "hub.tlog")
        assert count > 100
        # the writer is at most one round behind, and no record is torn but the last
        assert killed_at - last <= WRITE_PERIOD_S + SYNC_PERIOD_S
        [manifest] = read_manifests(records)
        assert manifest.state is FlightState.RECORDING  # nobody closed it

        agent = _recording_agent(tmp_path, sims, "crashy", 0)
        wait_until(
            "the crashed flight closed",
            lambda: read_manifests(records)[-1].state is FlightState.FAILED,
            10,
        )
        closed = read_manifests(records)[-1]
        assert "the agent stopped during the flight" in closed.message
        tlog = closed.file("hub.tlog")
        assert tlog is not None and tlog.sha256 is not None and tlog.bytes > 20_000
        # the restarted agent recorded the flight still going on; stopped, it says so
        wait_until("a second flight", lambda: len(read_manifests(records)) == 2, 10)
        agent.stop()
        stopped = read_manifests(records)[0]
        assert stopped.state is FlightState.FAILED
        assert stopped.message == "the agent was stopped during the flight"
    finally:
        agent.stop()


def test_the_agent_serves_its_records_on_the_records_port(
    tmp_path: Path, sims: list[SimulatedAutopilot]
) -> None:
    port = free_port()
    agent = _recording_agent(tmp_path, sims, "served", port)
    try:
        announced = agent.wait_for(lambda doc: "records" in doc, 15)
        assert announced["records"] == f"http://127.0.0.1:{port}/records"
        status, body = _get(port, "/records")
        assert status == 200
        assert json.loads(body) == {"vehicle": "served", "flights": []}
    finally:
        agent.stop()
