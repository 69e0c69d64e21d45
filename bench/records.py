"""Flight records: what recording costs the hub, and how fast the autopilots' logs come.

The vehicle of ``bench.hub`` (two simulated PX4 autopilots over real UDP in flight, an
in-process agent with its hub and a simulated bridge) with a
:class:`~roost_agent.records_recorder.FlightRecorder` on it.

- ``records.hub_added_latency_p99_ms``: the hub's added latency (``bench.hub``'s
  measurement: client COMMAND_LONGs through the hub minus straight to the sim, p99)
  with the recorder tapping every frame minus with it detached, in alternating blocks
  so the machine's drift falls on both.
- ``records.cpu_ms_per_10k_msgs``: the process's CPU time with the recorder tapping and
  writing minus detached, over equal windows, per 10 000 frames it recorded.
- ``records.log_download_kBps``: a 2 MB ULog fetched from a landed autopilot with the
  chart's default pacing (``agent.records.fetchKBps`` 100), and the link's message loss
  meanwhile: MAVLink sequence gaps in what a client of the hub receives from the
  autopilot (its telemetry and the LOG_DATA) during the download.
"""

from __future__ import annotations

import itertools
import statistics
import tempfile
import time
from pathlib import Path

import psutil

from bench.core import Figure
from bench.hub import VEHICLE_SYSID, _added_latency, _percentile, _vehicle
from roost_agent import Agent
from roost_agent.records_logs import FetchSettings, LogFetcher
from roost_agent.records_recorder import FlightRecorder
from roost_mavlink import MAV_CMD_NAV_LAND
from roost_sim import SimulatedAutopilot
from roost_sim.logs import Sample, StoredLog, ulog_bytes
from tests.support.hubclient import HubClient, Received

COMMAND = "python -m bench records"
BLOCKS = 4
BLOCK_SAMPLES = 600
CPU_WINDOW_S = 8.0
LOG_BYTES = 2_000_000
FETCH_KBPS = 100.0


def _set_tapping(recorder: FlightRecorder, on: bool) -> None:
    recorder.paused = not on
    recorder.step()  # attaches or detaches the links now


def _latency(
    sims: list[SimulatedAutopilot], agent: Agent, recorder: FlightRecorder
) -> tuple[list[float], list[float], list[float], list[float]]:
    on_via: list[float] = []
    on_direct: list[float] = []
    off_via: list[float] = []
    off_direct: list[float] = []
    for _ in range(BLOCKS):
        for on, via_out, direct_out in ((False, off_via, off_direct), (True, on_via, on_direct)):
            _set_tapping(recorder, on)
            via, direct = _added_latency(sims, agent, samples=BLOCK_SAMPLES)
            via_out.extend(via)
            direct_out.extend(direct)
    return on_via, on_direct, off_via, off_direct


def _cpu(recorder: FlightRecorder) -> tuple[float, int]:
    me = psutil.Process()

    def cpu_s() -> float:
        times = me.cpu_times()
        return float(times.user + times.system)

    _set_tapping(recorder, False)
    start = cpu_s()
    time.sleep(CPU_WINDOW_S)  # not a wait for a condition: the detached window
    off = cpu_s() - start
    _set_tapping(recorder, True)
    mark = recorder.frames_written
    start = cpu_s()
    time.sleep(CPU_WINDOW_S)  # not a wait for a condition: the recording window
    on = cpu_s() - start
    recorder.step()
    frames = recorder.frames_written - mark
    extra_ms = max(0.0, on - off) * 1000
    return (extra_ms * 10_000 / frames if frames else float("nan")), frames


