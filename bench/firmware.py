"""Benchmarks of the agent against firmware-like autopilots: unaided ArduPilot failover
and the altitude a post-failover hold gives away.

- ``failover.ardupilot_unaided_onset_to_switch_p99_ms``: two simulated ArduCopters that,
  like the real firmware, send nothing but HEARTBEAT until streams are requested; the
  agent (its own process, default thresholds) must ask for them itself. The active one
  goes silent; onset (taken here when the fault is requested) to the bridge switch (the
  agent's CLOCK_MONOTONIC timestamp), over repeated failovers. The sims run as the
  firmware does on its own MCU, out of reach of the host's load: in a process of their
  own at real-time priority (:mod:`tests.support.simprocess`); the agent at normal.
- ``safety.hold_altitude_loss_m``: after each failover the safety routine holds for
  :data:`HOLD_S` s and lands; the simulator's own altitude is sampled every 20 ms and the
  most altitude lost between entering the hold mode and leaving it is recorded, for the
  PX4 flavour (AUTO.LOITER) and the ArduCopter flavour (whose LOITER sinks 2.45 m/s with
  the throttle stick low, as measured on ArduCopter SITL; the hold must avoid it or
  escalate). The figure is the worst of both flavours; the note has each.

Knobs (environment): ``ROOST_BENCH_UNAIDED_FAILOVERS`` (default 20),
``ROOST_BENCH_HOLD_SAMPLES`` (failovers per flavour, default 3).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

from bench.agent import (
    SIMS_APART,
    _limits_text,
    _load,
    _thresholds_text,
    percentile,
    rest_after_outage,
    silence_limits,
)
from bench.core import Figure
from roost_agent.health import LEARN_WINDOWS
from roost_api.autopilot import (
    AutopilotSpec,
    FailoverPolicy,
    FinalAction,
    RedundantAutopilotSpec,
    SafetyRoutine,
    Thresholds,
)
from roost_sim import (
    FaultKind,
    SimConfig,
    SimulatedAutopilot,
    autopilot_specs,
    start_vehicle_sims,
    stop_sims,
)
from tests.support.agent import AgentProcess
from tests.support.flight import take_off
from tests.support.simprocess import SimProcess

UNAIDED_FAILOVERS = int(os.environ.get("ROOST_BENCH_UNAIDED_FAILOVERS", "20"))
HOLD_SAMPLES = int(os.environ.get("ROOST_BENCH_HOLD_SAMPLES", "3"))
COMMAND = "python -m bench firmware"
HOLD_S = 3.0

# No RC: ArduCopter LOITER reads the throttle stick as low and sinks (the sim's default).
LOITER_NO_RC = SimConfig.fast(takeoff_alt_m=6.0)
HOLD_MODES = {"px4": "AUTO.LOITER", "ardupilot": "BRAKE"}


def _spec(specs: list[AutopilotSpec], routine: SafetyRoutine) -> RedundantAutopilotSpec:
    return RedundantAutopilotSpec(
        vehicle_name="bench",
        autopilots=specs,
        primary="fc1",
        failover_policy=FailoverPolicy(thresholds=Thresholds(), safety_routine=routine),
    )


def unaided_ardupilot_cycles() -> tuple[list[float], list[int]]:
    """Onset->switch for silent ArduPilots that stream only what the agent requested, and
    the silence threshold each failover was judged by (learnt from the stream)."""
    onset_ms: list[float] = []
    limits: list[int] = []
    defaults = Thresholds()
    agent: AgentProcess | None = None
    with (
        SimProcess(["ardupilot", "ardupilot"]) as process,
        tempfile.TemporaryDirectory(prefix="roost-bench-firmware-") as tmp,
    ):
        try:
            routine = SafetyRoutine(hold_seconds=0, final_action=FinalAction.HOLD)
            spec = _spec(process.specs(), routine)
            agent = AgentProcess.standalone(Path(tmp), spec, log_level="WARNING")
            process.take_off()
            agent.wait_ok(["fc1", "fc2"])
            time.sleep(defaults.clear_ms / 1000 + 1.5)  # T_off, and a full rate window
            by_name, active = {s.name: s for s in process.sims}, "fc1"
            recovered = dict.fromkeys(by_name, time.monotonic())
            for _ in range(UNAIDED_FAILOVERS):
                rest_after_outage(recovered.get(active))
                onset = time.monotonic()
                by_name[active].inject(FaultKind.SILENCE)
                event = agent.wait_for(lambda d: d.get("event") == "Failover", 15)
                onset_ms.append((event["monotonic"]["switchedAt"] - onset) * 1000)
                limits.extend(silence_limits([event]))
                by_name[active].clear()
                assert agent.command("ClearLatch")["result"] == "Executed"
                agent.wait_ok([active])
                time.sleep(defaults.clear_ms / 1000 + 0.2)
                recovered[active] = time.monotonic()
                active = event["failover"]["to"]
        finally:
            if agent is not None:
                agent.stop()
    return onset_ms, limits


def _watch(sim: SimulatedAutopilot, stop: threading.Event, out: list[tuple[float, str]]) -> None:
    """Sample the simulator's altitude and mode every 20 ms until ``stop``."""
    while not stop.wait(0.02):
        snap = sim.snapshot()
        out.append((snap.altitude_m, snap.mode))


