"""Where simulated autopilots live on the network: one system id and port scheme.

Two autopilots must never share a system id or a port: pymavlink merges two autopilots
with one sysid behind one socket and a command then reaches both. Roost numbers SITL
instances globally, ``i = vehicle_instance * slots_per_vehicle + autopilot_index``, and
derives everything from ``i`` the way the stacks themselves do:

- PX4 SITL instance ``i``: ``MAV_SYS_ID = i + 1``; its onboard/API link sends to UDP
  ``14540 + i`` from local UDP ``14580 + i``. Valid for ``i < 40`` (from 40 on the two
  ranges overlap). Note: instance 10 sends to 14550, the port a ground station on the same
  host listens on; keep ``i < 10`` when QGroundControl runs beside the fleet.
- ArduPilot SITL instance ``i`` (``-I i``): serial0 is a TCP server on ``5760 + 10 i``
  (serial1/2 on +2/+3); its sysid stays 1 unless ``SYSID_THISMAV`` is set, so Roost sets
  it to ``i + 1`` like PX4. For a UDP link Roost points ``--serial1 udpclient:`` at the
  same ``14540 + i`` port, so one agent config shape serves both stacks.

The scheme is part of the API: the operator derives a SITL pod's ports from it, the
sandbox numbers its simulated autopilots with it, and the agent connects with it.
"""

from __future__ import annotations

from dataclasses import dataclass

from roost_api.core import Stack

PX4_API_PORT_BASE = 14540
PX4_LOCAL_PORT_BASE = 14580
ARDUPILOT_TCP_PORT_BASE = 5760
ARDUPILOT_TCP_PORT_STEP = 10
MAX_SITL_INSTANCES = PX4_LOCAL_PORT_BASE - PX4_API_PORT_BASE
DEFAULT_SLOTS_PER_VEHICLE = 4


@dataclass(frozen=True)
class SitlEndpoint:
    """Identity and ports of one simulated autopilot."""

    stack: Stack
    instance: int
    sysid: int
    agent_port: int  # UDP port the autopilot sends to; the agent listens here
    autopilot_port: int  # UDP port the autopilot sends from (PX4) / TCP server (ArduPilot)

    @property
    def connection(self) -> str:
        """The ``AutopilotSpec.connection`` an agent on the same host uses."""
        return f"udp://127.0.0.1:{self.agent_port}"


def sitl_instance(
    vehicle_instance: int, autopilot_index: int, slots_per_vehicle: int = DEFAULT_SLOTS_PER_VEHICLE
) -> int:
    """Global SITL instance number of one autopilot of one vehicle."""
    if vehicle_instance < 0 or not 0 <= autopilot_index < slots_per_vehicle:
        raise ValueError(
            f"autopilot index {autopilot_index} of vehicle {vehicle_instance} does not fit "
            f"{slots_per_vehicle} slots per vehicle"
        )
    return vehicle_instance * slots_per_vehicle + autopilot_index


def sitl_endpoint(
    vehicle_instance: int,
    autopilot_index: int,
    stack: Stack,
    slots_per_vehicle: int = DEFAULT_SLOTS_PER_VEHICLE,
) -> SitlEndpoint:
    """Sysid and ports for autopilot ``autopilot_index`` of vehicle ``vehicle_instance``."""
    stack = Stack(stack)
    i = sitl_instance(vehicle_instance, autopilot_index, slots_per_vehicle)
    if i >= MAX_SITL_INSTANCES:
        raise ValueError(f"SITL instance {i} exceeds the {MAX_SITL_INSTANCES} the ports allow")
    local = (
        PX4_LOCAL_PORT_BASE + i
        if stack is Stack.PX4
        else ARDUPILOT_TCP_PORT_BASE + ARDUPILOT_TCP_PORT_STEP * i
    )
    return SitlEndpoint(
        stack=stack, instance=i, sysid=i + 1, agent_port=PX4_API_PORT_BASE + i, autopilot_port=local
    )
