"""The simulator against recordings of the real firmware (PX4 v1.16 SIH, ArduCopter 4.7 SITL).

Each test reads a recording (.tlog: 8-byte big-endian microsecond timestamp, then one
MAVLink frame) and the simulator's live traffic on a real UDP socket, and compares what
the agent depends on: which messages arrive and how often, the boot timeline (MAV_STATE
changes, estimator flags, when arming is accepted), what ArduCopter sends unasked and on
request, the LOITER-without-RC descent and PX4's battery failsafe.

The recordings are test data kept outside the repository: ``$ROOST_CAPTURES_DIR``, else
``shared/captures`` next to the repository. Without them every test here is skipped and
says where it looked. Tolerances are loose (±30 % on rates, ±0.5 s on timelines): the
machine is shared and the recordings themselves jitter; the point is that the simulator
is not kinder than the firmware by a factor, as it was.
"""

from __future__ import annotations

import itertools
import math
import os
import statistics
import time
from collections import Counter
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from roost_api.meta import Stack
from roost_mavlink import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MavResult,
    custom_mode,
    pymavlink_device,
)
from roost_mavlink.status import MavState
from roost_sim import SimConfig, SimulatedAutopilot, free_udp_port, message_id
from roost_sim.battery import Battery
from roost_sim.model import AutopilotModel
from roost_sim.streams import PX4_STREAMS

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

# serial: the simulators' rates measured in real time
pytestmark = pytest.mark.serial

REPO = Path(__file__).resolve().parents[2]
CAPTURES_ENV = "ROOST_CAPTURES_DIR"
PX4_FLIGHT = "px4-v1.16-sih-boot-arm-takeoff-loiter-land.tlog"
PX4_BATTERY = "px4-v1.16-sih-battery-failsafe.tlog"
AP_UNREQUESTED = "arducopter-boot-unrequested.tlog"
AP_STREAMS = "arducopter-streams-arm-takeoff-brake-land.tlog"
AP_LOITER = "arducopter-loiter-no-rc.tlog"
RATE_TOLERANCE = 0.3
WINDOW_S = 6.0  # how long the simulator's traffic is measured
# The intervals the ArduCopter recordings requested (message -> Hz).
AP_REQUESTED = {
    "SYS_STATUS": 1.0,
    "EXTENDED_SYS_STATE": 1.0,
    "ATTITUDE": 50.0,
    "GLOBAL_POSITION_INT": 10.0,
    "EKF_STATUS_REPORT": 1.0,
}


def captures_dir() -> Path:
    configured = os.environ.get(CAPTURES_ENV)
    return Path(configured) if configured else REPO.parent / "shared" / "captures"


def capture(name: str) -> Path:
    path = captures_dir() / name
    if not path.is_file():
        pytest.skip(
            f"firmware recording {name} not found in {captures_dir()} "
            f"(set {CAPTURES_ENV} to the directory holding the .tlog files)"
        )
    return path


@cache
def _read(path: Path) -> tuple[tuple[float, Any], ...]:
    conn = mavutil.mavlink_connection(str(path))
    out: list[tuple[float, Any]] = []
    start: float | None = None
    while (msg := conn.recv_match()) is not None:
        if msg.get_type() == "BAD_DATA":
            continue
        start = msg._timestamp if start is None else start
        out.append((msg._timestamp - start, msg))
    conn.close()
    return tuple(out)


def recorded(name: str) -> tuple[tuple[float, Any], ...]:
    """(seconds since the first frame, message) for every frame of a recording."""
    return _read(capture(name))


def rates(frames: Iterator[tuple[float, Any]] | list[tuple[float, Any]]) -> dict[str, float]:
    """Messages per second by type over the frames' time span."""
    frames = list(frames)
    span = frames[-1][0] - frames[0][0]
    counts = Counter(m.get_type() for _, m in frames)
    return {kind: n / span for kind, n in counts.items()}


