"""Node-agent benchmarks: failover latency, link-loss detection next to MAVSDK and
MAVProxy, false failovers under loss and jitter, CPU time and resident memory.

How it measures: the agent runs as its own process (``roost-agent``, standalone,
simulated bridge, normal priority), as on a vehicle. The simulated autopilots
(``roost_sim``) stand for flight controllers, which are microcontrollers of their own
that no load on the companion computer can stall. In the silent-onset figures at the
defaults (``onset``, ``defaults``) and in every soak (``soak``, ``defaults``,
``starved``) they run that way: ``roost-sim run`` in a process of its own under
``SCHED_RR`` (:mod:`tests.support.simprocess`), so a busy host starves the agent (what
``starved`` is about) and never the autopilots, and an ERROR judgement in a soak is the
agent's, not a simulator's stall. Every ERROR judgement of a (healthy) autopilot in a
soak is a false one: ``failover.healthy_errors_10min_*`` count them beside the false
failovers, target 0. The other parts run the sims in this process (threads sharing the
bench's interpreter), as they were measured.

The agent is the build the image ships: its per-message path compiled by mypyc
(``tests.support.compiled``); ``agent.cpu_ms_per_10k_msgs_interpreted`` measures the same
agent from the checkout's Python modules (with the hand-written C extension, which every
install builds), for comparison. The agent prints every failover
as a JSON line that carries CLOCK_MONOTONIC timestamps (``time.monotonic()`` is that
clock in every process on one host), so a fault onset taken here when the fault is
injected and the bridge switch taken there are compared directly. Commands (ClearLatch,
Switch) reach the agent the standalone way: a new ``command`` in its config file and
SIGHUP.

Knobs (environment): ``ROOST_BENCH_FAILOVERS`` (failovers for the latency figures,
default 100), ``ROOST_BENCH_HEARTBEAT_FAILOVERS`` (default 12), ``ROOST_BENCH_PEER_SAMPLES``
(default 3), ``ROOST_BENCH_CPU_S`` (default 30), ``ROOST_BENCH_SOAK_S`` (healthy flight
under 5 % loss and 50 ms jitter, default 600: the committed figure must come from 600),
``ROOST_BENCH_AGENT_PARTS`` (a comma-separated subset of :data:`PARTS`, default all).
The ``replay`` part reads the recorded firmware traffic where the replay tests find it
(``$ROOST_CAPTURES_DIR``, else ``shared/captures`` beside the repository); ``starved``
runs the default soak while one busy-looping process per core competes for the CPU.
"""

from __future__ import annotations

import math
import os
import queue
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import psutil

from bench.core import Figure
from roost_agent.agent import STEERED_TICK_S
from roost_agent.health import LEARN_WINDOWS
from roost_api.autopilot import (
    AutopilotSpec,
    FailoverMode,
    FailoverPolicy,
    FinalAction,
    RedundantAutopilotSpec,
    SafetyRoutine,
    Thresholds,
)
from roost_api.meta import HealthLevel
from roost_sim import (
    FaultKind,
    SimConfig,
    SimulatedAutopilot,
    autopilot_specs,
    message_id,
    start_vehicle_sims,
    stop_sims,
)
from roost_sim.streams import PX4_STREAMS
from tests.support.agent import AgentProcess
from tests.support.compiled import compiled_tree
from tests.support.compiled import environment as compiled_environment
from tests.support.flight import take_off
from tests.support.simprocess import REALTIME_PRIORITY, FaultTarget, RemoteSim, SimProcess

FAILOVERS = int(os.environ.get("ROOST_BENCH_FAILOVERS", "100"))
HEARTBEAT_FAILOVERS = int(os.environ.get("ROOST_BENCH_HEARTBEAT_FAILOVERS", "12"))
PEER_SAMPLES = int(os.environ.get("ROOST_BENCH_PEER_SAMPLES", "3"))
CPU_S = float(os.environ.get("ROOST_BENCH_CPU_S", "30"))
SOAK_S = float(os.environ.get("ROOST_BENCH_SOAK_S", "600"))
PARTS = (
    "cpu",
    "cluster",
    "failover",
    "heartbeat",
    "peer",
    "soak",
    "defaults",
    "onset",
    "replay",
    "starved",
)
# "onset" is the first half of "defaults" (its silent onsets without the soak), to measure
# again alone; the default run has it once, inside "defaults".
DEFAULT_PARTS = ",".join(p for p in PARTS if p != "onset")
SELECTED = [p for p in os.environ.get("ROOST_BENCH_AGENT_PARTS", DEFAULT_PARTS).split(",") if p]
COMMAND = "make bench (python -m bench agent)"