def _lost_in_hold(samples: list[tuple[float, str]], hold: str) -> float:
    """Most altitude lost from entering ``hold`` to the lowest point while in it."""
    inside = [alt for alt, mode in samples if mode == hold]
    if not inside:
        modes = sorted({mode for _, mode in samples})
        raise RuntimeError(f"the hold mode {hold} was never entered (modes seen: {modes})")
    return inside[0] - min(inside)


def hold_losses(stack: str) -> list[float]:
    """Altitude lost during the post-failover hold, one value per failover."""
    losses: list[float] = []
    for _ in range(HOLD_SAMPLES):
        sims = start_vehicle_sims([stack, stack], config=LOITER_NO_RC)
        agent: AgentProcess | None = None
        with tempfile.TemporaryDirectory(prefix="roost-bench-hold-") as tmp:
            try:
                routine = SafetyRoutine(hold_seconds=HOLD_S, final_action=FinalAction.LAND)
                agent = AgentProcess.standalone(
                    Path(tmp), _spec(autopilot_specs(sims), routine), log_level="WARNING"
                )
                take_off(sims)
                agent.wait_ok(["fc1", "fc2"])
                time.sleep(Thresholds().clear_ms / 1000 + 1.5)
                samples: list[tuple[float, str]] = []
                stop = threading.Event()
                watcher = threading.Thread(
                    target=_watch, args=(sims[1], stop, samples), daemon=True
                )
                watcher.start()
                sims[0].inject(FaultKind.SILENCE)
                agent.wait_for(lambda d: d.get("reason") == "SafetyRoutineLanding", 30)
                stop.set()
                watcher.join()
                losses.append(_lost_in_hold(samples, HOLD_MODES[stack]))
            finally:
                if agent is not None:
                    agent.stop()
                stop_sims(sims)
    return losses


def run() -> list[Figure]:
    unaided, limits = unaided_ardupilot_cycles()
    unaided_load = _load()
    holds = {stack: hold_losses(stack) for stack in ("px4", "ardupilot")}
    worst = max(max(v) for v in holds.values())
    per_flavour = "; ".join(
        f"{stack} ({HOLD_MODES[stack]}): max {max(v):.2f} m over {len(v)} failovers"
        for stack, v in holds.items()
    )
    return [
        Figure(
            "failover.ardupilot_unaided_onset_to_switch_p99_ms",
            round(percentile(unaided, 99), 1),
            "ms",
            "<= 120",
            COMMAND,
            f"{len(unaided)} silent simulated ArduCopters that send only HEARTBEAT until "
            f"the agent requests streams, {SIMS_APART}; each silenced at least "
            f"{LEARN_WINDOWS + 1} s after its last silence "
            "ended or the flight began (rest_after_outage); default "
            f"{_thresholds_text(Thresholds())}; "
            f"median {statistics.median(unaided):.0f} ms, max {max(unaided):.0f} ms; "
            f"silence thresholds learnt from the streams: {_limits_text(limits)}; "
            f"1-min load {unaided_load}",
        ),
        Figure(
            "safety.hold_altitude_loss_m",
            round(worst, 3),
            "m",
            "<= 0.5",
            COMMAND,
            f"worst of both flavours; {per_flavour}; hold {HOLD_S:.0f} s then land; the "
            "simulated ArduCopter's LOITER sinks 2.45 m/s without RC (as measured on "
            "ArduCopter SITL), its BRAKE and PX4's AUTO.LOITER hold altitude exactly, so "
            "the figure shows the routine picking a hold that holds, not a controller's "
            "accuracy",
        ),
    ]
