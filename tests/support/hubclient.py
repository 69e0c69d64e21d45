"""A small MAVLink ground-station client over real UDP, for hub tests and benchmarks.

It talks to the vehicle endpoint the agent serves (``HubSpec.udp``) as a ground station
does: its own socket, a 1 Hz GCS heartbeat, commands addressed to the vehicle's system id,
and a record of everything the vehicle sent (type, sender, arrival time).
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_agent import Agent
from roost_agent.bridge import SimulatedBridge
from roost_agent.signing import LinkSigning
from roost_api.autopilot import (
    FailoverPolicy,
    HubEndpoint,
    HubSpec,
    ParametersSpec,
    RedundantAutopilotSpec,
    SafetyRoutine,
    StandbyLimits,
)
from roost_api.meta import Stack
from roost_api.plain import Condition
from roost_mavlink import MAV_CMD_DO_SET_MODE, set_mode_params
from roost_mavlink.signing import Timestamps, unix_to_ticks
from roost_sim import (
    SimConfig,
    SimulatedAutopilot,
    autopilot_specs,
    motor_listener,
    start_vehicle_sims,
    stop_sims,
)
from tests.support.flight import SIM_THRESHOLDS
from tests.support.waiting import wait_until

GCS_SYSID = 255
GCS_COMPONENT = 190  # MAV_COMP_ID_MISSIONPLANNER


@dataclass(frozen=True)
class Received:
    """One message from the vehicle endpoint."""

    at: float  # monotonic seconds
    kind: str
    sysid: int
    msg: Any


def source_system(msg: Any) -> int:
    """The sender's system id; read from the frame for an id pymavlink's dialect lacks
    (PX4's CURRENT_MODE, EVENT...), whose header pymavlink leaves undecoded (0)."""
    if msg.get_type().startswith("UNKNOWN_"):
        frame = bytes(msg.get_msgbuf())
        return frame[5] if frame[0] == mavlink.PROTOCOL_MARKER_V2 else frame[3]
    return int(msg.get_srcSystem())


class _OneSenderAtATime(mavlink.MAVLink):  # type: ignore[misc]  # pymavlink is untyped
    """pymavlink's MAVLink, whose ``send`` numbers, signs (the signing timestamp) and
    writes a frame in steps no lock holds together: the heartbeat thread and a test's
    command sent at once could leave in the opposite order of their signing timestamps,
    and the hub rightly drops the second to arrive, older-stamped, as a replay."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._send_lock = threading.Lock()

    def send(self, mavmsg: Any, force_mavlink1: bool = False) -> None:
        with self._send_lock:
            super().send(mavmsg, force_mavlink1=force_mavlink1)


class HubClient:
    """A ground station on ``address`` (the hub's UDP endpoint)."""

    def __init__(
        self,
        address: tuple[str, int],
        *,
        sysid: int = GCS_SYSID,
        key: bytes | None = None,
        link_id: int = 1,
    ) -> None:
        """With ``key`` the client signs what it sends (pymavlink's MAVLink 2 signing)
        and takes only frames signed with that key."""
        self.address = address
        self.key = key
        self.link_id = link_id
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.mav = _OneSenderAtATime(_SocketFile(self), srcSystem=sysid, srcComponent=GCS_COMPONENT)
        if key is not None:
            _sign_with(self.mav, key, link_id)
        self.received: list[Received] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._read, name="hubclient-read", daemon=True),
            threading.Thread(target=self._beat, name="hubclient-beat", daemon=True),
        ]
        self._on_message: Callable[[Received], None] | None = None

    def __enter__(self) -> HubClient:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        self.sock.close()

    def on_message(self, callback: Callable[[Received], None] | None) -> None:
        """Call ``callback`` on the reader thread for every message (benchmarks)."""
        self._on_message = callback

    def _beat(self) -> None:
        while not self._stop.is_set():
            self.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self._stop.wait(1.0)

    def _read(self) -> None:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        if self.key is not None:
            _sign_with(parser, self.key, self.link_id)
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65535)
            except (TimeoutError, OSError):
                continue
            now = time.monotonic()
            msg = parser.parse_char(data)
            while msg is not None:
                if msg.get_type() != "BAD_DATA":
                    item = Received(now, msg.get_type(), source_system(msg), msg)
                    callback = self._on_message
                    if callback is not None:
                        callback(item)
                    with self._cond:
                        self.received.append(item)
                        self._cond.notify_all()
                msg = parser.parse_char(b"")

    def messages(self, kind: str | None = None, since: float = 0.0) -> list[Received]:
        with self._cond:
            return [r for r in self.received if r.at >= since and (kind is None or r.kind == kind)]

    def wait_for(
        self, predicate: Callable[[Received], bool], timeout: float, since: float = 0.0
    ) -> Received:
        """The first message since ``since`` that satisfies ``predicate`` (waits)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for item in self.received:
                    if item.at >= since and predicate(item):
                        return item
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError("no matching message from the vehicle endpoint")
                self._cond.wait(remaining)

    def command(self, target: int, command: int, *params: float, timeout: float = 3.0) -> int:
        """COMMAND_LONG to ``target`` (the vehicle); its COMMAND_ACK result."""
        full = (list(params) + [0.0] * 7)[:7]
        since = time.monotonic()
        self.mav.command_long_send(target, 1, command, 0, *full)
        ack = self.wait_for(
            lambda r: r.kind == "COMMAND_ACK" and int(r.msg.command) == command, timeout, since
        )
        return int(ack.msg.result)

    def setpoint(self, target: int, north: float, east: float, down: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED: a position setpoint (velocities ignored)."""
        ignore_all_but_position = 0b0000_1111_1111_1000
        self.mav.set_position_target_local_ned_send(
            0, target, 1, mavlink.MAV_FRAME_LOCAL_NED, ignore_all_but_position,
            north, east, down, 0, 0, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip


def _sign_with(mav: mavlink.MAVLink, key: bytes, link_id: int) -> None:
    """pymavlink signs what ``mav`` sends and accepts only frames signed with ``key``."""
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = unix_to_ticks(time.time())


class _SocketFile:
    def __init__(self, client: HubClient) -> None:
        self.client = client

    def write(self, data: bytes) -> None:
        self.client.sock.sendto(bytes(data), self.client.address)


VEHICLE_SYSID = 42
POLL_S = 0.02


@contextlib.contextmanager
def repeating(send: Callable[[], None], period_s: float) -> Iterator[None]:
    """Call ``send`` every ``period_s`` on a thread while the block runs (a setpoint
    stream, as an offboard controller keeps one up)."""
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            send()
            stop.wait(period_s)

    thread = threading.Thread(target=loop, name="setpoint-stream", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


@dataclass
class HubVehicle:
    """Simulated autopilots behind an agent serving the hub, and a client on the hub."""

    sims: list[SimulatedAutopilot]
    agent: Agent
    bridge: SimulatedBridge
    client: HubClient
    spec: RedundantAutopilotSpec

    def sim(self, name: str) -> SimulatedAutopilot:
        return next(s for s in self.sims if s.name == name)

    def spec_with(self, **changes: object) -> RedundantAutopilotSpec:
        """The agent's spec with some fields changed (``parameters=``, ``firmware=``)."""
        return RedundantAutopilotSpec.model_validate(self.spec.model_copy(update=changes))

    def in_step(self, name: str) -> Condition | None:
        """The autopilot's StandbyInStep condition as the agent reports it."""
        return self.condition(name, "StandbyInStep")

    def condition(self, name: str, kind: str) -> Condition | None:
        """One of the autopilot's own conditions as the agent reports it."""
        for health in self.agent.status().autopilots:
            if health.name == name:
                return next((c for c in health.conditions if c.type == kind), None)
        return None


@contextlib.contextmanager
def hub_vehicle(
    stacks: list[str],
    *,
    mirror: bool = True,
    config: SimConfig | None = None,
    tcp: bool = False,
    parameters: ParametersSpec | None = None,
    endpoints: Sequence[HubEndpoint] = (),
    key: bytes | None = None,
) -> Iterator[HubVehicle]:
    """Sims on the ground and heard by the agent, which serves the hub on a free port,
    a :class:`HubClient` on it. With ``key`` the whole vehicle signs: the sims and the
    agent require it on their links, and the hub has it for ``endpoints`` that sign."""
    sims = start_vehicle_sims(stacks, config=config or SimConfig.fast())
    agent: Agent | None = None
    signing = None
    if key is not None:
        for sim in sims:
            sim.link.enable_signing(key, link_id=7)
        signing = LinkSigning(key=key, require=True, clock=Timestamps())
    try:
        spec = RedundantAutopilotSpec(
            vehicle_name="v1",
            autopilots=autopilot_specs(sims),
            primary=sims[0].name,
            failover_policy=FailoverPolicy(
                thresholds=SIM_THRESHOLDS, safety_routine=SafetyRoutine(hold_seconds=30)
            ),
            hub=HubSpec(
                sysid=VEHICLE_SYSID,
                udp="127.0.0.1:0",
                tcp="127.0.0.1:0" if tcp else None,
                mirror=mirror,
                standby_limits=StandbyLimits(confirm_ms=300),
                endpoints=list(endpoints),
            ),
            parameters=parameters,
        )
        bridge = SimulatedBridge(range(len(sims)))
        bridge.add_listener(motor_listener(sims))  # the sims know which one flies
        agent = Agent(spec, bridge, signing=signing)
        agent.start()
        hub = agent.hub
        assert hub is not None
        with HubClient(hub.udp_address) as client:
            client.wait_for(lambda r: r.kind == "HEARTBEAT", 10)
            for sim in sims:
                sim.wait_ready(timeout=5)
            links = agent.links
            wait_until(
                "every autopilot heard",
                lambda: all(link.locked_address for link in links.values()),
                10,
                POLL_S,
            )
            yield HubVehicle(sims, agent, bridge, client, spec)
    finally:
        if agent is not None:
            agent.stop()
        stop_sims(sims)


ALTITUDE_M = 5.0


def circle_setpoint(t: float, radius_m: float, speed_mps: float) -> tuple[float, float, float]:
    """(north, east, down) on a circle round home at :data:`ALTITUDE_M`, ``t`` s along it."""
    angle = speed_mps * t / radius_m
    return radius_m * math.sin(angle), radius_m * (1 - math.cos(angle)), -ALTITUDE_M


def separation_m(a: SimulatedAutopilot, b: SimulatedAutopilot) -> float:
    """How far apart two autopilots believe their vehicle is (3D, metres)."""
    sa, sb = a.snapshot(), b.snapshot()
    return math.dist((sa.north_m, sa.east_m, sa.altitude_m), (sb.north_m, sb.east_m, sb.altitude_m))


def fly_setpoint_circle(
    v: HubVehicle,
    seconds: float,
    *,
    radius_m: float = 20.0,
    speed_mps: float = 2.0,
    on_sample: Callable[[float], None] | None = None,
) -> list[float]:
    """Both autopilots airborne (taken off by their own API, so an unmirrored standby flies
    too), then the client streams a circle at 20 Hz through the hub in OFFBOARD for
    ``seconds``; the active/standby separation sampled every 0.5 s (``on_sample`` is
    called with the seconds flown at each sample, e.g. to inject a fault)."""
    for sim in v.sims:
        sim.fly()
    for sim in v.sims:
        sim.wait_until(lambda s: s.landed_state == "InAir" and s.altitude_m > 2.0, timeout=15)
    start = time.monotonic()

    def send() -> None:
        v.client.setpoint(
            VEHICLE_SYSID, *circle_setpoint(time.monotonic() - start, radius_m, speed_mps)
        )

    samples: list[float] = []
    with repeating(send, 0.05):
        send()  # a setpoint before the mode: PX4 refuses OFFBOARD without a stream
        params = set_mode_params(Stack(v.sims[0].stack), "OFFBOARD")
        result = v.client.command(VEHICLE_SYSID, MAV_CMD_DO_SET_MODE, *params)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"OFFBOARD refused through the hub ({result})")
        active, standby = v.sims[0], v.sims[1]
        end = start + seconds
        while time.monotonic() < end:  # sampling the flight, not waiting for a condition
            samples.append(separation_m(active, standby))
            if on_sample is not None:
                on_sample(time.monotonic() - start)
            time.sleep(0.5)
    return samples
