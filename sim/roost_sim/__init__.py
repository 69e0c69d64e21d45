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

    from roost_sim import SimConfig, SimulatedAutopilot, start_vehicle_sims, FaultKind
    with SimulatedAutopilot.udp("px4", sysid=1, target_port=port, config=SimConfig.fast()) as sim:
        sim.wait_ready()                       # start-up done (booted, position estimate)
        sim.fly(altitude_m=5)                  # arm + take off through the normal rules
        sim.inject(FaultKind.SENSOR, "gyro")   # or "silence", "freeze", "state", ...
        sim.clear()                            # every fault
        sim.snapshot().armed, sim.commands, sim.mode_history
        sim.wait_until(lambda s: s.landed_state == "OnGround", timeout=10)

    sims = start_vehicle_sims(["px4", "ardupilot"], config=SimConfig.fast())
    # names fc1.., sysids 1..N, free ports
    [s.connection for s in sims]                      # "udp://127.0.0.1:<agent port>"
    autopilot_specs(sims)                             # AutopilotSpec list for the agent
    stop_sims(sims)

A running ``roost-sim run`` process is reached through a unix socket per autopilot in a
state directory (:mod:`roost_sim.control`): ``roost-sim fault fc1 silence``. One process
can host many vehicles (``roost-sim run --config`` with a ``vehicles`` list; sockets
``<vehicle>/<autopilot>``): every autopilot in a process is ticked by one scheduler thread
in rounds on a 2.5 ms grid (:mod:`roost_sim.scheduler`), not by a thread of its own.

Calibrated against recordings of PX4 v1.16 (SIH) and ArduCopter 4.7 (SITL), so the sim
is not kinder than the firmware (details in :mod:`roost_sim.model`,
:mod:`roost_sim.streams`, :mod:`roost_sim.battery`):

- PX4 streams ~400 messages/s unasked (ATTITUDE 100 Hz, ATTITUDE_QUATERNION,
  GLOBAL_POSITION_INT, HIGHRES_IMU 50 Hz, ..., ESTIMATOR_STATUS 1 Hz), reports UNINIT for
  ~4 s after boot and refuses to arm until STANDBY, sends HEARTBEAT at 1 Hz only and
  refuses to change that rate, and switches itself to AUTO.LOITER after a takeoff.
- ArduCopter sends only HEARTBEAT until asked (SET_MESSAGE_INTERVAL,
  REQUEST_DATA_STREAM); a reboot forgets the requests. It reports BOOT ~2 s, then waits
  ~41 s for GPS, refusing to arm with its own texts; sends a heartbeat at once on a mode
  change; stays in GUIDED after a takeoff; its LOITER follows the throttle stick, which
  rests low without RC, so LOITER without a pilot descends into the ground at 2.5 m/s
  (``sim.touchdowns``) while BRAKE and GUIDED hold.
- Tests use ``SimConfig.fast()`` (``roost-sim run --fast-boot``): the same start-up in
  under a second. ``SimConfig.fast(preset_streams=True)`` makes ArduPilot stream unasked,
  as with its SRn_* parameters set, for clients that do not request streams.
- ``start_vehicle_sims(..., battery="shared" | "per-autopilot")``: a ``battery`` fault on
  a shared pack shows on every autopilot, so a failsafe must land rather than switch.
"""

from __future__ import annotations

from roost_sim.autopilot import CommandRecord, SimSnapshot, SimulatedAutopilot, message_id
from roost_sim.battery import Battery
from roost_sim.faults import FaultKind
from roost_sim.link import Impairment, PtyLink, UdpLink
from roost_sim.model import ModeChange, SimConfig
from roost_sim.vehicle import (
    autopilot_specs,
    free_udp_port,
    motor_listener,
    start_vehicle_sims,
    stop_sims,
)

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
    "motor_listener",
    "start_vehicle_sims",
    "stop_sims",
]