class FakeClock:
    """Monotonic time a model test advances by hand."""

    now = 0.0

    def __call__(self) -> float:
        return self.now


def take_off(model: AutopilotModel, clock: FakeClock) -> None:
    """Boot a fast-booting model, arm it and climb to its takeoff altitude."""
    clock.now = 1.0
    model.step()
    if model.stack is Stack.ARDUPILOT:
        model.set_mode(custom_mode(Stack.ARDUPILOT, "GUIDED"))
    assert model.arm(arm=True) == MavResult.ACCEPTED
    assert model.takeoff(math.nan) == MavResult.ACCEPTED
    for _ in range(300):
        clock.now += 0.02
        model.step()


class Listener:
    """Where the simulator streams to: a pymavlink ``udpin`` socket, as the agent has."""

    def __init__(self) -> None:
        self.port = free_udp_port()
        device = pymavlink_device(f"udp://127.0.0.1:{self.port}").device
        self.conn = mavutil.mavlink_connection(device, source_system=255, source_component=190)
        self.start = time.monotonic()

    def collect(self, seconds: float, sysid: int = 1) -> list[tuple[float, Any]]:
        out: list[tuple[float, Any]] = []
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(blocking=True, timeout=min(left, 0.1))
            if msg is not None and msg.get_type() != "BAD_DATA" and msg.get_srcSystem() == sysid:
                out.append((time.monotonic() - self.start, msg))
        return out

    def drain(self) -> None:
        """Drop what queued while nobody read (it would inflate a rate measured next)."""
        while self.conn.recv_match(blocking=False) is not None:
            pass

    def command(self, command: int, *params: float) -> int:
        padded = [*params, *([0.0] * (7 - len(params)))]
        self.conn.mav.command_long_send(1, 1, command, 0, *padded)
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            ack = self.conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
            if ack is not None and ack.command == command:
                return int(ack.result)
        raise AssertionError(f"no COMMAND_ACK for {command}")

    def close(self) -> None:
        self.conn.close()


def heartbeat_states(frames: list[tuple[float, Any]] | tuple[tuple[float, Any], ...]) -> list[
    tuple[float, int]
]:  # fmt: skip
    """(time, system_status) at each change of the heartbeat's MAV_STATE."""
    changes: list[tuple[float, int]] = []
    for t, msg in frames:
        if msg.get_type() == "HEARTBEAT" and (not changes or changes[-1][1] != msg.system_status):
            changes.append((t, msg.system_status))
    return changes


def assert_same_states(
    simulated: list[tuple[float, int]], real: list[tuple[float, int]], expected: list[MavState]
) -> None:
    assert [state for _, state in simulated] == [state for _, state in real] == expected


def assert_rate_close(kind: str, sim: float, real: float, seconds: float) -> None:
    """Within RATE_TOLERANCE, or one frame over ``seconds`` for slow streams."""
    slack = max(RATE_TOLERANCE * real, 1.1 / seconds)  # the window cuts a period
    assert abs(sim - real) <= slack, f"{kind}: sim {sim:.2f}/s, real {real:.2f}/s"


# ---- PX4 ------------------------------------------------------------------------------


def test_px4_streams_the_recorded_message_set_at_the_recorded_rates() -> None:
    frames = recorded(PX4_FLIGHT)
    real = rates(f for f in frames if 12.0 <= f[0] <= 30.0)  # steady hold in the air
    listener = Listener()
    sim = SimulatedAutopilot.udp("px4", 1, target_port=listener.port, config=SimConfig.fast())
    with sim:
        sim.wait_ready()
        sim.fly()
        sim.wait_until(lambda s: s.mode == "AUTO.LOITER" and s.landed_state == "InAir")
        listener.drain()
        simulated = rates(listener.collect(WINDOW_S))
    listener.close()
    unencodable = {k for k in real if k.startswith("UNKNOWN_")}
    one_shots = {"PARAM_VALUE", "COMMAND_LONG", "GPS_GLOBAL_ORIGIN"}
    assert set(real) - unencodable - one_shots <= set(simulated)
    for kind, hz in real.items():
        if kind in unencodable or kind in one_shots:
            continue
        assert_rate_close(kind, simulated[kind], hz, WINDOW_S)
    total_real = sum(hz for kind, hz in real.items() if kind not in unencodable)
    assert_rate_close("all", sum(simulated.values()), total_real, WINDOW_S)
    assert {message_id(k) for k in simulated if k != "GPS_GLOBAL_ORIGIN"} <= set(PX4_STREAMS)


