"""The dashboard's latency and cost, measured in a real browser (``python -m bench dashboard``).

``dashboard.state_to_dom_p99_ms``: a standalone ``roost-agent`` watches two flying
simulated autopilots and streams its state (``--telemetry-port auto``); ``roost
dashboard --no-cluster`` follows that stream and pushes to a headless Chromium. The page
records, for every sample it shows, the time from the agent taking the sample (its wall
clock, the same host's) to the DOM holding it — the agent samples when it sends, so this
is state-in-the-agent to state-on-screen, less at most one send period (100 ms) for a
change that happens just after a sample.

``dashboard.frame_ms_p99_100_vehicles`` and ``dashboard.backend_cpu_pct_100_vehicles``:
100 synthetic vehicles, each a real :class:`roost_agent.telemetry.TelemetryServer` (its
own port, 10 Hz) over a vehicle that flies a circle and, every few seconds, fails over —
so positions, trails, health and the timeline all change. The dashboard process follows
the 100 streams and pushes to the browser; the page times how long applying each
document takes (``frame``), and psutil reads the dashboard process's CPU (percent of one
core) over the same window. Synthetic streams stand in for 100 agents because 100 real
agents with 200 simulators do not fit on two cores.

Knobs (environment): ``ROOST_BENCH_DASHBOARD_S`` (seconds per measurement, default 20).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import psutil

from bench.agent import percentile, vehicle
from bench.core import Figure
from roost_agent.health import Fix
from roost_agent.telemetry import TelemetryServer
from roost_api.autopilot import FailoverTrigger, Thresholds
from roost_api.meta import HealthLevel
from roost_api.plain import FailoverRecord
from roost_api.telemetry import Origin
from tests.support.browser import chromium, wait_for

SECONDS = float(os.environ.get("ROOST_BENCH_DASHBOARD_S", "20"))
VEHICLES = 100
COMMAND = "python -m bench dashboard"
BIN = Path(sys.executable).parent
ANNOUNCE = re.compile(r"Roost dashboard on (http://\S+/)")
ORIGIN = Origin(47.397742, 8.545594)
METRES_PER_DEG_LAT = 111_320.0


@dataclass(frozen=True)
class _Level:
    level: HealthLevel


@dataclass
class _Link:
    vehicle: SyntheticVehicle

    def fix(self) -> Fix:
        return self.vehicle.position()


@dataclass
class SyntheticVehicle:
    """A vehicle flying a 10 m circle around its own point, failing over now and then."""

    name: str
    index: int
    started: float = field(default_factory=time.monotonic)
    last_failover: FailoverRecord | None = None

    @property
    def vehicle_name(self) -> str:
        return self.name

    def _cycle(self) -> int:
        return int((time.monotonic() - self.started + self.index * 0.37) / 6.0)

    @property
    def active(self) -> str:
        return "fc-b" if self._cycle() % 2 else "fc-a"

    @property
    def latched(self) -> bool:
        return self.active == "fc-b"

    @property
    def links(self) -> Mapping[str, _Link]:
        return {"fc-a": _Link(self), "fc-b": _Link(self)}

    def assessments(self) -> dict[str, _Level]:
        failed = self.active == "fc-b"
        if failed and (self.last_failover is None or self.last_failover.to_autopilot != "fc-b"):
            self.last_failover = FailoverRecord(
                time=datetime.now(UTC),
                from_autopilot="fc-a",
                to_autopilot="fc-b",
                reason="fc-a silent (synthetic)",
                trigger=FailoverTrigger.AUTOMATIC,
                latency_ms=0.3,
            )
        return {
            "fc-a": _Level(HealthLevel.STALE if failed else HealthLevel.OK),
            "fc-b": _Level(HealthLevel.OK),
        }

    def position(self) -> Fix:
        t = time.monotonic() - self.started
        row, col = divmod(self.index, 10)
        angle = t * 0.5 + self.index
        north = row * 30 + 10 * math.sin(angle)
        east = col * 30 + 10 * math.cos(angle)
        lat = ORIGIN.lat + north / METRES_PER_DEG_LAT
        lon = ORIGIN.lon + east / (METRES_PER_DEG_LAT * math.cos(math.radians(ORIGIN.lat)))
        return Fix(lat, lon, 5.0, math.degrees(angle) % 360, time.monotonic())


@contextmanager
def dashboard(agents: Mapping[str, str], log: Path) -> Iterator[tuple[str, psutil.Process]]:
    """``roost dashboard --no-cluster`` following ``agents``: its URL and process."""
    argv = [str(BIN / "roost"), "dashboard", "--no-cluster", "--port", "0"]
    for name, url in agents.items():
        argv += ["--agent", f"{name}={url}"]
    with log.open("w") as out:
        proc = subprocess.Popen(
            argv, stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "COLUMNS": "400"}
        )
    try:
        deadline = time.monotonic() + 30
        while not (found := ANNOUNCE.search(log.read_text())):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the dashboard did not start: {log.read_text()}")
            time.sleep(0.1)
        yield found.group(1), psutil.Process(proc.pid)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def state_to_dom(work: Path) -> tuple[float, float, int]:
    """(p50, p99 ms, samples) from an agent's sample to the page's DOM."""
    with vehicle(Thresholds(), extra_args=("--telemetry-port", "auto")) as (_, agent):
        url = next(str(d["telemetry"]) for d in agent.events() if "telemetry" in d)
        with (
            dashboard({"bench": url}, work / "dashboard-1.log") as (page, _),
            chromium(work / "chromedriver-1.log") as driver,
        ):
            driver.get(page)
            wait_for(
                driver,
                "the vehicle live",
                "return window.__roost.doc && window.__roost.doc.vehicles.length === 1"
                " && window.__roost.doc.vehicles[0].telemetry === 'live'",
                30,
            )
            driver.execute_script("window.__roost.latencies = []")
            time.sleep(SECONDS)
            latencies: list[float] = driver.execute_script("return window.__roost.latencies")
    return percentile(latencies, 50), percentile(latencies, 99), len(latencies)


def hundred_vehicles(work: Path) -> tuple[float, float, float, float]:
    """(frame p99 ms, frame p50 ms, dashboard CPU %, documents per second)."""
    fleet = [SyntheticVehicle(f"v{i:03d}", i) for i in range(VEHICLES)]
    with ExitStack() as stack:
        servers = []
        for v in fleet:
            server = TelemetryServer(v, origin=ORIGIN)
            stack.callback(server.close)
            servers.append(server)
        agents = {v.name: s.url for v, s in zip(fleet, servers, strict=True)}
        page, proc = stack.enter_context(dashboard(agents, work / "dashboard-100.log"))
        driver = stack.enter_context(chromium(work / "chromedriver-100.log"))
        driver.get(page)
        wait_for(
            driver,
            f"{VEHICLES} vehicles live",
            "return window.__roost.doc && window.__roost.doc.vehicles"
            ".filter((v) => v.telemetry === 'live').length === arguments[0]",
            60,
            VEHICLES,
        )
        driver.execute_script("window.__roost.frames = []; window.__roost.documents = 0")
        cpu0, t0 = sum(proc.cpu_times()[:2]), time.monotonic()
        time.sleep(SECONDS)
        cpu1, t1 = sum(proc.cpu_times()[:2]), time.monotonic()
        frames: list[float] = driver.execute_script("return window.__roost.frames")
        documents: int = driver.execute_script("return window.__roost.documents")
    seconds = t1 - t0
    cpu = (cpu1 - cpu0) / seconds * 100
    return percentile(frames, 99), percentile(frames, 50), cpu, documents / seconds


def run() -> list[Figure]:
    with tempfile.TemporaryDirectory(prefix="roost-bench-dashboard-") as tmp:
        work = Path(tmp)
        p50, p99, samples = state_to_dom(work)
        frame_p99, frame_p50, cpu, rate = hundred_vehicles(work)
    return [
        Figure(
            "dashboard.state_to_dom_p99_ms",
            p99,
            "ms",
            "<= 250",
            COMMAND,
            f"agent sample -> DOM in headless Chromium, real agent + 2 flying sims; p50 "
            f"{p50:.0f} ms over {samples} samples in {SECONDS:.0f} s",
        ),
        Figure(
            "dashboard.frame_ms_p99_100_vehicles",
            frame_p99,
            "ms",
            "<= 16",
            COMMAND,
            f"applying one pushed document (arena, table, missions, timeline) in the page; "
            f"{VEHICLES} synthetic vehicles at 10 Hz; p50 {frame_p50:.1f} ms, "
            f"{rate:.1f} documents/s",
        ),
        Figure(
            "dashboard.backend_cpu_pct_100_vehicles",
            cpu,
            "%",
            "<= 50",
            COMMAND,
            f"roost dashboard process (percent of one core) following {VEHICLES} streams "
            f"at 10 Hz and pushing to one browser",
        ),
    ]