# Tuned for 50 Hz telemetry: silent after 200 ms (10 missed ATTITUDE samples), confirm
# 20 ms. The false-failover soak runs with the same thresholds, which is what makes them
# defensible.
FAST = Thresholds(message_warn_ms=100, message_error_ms=200, confirm_ms=20, clear_ms=300)
# Every PX4 stream off but HEARTBEAT and 1 Hz status: liveness from heartbeats alone.
HEARTBEAT_ONLY_RATES = {
    **{msg_id: 0.0 for msg_id in PX4_STREAMS if msg_id != message_id("HEARTBEAT")},
    message_id("SYS_STATUS"): 1.0,
    message_id("EXTENDED_SYS_STATE"): 1.0,
}
# The simulated PX4 streams its onboard link's real set and rates (~400 messages/s).
PX4_ONBOARD_RATES: dict[int, float] = {}
SIMS_APART = (
    f"the sims in a process of their own at SCHED_RR priority {REALTIME_PRIORITY}, as "
    "autopilots on their own MCUs; the agent at normal priority"
)


def percentile(values: list[float], q: float) -> float:
    """Nearest-rank percentile (q in 0..100)."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(q / 100 * len(ordered)) - 1)]


@contextmanager
def vehicle(
    thresholds: Thresholds,
    rates: dict[int, float] | None = None,
    status_interval_s: float = 0.25,
    mode: FailoverMode = FailoverMode.AUTOMATIC,
    *,
    stacks: Sequence[str] = ("px4", "px4"),
    extra_args: Sequence[str] = (),
) -> Iterator[tuple[list[SimulatedAutopilot], AgentProcess]]:
    """Two flying PX4 sims in this process and an agent watching them, standbys ready
    (``mode`` Manual: the agent judges but never switches on its own)."""
    sims = start_vehicle_sims(list(stacks), rates=rates, config=SimConfig.fast())
    try:
        specs = autopilot_specs(sims)
        with _flying(
            thresholds,
            specs,
            lambda: take_off(sims),
            status_interval_s=status_interval_s,
            mode=mode,
            extra_args=extra_args,
        ) as agent:
            yield sims, agent
    finally:
        stop_sims(sims)


@contextmanager
def vehicle_apart(
    thresholds: Thresholds, stacks: Sequence[str] = ("px4", "px4")
) -> Iterator[tuple[list[RemoteSim], AgentProcess]]:
    """As :func:`vehicle`, the sims in a process of their own at real-time priority
    (:mod:`tests.support.simprocess`, the firmware's default rates), as autopilots on
    their own MCUs."""
    with (
        SimProcess(stacks) as process,
        _flying(thresholds, process.specs(), process.take_off) as agent,
    ):
        yield process.sims, agent


@contextmanager
def _flying(
    thresholds: Thresholds,
    specs: list[AutopilotSpec],
    take_off_all: Callable[[], None],
    *,
    status_interval_s: float = 0.25,
    mode: FailoverMode = FailoverMode.AUTOMATIC,
    extra_args: Sequence[str] = (),
) -> Iterator[AgentProcess]:
    """The agent over ``specs``, the autopilots airborne, every standby ready."""
    with vehicle_agent(thresholds, specs, status_interval_s, mode, extra_args) as agent:
        take_off_all()
        agent.wait_ok([s.name for s in specs])
        # The any-message age applies once a full rate window has been seen (1 s).
        time.sleep(thresholds.clear_ms / 1000 + 1.5)
        yield agent


@contextmanager
def vehicle_agent(
    thresholds: Thresholds,
    specs: list[AutopilotSpec],
    status_interval_s: float = 0.25,
    mode: FailoverMode = FailoverMode.AUTOMATIC,
    extra_args: Sequence[str] = (),
) -> Iterator[AgentProcess]:
    """A standalone agent (its own process, normal priority) over ``specs``, fc1 primary."""
    agent: AgentProcess | None = None
    with tempfile.TemporaryDirectory(prefix="roost-bench-agent-") as tmp:
        try:
            spec = RedundantAutopilotSpec(
                vehicle_name="bench",
                autopilots=specs,
                primary="fc1",
                failover_policy=FailoverPolicy(
                    mode=mode,
                    thresholds=thresholds,
                    safety_routine=SafetyRoutine(hold_seconds=0, final_action=FinalAction.HOLD),
                ),
            )
            agent = AgentProcess.standalone(
                Path(tmp),
                spec,
                status_interval_s=status_interval_s,
                log_level="WARNING",
                extra_args=extra_args,
            )
            yield agent
        finally:
            if agent is not None:
                agent.stop()


def _by_name(sims: Sequence[FaultTarget]) -> dict[str, FaultTarget]:
    return {s.name: s for s in sims}


def _recover(agent: AgentProcess, sim: FaultTarget, thresholds: Thresholds) -> None:
    """Clear the fault, unlatch, and wait until the failed autopilot is a target again."""
    sim.clear()
    assert agent.command("ClearLatch")["result"] == "Executed"
    agent.wait_ok([sim.name])
    time.sleep(thresholds.clear_ms / 1000 + 0.1)


ALTERNATING_FAULTS: list[tuple[FaultKind, str | None]] = [
    (FaultKind.SILENCE, None),
    (FaultKind.STATE, "EMERGENCY"),
    (FaultKind.SILENCE, None),
    (FaultKind.SENSOR, "gyro"),
]


@dataclass
class Cycles:
    """What :func:`failover_cycles` measured, in ms: detection -> switch for every
    failover, onset -> switch for the silences (from the injection) and for the
    MAV_STATE claims (from the claiming heartbeat's arrival, as the agent stamped it)."""

    detect_ms: list[float] = field(default_factory=list)
    silent_ms: list[float] = field(default_factory=list)
    limits_ms: list[int] = field(default_factory=list)  # the learnt silence thresholds
    claim_ms: list[float] = field(default_factory=list)


def failover_cycles(
    count: int = FAILOVERS,
    extra_args: Sequence[str] = (),
    thresholds: Thresholds = FAST,
    faults: Sequence[tuple[FaultKind, str | None]] = ALTERNATING_FAULTS,
    *,
    apart: bool = False,
) -> Cycles:
    """Faults in turn on whichever autopilot is active (``apart``: as :func:`vehicle`,
    and each autopilot silenced only once its last silence has left the learning
    windows: :func:`rest_after_outage`)."""
    cycles = Cycles()
    fleet = vehicle_apart(thresholds) if apart else vehicle(thresholds, extra_args=extra_args)
    with fleet as (sims, agent):
        by_name, active = _by_name(sims), "fc1"
        recovered = dict.fromkeys(by_name, time.monotonic())
        for i in range(count):
            kind, value = faults[i % len(faults)]
            if apart:
                rest_after_outage(recovered.get(active))
            onset = time.monotonic()
            by_name[active].inject(kind, value)
            event = agent.wait_for(lambda d: d.get("event") == "Failover", 10)
            cycles.detect_ms.append(float(event["latencyMs"]))
            switched_at = event["monotonic"]["switchedAt"]
            if kind is FaultKind.SILENCE:
                cycles.silent_ms.append((switched_at - onset) * 1000)
                cycles.limits_ms.extend(silence_limits([event]))
            claimed_at = event["monotonic"]["onsetAt"]
            if kind is FaultKind.STATE and claimed_at is not None:
                cycles.claim_ms.append((switched_at - claimed_at) * 1000)
            _recover(agent, by_name[active], thresholds)
            recovered[active] = time.monotonic()
            active = event["failover"]["to"]
    return cycles


def rest_after_outage(recovered_at: float | None) -> None:
    """Wait until an autopilot's last outage, or its streams' start, has left its
    learning windows. An outage shorter than the ceiling is learnt as a gap of its
    stream, and so are the longer gaps while requested streams start, so for
    LEARN_WINDOWS seconds after either the silence threshold sits higher, up to the
    ceiling (conservative by design). The onset figures measure an autopilot going
    silent out of a steady stream, not one that stalled or started seconds before."""
    if recovered_at is not None:
        time.sleep(max(0.0, recovered_at + LEARN_WINDOWS + 1.0 - time.monotonic()))


def heartbeat_only_cycles() -> list[float]:
    """Silent autopilot that streams nothing faster than 1 Hz, default thresholds."""
    onset_ms: list[float] = []
    defaults = Thresholds()
    with vehicle(defaults, HEARTBEAT_ONLY_RATES) as (sims, agent):
        by_name, active = _by_name(sims), "fc1"
        for _ in range(HEARTBEAT_FAILOVERS):
            onset = time.monotonic()
            by_name[active].inject(FaultKind.SILENCE)
            event = agent.wait_for(lambda d: d.get("event") == "Failover", 15)
            onset_ms.append((event["monotonic"]["switchedAt"] - onset) * 1000)
            _recover(agent, by_name[active], defaults)
            active = event["failover"]["to"]
    return onset_ms


class MavproxyWatch:
    """MAVProxy on the autopilot's UDP port; reports when it says the link is down/OK."""

    def __init__(self, host: str, port: int, workdir: Path) -> None:
        exe = Path(sys.executable).with_name("mavproxy.py")
        self.proc = subprocess.Popen(
            [str(exe), f"--master=udpout:{host}:{port}", "--daemon", "--non-interactive"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=workdir,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.lines: queue.Queue[tuple[float, str]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put((time.monotonic(), line.strip()))

    def wait_for(self, text: str, timeout: float) -> float:
        deadline = time.monotonic() + timeout
        while True:
            at, line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            if text in line:
                return at

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def peer_link_lost() -> tuple[list[float], list[float], list[float]]:
    """One silent autopilot watched at once by the agent, MAVSDK and MAVProxy."""
    from mavsdk import ComponentType, Configuration, Mavsdk  # noqa: PLC0415 - bench only

    agent_ms: list[float] = []
    mavsdk_ms: list[float] = []
    mavproxy_ms: list[float] = []
    with vehicle(FAST) as (sims, agent), tempfile.TemporaryDirectory() as tmp:
        fc1 = _by_name(sims)["fc1"]
        host, port = fc1.link.local_address  # type: ignore[attr-defined]
        mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        mavproxy = MavproxyWatch(host, port, Path(tmp))
        try:
            mavsdk.add_any_connection(f"udpout://{host}:{port}")
            system = mavsdk.first_autopilot(10.0)
            assert system is not None
            changes: queue.Queue[tuple[float, bool]] = queue.Queue()
            handle = system.subscribe_is_connected(
                lambda connected, _: changes.put((time.monotonic(), bool(connected)))
            )
            mavproxy.wait_for("online system", 20)
            for _ in range(PEER_SAMPLES):
                while not system.is_connected():
                    time.sleep(0.05)
                time.sleep(1.0)
                _ = [changes.get_nowait() for _ in range(changes.qsize())]
                onset = time.monotonic()
                fc1.inject(FaultKind.SILENCE)
                event = agent.wait_for(lambda d: d.get("event") == "Failover", 10)
                agent_ms.append((event["monotonic"]["switchedAt"] - onset) * 1000)
                lost_at, connected = changes.get(timeout=20)
                assert not connected
                mavsdk_ms.append((lost_at - onset) * 1000)
                mavproxy_ms.append((mavproxy.wait_for("link 1 down", 20) - onset) * 1000)
                _recover(agent, fc1, FAST)
                mavproxy.wait_for("link 1 OK", 20)
                assert agent.command("Switch", "fc1")["result"] == "Executed"
            system.unsubscribe_is_connected(handle)
        finally:
            mavproxy.stop()
            mavsdk.destroy()
    return agent_ms, mavsdk_ms, mavproxy_ms


def cpu_and_memory(
    stacks: Sequence[str] = ("px4", "px4"),
    extra_args: Sequence[str] = (),
    meanwhile: Callable[[], None] = lambda: None,
    seconds: float = CPU_S,
) -> tuple[float, float, float]:
    """(CPU ms per 10k messages, peak RSS MB, messages/s) at PX4 onboard stream rates;
    ``meanwhile`` runs every half second of the measurement (a scraper, say)."""
    with vehicle(Thresholds(), PX4_ONBOARD_RATES, 1.0, stacks=stacks, extra_args=extra_args) as (
        _,
        agent,
    ):
        proc = psutil.Process(agent.pid)
        time.sleep(2.0)

        def messages() -> int:
            return sum(c["accepted"] + c["foreign"] + c["bad"] for c in agent.links.values())

        cpu0, msgs0, t0 = sum(proc.cpu_times()[:2]), messages(), time.monotonic()
        peak = 0.0
        while time.monotonic() - t0 < seconds:
            peak = max(peak, proc.memory_info().rss / 1e6)
            meanwhile()
            time.sleep(0.5)
        cpu1, msgs1, t1 = sum(proc.cpu_times()[:2]), messages(), time.monotonic()
        count = msgs1 - msgs0
        return (cpu1 - cpu0) * 1000 / count * 10_000, peak, count / (t1 - t0)


@dataclass(frozen=True)
class Soak:
    """What :data:`SOAK_S` of healthy flight under loss and jitter produced."""

    failovers: int
    errors: list[str]  # every ERROR judgement, with the other autopilot's warnings near it
    warnings: Counter[str]  # WARN judgements by reason, numbers left out
    received: int  # messages accepted


def false_failovers(thresholds: Thresholds = FAST) -> Soak:
    """Failovers and judgements in SOAK_S of healthy flight with 5 % loss and 50 ms
    jitter on every autopilot link, the sims apart (:data:`SIMS_APART`). Each ERROR comes
    with the other autopilot's warnings within a second of it: both late at once points
    at the agent's host, not at one link."""
    with vehicle_apart(thresholds) as (sims, agent):
        for sim in sims:
            sim.inject(FaultKind.LOSS, 5)
            sim.inject(FaultKind.JITTER, 50)
        start = sum(c["accepted"] for c in agent.links.values())
        agent.read()
        time.sleep(SOAK_S)
        seen = agent.read()
        received = sum(c["accepted"] for c in agent.links.values()) - start
    failovers = sum(1 for d in seen if d.get("event") == "Failover")
    health = [d for d in seen if d.get("event") == "HealthChanged"]
    judged: list[str] = []
    warnings: Counter[str] = Counter()
    for doc in health:
        if doc["health"]["level"] == "WARN":
            warnings.update(re.sub(r"\d+", "N", r) for r in doc["health"]["reasons"])
        if doc["health"]["level"] in ("OK", "WARN"):
            continue
        at = datetime.fromisoformat(doc["time"])
        nearby = [
            d["message"]
            for d in health
            if d["autopilot"] != doc["autopilot"]
            and abs((datetime.fromisoformat(d["time"]) - at).total_seconds()) <= 1.0
            and d["health"]["level"] != "OK"
        ]
        judged.append(doc["message"] + (f" (meanwhile {'; '.join(nearby)})" if nearby else ""))
    return Soak(failovers, judged, warnings, received)


def silence_limits(events: Sequence[dict[str, Any]]) -> list[int]:
    """The silence thresholds (ms) the agent judged these failovers by, from their reasons."""
    found = (re.search(r"\(limit (\d+) ms\)", e["failover"]["reason"]) for e in events)
    return [int(m[1]) for m in found if m is not None]


def _limits_text(limits: list[int]) -> str:
    if not limits:
        return "none reported"
    return f"median {statistics.median(limits):.0f} ms, {min(limits)}-{max(limits)} ms"


def _load() -> str:
    """The 1-minute load average (CPU here is shared; figures note it)."""
    return f"{os.getloadavg()[0]:.2f}"


def _thresholds_text(th: Thresholds) -> str:
    return (
        f"thresholds message warn/error {th.message_warn_ms}/{th.message_error_ms} ms "
        f"(silence learnt: {th.silence_margin:g} x the worst recent gap, at least "
        f"{th.message_error_min_ms} ms), "
        f"heartbeat warn/error {th.heartbeat_warn_ms}/{th.heartbeat_error_ms} ms, "
        f"confirm {th.confirm_ms} ms"
    )


def _soak_note(th: Thresholds, soak: Soak, meanwhile: str = "") -> str:
    judgements = "; ".join(soak.errors) or "none"
    warnings = ", ".join(f"{why} x{n}" for why, n in soak.warnings.most_common()) or "none"
    return (
        f"{SOAK_S:.0f} s of healthy flight{meanwhile}, two PX4 sims ({SIMS_APART}), 5 % loss "
        f"and 50 ms jitter on every link, {_thresholds_text(th)}; {soak.received} messages "
        f"accepted; {len(soak.errors)} ERROR judgements of healthy autopilots "
        f"(failover.healthy_errors_* counts them): {judgements}; "
        f"{soak.warnings.total()} WARN judgements: {warnings}; 1-min load {_load()} at the end"
    )


def _set_environment(values: dict[str, str | None]) -> None:
    for name, value in values.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


_BEFORE_COMPILED: dict[str, str | None] = {}
"""The variables :func:`run` changed to run the compiled build, as they were before."""


@contextmanager
def _interpreted() -> Iterator[None]:
    """Agents started inside run from the checkout's Python modules, not compiled ones."""
    compiled = {name: os.environ.get(name) for name in _BEFORE_COMPILED}
    _set_environment(_BEFORE_COMPILED)
    try:
        yield
    finally:
        _set_environment(compiled)


def cpu_figures() -> list[Figure]:
    cpu_ms, rss_mb, rate = cpu_and_memory()
    load2 = _load()
    with _interpreted():
        interpreted_ms, _, interpreted_rate = cpu_and_memory()
    load_interpreted = _load()
    cpu3_ms, rss3_mb, rate3 = cpu_and_memory(("px4", "px4", "px4"))
    load3 = _load()
    return [
        Figure(
            "agent.cpu_ms_per_10k_msgs",
            round(cpu_ms, 1),
            "ms",
            "<= 150",
            COMMAND,
            f"roost-agent process user+system CPU over {CPU_S:.0f} s at {rate:.0f} msg/s (two "
            "sims at PX4 onboard-like rates), including its decision loop (the bulk read every "
            f"{STEERED_TICK_S * 1000:.0f} ms; heartbeats and command answers, steered to an "
            f"urgent socket, at once) and a status line per second; the image's build (codec, "
            f"links and health compiled by mypyc); 1-min load {load2} (2 cores shared)",
        ),
        Figure(
            "agent.cpu_ms_per_10k_msgs_interpreted",
            round(interpreted_ms, 1),
            "ms",
            "",
            COMMAND,
            "as agent.cpu_ms_per_10k_msgs, measured right after it, with the agent running from "
            "the checkout's Python modules (nothing compiled by mypyc; the C extension, which "
            f"every install builds, as in the image): {interpreted_rate:.0f} msg/s; "
            f"1-min load {load_interpreted}",
        ),
        Figure(
            "agent.cpu_ms_per_10k_msgs_3_autopilots",
            round(cpu3_ms, 1),
            "ms",
            "<= 150",
            COMMAND,
            f"as agent.cpu_ms_per_10k_msgs with three PX4 sims: {rate3:.0f} msg/s, peak RSS "
            f"{rss3_mb:.1f} MB; 1-min load {load3}",
        ),
        Figure(
            "agent.rss_mb",
            round(rss_mb, 1),
            "MB",
            "<= 32",
            COMMAND,
            "peak RSS of the standalone roost-agent process with two autopilots at "
            f"{rate:.0f} msg/s",
        ),
    ]


def failover_figures() -> list[Figure]:
    cycles = failover_cycles()
    detect, silent, claim = cycles.detect_ms, cycles.silent_ms, cycles.claim_ms
    fast = _thresholds_text(FAST)
    return [
        Figure(
            "failover.detect_to_switch_p50_ms",
            round(percentile(detect, 50), 3),
            "ms",
            "",
            COMMAND,
            f"{len(detect)} failovers (silence, MAV_STATE EMERGENCY, gyro); from the start of "
            "the decision tick that saw the confirmed failure to the bridge write returning "
            f"(simulated bridge); thesis: 20 ms; 1-min load {_load()}",
        ),
        Figure(
            "failover.detect_to_switch_p99_ms",
            round(percentile(detect, 99), 3),
            "ms",
            "<= 5",
            COMMAND,
            f"{len(detect)} failovers; max {max(detect):.3f} ms",
        ),
        Figure(
            "failover.silent_onset_to_switch_p99_ms",
            round(percentile(silent, 99), 1),
            "ms",
            "<= 250",
            COMMAND,
            f"{len(silent)} silent autopilots streaming ATTITUDE at 50 Hz; {fast}; "
            f"median {statistics.median(silent):.0f} ms; 1-min load {_load()}",
        ),
        Figure(
            "failover.claim_onset_to_switch_p99_ms",
            round(percentile(claim, 99), 1),
            "ms",
            "",
            COMMAND,
            f"{len(claim)} heartbeats claiming MAV_STATE EMERGENCY, from the claim's kernel "
            "arrival stamp to the bridge write: the claim wakes the reader (steered to the "
            "urgent socket), waits for the next message to corroborate it, then "
            f"confirm_ms; {fast}; median {statistics.median(claim):.0f} ms, max "
            f"{max(claim):.0f} ms",
        ),
    ]


def heartbeat_figures() -> list[Figure]:
    heartbeat = heartbeat_only_cycles()
    return [
        Figure(
            "failover.heartbeat_only_onset_to_switch_p99_ms",
            round(percentile(heartbeat, 99), 1),
            "ms",
            "<= 3500",
            COMMAND,
            f"{len(heartbeat)} silent autopilots that stream only 1 Hz HEARTBEAT, SYS_STATUS, "
            "EXTENDED_SYS_STATE on their own; the agent's stream keeper requests the streams "
            "the health model reads (ATTITUDE 50 Hz...) and the simulated PX4 grants them, so "
            "the silence is caught on those, not after the "
            f"{Thresholds().heartbeat_error_ms} ms heartbeat error; default "
            f"{_thresholds_text(Thresholds())}; p99 of {len(heartbeat)} is their maximum; "
            f"median {statistics.median(heartbeat):.0f} ms; 1-min load {_load()}",
        ),
    ]


def peer_figures() -> list[Figure]:
    agent_ms, mavsdk_ms, mavproxy_ms = peer_link_lost()
    return [
        Figure(
            "peer.mavsdk_link_lost_ms",
            round(statistics.median(mavsdk_ms), 1),
            "ms",
            "",
            COMMAND,
            f"median of {len(mavsdk_ms)}: MAVSDK 4.1.0 is_connected -> false after the same "
            f"silent onsets where the agent switched after a median "
            f"{statistics.median(agent_ms):.0f} ms ({_thresholds_text(FAST)})",
        ),
        Figure(
            "peer.mavproxy_link_lost_ms",
            round(statistics.median(mavproxy_ms), 1),
            "ms",
            "",
            COMMAND,
            f"median of {len(mavproxy_ms)}: MAVProxy prints 'link 1 down' (5 s timeout) after "
            "the same silent onsets",
        ),
    ]


def soak_result_figures(suffix: str, command: str, soak: Soak, note: str) -> list[Figure]:
    """The false failovers and the ERROR judgements of healthy autopilots of one soak."""
    return [
        Figure(f"failover.false_failovers_10min{suffix}", float(soak.failovers), "count",
               "== 0", command, note),
        Figure(f"failover.healthy_errors_10min{suffix}", float(len(soak.errors)), "count",
               "== 0", command, f"ERROR judgements of healthy autopilots in the soak of "
               f"failover.false_failovers_10min{suffix}, whose note lists them"),
    ]  # fmt: skip


def soak_figures() -> list[Figure]:
    soak = false_failovers(FAST)
    command = f"ROOST_BENCH_SOAK_S={SOAK_S:.0f} {COMMAND}"
    return soak_result_figures("", command, soak, _soak_note(FAST, soak))


def cluster_rss(seconds: float = CPU_S) -> float:
    """Peak RSS (MB) of an agent in cluster mode: the local control plane, the
    operator, two flying PX4 sims at onboard rates; measured once the Vehicle is Ready."""
    from bench import cluster as rig  # noqa: PLC0415 - the control plane only for this part
    from roost_localcluster import binaries  # noqa: PLC0415
    from roost_localcluster.cluster import Cluster  # noqa: PLC0415
    from roost_localcluster.controlplane import ControlPlane  # noqa: PLC0415
    from tests.support.operator import OperatorProcess  # noqa: PLC0415
    from tests.support.waiting import wait_until  # noqa: PLC0415

    binaries.ensure_built()
    with (
        tempfile.TemporaryDirectory(prefix="bench-agent-cluster-") as tmp,
        ControlPlane(Path(tmp)) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        cluster.add_node(rig.NODE)
        operator = OperatorProcess(cluster, Path(tmp) / "operator.log", namespace=rig.NAMESPACE)
        sims = start_vehicle_sims(["px4", "px4"], rates=PX4_ONBOARD_RATES, config=SimConfig.fast())
        agent = AgentProcess.in_cluster(cluster, rig.NODE, Path(tmp) / "agent")
        operator.start()
        try:
            rig._fly(sims)
            rig._apply_vehicle(cluster, sims)
            agent.start()
            with cluster.kube("roost-bench") as kube:
                wait_until("the vehicle Ready", lambda: rig._ready(kube), rig.WAIT_S)
            proc = psutil.Process(agent.pid)
            t0, peak = time.monotonic(), 0.0
            while time.monotonic() - t0 < seconds:
                peak = max(peak, proc.memory_info().rss / 1e6)
                time.sleep(0.5)
        finally:
            agent.stop()
            operator.stop()
            stop_sims(sims)
    return peak


def cluster_figures() -> list[Figure]:
    rss_mb = cluster_rss()
    return [
        Figure(
            "agent.rss_mb_cluster",
            round(rss_mb, 1),
            "MB",
            "<= 45",
            f"ROOST_BENCH_AGENT_PARTS=cluster {COMMAND}",
            "peak RSS of roost-agent in cluster mode (local control plane, operator running, "
            "the Vehicle Ready, reporting) with two PX4 sims at onboard rates, over "
            f"{CPU_S:.0f} s; 1-min load {_load()}",
        )
    ]


def onset_figures() -> list[Figure]:
    """The vehicle as shipped: silent onsets at the default thresholds."""
    defaults = Thresholds()
    silences = [(FaultKind.SILENCE, None)]
    cycles = failover_cycles(
        max(1, FAILOVERS // 2), thresholds=defaults, faults=silences, apart=True
    )
    silent = cycles.silent_ms
    load = _load()
    return [
        Figure(
            "failover.silent_onset_to_switch_default_p99_ms",
            round(percentile(silent, 99), 1),
            "ms",
            "<= 100",
            COMMAND,
            f"{len(silent)} silent autopilots streaming PX4's recorded onboard set (~400 "
            f"messages/s, ATTITUDE 100 Hz), {SIMS_APART}; each autopilot silenced at least "
            f"{LEARN_WINDOWS + 1} s after its last silence "
            "ended or the flight began (rest_after_outage); from "
            "the injection request to the bridge write; default "
            f"{_thresholds_text(defaults)}; median {statistics.median(silent):.0f} ms; "
            f"silence thresholds learnt from the streams: {_limits_text(cycles.limits_ms)}; "
            f"1-min load {load}",
        )
    ]


def default_figures() -> list[Figure]:
    """The vehicle as shipped: default thresholds, silent onsets and the soak."""
    defaults = Thresholds()
    figures = onset_figures()
    soak = false_failovers(defaults)
    command = f"ROOST_BENCH_SOAK_S={SOAK_S:.0f} {COMMAND}"
    return [*figures, *soak_result_figures("_default", command, soak, _soak_note(defaults, soak))]


@contextmanager
def busy_cores() -> Iterator[int]:
    """One busy-looping process per core (this machine's), stopped by pid afterwards."""
    count = os.cpu_count() or 1
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield count
    finally:
        for spinner in spinners:
            spinner.kill()
            spinner.wait()


def starved_figures() -> list[Figure]:
    """The default soak while other processes keep every core busy."""
    defaults = Thresholds()
    with busy_cores() as count:
        soak = false_failovers(defaults)
        load = _load()
    meanwhile = (
        f" while {count} busy-looping processes (normal priority, as the agent) kept the "
        f"{count} cores busy"
    )
    command = f"ROOST_BENCH_SOAK_S={SOAK_S:.0f} ROOST_BENCH_AGENT_PARTS=starved {COMMAND}"
    note = _soak_note(defaults, soak, meanwhile) + f" (1-min load {load} with the spinners)"
    return soak_result_figures("_cpu_starved", command, soak, note)


def replay_figures() -> list[Figure]:
    """ERROR or STALE judgements on healthy autopilots over every recording there is."""
    from tests.support.captures import CAPTURES  # noqa: PLC0415 - this part only
    from tests.support.replay import healthy_until, replay, stack_of  # noqa: PLC0415

    names = sorted(p.name for p in CAPTURES.glob("*.tlog"))
    if not names:
        raise SystemExit(f"bench replay: no .tlog in {CAPTURES} (set ROOST_CAPTURES_DIR)")
    judged, errors = 0, []
    for name in names:
        r = replay(name, stack_of(name))
        healthy = r.during(0, healthy_until(r))
        judged += len(healthy)
        errors += [
            f"{name} at {a.at:.2f} s: {a.failure_reason}"
            for a in healthy
            if a.level in (HealthLevel.ERROR, HealthLevel.STALE)
        ]
    return [
        Figure(
            "failover.replay_false_errors",
            float(len(errors)),
            "count",
            "== 0",
            f"ROOST_BENCH_AGENT_PARTS=replay {COMMAND}",
            f"{len(names)} recordings of PX4 v1.16 SIH and ArduCopter SITL replayed through "
            f"the health model at the default thresholds, {judged} judgements (every 50 ms) "
            "up to where the autopilot reports trouble itself or the recording ends; "
            f"ERROR/STALE: {'; '.join(errors) or 'none'}",
        )
    ]


def run() -> list[Figure]:
    parts: dict[str, Callable[[], list[Figure]]] = {
        "cpu": cpu_figures,
        "cluster": cluster_figures,
        "failover": failover_figures,
        "heartbeat": heartbeat_figures,
        "peer": peer_figures,
        "soak": soak_figures,
        "defaults": default_figures,
        "onset": onset_figures,
        "replay": replay_figures,
        "starved": starved_figures,
    }
    unknown = sorted(set(SELECTED) - set(parts))
    if unknown:
        raise SystemExit(f"ROOST_BENCH_AGENT_PARTS: unknown {', '.join(unknown)} (of {PARTS})")
    # Every agent started from here on runs the image's compiled build.
    compiled = compiled_environment(compiled_tree())
    _BEFORE_COMPILED.update({name: os.environ.get(name) for name in compiled})
    os.environ.update(compiled)
    figures: list[Figure] = []
    for name in PARTS:
        if name in SELECTED:
            figures.extend(parts[name]())
    return figures