def test_px4_boots_through_uninit_and_arms_only_after_standby_as_recorded() -> None:
    frames = recorded(PX4_FLIGHT)
    real_states = heartbeat_states([f for f in frames if f[0] < 5.0])
    launch = -0.34  # the PX4 process started 0.34 s before its first frame
    real_flags = []
    for t, msg in frames:
        is_flags = msg.get_type() == "ESTIMATOR_STATUS" and t < 5.0
        if is_flags and (not real_flags or real_flags[-1] != msg.flags):
            real_flags.append(msg.flags)
    listener = Listener()
    sim = SimulatedAutopilot.udp("px4", 1, target_port=listener.port)  # realistic timing
    with sim:
        early = listener.collect(2.5)
        refused = listener.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
        late = listener.collect(2.0)
        accepted = listener.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
    listener.close()
    frames_sim = early + late
    sim_states = heartbeat_states(frames_sim)
    assert_same_states(sim_states, real_states, [MavState.UNINIT, MavState.STANDBY])
    for (t_sim, _), (t_real, _) in zip(sim_states, real_states, strict=True):
        assert t_sim == pytest.approx(t_real - launch, abs=0.5)
    sim_flags = []
    for _, msg in frames_sim:
        if msg.get_type() == "ESTIMATOR_STATUS" and (not sim_flags or sim_flags[-1] != msg.flags):
            sim_flags.append(msg.flags)
    assert sim_flags == real_flags == [0x400, 0xE5, 0x3FF]
    assert refused == MavResult.TEMPORARILY_REJECTED
    assert accepted == MavResult.ACCEPTED
    heartbeats = [t for t, m in frames_sim if m.get_type() == "HEARTBEAT"]
    gaps = [b - a for a, b in itertools.pairwise(heartbeats)]
    assert all(0.8 <= gap <= 1.2 for gap in gaps)  # 1 Hz only, also across the state change


def test_px4_battery_failsafe_timeline_matches_the_recording() -> None:
    frames = recorded(PX4_BATTERY)
    injected = 18.63  # MAV_CMD_INJECT_FAILURE battery sent (on the GCS link)
    critical = next(t for t, m in frames if m.get_type() == "HEARTBEAT" and m.system_status == 5)
    land_mode = custom_mode(Stack.PX4, "AUTO.LAND")
    landing = next(
        t for t, m in frames if m.get_type() == "HEARTBEAT" and m.custom_mode == land_mode
    )

    clock = FakeClock()
    battery = Battery(clock=clock)
    model = AutopilotModel(Stack.PX4, SimConfig.fast(), clock=clock, battery=battery)
    take_off(model, clock)
    battery.fail()
    failed_at, sim_critical, sim_land = clock.now, None, None
    while sim_land is None and clock.now < failed_at + 20:
        clock.now += 0.02
        model.step()
        if sim_critical is None and model.system_status() is MavState.CRITICAL:
            sim_critical = clock.now - failed_at
        if model.mode == "AUTO.LAND":
            sim_land = clock.now - failed_at
    # The heartbeat shows a change up to 1 s late: compare with that slack.
    assert sim_critical == pytest.approx(critical - injected, abs=1.0)
    assert sim_land == pytest.approx(landing - injected, abs=1.0)


# ---- ArduCopter -----------------------------------------------------------------------


