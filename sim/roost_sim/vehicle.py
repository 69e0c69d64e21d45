"""Start the simulated autopilots of one vehicle on free ports, for tests and benchmarks.

Each autopilot gets a unique sysid (two with one sysid behind one socket get merged by
pymavlink) and its own agent port. The agent binds that port later, so it is picked by
:func:`roost_api.ports.free_port`: below the kernel's ephemeral range, where no socket is
given it meanwhile, and from this process's own block of ports.

``battery`` says how the vehicle is powered: ``shared`` (one flight battery; every
autopilot measures the same pack, so a battery fault shows on all of them) or
``per-autopilot`` (each has its own supply). :mod:`roost_sim.battery` explains what a
battery failsafe should do in each case.
"""

from __future__ import annotations

import socket
from collections.abc import Callable, Sequence
from typing import Protocol

from roost_api.autopilot import AutopilotSpec
from roost_api.meta import Stack
from roost_api.ports import LOOPBACK, free_port
from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.battery import Battery
from roost_sim.model import SimConfig

BATTERY_LAYOUTS = ("shared", "per-autopilot")


def free_udp_port(host: str = LOOPBACK) -> int:
    """A UDP port on ``host`` for a program to bind later (:func:`roost_api.ports.free_port`)."""
    return free_port(socket.SOCK_DGRAM, host)


def start_vehicle_sims(
    stacks: Sequence[Stack | str],
    *,
    sysids: Sequence[int] | None = None,
    transport: str = "udp",
    config: SimConfig | None = None,
    rates: dict[int, float] | None = None,
    name_prefix: str = "fc",
    battery: str = "shared",
) -> list[SimulatedAutopilot]:
    """Start one sim per stack: names fc1..fcN, sysids 1..N unless given.

    ``transport`` is ``udp`` (each sim streams to its own free agent port; its
    ``connection`` is ``udp://127.0.0.1:PORT``) or ``pty`` (``serial:///dev/pts/N:57600``).
    Each sim gets its own copy of ``config``; ``rates`` overrides stream rates by message
    id (e.g. ``{message_id("ATTITUDE"): 0}`` for heartbeats and slow streams only).
    ``config`` defaults to the firmware's own timing (PX4 arms after ~4 s, ArduCopter
    after ~41 s): tests pass ``SimConfig.fast()``. ``battery`` is ``shared`` or
    ``per-autopilot``. Stop them with :func:`stop_sims`.
    """
    ids = list(sysids) if sysids is not None else list(range(1, len(stacks) + 1))
    if len(ids) != len(stacks) or len(set(ids)) != len(ids):
        raise ValueError(f"need {len(stacks)} unique sysids, got {ids}")
    if transport not in ("udp", "pty"):
        raise ValueError(f"transport must be udp or pty, not {transport!r}")
    if battery not in BATTERY_LAYOUTS:
        raise ValueError(f"battery must be one of {BATTERY_LAYOUTS}, not {battery!r}")
    shared = Battery() if battery == "shared" else None
    sims: list[SimulatedAutopilot] = []
    try:
        for index, (stack, sysid) in enumerate(zip(stacks, ids, strict=True)):
            name = f"{name_prefix}{index + 1}"
            own_config = SimConfig(**vars(config)) if config else None
            pack = shared or Battery()
            sim = (
                SimulatedAutopilot.udp(
                    stack,
                    sysid,
                    target_port=free_udp_port(),
                    name=name,
                    config=own_config,
                    rates=rates,
                    battery=pack,
                )
                if transport == "udp"
                else SimulatedAutopilot.pty(
                    stack, sysid, name=name, config=own_config, rates=rates, battery=pack
                )
            )
            sims.append(sim.start())
    except BaseException:
        stop_sims(sims)
        raise
    return sims


def stop_sims(sims: Sequence[SimulatedAutopilot]) -> None:
    """Stop every sim (each stop is idempotent)."""
    for sim in sims:
        sim.stop()


class Reachable(Protocol):
    """What an agent's spec needs of a running sim: in this process or another."""

    @property
    def name(self) -> str: ...
    @property
    def stack(self) -> Stack: ...
    @property
    def connection(self) -> str: ...
    @property
    def sysid(self) -> int: ...
    @property
    def component_id(self) -> int: ...


def autopilot_specs(sims: Sequence[Reachable]) -> list[AutopilotSpec]:
    """``AutopilotSpec`` entries for running sims: bridge channel = position in the list."""
    return [
        AutopilotSpec(
            name=sim.name,
            stack=sim.stack,
            connection=sim.connection,
            sysid=sim.sysid,
            component_id=sim.component_id,
            bridge_channel=channel,
        )
        for channel, sim in enumerate(sims)
    ]


def motor_listener(sims: Sequence[SimulatedAutopilot]) -> Callable[[int], None]:
    """A bridge listener (``SimulatedBridge.add_listener``) that tells each sim whether it
    drives the motors; bridge channel = position in the list, as in
    :func:`autopilot_specs`."""
    snapshot = list(sims)

    def selected(channel: int) -> None:
        for index, sim in enumerate(snapshot):
            sim.set_driving(index == channel)

    return selected