def _big_log() -> bytes:
    """A ULog of about :data:`LOG_BYTES` (29 bytes a sample), built before the vehicle
    runs: building it holds the interpreter for seconds, which would stall the sims."""
    samples = [
        Sample(i * 100_000, 1_700_000_000_000_000 + i, 1.0, 2.0, 5.0, 0.0, True, 1, "m")
        for i in range(LOG_BYTES // 29)
    ]
    return ulog_bytes(samples, {})


def _loss(frames: list[Received]) -> float:
    """Sequence gaps over what arrived and what did not (one sender)."""
    seqs = [int(r.msg.get_seq()) for r in frames]
    lost = sum((b - a - 1) % 256 for a, b in itertools.pairwise(seqs))
    return lost / (lost + len(seqs)) if seqs else float("nan")


def _land(sims: list[SimulatedAutopilot], agent: Agent) -> None:
    assert agent.hub is not None
    with HubClient(agent.hub.udp_address) as client:
        client.wait_for(lambda r: r.kind == "HEARTBEAT", 10)
        client.command(VEHICLE_SYSID, MAV_CMD_NAV_LAND)
    for sim in sims:
        sim.wait_until(lambda s: not s.armed, timeout=60)


def _download(
    sims: list[SimulatedAutopilot], agent: Agent, data: bytes
) -> tuple[float, float, float, int]:
    """(kB/s, loss during the download, loss over as long after it, frames seen)."""
    active = next(s for s in sims if s.name == agent.active)
    log_id = (active.logs.logs[-1].id if active.logs.logs else 0) + 1
    active.logs.logs.append(StoredLog(log_id, 0, data, len(data)))
    assert agent.hub is not None
    link = agent.links[active.name]
    fetcher = LogFetcher(
        lambda: {active.name: link}, settings=FetchSettings(rate_bytes_per_s=FETCH_KBPS * 1000)
    )
    with tempfile.TemporaryDirectory() as tmp, HubClient(agent.hub.udp_address) as client:
        client.wait_for(lambda r: r.kind == "HEARTBEAT", 10)
        started = time.monotonic()
        fetcher(Path(tmp), lambda change: None)
        seconds = time.monotonic() - started
        during = [r for r in client.received if r.at >= started]
        client.received.clear()
        time.sleep(seconds)  # not a wait for a condition: the baseline window
        after = list(client.received)
        fetched = (Path(tmp) / "autopilot-logs" / active.name / f"{log_id}.ulg").read_bytes()
    assert fetched == data, "the fetched log differs from the autopilot's"
    return len(data) / seconds / 1000, _loss(during), _loss(after), len(during)


def run() -> list[Figure]:
    data = _big_log()
    with _vehicle() as (sims, agent), tempfile.TemporaryDirectory() as tmp:
        recorder = FlightRecorder(agent, Path(tmp) / "records", budget_bytes=10**9)
        recorder.start()
        try:
            on_via, on_direct, off_via, off_direct = _latency(sims, agent, recorder)
            cpu, frames = _cpu(recorder)
        finally:
            recorder.stop()
        _land(sims, agent)  # landed and disarmed: the logs may be fetched
        rate, loss, baseline, seen = _download(sims, agent, data)
    added_on = _percentile(on_via, 0.99) - _percentile(on_direct, 0.99)
    added_off = _percentile(off_via, 0.99) - _percentile(off_direct, 0.99)
    return [
        Figure(
            "records.hub_added_latency_p99_ms",
            round(added_on - added_off, 3),
            "ms",
            "<= 0.2",
            COMMAND,
            f"hub added latency p99 with the recorder tapping {added_on:.3f} ms vs detached "
            f"{added_off:.3f} ms ({BLOCKS} alternating blocks of {BLOCK_SAMPLES} client "
            f"COMMAND_LONGs each way, two PX4 sims in flight); median via the hub "
            f"{statistics.median(on_via):.3f} vs {statistics.median(off_via):.3f} ms",
        ),
        Figure(
            "records.cpu_ms_per_10k_msgs",
            round(cpu, 2),
            "ms",
            "informational",
            COMMAND,
            f"process CPU with the recorder tapping and writing minus detached, "
            f"{CPU_WINDOW_S:.0f} s each; {frames} frames recorded (tlog written, fsynced "
            "0.8 s apart)",
        ),
        Figure(
            "records.log_download_kBps",
            round(rate, 1),
            "kB/s",
            "informational",
            COMMAND,
            f"a {len(data) / 1e6:.1f} MB ULog over the simulator's UDP link paced at the "
            f"chart's default {FETCH_KBPS:.0f} kB/s (LOG_REQUEST_DATA windows of 5760 B); the "
            f"link's message loss meanwhile {loss * 100:.2f}% vs {baseline * 100:.2f}% over "
            f"as long after it ({seen} frames at a hub client, sequence gaps counted)",
        ),
    ]