def test_ardupilot_unrequested_link_carries_only_heartbeats_as_recorded() -> None:
    frames = recorded(AP_UNREQUESTED)
    real_kinds = {m.get_type() for t, m in frames if t < 8.0}
    real_states = heartbeat_states(frames)
    listener = Listener()
    with SimulatedAutopilot.udp("ardupilot", 1, target_port=listener.port):
        simulated = listener.collect(3.0)
    listener.close()
    assert {m.get_type() for _, m in simulated} == real_kinds == {"HEARTBEAT"}
    sim_states = heartbeat_states(simulated)
    assert_same_states(sim_states, real_states, [MavState.BOOT, MavState.STANDBY])
    assert sim_states[1][0] - sim_states[0][0] == pytest.approx(
        real_states[1][0] - real_states[0][0], abs=0.5
    )


def test_ardupilot_streams_at_the_requested_rates_as_recorded() -> None:
    frames = recorded(AP_STREAMS)
    real = rates(f for f in frames if 45.0 <= f[0] <= 70.0)
    listener = Listener()
    config = SimConfig.fast()
    with SimulatedAutopilot.udp("ardupilot", 1, target_port=listener.port, config=config) as sim:
        listener.collect(0.5)  # it must hear us before it answers (and before STATUSTEXT)
        for name, hz in AP_REQUESTED.items():
            result = listener.command(MAV_CMD_SET_MESSAGE_INTERVAL, message_id(name), 1e6 / hz)
            assert result == MavResult.ACCEPTED
        sim.wait_ready()
        listener.drain()
        simulated = rates(listener.collect(WINDOW_S))
    listener.close()
    for name in [*AP_REQUESTED, "HEARTBEAT"]:
        assert_rate_close(name, simulated[name], real[name], WINDOW_S)


def test_ardupilot_loiter_without_rc_descends_into_the_ground_as_recorded() -> None:
    frames = recorded(AP_LOITER)
    loiter = custom_mode(Stack.ARDUPILOT, "LOITER")
    entered = next(t for t, m in frames if m.get_type() == "HEARTBEAT" and m.custom_mode == loiter)
    positions = [
        (t, m.relative_alt / 1000, m.vz / 100)
        for t, m in frames
        if m.get_type() == "GLOBAL_POSITION_INT" and entered <= t <= entered + 5
    ]
    peak_t, peak_alt, _ = max(positions, key=lambda p: p[1])
    ground_t = next(t for t, alt, _ in positions if t > peak_t and alt <= 0.05)
    real_speed = max(vz for _, _, vz in positions)

    clock = FakeClock()
    model = AutopilotModel(Stack.ARDUPILOT, SimConfig.fast(takeoff_alt_m=peak_alt), clock=clock)
    take_off(model, clock)
    model.set_mode(loiter)
    start, fastest = clock.now, 0.0
    while not model.touchdowns:
        clock.now += 0.02
        model.step()
        fastest = max(fastest, -model.climb_mps)
        assert clock.now - start < 10
    assert fastest == pytest.approx(real_speed, abs=0.15)
    assert model.touchdowns[0].at - start == pytest.approx(ground_t - peak_t, abs=0.5)


@pytest.mark.parametrize(
    ("stack", "name", "land_mode"),
    [(Stack.PX4, PX4_FLIGHT, "AUTO.LAND"), (Stack.ARDUPILOT, AP_STREAMS, "LAND")],
)
def test_land_mode_descends_at_the_recorded_rate(stack: Stack, name: str, land_mode: str) -> None:
    frames = recorded(name)
    land = custom_mode(stack, land_mode)
    entered = next(t for t, m in frames if m.get_type() == "HEARTBEAT" and m.custom_mode == land)
    speeds = [
        m.vz / 100
        for t, m in frames
        if m.get_type() == "GLOBAL_POSITION_INT" and t > entered + 1.5 and m.relative_alt > 300
    ]
    assert len(speeds) > 10
    assert SimConfig().landing(stack).descent_mps == pytest.approx(
        statistics.median(speeds), abs=0.15
    )
