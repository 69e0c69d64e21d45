"""A simulated MAVLink autopilot (PX4 or ArduPilot flavour) with fault injection.

Why it exists: the agent's failover must be proven against real MAVLink bytes on real
UDP sockets and serial lines, with faults a real flight controller shows (silent link,
frozen values, failing gyro, MAV_STATE changes, reboots, garbage, loss and jitter), and
real SITL images need a container engine this project cannot assume. The simulator
speaks MAVLink 2 with each stack's conventions from :mod:`roost_mavlink`.

Connection scheme (the same one ``roost_api.autopilot.AutopilotSpec.connection`` uses):

- ``udp://127.0.0.1:P`` -- the AGENT listens on P (pymavlink ``udpin:127.0.0.1:P``). The
  sim binds its own socket on 127.0.0.1 (a free port unless given), sends every stream
  to P and answers whoever sends to it. This is PX4 SITL's onboard link shape.
- ``udpout://127.0.0.1:Q`` -- the AGENT sends to the sim's own port Q (pymavlink
  ``udpout:``); the sim streams to every address that has sent it a packet.
- ``serial:///dev/pts/N:57600`` -- the sim holds the master side of a pseudo-terminal;
  the agent opens the slave path like a USB serial port.

API in short (see :mod:`roost_sim.autopilot`, :mod:`roost_sim.vehicle`)::

    from roost_sim import SimulatedAutopilot, start_vehicle_sims, FaultKind
    with SimulatedAutopilot.udp("px4", sysid=1, target_port=port) as sim:
        sim.fly(altitude_m=5)                  # arm + take off through the normal rules
        sim.inject(FaultKind.SENSOR, "gyro")   # or "silence", "freeze", "state", ...
        sim.clear()                            # every fault
        sim.snapshot().armed, sim.commands, sim.mode_history
        sim.wait_until(lambda s: s.landed_state == "OnGround", timeout=10)

    sims = start_vehicle_sims(["px4", "ardupilot"])  # names fc1.., sysids 1..N, free ports
    [s.connection for s in sims]                      # "udp://127.0.0.1:<agent port>"
    autopilot_specs(sims)                             # AutopilotSpec list for the agent
    stop_sims(sims)

A running ``roost-sim run`` process is reached through a unix socket per autopilot in a
state directory (:mod:`roost_sim.control`): ``roost-sim fault fc1 silence``.
"""

from __future__ import annotations

from roost_sim.autopilot import CommandRecord, SimSnapshot, SimulatedAutopilot, message_id
from roost_sim.battery import Battery
from roost_sim.faults import FaultKind
from roost_sim.link import Impairment, PtyLink, UdpLink
from roost_sim.model import ModeChange, SimConfig
from roost_sim.vehicle import autopilot_specs, free_udp_port, start_vehicle_sims, stop_sims

__all__ = [
    "Battery",
    "CommandRecord",
    "FaultKind",
    "Impairment",
    "ModeChange",
    "PtyLink",
    "SimConfig",
    "SimSnapshot",
    "SimulatedAutopilot",
    "UdpLink",
    "autopilot_specs",
    "free_udp_port",
    "message_id",
    "start_vehicle_sims",
    "stop_sims",
]
