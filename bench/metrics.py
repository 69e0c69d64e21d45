"""Cost of the agent's Prometheus endpoint: scrape time, and CPU and memory with it on.

A standalone ``roost-agent`` watches three simulated PX4 autopilots streaming at PX4
onboard rates over UDP (about 1400 messages/s in all) with ``--metrics-port``; this
process scrapes ``/metrics`` over HTTP twice a second (Prometheus scrapes every 15 to
60 s: thirty times fewer) and times every scrape from request to the last byte. The same
flight without metrics gives the CPU and memory baseline.

Last, the failover cycles of ``bench.agent`` run with metrics on while this process
scrapes every 50 ms: the decision loop's detection-to-switch time under scraping.

Knobs (environment): ``ROOST_BENCH_METRICS_S`` (seconds per run, default 20),
``ROOST_BENCH_METRICS_FAILOVERS`` (default 20).
"""

from __future__ import annotations

import os
import statistics
import threading
import time
import urllib.request

from bench.agent import cpu_and_memory, failover_cycles, percentile
from bench.core import Figure
from roost_api.ports import free_port

SECONDS = float(os.environ.get("ROOST_BENCH_METRICS_S", "20"))
FAILOVERS = int(os.environ.get("ROOST_BENCH_METRICS_FAILOVERS", "20"))
STACKS = ("px4", "px4", "px4")
COMMAND = "python -m bench metrics"


def run() -> list[Figure]:
    port = free_port()
    url = f"http://127.0.0.1:{port}/metrics"
    scrapes: list[float] = []
    sizes: list[int] = []

    def scrape() -> None:
        start = time.perf_counter()
        with urllib.request.urlopen(url, timeout=5) as response:
            body = response.read()
        scrapes.append((time.perf_counter() - start) * 1000)
        sizes.append(len(body))

    on_cpu, on_rss, on_rate = cpu_and_memory(STACKS, ("--metrics-port", str(port)), scrape, SECONDS)
    off_cpu, off_rss, off_rate = cpu_and_memory(STACKS, seconds=SECONDS)
    stop = threading.Event()
    hammered: list[float] = []

    def hammer() -> None:  # a scrape every 50 ms while the agent fails over
        while not stop.wait(0.05):
            try:
                start = time.perf_counter()
                with urllib.request.urlopen(url, timeout=5) as response:
                    response.read()
                hammered.append((time.perf_counter() - start) * 1000)
            except OSError:
                continue  # between two vehicles: no agent on the port yet

    scraper = threading.Thread(target=hammer, daemon=True)
    scraper.start()
    try:
        detect = failover_cycles(FAILOVERS, ("--metrics-port", str(port))).detect_ms
    finally:
        stop.set()
        scraper.join()
    return [
        Figure(
            "agent.metrics_scrape_ms",
            round(statistics.median(scrapes), 2),
            "ms",
            "",
            COMMAND,
            f"median of {len(scrapes)} scrapes of a roost-agent with 3 autopilots at "
            f"{on_rate:.0f} msg/s, {statistics.median(sizes) / 1000:.1f} kB each; p99 "
            f"{percentile(scrapes, 99):.2f} ms; agent CPU {on_cpu:.0f} ms per 10k messages "
            f"scraped at 2 Hz vs {off_cpu:.0f} without metrics ({off_rate:.0f} msg/s); "
            f"peak RSS {on_rss:.1f} MB vs {off_rss:.1f} MB; detection to switch while "
            f"scraped every 50 ms ({len(hammered)} scrapes): p99 {percentile(detect, 99):.3f} "
            f"ms, max {max(detect):.3f} ms over {len(detect)} failovers",
        ),
    ]
